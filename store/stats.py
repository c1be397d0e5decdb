"""``rainbench stats DATA``: the seed paper's Table I, and more, for any dataset.

What is counted (labels are per frame and shared by every rain rate, so each is counted once):

- objects: distinct actors, i.e. distinct (scene seed, instance id) pairs (instance ids are per
  scene, and a scene split over several shards keeps its ids); instances: labelled boxes over
  all frames; ignore regions: visible actors too small or hidden to be labels, over all frames
  (``/ignore``; in total and per labelled class);
- per class (only classes that occur, in class-id order): objects and instances, box height
  percentiles in pixels (``PERCENTILES``, numpy's linear interpolation), histograms of
  ``visible_fraction`` and ``truncation`` (``HIST_BINS`` bins of width 0.1 over [0, 1], the last
  one closed), and instances per frame (mean and max over every frame of the dataset, and a
  histogram: ``hist[k]`` frames hold k boxes of the class); the same per-frame numbers over all
  classes;
- per layout and per time of day (shard attributes ``layout`` and ``time_of_day``; a shard
  without them counts as ``street`` and ``day``): scenes, frames, objects and instances.

:func:`read_dataset_labels` reads the label arrays through :class:`rainbench.store.Dataset`; a path
without shards or a corrupt shard is a one-line ValueError naming it. :func:`label_stats` and
:func:`render_stats` are pure. The keys of :func:`label_stats`'s dict (the ``--json`` output) are
listed in docs/datasets.md ("Dataset statistics").
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .classes import CLASS_NAMES
from .dataset import Dataset

PERCENTILES: tuple[int, ...] = (5, 25, 50, 75, 95)
"""Box height percentiles reported per class."""
HIST_BINS = 10
"""Bins of the visible-fraction and truncation histograms, equal width over [0, 1]."""
BIN_EDGES: tuple[float, ...] = tuple(round(i / HIST_BINS, 10) for i in range(HIST_BINS + 1))
"""(HIST_BINS + 1,) bin edges 0.0, 0.1, ..., 1.0; bin i is [edge i, edge i+1), the last closed."""
DEFAULT_LAYOUT = "street"
"""Layout of a shard without a ``layout`` attribute."""
DEFAULT_TIME_OF_DAY = "day"
"""Time of day of a shard without a ``time_of_day`` attribute."""
_SCENE_NAME = re.compile(r"scene(\d+)_f\d+")


@dataclass(frozen=True)
class ShardLabels:
    """The labels of one shard that the statistics need; M labels, ``frames`` frames.

    Attributes:
        path (str): The shard file.
        scene (int | str): Scene key of its objects: the ``scene_seed`` attribute, else the seed in
            the file name (``scene000007_f00000.h5`` -> 7), else the path.
        layout (str): The ``layout`` attribute, ``DEFAULT_LAYOUT`` when absent.
        time_of_day (str): The ``time_of_day`` attribute, ``DEFAULT_TIME_OF_DAY`` when absent.
        frames (int): Frames of the shard.
        frame (np.ndarray): (M,) int64 frame index (within the shard) of each label.
        class_id (np.ndarray): (M,) int64 class ids.
        instance_id (np.ndarray): (M,) int64 instance ids.
        height_px (np.ndarray): (M,) float64 box height ``y2 - y1`` in pixels.
        visible_fraction (np.ndarray): (M,) float64 in [0, 1].
        truncation (np.ndarray): (M,) float64 in [0, 1].
    """

    path: str
    scene: int | str
    layout: str
    time_of_day: str
    frames: int
    frame: np.ndarray
    class_id: np.ndarray
    instance_id: np.ndarray
    height_px: np.ndarray
    visible_fraction: np.ndarray
    truncation: np.ndarray
    ignore_class_id: np.ndarray  # (N,) the class of each ignore region of the shard's frames


def _text_attr(handle: Any, key: str, default: str) -> str:
    value = handle.attrs.get(key)
    if value is None:
        return default
    if isinstance(value, (bytes, np.bytes_)):
        return value.decode("utf-8", "replace")
    return str(value)


def _scene_key(handle: Any, path: Path) -> int | str:
    seed = handle.attrs.get("scene_seed")
    if seed is not None and np.ndim(seed) == 0 and np.issubdtype(np.asarray(seed).dtype, np.integer):
        return int(seed)
    match = _SCENE_NAME.fullmatch(path.stem)
    return int(match.group(1)) if match else str(path)


def read_shard_labels(handle: Any, path: str | Path) -> ShardLabels:
    """The :class:`ShardLabels` of an open, checked shard (:meth:`Dataset.open`)."""
    path = Path(path)
    offsets = handle["labels/offsets"][()].astype(np.int64)
    frames = len(offsets) - 1
    boxes = handle["labels/bbox"][()].astype(np.float64).reshape(-1, 4)
    return ShardLabels(
        path=str(path), scene=_scene_key(handle, path),
        layout=_text_attr(handle, "layout", DEFAULT_LAYOUT),
        time_of_day=_text_attr(handle, "time_of_day", DEFAULT_TIME_OF_DAY),
        frames=frames, frame=np.repeat(np.arange(frames, dtype=np.int64), np.diff(offsets)),
        class_id=handle["labels/class_id"][()].astype(np.int64),
        instance_id=handle["labels/instance_id"][()].astype(np.int64),
        height_px=boxes[:, 3] - boxes[:, 1],
        visible_fraction=handle["labels/visible_fraction"][()].astype(np.float64),
        truncation=handle["labels/truncation"][()].astype(np.float64),
        ignore_class_id=(handle["ignore/class_id"][()].astype(np.int64) if "ignore" in handle
                         else np.zeros(0, np.int64)))


def read_dataset_labels(data: str | Path | Sequence[str | Path]) -> list[ShardLabels]:
    """:class:`ShardLabels` of every shard of ``data`` (a dataset directory, one shard, or a list
    of shards), in manifest order. Raises a one-line ValueError (``DatasetError``,
    ``ShardFormatError``) naming the path without shards or the corrupt shard."""
    dataset = Dataset(data, labels_only=True)  # labels are the same at every rate
    result = []
    for number, path in enumerate(dataset.shards):
        with dataset.open(number) as handle:
            result.append(read_shard_labels(handle, path))
    return result


def _per_frame(counts: np.ndarray) -> dict[str, Any]:
    """Mean, max and histogram (``hist[k]``: frames with k boxes) of (F,) per-frame counts."""
    counts = np.asarray(counts, np.int64)
    if counts.size == 0:
        return {"mean": 0.0, "max": 0, "hist": [0]}
    return {"mean": float(counts.mean()), "max": int(counts.max()),
            "hist": np.bincount(counts).astype(int).tolist()}


def _histogram(values: np.ndarray) -> list[int]:
    return np.histogram(values, bins=HIST_BINS, range=(0.0, 1.0))[0].astype(int).tolist()


def _group_counts(shards: Sequence[ShardLabels], key: str) -> dict[str, dict[str, int]]:
    """``{value of attribute key: {scenes, frames, objects, instances}}``, values sorted."""
    groups: dict[str, dict[str, Any]] = {}
    for shard in shards:
        entry = groups.setdefault(getattr(shard, key), {"scenes": set(), "frames": 0, "objects": set(),
                                                        "instances": 0})
        entry["scenes"].add(shard.scene)
        entry["frames"] += shard.frames
        entry["objects"].update((shard.scene, int(i)) for i in np.unique(shard.instance_id))
        entry["instances"] += int(shard.class_id.size)
    return {name: {"scenes": len(entry["scenes"]), "frames": entry["frames"], "objects": len(entry["objects"]),
                   "instances": entry["instances"]} for name, entry in sorted(groups.items())}


def label_stats(shards: Sequence[ShardLabels]) -> dict[str, Any]:
    """The statistics of a dataset's labels, as plain JSON-ready data (keys: module docstring and
    docs/datasets.md): ``shards``, ``scenes``, ``frames``, ``objects``, ``instances``,
    ``percentiles``, ``bins``, ``classes`` (one dict per class that occurs, in class-id order),
    ``per_frame`` (all classes), ``layout`` and ``time_of_day``."""
    frame_base = np.cumsum([0] + [shard.frames for shard in shards])
    n_frames = int(frame_base[-1])
    frame = np.concatenate([shard.frame + base for shard, base in zip(shards, frame_base)] or [np.zeros(0, np.int64)])

    def joined(name: str, dtype) -> np.ndarray:
        return np.concatenate([getattr(shard, name) for shard in shards] or [np.zeros(0, dtype)]).astype(dtype)

    class_id = joined("class_id", np.int64)
    ignore_class_id = joined("ignore_class_id", np.int64)
    instance_id = joined("instance_id", np.int64)
    height = joined("height_px", np.float64)
    visible = joined("visible_fraction", np.float64)
    truncation = joined("truncation", np.float64)
    scene = [shard.scene for shard in shards for _ in range(shard.class_id.size)]
    objects = list(zip(scene, instance_id.tolist()))

    classes = []
    for class_id_value in np.unique(class_id).tolist():
        rows = np.flatnonzero(class_id == class_id_value)
        percentiles = np.percentile(height[rows], PERCENTILES)
        classes.append({
            "class_id": int(class_id_value),
            "class": CLASS_NAMES[class_id_value] if 0 <= class_id_value < len(CLASS_NAMES) else str(class_id_value),
            "objects": len({objects[row] for row in rows.tolist()}),
            "instances": int(rows.size),
            "ignore_regions": int(np.count_nonzero(ignore_class_id == class_id_value)),
            "height_px": {f"p{p}": float(v) for p, v in zip(PERCENTILES, percentiles)},
            "visible_fraction_hist": _histogram(visible[rows]),
            "truncation_hist": _histogram(truncation[rows]),
            "per_frame": _per_frame(np.bincount(frame[rows], minlength=n_frames)),
        })
    labelled = set(np.unique(class_id).tolist())
    ignore_only = [{"class_id": int(value),
                    "class": CLASS_NAMES[value] if 0 <= value < len(CLASS_NAMES) else str(value),
                    "ignore_regions": int(np.count_nonzero(ignore_class_id == value))}
                   for value in np.unique(ignore_class_id).tolist() if value not in labelled]
    return {
        "shards": len(shards),
        "scenes": len({shard.scene for shard in shards}),
        "frames": n_frames,
        "objects": len(set(objects)),
        "instances": int(class_id.size),
        "ignore_regions": int(ignore_class_id.size),
        "percentiles": list(PERCENTILES),
        "bins": list(BIN_EDGES),
        "classes": classes,
        "ignore_only_classes": ignore_only,
        "per_frame": _per_frame(np.bincount(frame, minlength=n_frames)),
        "layout": _group_counts(shards, "layout"),
        "time_of_day": _group_counts(shards, "time_of_day"),
    }


def dataset_stats(data: str | Path | Sequence[str | Path]) -> dict[str, Any]:
    """:func:`label_stats` of the shards of ``data``, with ``data`` (the path as given, a string)
    first. Errors as :func:`read_dataset_labels`."""
    shown = str(data) if isinstance(data, (str, Path)) else ", ".join(str(p) for p in data)
    return {"data": shown, **label_stats(read_dataset_labels(data))}


def _text_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """Plain monospace table: the first column left-aligned, the others right-aligned."""
    widths = [max(len(str(row[i])) for row in [header, *rows]) for i in range(len(header))]

    def line(cells: Sequence[str]) -> str:
        parts = [str(cells[0]).ljust(widths[0])] + [str(c).rjust(w) for c, w in zip(cells[1:], widths[1:])]
        return "  ".join(parts).rstrip()

    return [line(header), line(["-" * w for w in widths])] + [line(row) for row in rows]


def _plural(count: int, word: str) -> str:
    return f"{count} {word}{'' if count == 1 else 's'}"


def render_stats(stats: dict[str, Any]) -> str:
    """Human-readable tables of :func:`dataset_stats` (or of its JSON read back): plain text,
    aligned columns. Heights with one decimal, per-frame means with two."""
    classes = stats["classes"]
    lines = [f"rainbench stats: {stats.get('data', '')}".rstrip(),
             f"{_plural(stats['shards'], 'shard')}, {_plural(stats['scenes'], 'scene')}, "
             f"{_plural(stats['frames'], 'frame')}; {_plural(stats['objects'], 'object')}, "
             f"{_plural(stats['instances'], 'instance')} (labels counted once per frame, not per rain rate); "
             f"{_plural(stats['ignore_regions'], 'ignore region')} (visible actors too small or hidden to be labels)",
             ""]
    lines += ["Objects and instances per class (the seed paper's Table I)"]
    rows = [[c["class"], str(c["class_id"]), str(c["objects"]), str(c["instances"]), str(c["ignore_regions"])]
            for c in classes]
    # classes seen only as ignore regions: their rows make the column add up to "all"
    rows += [[c["class"], str(c["class_id"]), "0", "0", str(c["ignore_regions"])]
             for c in stats.get("ignore_only_classes", [])]
    rows.sort(key=lambda row: int(row[1]))
    rows.append(["all", "", str(stats["objects"]), str(stats["instances"]), str(stats["ignore_regions"])])
    lines += _text_table(["class", "id", "objects", "instances", "ignore regions"], rows) + [""]
    if classes:
        lines += ["Box height (px) percentiles"]
        lines += _text_table(["class"] + [f"p{p}" for p in stats["percentiles"]],
                             [[c["class"]] + [f"{c['height_px'][f'p{p}']:.1f}" for p in stats["percentiles"]]
                              for c in classes]) + [""]
        edges = stats["bins"]
        for key, title in (("visible_fraction_hist", "Visible fraction"), ("truncation_hist", "Truncation")):
            lines += [f"{title}: boxes per bin [lower edge, lower edge + {edges[1] - edges[0]:g}) over "
                      f"[{edges[0]:g}, {edges[-1]:g}], the last bin closed"]
            lines += _text_table(["class"] + [f"{edge:.1f}" for edge in edges[:-1]],
                                 [[c["class"]] + [str(v) for v in c[key]] for c in classes]) + [""]
    lines += ["Instances per frame (histogram: frames with 0, 1, 2, ... instances)"]
    per_frame_rows = [[c["class"], f"{c['per_frame']['mean']:.2f}", str(c["per_frame"]["max"]),
                       " ".join(str(v) for v in c["per_frame"]["hist"])] for c in classes]
    per_frame_rows.append(["all", f"{stats['per_frame']['mean']:.2f}", str(stats["per_frame"]["max"]),
                           " ".join(str(v) for v in stats["per_frame"]["hist"])])
    lines += _text_table(["class", "mean", "max", "histogram"], per_frame_rows) + [""]
    for key, title in (("layout", "Per layout"), ("time_of_day", "Per time of day")):
        lines += [f"{title} (shards without the attribute count as "
                  f"{DEFAULT_LAYOUT if key == 'layout' else DEFAULT_TIME_OF_DAY})"]
        lines += _text_table([key, "scenes", "frames", "objects", "instances"],
                             [[name, str(v["scenes"]), str(v["frames"]), str(v["objects"]), str(v["instances"])]
                              for name, v in stats[key].items()]) + [""]
    return "\n".join(lines).rstrip("\n") + "\n"
