"""Dataset exports: YOLO folders (trainable with ultralytics) and COCO JSON, one per rain rate.

Both exports read through :class:`rainbench.store.dataset.Dataset` and number images as it does
(1-based, manifest shard order, then frame order), the numbering used everywhere in rainbench, so an exported
image ``000007.png`` is image id 7 in evaluation too.

Layout of ``out_dir`` (``<token>`` is :func:`rainbench.store.rates.rate_token` of the rate,
e.g. ``0``, ``12.5``):

- YOLO: ``rate_<token>/images/<id:06d>.png``, ``rate_<token>/labels/<id:06d>.txt``,
  ``rate_<token>/data.yaml``;
- COCO: ``rate_<token>.json`` whose ``file_name`` s are ``rate_<token>/images/<id:06d>.png``
  (relative to ``out_dir``; the images are written there too unless ``images=False``).

Boxes in shards are float32 ``x1, y1, x2, y2`` in pixel-edge coordinates (docs/format.md).

Class ids stay COCO-80 ids in both exports (:mod:`rainbench.store.classes`: 0 person, 1 bicycle,
2 car, 3 motorcycle, 5 bus, 7 truck). The classes an export declares are those its labels need
(:func:`export_classes`): the paper's four when every label is one of them, else all six
labelled classes. YOLO ``data.yaml`` ``names`` is the dict ``{id: name}`` over the dense ids
0..3 or 0..7 (``nc`` 4 or 8; ultralytics needs dense ids, so 4 airplane and 6 train are named
though never labelled), and COCO ``categories`` list exactly the declared classes with their
COCO ids (so 4 and 6 are left out).

An export is written into a hidden staging folder ``out_dir/.export-tmp-<pid>/`` and its
folders and files are renamed into place only when everything is written, so a failed or
interrupted export leaves nothing under a final name (a killed one leaves its staging folder,
removed by the next export into ``out_dir``).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from .classes import CLASS_NAMES, LABELLED_CLASSES, PAPER_CLASSES, parse_classes
from .dataset import Dataset
from .images import write_image
from .manifest import DatasetError
from .rates import rate_token
from .signals import signals_held

IMAGE_FORMATS = ("png", "jpg")
_JPEG_QUALITY = 95


class ExportError(DatasetError):
    """An export request that cannot be honoured; the message is one line naming the thing."""


def open_for_export(data, rates: Sequence[float] | None) -> Dataset:
    """:class:`Dataset` of ``data`` at ``rates`` (None: every rate of the dataset); a rate not
    in every shard, or a malformed rate list, raises one-line :class:`ExportError`."""
    try:
        return Dataset(data, rates)
    except DatasetError as error:
        if type(error) is not DatasetError:
            raise
        raise ExportError(str(error)) from None


def export_classes(class_ids: Sequence[int]) -> tuple[int, ...]:
    """The class ids an export declares for labels with the ids ``class_ids``: the paper's four
    (``PAPER_CLASSES``) when every id is one of them, else every labelled class
    (``LABELLED_CLASSES``, adding 5 bus and 7 truck)."""
    return PAPER_CLASSES if set(int(c) for c in class_ids) <= set(PAPER_CLASSES) else LABELLED_CLASSES


def yolo_names(class_ids: Sequence[int]) -> list[str]:
    """YOLO ``names`` for labels with the ids ``class_ids``: ``CLASS_NAMES`` over the dense ids
    0..max of :func:`export_classes` (ultralytics needs ids 0..nc-1)."""
    return list(CLASS_NAMES[:max(export_classes(class_ids)) + 1])


def _check_classes(classes: Sequence[int | str] | None) -> np.ndarray | None:
    """(K,) int64 ids of the ``classes`` to export (:func:`rainbench.store.classes.parse_classes`),
    None for every class; a bad entry raises one-line :class:`ExportError`."""
    if classes is None:
        return None
    try:
        return np.asarray(parse_classes(classes), np.int64)
    except ValueError as error:
        raise ExportError(str(error).replace("--classes", "classes", 1)) from None


_STAGE_PREFIX = ".export-tmp-"


def _stage_owner_alive(stage: Path) -> bool:
    pid = stage.name[len(_STAGE_PREFIX):]
    if not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return int(pid) != os.getpid()


@contextlib.contextmanager
def _staged(out_dir: Path, overwrite: bool, targets: Sequence[str]):
    """Yield a staging folder inside ``out_dir``; when the block succeeds, move each of
    ``targets`` (paths relative to the staging folder, in order) to the same place in
    ``out_dir``, replacing what is there (:func:`_swap_in`: all of them or, after a failure or an
    interrupt, none). On failure nothing is moved and the staging folder is removed (and
    ``out_dir`` and the parents this export created, when empty). A non-empty ``out_dir`` is
    refused unless ``overwrite``."""
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"OUT: {out_dir} exists and is not a directory")
    created = [folder for folder in (out_dir, *out_dir.parents) if not folder.exists()]
    if not created:
        for stage in out_dir.glob(f"{_STAGE_PREFIX}*"):
            if _stage_owner_alive(stage):
                raise ExportError(f"OUT: another export is writing into {out_dir} "
                                  f"({stage.name}); wait for it or choose another directory")
            shutil.rmtree(stage, ignore_errors=True)  # left by a killed export
        if any(out_dir.iterdir()) and not overwrite:
            raise ExportError(f"OUT: {out_dir} is not empty; use --overwrite or choose another "
                              "directory")
        for relative in targets:  # a file where a target's folder goes would stop the swap half way
            for folder in reversed((out_dir / relative).relative_to(out_dir).parents[:-1]):
                if (out_dir / folder).exists() and not (out_dir / folder).is_dir():
                    raise ExportError(f"OUT: {out_dir / folder} is a file where the export puts a folder; "
                                      "remove it or choose another directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    stage = out_dir / f"{_STAGE_PREFIX}{os.getpid()}"
    stage.mkdir()
    try:
        yield stage
        _swap_in(stage, out_dir, targets)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        for folder in created:  # deepest first; only when empty: a failed export into a new directory
            with contextlib.suppress(OSError):
                folder.rmdir()


def _swap_in(stage: Path, out_dir: Path, targets: Sequence[str]) -> None:
    """Move ``targets`` from ``stage`` into ``out_dir``. What a target replaces is first moved
    aside (into the staging folder: renames in one file system), so that an error or an
    interrupt part way moves the new targets back into the stage and what they replaced back into
    place, by renames, with Ctrl-C and termination signals held: ``out_dir`` then holds the
    previous export, never a mix of two. Should a rename of that rollback fail, the previous
    export's files are kept in ``OUT/.export-previous-<pid>`` and the error says so."""
    aside = stage / ".replaced"
    moved_in: list[str] = []
    moved_aside: list[str] = []
    try:
        for relative in targets:
            final = out_dir / relative
            if final.exists() or final.is_symlink():
                (aside / relative).parent.mkdir(parents=True, exist_ok=True)
                os.replace(final, aside / relative)
                moved_aside.append(relative)
            final.parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / relative, final)
            moved_in.append(relative)
    except BaseException:
        with signals_held():
            try:
                for relative in reversed(moved_in):
                    os.replace(out_dir / relative, stage / relative)
                for relative in reversed(moved_aside):
                    os.replace(aside / relative, out_dir / relative)
            except OSError as error:
                kept = out_dir / f".export-previous-{os.getpid()}"
                os.replace(aside, kept)  # out of the stage, which is removed next
                raise ExportError(f"OUT: the previous export could not be put back ({error.strerror or error}); "
                                  f"its files are in {kept}") from None
        raise


