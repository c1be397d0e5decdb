"""The ``rainbench eval`` pipeline: dataset -> detections per model and rate -> metrics, report, plots.

Building blocks (each usable alone):

- :func:`open_dataset` opens ``--data`` through :class:`rainbench.store.Dataset` (image ids
  1-based, manifest shard order, then frame order: the numbering everywhere in rainbench);
- :func:`ground_truth` reads the COCO ground truth (labels are the same at every rate, so one
  ground truth serves all rates);
- :func:`rate_token` names prediction files ``rate_<token>.json``;
- :func:`load_predictions_file` reads and checks one COCO results file;
- :func:`run_eval` orchestrates everything and writes the outputs (see docs/eval.md).

Every user-facing failure is an :class:`EvalError` (a ValueError) with a one-line message.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import math
import os
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.store import (SHARD_GLOB, Dataset, DatasetError, Image, read_frame_ignore, read_frame_labels,
                             read_manifest)
from rainbench.store.rates import rate_token

from rainbench.store.classes import CLASS_NAMES, LABELLED_CLASSES, PAPER_CLASSES, class_list, parse_classes
from .comparison import comparison_references, comparison_rows
from .metrics.bootstrap import bootstrap_ci
from .metrics.coco import DEFAULT_BACKEND, METRICS_BACKENDS, coco_detections, coco_ground_truth
from .metrics.evaluation import evaluate
from .report.figures import plot_detection_strip
from rainbench.store.images import file_error
from rainbench.store.locks import locked_output_dir
from .report.markdown import render_report_md
from .report.paper import PAPER_TABLES
from .report.plots import plot_metric_vs_rate
from .report.records import json_ready, metric_records, write_metrics

BOOTSTRAP_SEED = 0
"""Seed of the bootstrap generator (``np.random.default_rng(BOOTSTRAP_SEED)`` per model and rate)."""


class EvalError(ValueError):
    """A user-facing evaluation error with a one-line message."""


MAX_BOX_PIXELS = 1e6
"""Largest ``|x|``, ``|y|``, ``w`` and ``h`` of a detection's ``[x, y, w, h]`` box, in pixels
(:func:`check_detections`): far beyond any image, yet small enough that areas, IoUs and drawing
never overflow. A box beyond it is an error, not a detection."""


# --------------------------------------------------------------------------------------------
# Dataset
# --------------------------------------------------------------------------------------------


def open_dataset(data_dir: str | Path) -> Dataset:
    """The dataset of ``--data`` (:class:`rainbench.store.Dataset`: image ids 1-based, manifest
    shard order, then frame order; every shard holding the same rates).

    Raises :class:`EvalError` for a missing or empty folder, and for shards whose rates differ.
    """
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise EvalError(f"--data: {data_dir} is not a directory")
    if not any(data_dir.glob(SHARD_GLOB)) and read_manifest(data_dir) is None:
        raise EvalError(f"--data: no shard ({SHARD_GLOB}) in {data_dir}")
    try:
        dataset = Dataset(data_dir)
    except DatasetError as error:
        raise EvalError(f"--data: {error}") from error
    if not dataset.images:
        raise EvalError(f"--data: the shards in {data_dir} hold no frames")
    return dataset


@dataclass(frozen=True)
class TargetFilter:
    """Which labels are scored as targets, KITTI's difficulty levels made explicit (its
    "moderate": at least 25 px tall, at most 30 % truncated). A label outside them becomes an
    ignore region of the scoring (a COCO crowd box: never missed, a detection of it neither right
    nor wrong), like the shards' own ignore regions; nothing is dropped.

    - ``min_height``: box height in pixels (the shards' labels are >= 8 px already);
    - ``min_visible``: ``visible_fraction``, visible pixels / the actor's unoccluded in-image pixels;
    - ``max_truncation``: ``truncation``, the part of the actor outside the image.

    The defaults score every label. Bad values raise :class:`EvalError` naming the option."""

    min_height: float = 0.0
    min_visible: float = 0.0
    max_truncation: float = 1.0

    def __post_init__(self) -> None:
        for option, value, low, high in (("--min-height", self.min_height, 0.0, 100_000.0),
                                         ("--min-visible", self.min_visible, 0.0, 1.0),
                                         ("--max-truncation", self.max_truncation, 0.0, 1.0)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
                raise EvalError(f"{option}: expected a number in {low:g}..{high:g}, got {value!r}")

    @property
    def scores_everything(self) -> bool:
        return self.min_height == 0.0 and self.min_visible == 0.0 and self.max_truncation == 1.0

    def describe(self) -> str:
        """The thresholds in words, e.g. ``height >= 25 px, truncation <= 0.3``."""
        parts = [f"height >= {self.min_height:g} px" if self.min_height else "",
                 f"visible fraction >= {self.min_visible:g}" if self.min_visible else "",
                 f"truncation <= {self.max_truncation:g}" if self.max_truncation < 1.0 else ""]
        return ", ".join(part for part in parts if part) or "every label"

    def keeps(self, labels: dict[str, np.ndarray]) -> np.ndarray:
        """(M,) bool: which of a frame's labels (:func:`rainbench.store.read_frame_labels`) are
        targets."""
        box = np.asarray(labels["bbox"], np.float64).reshape(-1, 4)
        return ((box[:, 3] - box[:, 1] >= self.min_height)
                & (np.asarray(labels["visible_fraction"], np.float64) >= self.min_visible)
                & (np.asarray(labels["truncation"], np.float64) <= self.max_truncation))


def ground_truth(dataset: Dataset, images: Sequence[Image] | None = None, *,
                 ignore_regions: bool = True, targets: TargetFilter = TargetFilter()) -> dict[str, list[dict]]:
    """COCO ground-truth dict of ``images`` (default all) of ``dataset``; valid at every rate.

    Categories are every class id 0..7 (``CLASS_NAMES``), whatever the shards' ``class_names``
    (older shards list the first four; the ids mean the same), so bus (5) and truck (7) boxes
    are ground truth too; which classes are scored is the evaluator's ``class_ids``.

    Each image's annotations are its labels, then (``ignore_regions``) its ignore regions
    (:func:`rainbench.store.read_frame_ignore`: visible actors the label filter left out) with
    ``iscrowd = 1``: a detection lying mostly inside one is neither a true nor a false positive,
    and none is ever missed (KITTI's DontCare). Shards written before ignore regions have none.
    Labels that ``targets`` does not keep are crowd boxes too (:class:`TargetFilter`).
    """
    entries = []
    for image, handle in dataset.walk(images):
        labels = read_frame_labels(handle, image.frame)
        boxes = np.asarray(labels["bbox"], np.float32).reshape(-1, 4)
        class_ids = np.asarray(labels["class_id"]).astype(np.int64)
        ignore = ~targets.keeps(labels)
        if ignore_regions:
            regions = read_frame_ignore(handle, image.frame)
            boxes = np.concatenate([boxes, np.asarray(regions["bbox"], np.float32).reshape(-1, 4)])
            class_ids = np.concatenate([class_ids, np.asarray(regions["class_id"]).astype(np.int64)])
            ignore = np.concatenate([ignore, np.ones(len(regions["class_id"]), bool)])
        height, width = dataset.size(image.shard_index)
        entries.append((image.image_id, width, height, boxes, class_ids, ignore))
    return coco_ground_truth(entries, CLASS_NAMES)


def _read_rgb(dataset: Dataset, rate: float, batch: int):
    """Yield ``(image_ids, [RGB arrays])`` at ``rate`` in batches of at most ``batch`` frames of
    one shard."""
    chunk: list[tuple[int, np.ndarray]] = []
    current = None
    for image, handle in dataset.walk():
        if chunk and (image.shard_index != current or len(chunk) == batch):
            yield [i for i, _ in chunk], [a for _, a in chunk]
            chunk = []
        current = image.shard_index
        chunk.append((image.image_id, dataset.read_rgb(handle, image, rate)))
    if chunk:
        yield [i for i, _ in chunk], [a for _, a in chunk]


# --------------------------------------------------------------------------------------------
# Prediction files
# --------------------------------------------------------------------------------------------


def predictions_path(root: str | Path, model: str, rate: float) -> Path:
    """``root/<model>/rate_<rate_token>.json``."""
    return Path(root) / model / f"rate_{rate_token(rate)}.json"


def check_detections(records: Any, image_ids: set[int], where: str,
                     classes: Sequence[int] = PAPER_CLASSES) -> list[dict]:
    """Check COCO results records; errors name ``where`` (the file). Returns the clean records of
    the evaluated ``classes`` (rainbench ids, default the paper's four): a record of another
    rainbench class (``LABELLED_CLASSES``, e.g. a bus while evaluating the paper's classes) is
    checked and left out; any other ``category_id`` is an error."""
    if not isinstance(records, list):
        raise EvalError(f"{where}: expected a JSON list of COCO results records, got {type(records).__name__}")
    known = set(LABELLED_CLASSES)
    kept = {int(c) for c in classes}
    clean = []
    for position, record in enumerate(records):
        try:
            image_id, category_id = record["image_id"], record["category_id"]
            bbox, score = [float(v) for v in record["bbox"]], float(record["score"])
        except (TypeError, KeyError, ValueError, OverflowError) as error:
            raise EvalError(f"{where}: record {position}: expected image_id, category_id, bbox [x, y, w, h] "
                            f"and score ({type(error).__name__}: {error})") from None
        if isinstance(category_id, bool) or not isinstance(category_id, int) or category_id not in known:
            raise EvalError(f"{where}: record {position}: category_id {category_id!r} is not a rainbench "
                            f"class id ({class_list(LABELLED_CLASSES)})")
        if isinstance(image_id, bool) or not isinstance(image_id, int) or image_id not in image_ids:
            raise EvalError(f"{where}: record {position}: image_id {image_id!r} is not an image of the dataset "
                            f"(ids 1..{len(image_ids)})")
        if not isinstance(record["bbox"], list) or len(bbox) != 4 or not all(math.isfinite(v) for v in bbox) or bbox[2] < 0 or bbox[3] < 0:
            raise EvalError(f"{where}: record {position}: bbox {record['bbox']!r} is not a finite [x, y, w, h] "
                            "with w, h >= 0")
        if not all(abs(v) <= MAX_BOX_PIXELS for v in bbox):
            raise EvalError(f"{where}: record {position}: bbox {record['bbox']!r} is not an image box: "
                            f"|x|, |y|, w and h must be at most {MAX_BOX_PIXELS:.0f} pixels")
        if not 0.0 <= score <= 1.0:
            raise EvalError(f"{where}: record {position}: score {score} is not in [0, 1]")
        if category_id not in kept:
            continue
        clean.append({"image_id": image_id, "category_id": category_id, "bbox": bbox, "score": score})
    return clean


def load_predictions_file(path: str | Path, image_ids: set[int], classes: Sequence[int] = PAPER_CLASSES, *,
                          cache: bool = False) -> list[dict]:
    """Read and check one COCO results file (errors name the file); the records of the evaluated
    ``classes`` (:func:`check_detections`). ``cache``: the file is eval's own detection cache
    (``OUT/predictions``), so its errors suggest ``--force`` (infer again) rather than a fix to
    the file."""
    path = Path(path)
    hint = "; it is eval's detection cache: add --force to infer it again" if cache else ""
    if not path.is_file():
        raise EvalError(f"predictions: {path} is missing{hint}")
    try:
        records = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise EvalError(f"predictions: {path} is not valid JSON ({error}){hint}") from None
    except RecursionError:
        raise EvalError(f"predictions: {path} is not a COCO results list (JSON nested too "
                        f"deeply to read){hint}") from None
    except OSError as error:
        raise EvalError(f"predictions: {path} cannot be read ({error.strerror}){hint}") from None
    try:
        return check_detections(records, image_ids, str(path), classes)
    except EvalError as error:
        if not cache:
            raise
        raise EvalError(f"{error}{hint}") from None


def _write_json(path: Path, data: Any) -> None:
    """Write JSON under a temporary name and rename it, so a final name is always whole; the
    temporary is removed when writing fails, and an OSError names ``path``."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(data) + "\n", encoding="utf-8")
        os.replace(tmp, path)
    except BaseException as error:
        _remove(tmp)
        if isinstance(error, OSError):
            raise file_error(error, path) from error
        raise


def _remove(path: Path) -> None:
    """Remove a file if it is there; a failure to (a read-only folder) is left to the caller's error."""
    with contextlib.suppress(OSError):
        path.unlink(missing_ok=True)


def prediction_models(predictions_dir: str | Path) -> list[str]:
    """Model names of a predictions folder: its sub-folders, sorted."""
    root = Path(predictions_dir)
    if not root.is_dir():
        raise EvalError(f"--predictions: {root} is not a directory")
    models = sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not models:
        raise EvalError(f"--predictions: no model folder (<model>/rate_<rate>.json) in {root}")
    return models


# --------------------------------------------------------------------------------------------
# Orchestrator
# --------------------------------------------------------------------------------------------


@dataclass
class EvalOutputs:
    """What :func:`run_eval` wrote: the records and the paths, keyed by output name."""

    records: list[dict[str, Any]]
    paths: dict[str, Path] = field(default_factory=dict)
    inference_runs: int = 0
    """(model, rate) pairs whose detections were computed by a backend in this run (not cached)."""
    robustness: list[dict[str, Any]] = field(default_factory=list)
    """Rows of the robustness comparison (:func:`rainbench.eval.comparison.comparison_rows`); empty
    without rate 0 and a rainy rate."""


def _cache_settings(weights: Path, *, imgsz, conf, iou, max_det, class_map, classes, pt_backend="batched",
                    device=None, trained=None) -> dict[str, Any]:
    from rainbench.store.manifest import sha256_of

    # the weights' own bytes (a file replaced by another of the same size and time, as `cp -p`,
    # `rsync -a` or an archive leave it, is another model), and a Darknet model's .cfg beside them
    settings = {"weights": str(weights.resolve()), "sha256": sha256_of(weights),
                "imgsz": imgsz, "conf": conf, "iou": iou, "max_det": max_det, "class_map": class_map,
                "classes": list(classes)}
    if weights.suffix.lower() == ".weights" and weights.with_suffix(".cfg").is_file():
        settings["cfg_sha256"] = sha256_of(weights.with_suffix(".cfg"))
    if trained is not None and set(LABELLED_CLASSES) - set(trained):  # its card leaves classes out
        settings["trained"] = list(trained)
    if weights.suffix.lower() == ".pt":  # how it runs changes its detections (fp16 on CUDA)
        from rainbench.devices import runs_on_cuda

        from .backends import BackendError

        settings["pt_backend"] = pt_backend
        settings["cuda"] = runs_on_cuda(device, BackendError)
        if settings["cuda"] and pt_backend == "batched":  # since 2026-11-27 OpenCV's, not the GPU's
            settings["letterbox"] = "opencv"
    return settings


def default_read_workers(cpu_count: int | None = None) -> int:
    """Shard-decoding worker processes of the batched torch backend when ``workers`` is not given:
    one core is left to the process that runs the network, at most 8 (``min(8, cores - 1)``, 0 on
    one core)."""
    cores = cpu_count if cpu_count is not None else (os.cpu_count() or 1)
    return max(0, min(8, cores - 1))


def _infer(detector, dataset: Dataset, rates: Sequence[float], *, batch, imgsz, conf, iou, max_det, bar,
           classes: Sequence[int], workers: int = 0):
    """Yield ``(rate, COCO results records)`` of ``detector`` at each of ``rates`` in turn, of the
    rainbench ids ``classes`` only. A batched torch detector gets its frames decoded and
    letterboxed by ``workers`` processes, started once for all the rates
    (:func:`rainbench.eval.backends.torch_batched.frame_batches`); the others get lists of arrays
    read here, rate by rate."""
    if hasattr(detector, "predict_canvases"):
        from .backends.torch_batched import frame_batches

        def batches():
            for rate, image_ids, canvases in frame_batches(dataset, rates, batch, workers, imgsz=imgsz,
                                                           device=detector.device):
                size = dataset.size(dataset.image(image_ids[0]).shard_index)
                yield rate, image_ids, detector.predict_canvases(canvases, size, conf=conf, iou=iou, max_det=max_det)
    else:
        def batches():
            for rate in rates:
                for image_ids, arrays in _read_rgb(dataset, rate, batch):
                    yield rate, image_ids, detector.predict(arrays, imgsz=imgsz, conf=conf, iou=iou, max_det=max_det)
    records: list[dict] = []
    current = None
    done = set()
    for rate, image_ids, outputs in batches():
        if current is not None and rate != current:
            yield current, records
            done.add(current)
            records = []
        current = rate
        for image_id, (boxes, scores, class_ids) in zip(image_ids, outputs, strict=True):
            class_ids = np.asarray(class_ids, np.int64).reshape(-1)
            keep = np.isin(class_ids, np.asarray(classes, np.int64))
            records += coco_detections(image_id, np.asarray(boxes, np.float64).reshape(-1, 4)[keep],
                                       np.clip(np.asarray(scores, np.float64).reshape(-1), 0.0, 1.0)[keep],
                                       class_ids[keep])
        bar.update(len(image_ids))
    if current is not None:
        yield current, records
        done.add(current)
    for rate in rates:  # a dataset without frames: nothing was read at any rate
        if rate not in done:
            yield rate, []


INFERENCE_SETTINGS = ("imgsz", "batch", "conf", "iou", "max_det", "class_map", "device", "pt_backend",
                      "workers", "force", "trust_pickle")
""":func:`run_eval`'s arguments (and ``rainbench eval``'s flags) that only running detectors uses:
with ``predictions_dir`` (``--predictions``) a value other than the default is refused."""


def run_eval(data_dir: str | Path, out_dir: str | Path, *, predictions_dir: str | Path | None = None,
             weights: Sequence[str | Path] = (), imgsz: int | None = None, batch: int = 32, conf: float = 0.001,
             iou: float = 0.7, max_det: int = 300, report_conf: float = 0.25, n_boot: int = 1000,
             class_map: str | None = None, device: str | None = None, force: bool = False,
             progress: bool = True, trust_pickle: bool | None = None,
             classes: str | Sequence[int | str] | None = None,
             references: Sequence[tuple[str, str]] = (), metrics: str = DEFAULT_BACKEND,
             pt_backend: str = "batched", workers: int | None = None,
             ignore_regions: bool = True, targets: TargetFilter = TargetFilter()) -> EvalOutputs:
    """Evaluate every model at every rain rate of a dataset and write the outputs under ``out_dir``.

    Detections come either from ``predictions_dir`` (``<model>/rate_<rate_token>.json`` COCO
    results files, one per rate) or from running each of ``weights`` through
    :func:`rainbench.eval.backends.load_detector`; backend detections are cached as
    ``out_dir/predictions/<model>/rate_<rate>.json`` and reused by later runs with the same
    weights file and settings on the same images at that rate unless ``force``.

    ``imgsz``: letterbox size of every model; None gives each model its own
    (:func:`rainbench.eval.weights.model_imgsz`: the model's card, else 640).
    ``trust_pickle``: load ``.pt`` files that ultralytics' safe loading refuses with Python's
    full unpickler (see :func:`rainbench.eval.backends.load_detector`).

    ``classes``: the classes to score, names or ids (``"person,car,bus,truck"``, ``[2, 5, 7]``;
    :func:`rainbench.store.classes.parse_classes`); None scores the paper's four (0..3). Only
    they appear in the records, tables and plots, and detectors keep only them. Given
    explicitly, every model must be able to predict every one of them (a model that cannot:
    one-line error naming the model and the class).

    ``references``: ``(model, reference)`` pairs of the robustness comparison (``--compare``;
    :func:`rainbench.eval.comparison.comparison_references`), checked before any inference.

    ``pt_backend``: how ``.pt`` weights run (``--pt-backend``;
    :data:`rainbench.eval.backends.PT_BACKENDS`): "batched" (default: torch in batches, letterbox
    and NMS on the device, fp16 on CUDA) or "ultralytics" (its own predict, the reference).
    ``workers``: processes decoding shards for the batched backend (``--workers``; None:
    :func:`default_read_workers`).

    ``ignore_regions``: whether the shards' ignore regions (visible actors too small or too
    hidden to be labels) take part as COCO crowd boxes (default; :func:`ground_truth`), or are
    left out so that detections of them count as false positives (``--no-ignore-regions``).
    ``targets``: which labels are scored (``--min-height``, ``--min-visible``,
    ``--max-truncation``; :class:`TargetFilter`); the others become ignore regions.

    ``metrics``: the implementation of COCO's matching and AP (``--metrics``;
    :data:`rainbench.eval.metrics.coco.METRICS_BACKENDS`): "numpy" (default, vectorised) or
    "pycocotools" (the reference ``COCOeval``); the outputs are the same (to 1e-9).

    Outputs: ``metrics.json``, ``metrics.csv``, ``images.json``, ``report.md``,
    ``ap50_vs_rate.png``, ``f1_vs_rate.png``, ``detections_strip.png``, and with rate 0 and a
    rainy rate ``robustness.json`` (:func:`rainbench.eval.comparison.comparison_rows`: mPC and
    rPC with bootstrap intervals, paired differences between models; also in ``report.md``).
    They are written all or nothing (:func:`_write_outputs`): a failure while writing leaves none
    of them, and an OSError names the file.
    """
    arguments = locals()
    class_ids = _check_settings(predictions_dir, weights, imgsz=imgsz, batch=batch, max_det=max_det,
                                n_boot=n_boot, conf=conf, iou=iou, report_conf=report_conf, classes=classes,
                                metrics=metrics, pt_backend=pt_backend, workers=workers)
    if predictions_dir is not None:  # as the CLI refuses their flags: not silently ignored
        defaults = inspect.signature(run_eval).parameters
        for name in INFERENCE_SETTINGS:
            value = arguments[name]
            if value != defaults[name].default:
                raise EvalError(f"{name}: has no effect with predictions_dir (detections are read from "
                                f"its files, not inferred); leave it at {defaults[name].default!r}")
    dataset = open_dataset(data_dir)
    if not isinstance(targets, TargetFilter):
        raise EvalError(f"targets: expected a TargetFilter, got {type(targets).__name__}")
    gt = ground_truth(dataset, ignore_regions=ignore_regions, targets=targets)
    with locked_output_dir(out_dir, "eval", option="--out", error=EvalError) as out_dir:
        return _evaluate_into(dataset, gt, out_dir, predictions_dir=predictions_dir, weights=weights,
                              imgsz=imgsz, batch=batch, conf=conf, iou=iou, max_det=max_det,
                              report_conf=report_conf, n_boot=n_boot, class_map=class_map, device=device,
                              force=force, progress=progress, trust_pickle=trust_pickle, class_ids=class_ids,
                              classes_given=classes is not None, references=references, metrics=metrics,
                              pt_backend=pt_backend, workers=workers, ignore_regions=ignore_regions,
                              targets=targets)


def _evaluate_into(dataset: Dataset, gt: dict, out_dir: Path, *, predictions_dir, weights, imgsz, batch, conf,
                   iou, max_det, report_conf, n_boot, class_map, device, force, progress, trust_pickle,
                   class_ids, classes_given, references, metrics, pt_backend, workers, ignore_regions,
                   targets) -> EvalOutputs:
    """:func:`run_eval`'s work once its settings are checked and ``out_dir`` is locked."""
    rates = list(dataset.rates)
    image_ids = {image.image_id for image in dataset.images}
    inference_runs = 0
    if predictions_dir is not None:
        models = prediction_models(predictions_dir)
        _references(models, references)
        detections = {(model, rate): load_predictions_file(predictions_path(predictions_dir, model, rate),
                                                           image_ids, class_ids)
                      for model in models for rate in rates}
    else:
        models, detections, inference_runs = _backend_detections(
            dataset, list(weights), out_dir / "predictions", image_ids=image_ids, imgsz=imgsz, batch=batch,
            conf=conf, iou=iou, max_det=max_det, class_map=class_map, device=device, force=force,
            progress=progress, trust_pickle=trust_pickle, class_ids=class_ids,
            classes_given=classes_given, references=references, pt_backend=pt_backend,
            workers=default_read_workers() if workers is None else workers)
    records = _score(gt, detections, models, rates, class_ids=class_ids, report_conf=report_conf,
                     n_boot=n_boot, progress=progress, backend=metrics)
    robustness = []
    if 0.0 in rates and len(rates) > 1:
        robustness = comparison_rows(gt, {model: {rate: detections[(model, rate)] for rate in rates} for model in models},
                                     class_ids, n_boot, _references(models, references), backend=metrics)
    paths = _write_outputs(records, dataset, gt, detections, models, out_dir, class_ids=class_ids,
                           report_conf=report_conf, robustness=robustness, ignore_regions=ignore_regions,
                           targets=targets)
    return EvalOutputs(records=records, paths=paths, inference_runs=inference_runs, robustness=robustness)


def _references(models: Sequence[str], chosen: Sequence[tuple[str, str]]) -> dict[str, str]:
    """The robustness comparison's ``{model: reference}``; a chosen name that is not an evaluated
    model is an :class:`EvalError`."""
    try:
        return comparison_references(list(models), chosen)
    except ValueError as error:
        raise EvalError(str(error)) from None


def check_metrics(metrics: Any) -> str:
    """``metrics`` if it names a metrics backend (``--metrics``), else a one-line :class:`EvalError`."""
    if metrics not in METRICS_BACKENDS:
        raise EvalError(f"--metrics: expected one of {', '.join(METRICS_BACKENDS)}, got {metrics!r}")
    return metrics


def _check_settings(predictions_dir, weights, *, imgsz, batch, max_det, n_boot, conf, iou, report_conf,
                    classes, metrics, pt_backend="batched", workers=None) -> tuple[int, ...]:
    """Refuse bad evaluator settings before any work; returns the class ids to score."""
    from .backends import PT_BACKENDS

    if (predictions_dir is None) == (not weights):
        raise EvalError("expected exactly one of --weights or --predictions")
    check_metrics(metrics)
    if pt_backend not in PT_BACKENDS:
        raise EvalError(f"--pt-backend: expected one of {', '.join(PT_BACKENDS)}, got {pt_backend!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 0):
        raise EvalError(f"--workers: expected an integer >= 0, got {workers!r}")
    for name, value in (("--imgsz", imgsz), ("--batch", batch), ("--max-det", max_det), ("n_boot", n_boot)):
        if value is None:
            continue
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise EvalError(f"{name}: expected an integer >= 1, got {value!r}")
        if value < 1:
            raise EvalError(f"{name}: expected >= 1, got {value}")
    for name, value in (("--conf", conf), ("--iou", iou), ("--report-conf", report_conf)):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
                or not 0.0 <= float(value) <= 1.0:
            raise EvalError(f"{name}: expected a value in [0, 1], got {value!r}")
    try:
        return PAPER_CLASSES if classes is None else parse_classes(classes)
    except ValueError as error:
        raise EvalError(str(error)) from None


def _backend_detections(dataset: Dataset, specs: list, cache_root: Path, *, image_ids: set[int], imgsz, batch,
                        conf, iou, max_det, class_map, device, force, progress, trust_pickle,
                        class_ids: Sequence[int], classes_given: bool, references: Sequence[tuple[str, str]] = (),
                        pt_backend: str = "batched", workers: int = 0
                        ) -> tuple[list[str], dict[tuple[str, float], list[dict]], int]:
    """Detections of every weights file at every rate of ``dataset``: (model names, {(model, rate):
    COCO results records}, number of (model, rate) pairs inferred in this run). Backend
    detections are cached under ``cache_root/<model>/`` and reused unless ``force``: a rate's
    file only while the weights and settings are those of ``settings.json`` and the rate's images
    are those it was inferred on (``settings.json``'s ``"images"``: the
    :meth:`~rainbench.store.Dataset.images_fingerprint` of each rate token), so a dataset
    regenerated in place (another seed, other rain) is inferred again."""
    from tqdm import tqdm

    from . import backends
    from . import weights as registry
    from .backends.classes import parse_class_map

    rates = list(dataset.rates)
    fingerprints = {rate_token(rate): dataset.images_fingerprint(rate) for rate in rates}
    resolved = [registry.resolve_weights(w, device) for w in specs]
    if class_map is not None:
        parse_class_map(class_map)  # fail early on a bad spec
    models = [name for _, name in resolved]
    duplicates = sorted({m for m in models if models.count(m) > 1})
    if duplicates:
        raise EvalError(f"--weights: several weights files are named {duplicates[0]!r}; model names "
                        "(file stems) must be unique")
    _references(models, references)
    # First load (and check) every detector that has rates to infer, then infer: a model that
    # cannot predict a requested class fails the run before any inference.
    plans = []
    for spec, (path, model) in zip(specs, resolved, strict=True):
        model_imgsz = registry.model_imgsz(spec) if imgsz is None else imgsz
        settings = _cache_settings(path, imgsz=model_imgsz, conf=conf, iou=iou, max_det=max_det,
                                   class_map=class_map, classes=class_ids, pt_backend=pt_backend, device=device,
                                   trained=registry.trained_classes(spec))
        meta_path = cache_root / model / "settings.json"
        try:
            cached_settings = json.loads(meta_path.read_text(encoding="utf-8"))
            cached_images = cached_settings.pop("images")
        except (OSError, ValueError, AttributeError, KeyError):
            cached_settings, cached_images = None, None
        reuse = not force and cached_settings == settings
        fresh = {rate for rate in rates if reuse and isinstance(cached_images, dict)
                 and cached_images.get(rate_token(rate)) == fingerprints[rate_token(rate)]
                 and predictions_path(cache_root, model, rate).is_file()}
        detector = None
        if len(fresh) < len(rates):
            extra = {"pt_backend": pt_backend}
            if trust_pickle is not None:
                extra["trust_pickle"] = trust_pickle
            if classes_given:
                extra["classes"] = class_ids
            detector = backends.load_detector(spec, class_map=class_map, device=device, **extra)
            if classes_given:
                backends.check_model_classes(detector, model, class_ids)
            # Rate files are about to change: until all are written again no cache is trusted.
            meta_path.unlink(missing_ok=True)
        plans.append((model, model_imgsz, settings, meta_path, fresh, detector))
    detections: dict[tuple[str, float], list[dict]] = {}
    inference_runs = 0
    for model, model_imgsz, settings, meta_path, fresh, detector in plans:
        for rate in fresh:
            detections[(model, rate)] = load_predictions_file(predictions_path(cache_root, model, rate), image_ids,
                                                              class_ids, cache=True)
        stale = [rate for rate in rates if rate not in fresh]
        if stale:
            rate_names = ", ".join(rate_token(rate) for rate in stale)
            with tqdm(total=len(dataset) * len(stale), unit="img", desc=f"{model} at {rate_names} mm/h",
                      disable=not progress, dynamic_ncols=True) as bar:
                for rate, records in _infer(detector, dataset, stale, batch=batch, imgsz=model_imgsz, conf=conf,
                                            iou=iou, max_det=max_det, bar=bar, classes=class_ids, workers=workers):
                    if classes_given:  # an ONNX file without names learns its classes at its first batch
                        backends.check_model_classes(detector, model, class_ids)
                    _write_json(predictions_path(cache_root, model, rate), records)
                    detections[(model, rate)] = records
                    inference_runs += 1
        if detector is not None:
            # Written once every rate is cached, so an interrupted run re-infers what is stale.
            _write_json(meta_path, {**settings, "images": fingerprints})
    return models, detections, inference_runs


def _score(gt: dict, detections: dict, models: Sequence[str], rates: Sequence[float], *,
           class_ids: Sequence[int], report_conf: float, n_boot: int, progress: bool,
           backend: str) -> list[dict[str, Any]]:
    """Metric records (:func:`rainbench.eval.report.records.metric_records`) of every model and rate,
    with bootstrap intervals of AP50 and AP50:95, computed by the metrics ``backend``."""
    from tqdm import tqdm

    results, ci50, ci5095 = {}, {}, {}
    with tqdm(total=len(models) * len(rates), unit="eval", desc="metrics", disable=not progress,
              dynamic_ncols=True) as bar:
        for model in models:
            for rate in rates:
                dets = detections[(model, rate)]
                results[(model, rate)] = evaluate(gt, dets, class_ids=class_ids, conf=report_conf, backend=backend)
                rng = np.random.default_rng(BOOTSTRAP_SEED)
                ci50[(model, rate)] = bootstrap_ci(gt, dets, n_boot, rng=rng, metric="ap50", class_ids=class_ids,
                                                   backend=backend)
                ci5095[(model, rate)] = bootstrap_ci(gt, dets, n_boot, rng=rng, metric="ap50_95",
                                                     class_ids=class_ids, backend=backend)
                bar.update(1)
    clean_rate = 0.0 if 0.0 in rates else rates[0]
    return metric_records(results, [ci50, ci5095], clean_rate=clean_rate)


def _strip_image(dataset: Dataset, gt: dict, class_ids: Sequence[int]) -> Image:
    """The frame of the detection strip: the one with the most labels of the scored classes (the
    first such)."""
    counts: dict[int, int] = {}
    for annotation in gt["annotations"]:
        if annotation["category_id"] in class_ids and not annotation["iscrowd"]:
            counts[annotation["image_id"]] = counts.get(annotation["image_id"], 0) + 1
    return max(dataset.images, key=lambda image: counts.get(image.image_id, 0))


REPORT_OUTPUTS = ("metrics.json", "metrics.csv", "images.json", "robustness.json", "ap50_vs_rate.png",
                  "f1_vs_rate.png", "detections_strip.png", "report.md")
"""The report files :func:`run_eval` writes under ``--out`` (``robustness.json`` only with rate 0
and a rainy rate), in the order they are put in place: ``report.md`` last."""


def _write_outputs(records: list[dict[str, Any]], dataset: Dataset, gt: dict, detections: dict,
                   models: Sequence[str], out_dir: Path, *, class_ids: Sequence[int],
                   report_conf: float, robustness: list[dict[str, Any]],
                   ignore_regions: bool = True, targets: TargetFilter = TargetFilter()) -> dict[str, Path]:
    """Write metrics, image list, robustness rows (when there are any), report, plots and the
    detection strip (the first model's boxes of the scored classes, across rates); returns the
    paths by output name.

    All or nothing: the previous run's outputs (:data:`REPORT_OUTPUTS`) are removed first, every
    file is written into a hidden staging folder in ``out_dir`` and only once all are written
    are they renamed into place (``os.replace``, same file system); any failure removes the
    staging folder and whatever was already renamed, so no output is left under its final name.
    An OSError names the file (``OUT/report.md: No space left on device``)."""
    rates = list(dataset.rates)
    clean_rate = 0.0 if 0.0 in rates else rates[0]
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise file_error(error, out_dir) from error
    for name in REPORT_OUTPUTS:  # a stale report must not pass for this run's
        try:
            (out_dir / name).unlink(missing_ok=True)
        except OSError as error:
            raise file_error(error, out_dir / name) from error
    for stale in out_dir.glob(".report.tmp-*"):  # the staging folder of a run killed while writing
        shutil.rmtree(stale, ignore_errors=True)
    try:
        staging = Path(tempfile.mkdtemp(prefix=".report.tmp-", dir=out_dir))
    except OSError as error:
        raise file_error(error, out_dir) from error
    placed: list[Path] = []
    try:
        def stage(name: str, write) -> None:
            try:
                write(staging / name)
            except OSError as error:
                message = " ".join(str(error).split())
                if error.strerror or str(staging) not in message:
                    raise file_error(error, out_dir / name) from error
                named = OSError(message.replace(str(staging), str(out_dir)))
                named.errno = error.errno
                raise named from error

        def json_file(data: Any):
            return lambda path: path.write_text(json.dumps(data, indent=1, allow_nan=False) + "\n",
                                                encoding="utf-8")

        stage("metrics.json", lambda path: write_metrics(records, path.parent))  # and metrics.csv
        stage("images.json", json_file([{"id": image.image_id, "shard": image.shard.name, "frame": image.frame}
                                        for image in dataset.images]))
        if robustness:
            stage("robustness.json", json_file([{key: json_ready(value) for key, value in row.items()}
                                                for row in robustness]))
        ignored: dict[str, int] | bool = False
        if ignore_regions:
            ignored = {CLASS_NAMES[c]: sum(1 for a in gt["annotations"] if a["iscrowd"] and a["category_id"] == c)
                       for c in class_ids}
        report = render_report_md(records, paper=PAPER_TABLES, clean_rate=clean_rate, robustness=robustness,
                                  ignore_regions=ignored,
                                  scored_labels=None if targets.scores_everything else targets.describe())
        stage("report.md", lambda path: path.write_text(report, encoding="utf-8"))
        stage("ap50_vs_rate.png", lambda path: plot_metric_vs_rate(records, "ap50", path))
        stage("f1_vs_rate.png", lambda path: plot_metric_vs_rate(records, "f1", path))
        strip = _strip_image(dataset, gt, class_ids)
        with dataset.open(strip.shard_index) as handle:
            frames_by_rate = {rate: dataset.read_rgb(handle, strip, rate) for rate in rates}
        strip_dets = {rate: [d for d in detections[(models[0], rate)] if d["image_id"] == strip.image_id]
                      for rate in rates}
        stage("detections_strip.png", lambda path: plot_detection_strip(frames_by_rate, strip_dets, path,
                                                                        class_names=CLASS_NAMES,
                                                                        min_score=report_conf))
        paths: dict[str, Path] = {}
        for name in REPORT_OUTPUTS:
            if not (staging / name).is_file():
                continue
            try:
                os.replace(staging / name, out_dir / name)
            except OSError as error:
                raise file_error(error, out_dir / name) from error
            placed.append(out_dir / name)
            paths[name] = out_dir / name
        return paths
    except BaseException:
        for path in placed:
            _remove(path)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