def _check_image_format(image_format: str) -> str:
    if image_format not in IMAGE_FORMATS:
        raise ExportError(f"image_format: expected one of {', '.join(IMAGE_FORMATS)}, got "
                          f"{image_format!r}")
    return image_format


def _write_image(path: Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB image (PNG lossless, JPEG quality 95)."""
    write_image(path, rgb, [cv2.IMWRITE_JPEG_QUALITY, _JPEG_QUALITY] if path.suffix == ".jpg" else [])


def _yolo_lines(boxes: np.ndarray, class_ids: np.ndarray, width: int, height: int) -> str:
    """YOLO label text: ``class cx cy w h`` per box, normalised to [0, 1], 6 decimals."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    x1, y1, x2, y2 = boxes.T
    columns = np.stack([(x1 + x2) / 2 / width, (y1 + y2) / 2 / height,
                        (x2 - x1) / width, (y2 - y1) / height], axis=1)
    columns = np.clip(columns, 0.0, 1.0)
    return "".join(f"{int(c)} {cx:.6f} {cy:.6f} {w:.6f} {h:.6f}\n"
                   for c, (cx, cy, w, h) in zip(class_ids, columns))


def _data_yaml(folder: Path, names: Sequence[str], image_dir: str = "images") -> str:
    # JSON strings are valid YAML double-quoted scalars, so names and paths need no escaping.
    lines = [f"path: {json.dumps(str(folder.resolve()))}", f"train: {image_dir}",
             f"val: {image_dir}", f"nc: {len(names)}", "names:"]
    lines += [f"  {i}: {json.dumps(name)}" for i, name in enumerate(names)]
    return "\n".join(lines) + "\n"


def export_yolo(data, out_dir, *, rates: Sequence[float] | None = None,
                image_format: str = "png", overwrite: bool = False,
                classes: Sequence[int] | None = None) -> list[Path]:
    """Export the dataset ``data`` (a dataset directory, a shard, or a list of shards) as one
    ultralytics YOLO folder per rain rate; returns the ``data.yaml`` paths (in rate order).

    ``out_dir/rate_<token>/``: ``images/<id:06d>.<image_format>`` (RGB of the shard, lossless
    for png), ``labels/<id:06d>.txt`` (one ``class cx cy w h`` line per box: the shard's xyxy
    pixel-edge ``bbox`` normalised by the image size, 6 decimals; an empty file for no boxes),
    ``data.yaml`` (``path`` absolute, ``train``/``val`` = ``images``, ``nc``, ``names`` the
    dict ``{class id: name}`` of :func:`yolo_names`: 0..3 for the paper's classes, 0..7 when bus
    or truck labels are exported, COCO ids kept):
    ``YOLO("yolo11n.pt").train(data=".../rate_0/data.yaml")`` trains on it directly.

    ``classes``: export only the labels of these class ids (e.g. ``PAPER_CLASSES`` for a
    four-class model); None exports every label.

    ``rates=None`` exports every rate of the dataset; a rate not in the dataset raises
    :class:`ExportError`. A non-empty ``out_dir`` raises unless ``overwrite`` (then the
    ``rate_<token>/`` folders of the exported rates are replaced; other files are left alone).
    """
    _check_image_format(image_format)
    keep = _check_classes(classes)
    dataset = open_for_export(data, rates)
    out_dir = Path(out_dir)
    folder_names = [f"rate_{rate_token(rate)}" for rate in dataset.rates]
    seen: set[int] = set()
    with _staged(out_dir, overwrite, folder_names) as stage:
        folders = [stage / name for name in folder_names]
        for folder in folders:
            (folder / "images").mkdir(parents=True, exist_ok=True)
            (folder / "labels").mkdir(parents=True, exist_ok=True)
        for frame in dataset.frames(keep):
            labels, (height, width), image_id = frame.labels, frame.size, frame.image.image_id
            seen.update(labels["class_id"].tolist())
            text = _yolo_lines(labels["bbox"], labels["class_id"], width, height)
            for folder, rgb in zip(folders, frame.rgb):
                _write_image(folder / "images" / f"{image_id:06d}.{image_format}", rgb)
                (folder / "labels" / f"{image_id:06d}.txt").write_text(text)
        names = yolo_names(seen)
        for name, folder in zip(folder_names, folders):
            (folder / "data.yaml").write_text(_data_yaml(out_dir / name, names))
    return [out_dir / name / "data.yaml" for name in folder_names]


def read_yolo_labels(txt_path, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Read a YOLO label file back to pixels: boxes (M, 4) float32 xyxy pixel-edge and
    class ids (M,) int32 (M = 0 for an empty file). Malformed lines raise naming file and line."""
    txt_path = Path(txt_path)
    boxes, class_ids = [], []
    for number, line in enumerate(txt_path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        fields = line.split()
        try:
            if len(fields) != 5:
                raise ValueError(f"expected 5 fields, got {len(fields)}")
            class_id = int(fields[0])
            cx, cy, w, h = (float(value) for value in fields[1:])
        except ValueError as error:
            raise ExportError(f"{txt_path}:{number}: not a YOLO box line ({error})") from error
        boxes.append([(cx - w / 2) * width, (cy - h / 2) * height,
                      (cx + w / 2) * width, (cy + h / 2) * height])
        class_ids.append(class_id)
    return (np.asarray(boxes, dtype=np.float32).reshape(-1, 4),
            np.asarray(class_ids, dtype=np.int32))


def export_coco(data, out_dir, *, rates: Sequence[float] | None = None, images: bool = True,
                image_format: str = "png", overwrite: bool = False,
                classes: Sequence[int] | None = None) -> list[Path]:
    """Export the dataset ``data`` as one COCO detection JSON per rain rate; returns the JSON
    paths ``out_dir/rate_<token>.json`` (in rate order).

    - ``images``: ``id`` = rainbench image id (1-based, :class:`Dataset` numbering), ``file_name``
      ``rate_<token>/images/<id:06d>.<image_format>`` relative to ``out_dir``, ``width``, ``height``,
      ``shard`` (shard file path relative to the dataset directory), ``frame`` (index in it);
    - ``annotations``: ``id`` 1-based, ``image_id``, ``category_id`` = rainbench class id
      (COCO-80 index, 0 = person), ``bbox`` ``[x, y, w, h]`` from the shard's xyxy pixel-edge
      box, ``area`` = w * h, ``iscrowd`` 0, plus ``visible_fraction``, ``truncation``,
      ``instance_id`` and, at this rate, ``rain_coverage`` and ``contrast_loss``; then each
      image's ignore regions (actors too small or hidden to be labels): ``bbox``, ``area``,
      ``instance_id``, ``iscrowd`` 1 and ``ignore`` 1, so pycocotools' ``COCOeval`` neither
      misses them nor counts a detection of one as a false positive (``rainbench eval``'s
      scoring);
    - ``categories``: ``{"id": i, "name": CLASS_NAMES[i], "supercategory": "object"}`` for the
      COCO ids ``i`` of :func:`export_classes` (0..3, or 0..3, 5 and 7 when bus or truck labels
      or ignore regions are exported: every annotation's category is listed).

    ``images=True`` also writes the images at the ``file_name`` paths (the same files as
    :func:`export_yolo`, so both exports can share one ``out_dir`` with ``overwrite=True``).
    Rate selection and ``overwrite`` as in :func:`export_yolo` (replaced: ``rate_<token>.json``
    and, with ``images``, ``rate_<token>/images/``); ``classes`` as in :func:`export_yolo`.
    """
    _check_image_format(image_format)
    keep = _check_classes(classes)
    dataset = open_for_export(data, rates)
    selected = dataset.rates
    out_dir = Path(out_dir)
    tokens = [rate_token(rate) for rate in selected]
    # images first, the JSON files (which name the images) last
    targets = [f"rate_{token}/images" for token in tokens] if images else []
    targets += [f"rate_{token}.json" for token in tokens]
    with _staged(out_dir, overwrite, targets) as stage:
        if images:
            for token in tokens:
                (stage / f"rate_{token}" / "images").mkdir(parents=True, exist_ok=True)
        root = dataset.root
        image_records, annotation_records = [], []  # rate-independent parts; file_name added later
        per_rate_extra: list[list[tuple[float, float]]] = []  # (rain_coverage, contrast_loss)
        for frame_record in dataset.frames(keep):
            image_id, path, frame = (frame_record.image.image_id, frame_record.image.shard,
                                     frame_record.image.frame)
            labels, (height, width), rgb_by_rate = frame_record.labels, frame_record.size, frame_record.rgb
            try:
                shard = path.relative_to(root).as_posix() if root is not None else path.name
            except ValueError:
                shard = path.name
            image_records.append({"id": image_id, "width": width, "height": height,
                                  "shard": shard, "frame": frame})
            if images:
                for token, rgb in zip(tokens, rgb_by_rate):
                    _write_image(stage / f"rate_{token}" / "images" /
                                 f"{image_id:06d}.{image_format}", rgb)
            count = labels["bbox"].shape[0]
            coverage = labels.get("rain_coverage", np.zeros((len(selected), count), np.float32))
            contrast = labels.get("contrast_loss", np.zeros((len(selected), count), np.float32))
            for row in range(count):
                x1, y1, x2, y2 = (float(value) for value in labels["bbox"][row])
                w, h = x2 - x1, y2 - y1
                annotation_records.append({
                    "id": len(annotation_records) + 1, "image_id": image_id,
                    "category_id": int(labels["class_id"][row]), "bbox": [x1, y1, w, h],
                    "area": w * h, "iscrowd": 0,
                    "visible_fraction": float(labels["visible_fraction"][row]),
                    "truncation": float(labels["truncation"][row]),
                    "instance_id": int(labels["instance_id"][row]),
                })
                per_rate_extra.append([(float(coverage[r, row]), float(contrast[r, row]))
                                       for r in range(len(selected))])
            for box, class_id, instance_id in zip(frame_record.ignore["bbox"].tolist(),
                                                  frame_record.ignore["class_id"].tolist(),
                                                  frame_record.ignore["instance_id"].tolist()):
                x1, y1, x2, y2 = box
                annotation_records.append({
                    "id": len(annotation_records) + 1, "image_id": image_id,
                    "category_id": int(class_id), "bbox": [x1, y1, x2 - x1, y2 - y1],
                    "area": (x2 - x1) * (y2 - y1), "iscrowd": 1, "ignore": 1,
                    "instance_id": int(instance_id),
                })
                per_rate_extra.append(None)
        seen = {record["category_id"] for record in annotation_records}
        categories = [{"id": i, "name": CLASS_NAMES[i], "supercategory": "object"}
                      for i in export_classes(seen)]
        for position, (rate, token) in enumerate(zip(selected, tokens)):
            payload = {
                "info": {"description": "rainbench export", "rate_mm_h": rate},
                "images": [dict(record, file_name=f"rate_{token}/images/{record['id']:06d}."
                                                  f"{image_format}")
                           for record in image_records],
                "annotations": [record if extra is None else
                                dict(record, rain_coverage=extra[position][0],
                                     contrast_loss=extra[position][1])
                                for record, extra in zip(annotation_records, per_rate_extra)],
                "categories": categories,
            }
            (stage / f"rate_{token}.json").write_text(json.dumps(payload))
    return [out_dir / f"rate_{token}.json" for token in tokens]
