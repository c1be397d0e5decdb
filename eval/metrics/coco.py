"""COCO set-up and matching: the one place rainbench evaluates detections the COCO way.

:func:`coco_ground_truth` and :func:`coco_detections` turn per-image arrays into COCO dicts and
results records; :func:`run_cocoeval` validates them and runs COCO's bbox evaluation with
rainbench's parameters (maxDets 100, the given area ranges and IoU thresholds) through one of two
backends (``METRICS_BACKENDS``): "numpy", the vectorised matching of
:mod:`rainbench.eval.metrics.matching` and the accumulation of
:mod:`rainbench.eval.metrics.accumulate` (the default), or "pycocotools", the reference
``COCOeval``. Every metric that needs COCO (AP, the YOLO F1 matches, the AP breakdowns, the
bootstrap) goes through it; :func:`class_matches` and :func:`ap_per_iou` read its results, the
same arrays whatever the backend. Conventions: see :mod:`rainbench.eval.metrics`.
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval, Params

from rainbench.store.classes import PAPER_CLASS_NAMES, PAPER_CLASSES

from .accumulate import interpolated_ap
from .matching import match_boxes

IOU_THRESHOLDS: np.ndarray = Params(iouType="bbox").iouThrs.copy()
"""(10,) float64 COCO IoU thresholds 0.50:0.05:0.95, exactly as pycocotools builds them."""

METRICS_BACKENDS = ("numpy", "pycocotools")
"""Implementations of COCO's bbox evaluation: "numpy" (vectorised, :mod:`.matching` and
:mod:`.accumulate`) and "pycocotools" (``COCOeval``, the reference); same matches and AP."""

DEFAULT_BACKEND = "numpy"
"""The metrics backend used unless another is asked for (``rainbench eval --metrics``)."""

MAX_DETECTIONS = 100
"""Detections kept per image and class (COCO maxDets; the largest of COCO's default [1, 10, 100])."""

AREA_ALL: tuple[float, float] = (0.0, 1e5**2)
"""COCO "all" area range in squared pixels."""


@dataclass(frozen=True)
class ClassMatches:
    """COCOeval's matching of one class, concatenated over images in COCO's accumulate order.

    Detections are those COCOeval keeps (top ``MAX_DETECTIONS`` per image), ordered as
    ``COCOeval.accumulate`` orders them: images in ascending id, detections by descending score
    within an image, then a stable (mergesort) sort by descending score.

    Attributes:
        class_id (int): COCO-80 class id.
        image_ids (np.ndarray): (N,) int64 evaluated image ids, ascending.
        iou_thresholds (np.ndarray): (T,) float64 IoU thresholds of the matching.
        scores (np.ndarray): (D,) float64 detection scores, descending.
        true_positive (np.ndarray): (T, D) bool, detection matched to a ground truth at IoU
            threshold t (matched to an ignored ground truth also counts as matched here).
        ignored (np.ndarray): (T, D) bool, COCO ``dtIgnore``: matched to an ignored / crowd /
            out-of-range ground truth, or unmatched and outside the area range. Ignored
            detections are neither TP nor FP.
        image_index (np.ndarray): (D,) int64 index into ``image_ids`` of each detection.
        n_gt_per_image (np.ndarray): (N,) int64 non-ignored ground truths per image.
    """

    class_id: int
    image_ids: np.ndarray
    iou_thresholds: np.ndarray
    scores: np.ndarray
    true_positive: np.ndarray
    ignored: np.ndarray
    image_index: np.ndarray
    n_gt_per_image: np.ndarray


def _as_positive_int(value: Any, what: str) -> int:
    """Return ``value`` as a Python int >= 1 or raise a one-line ValueError naming ``what``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{what}: expected a positive int, got {value!r} ({type(value).__name__})")
    if value < 1:
        raise ValueError(f"{what}: expected a positive int, got {value}")
    return int(value)


def _check_known_class_ids(class_ids: np.ndarray, known: Sequence[int], what: str) -> None:
    """Raise if any entry of the (M,) int array ``class_ids`` is not in ``known``."""
    unknown = sorted(set(class_ids.tolist()) - set(known))
    if unknown:
        raise ValueError(f"{what}: unknown class id(s) {unknown}, expected ids in {tuple(known)}")


def coco_ground_truth(
    images: Sequence[tuple], class_names: Sequence[str] = PAPER_CLASS_NAMES
) -> dict[str, list[dict]]:
    """Build a COCO ground-truth dict from per-image arrays.

    Args:
        images: Sequence of ``(image_id, width, height, boxes, class_ids)`` or
            ``(image_id, width, height, boxes, class_ids, ignore)`` tuples, one per image:
            ``image_id`` a unique positive int; ``width``, ``height`` positive ints (pixels);
            ``boxes`` (M, 4) float array (float32 in the dataset), x1, y1, x2, y2 pixel-edge
            coordinates with ``x2 >= x1`` and ``y2 >= y1``; ``class_ids`` (M,) int array of ids
            into ``class_names``; ``ignore`` (M,) bool array, optional.
        class_names: Category names; category id ``i`` is ``class_names[i]``. The default is
            the paper's four classes (ids 0..3); pass ``CLASS_NAMES`` for ids 0..7 (bus 5,
            truck 7), as the evaluation pipeline does.

    Returns:
        A COCO dict ``{"images", "annotations", "categories"}``. Annotation ids run from 1,
        ``bbox`` is ``[x1, y1, x2 - x1, y2 - y1]`` and ``area`` is the box area (so COCO's
        small/medium/large ranges apply to box area).

    Ignored boxes (``ignore=True``, e.g. objects filtered out as too small or too occluded to be
    fair targets) are written with ``iscrowd=1`` (and ``ignore=1`` for readers). That is the only
    ignore flag pycocotools honours: COCOeval overwrites ``ignore`` with ``iscrowd``. An ignored
    box is never a false negative, and a detection that matches it is neither TP nor FP. Because
    COCOeval matches crowd boxes by intersection over the *detection's* area (not IoU), a
    detection lying at least 50 % inside an ignored box is absorbed by it (and several may be);
    a detection much larger than the ignored box is still a false positive when it matches
    nothing else.
    """
    known_ids = tuple(range(len(class_names)))
    coco_images: list[dict] = []
    annotations: list[dict] = []
    seen_ids: set[int] = set()
    for position, entry in enumerate(images):
        if len(entry) not in (5, 6):
            raise ValueError(
                f"images[{position}]: expected (image_id, width, height, boxes, class_ids[, ignore]), "
                f"got a {len(entry)}-tuple"
            )
        image_id = _as_positive_int(entry[0], f"images[{position}] image_id")
        if image_id in seen_ids:
            raise ValueError(f"images[{position}]: image_id {image_id} is repeated, expected unique ids")
        seen_ids.add(image_id)
        width = _as_positive_int(entry[1], f"image {image_id} width")
        height = _as_positive_int(entry[2], f"image {image_id} height")
        boxes = np.asarray(entry[3], dtype=np.float64)
        if boxes.size == 0:
            boxes = boxes.reshape(0, 4)
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise ValueError(f"image {image_id} boxes: expected shape (M, 4), got {boxes.shape}")
        class_ids = np.asarray(entry[4])
        if class_ids.size == 0:
            class_ids = class_ids.reshape(0).astype(np.int64)
        if class_ids.shape != (len(boxes),):
            raise ValueError(
                f"image {image_id} class_ids: expected shape ({len(boxes)},) to match boxes, got {class_ids.shape}"
            )
        if not np.issubdtype(class_ids.dtype, np.integer):
            raise ValueError(f"image {image_id} class_ids: expected an integer array, got dtype {class_ids.dtype}")
        _check_known_class_ids(class_ids, known_ids, f"image {image_id} class_ids")
        if len(entry) == 6 and entry[5] is not None:
            ignore = np.asarray(entry[5])
            if ignore.shape != (len(boxes),) or ignore.dtype != np.bool_:
                raise ValueError(
                    f"image {image_id} ignore: expected a bool array of shape ({len(boxes)},), "
                    f"got {ignore.dtype} {ignore.shape}"
                )
        else:
            ignore = np.zeros(len(boxes), dtype=bool)
        if not np.all(np.isfinite(boxes)):
            raise ValueError(f"image {image_id} boxes: expected finite coordinates, got nan or inf")
        bad = np.flatnonzero((boxes[:, 2] < boxes[:, 0]) | (boxes[:, 3] < boxes[:, 1]))
        if bad.size:
            raise ValueError(
                f"image {image_id} box {int(bad[0])}: expected x1 <= x2 and y1 <= y2 (xyxy), "
                f"got {boxes[bad[0]].tolist()}"
            )
        coco_images.append({"id": image_id, "width": width, "height": height})
        widths = boxes[:, 2] - boxes[:, 0]
        heights = boxes[:, 3] - boxes[:, 1]
        for box, box_width, box_height, class_id, is_ignored in zip(
            boxes.tolist(), widths.tolist(), heights.tolist(), class_ids.tolist(), ignore.tolist(), strict=True
        ):
            annotations.append(
                {
                    "id": len(annotations) + 1,
                    "image_id": image_id,
                    "category_id": int(class_id),
                    "bbox": [box[0], box[1], box_width, box_height],
                    "area": box_width * box_height,
                    "iscrowd": int(is_ignored),
                    "ignore": int(is_ignored),
                }
            )
    categories = [{"id": i, "name": name, "supercategory": "object"} for i, name in enumerate(class_names)]
    return {"images": coco_images, "annotations": annotations, "categories": categories}


def coco_detections(
    image_id: int, boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray
) -> list[dict[str, Any]]:
    """Convert one image's detector output to COCO results records.

    Args:
        image_id: Positive int image id.
        boxes: (D, 4) float array, x1, y1, x2, y2 pixel-edge coordinates (x2 >= x1, y2 >= y1).
        scores: (D,) float array of confidences in [0, 1].
        class_ids: (D,) int array of COCO-80 class ids.

    Returns:
        D records ``{"image_id", "category_id", "bbox": [x, y, w, h], "score"}``.
    """
    image_id = _as_positive_int(image_id, "image_id")
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.size == 0:
        boxes = boxes.reshape(0, 4)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"boxes: expected shape (D, 4), got {boxes.shape}")
    scores = np.asarray(scores, dtype=np.float64).reshape(-1) if np.size(scores) else np.zeros(0)
    class_ids = np.asarray(class_ids).reshape(-1) if np.size(class_ids) else np.zeros(0, np.int64)
    if scores.shape != (len(boxes),) or class_ids.shape != (len(boxes),):
        raise ValueError(
            f"scores/class_ids: expected shape ({len(boxes)},) to match boxes, got {scores.shape} and {class_ids.shape}"
        )
    if not np.issubdtype(class_ids.dtype, np.integer):
        raise ValueError(f"class_ids: expected an integer array, got dtype {class_ids.dtype}")
    if not (np.isfinite(boxes).all() and np.isfinite(scores).all()):
        raise ValueError(f"boxes/scores of image {image_id}: expected finite values, got NaN or inf "
                         "(a detector's broken output)")
    if np.any((boxes[:, 2] < boxes[:, 0]) | (boxes[:, 3] < boxes[:, 1])):
        raise ValueError("boxes: expected x1 <= x2 and y1 <= y2 (xyxy), got a box with x2 < x1 or y2 < y1")
    xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], axis=1)
    return [
        {"image_id": image_id, "category_id": int(c), "bbox": b, "score": float(s)}
        for b, s, c in zip(xywh.tolist(), scores.tolist(), class_ids.tolist(), strict=True)
    ]


def validate_gt_dict(gt_dict: Mapping[str, Any]) -> None:
    """Check the parts of a COCO ground-truth dict that COCOeval silently misreads."""
    for key in ("images", "annotations", "categories"):
        if key not in gt_dict:
            raise ValueError(f"gt_dict: expected keys images/annotations/categories, missing {key!r}")
    if not gt_dict["images"]:
        raise ValueError("gt_dict: expected at least one image, got none")
    required = ("id", "image_id", "category_id", "bbox", "area", "iscrowd")
    for position, ann in enumerate(gt_dict["annotations"]):
        missing = [key for key in required if key not in ann]
        if missing:
            raise ValueError(f"gt_dict annotations[{position}]: expected keys {required}, missing {missing}")
    ann_ids = [ann["id"] for ann in gt_dict["annotations"]]
    if any(not isinstance(i, (int, np.integer)) or i < 1 for i in ann_ids):
        raise ValueError("gt_dict annotations: expected int ids >= 1 (COCOeval reads id 0 as unmatched), got others")
    if len(set(ann_ids)) != len(ann_ids):
        raise ValueError("gt_dict annotations: expected unique ids, got repeated ids")


def _quiet() -> contextlib.AbstractContextManager:
    """Context manager silencing pycocotools' prints."""
    return contextlib.redirect_stdout(io.StringIO())


def check_backend(backend: Any) -> str:
    """Return ``backend`` if it names a metrics backend, else raise a one-line ValueError."""
    if not isinstance(backend, str) or backend not in METRICS_BACKENDS:
        raise ValueError(f"metrics backend: expected one of {', '.join(METRICS_BACKENDS)}, got {backend!r}")
    return backend


@dataclass(frozen=True)
class _DetectionTable:
    """Validated detection records as arrays, in record order (record k has COCO id k + 1).

    Attributes:
        image_id (np.ndarray): (D,) int64 image ids.
        category_id (np.ndarray): (D,) int64 category ids.
        bbox (np.ndarray): (D, 4) float64 ``[x, y, w, h]`` boxes.
        score (np.ndarray): (D,) float64 scores in [0, 1].
        area (np.ndarray): (D,) float64 area of the area-range test (``w * h`` unless replaced).
    """

    image_id: np.ndarray
    category_id: np.ndarray
    bbox: np.ndarray
    score: np.ndarray
    area: np.ndarray


def _detection_columns(detections: Sequence[Mapping[str, Any]]) -> tuple[list, list, list, list, int | None]:
    """``(image_ids, category_ids, bboxes, scores, broken)``: the fields of the records before the
    first one that is not a dict with all four fields (``broken``, its position; None when all are)."""
    records = list(detections)
    broken = None
    try:
        columns = [[record[key] for record in records] for key in ("image_id", "category_id", "bbox", "score")]
    except (KeyError, TypeError):
        for position, record in enumerate(records):
            try:
                record["image_id"], record["category_id"], record["bbox"], record["score"]
            except (KeyError, TypeError):
                broken = position
                break
        records = records[:broken]
        columns = [[record[key] for record in records] for key in ("image_id", "category_id", "bbox", "score")]
    return columns[0], columns[1], columns[2], columns[3], broken


def _detection_table(
    detections: Sequence[Mapping[str, Any]],
    known_images: Collection[Any],
    known_categories: Collection[Any],
    area_override: float | None = None,
) -> _DetectionTable:
    """Validate COCO results records (the first bad record raises a one-line ValueError naming it)
    and return them as arrays. ``area_override`` replaces every detection's area (used by the
    visibility breakdown)."""
    image_ids, category_ids, bboxes, scores, broken = _detection_columns(detections)
    n = len(image_ids)
    bad_image = np.fromiter((i not in known_images for i in image_ids), dtype=bool, count=n)
    bad_category = np.fromiter((c not in known_categories for c in category_ids), dtype=bool, count=n)
    try:
        boxes = np.asarray(bboxes, dtype=np.float64) if n else np.zeros((0, 4))
    except (ValueError, TypeError):
        boxes = np.zeros((n, 0))
    if boxes.shape == (n, 4):
        bad_length = np.zeros(n, dtype=bool)
    else:  # ragged: the records with four numbers are converted one by one
        bad_length = np.fromiter((not hasattr(b, "__len__") or len(b) != 4 for b in bboxes), dtype=bool, count=n)
        boxes = np.array([[float(v) for v in b] if not bad else [np.nan] * 4 for b, bad in zip(bboxes, bad_length)],
                         dtype=np.float64).reshape(n, 4)
    bad_box = ~bad_length & ~(np.all(np.isfinite(boxes), axis=1) & (boxes[:, 2] >= 0) & (boxes[:, 3] >= 0))
    score = np.asarray(scores, dtype=np.float64).reshape(n)
    bad_score = ~((score >= 0.0) & (score <= 1.0))
    bad = np.flatnonzero(bad_image | bad_category | bad_length | bad_box | bad_score)
    if bad.size:
        position = int(bad[0])
        if bad_image[position]:
            raise ValueError(f"detections[{position}]: image_id {image_ids[position]!r} is not in the ground truth")
        if bad_category[position]:
            raise ValueError(f"detections[{position}]: unknown category_id {category_ids[position]!r}, "
                             f"expected one of {sorted(known_categories)}")
        if bad_length[position]:
            raise ValueError(f"detections[{position}] bbox: expected [x, y, w, h], got {bboxes[position]!r}")
        if bad_box[position]:
            raise ValueError(f"detections[{position}] bbox: expected finite [x, y, w, h] with w, h >= 0, "
                             f"got {bboxes[position]!r}")
        raise ValueError(
            f"detections[{position}] score: expected a confidence in [0, 1], got {float(score[position])!r}"
        )
    if broken is not None:
        record = list(detections)[broken]
        raise ValueError(
            f"detections[{broken}]: expected a dict with image_id, category_id, bbox, score, got {record!r}"
        )
    area = boxes[:, 2] * boxes[:, 3] if area_override is None else np.full(n, float(area_override))
    return _DetectionTable(
        image_id=np.asarray(image_ids).astype(np.int64).reshape(n),
        category_id=np.asarray(category_ids).astype(np.int64).reshape(n),
        bbox=boxes,
        score=score,
        area=area,
    )


def _coco_from_gt(gt_dict: Mapping[str, Any], area_override: Sequence[float] | None = None) -> COCO:
    """Index a COCO ground-truth dict; annotation dicts are copied (COCOeval writes into them)."""
    annotations = [dict(ann) for ann in gt_dict["annotations"]]
    if area_override is not None:
        for ann, area in zip(annotations, area_override, strict=True):
            ann["area"] = float(area)
    coco = COCO()
    coco.dataset = {
        "images": [dict(image) for image in gt_dict["images"]],
        "annotations": annotations,
        "categories": [dict(category) for category in gt_dict["categories"]],
    }
    with _quiet():
        coco.createIndex()
    return coco


def _coco_from_detections(coco_gt: COCO, table: _DetectionTable) -> COCO:
    """Index validated detections as a COCO results object.

    Equivalent to ``coco_gt.loadRes(detections)`` for bbox results (ids from 1, ``area = w * h``
    unless replaced, ``iscrowd = 0``) but builds new records instead of mutating them, and accepts
    no detections (``loadRes`` raises IndexError on an empty list).
    """
    annotations = [
        {"id": position + 1, "image_id": image_id, "category_id": category_id, "bbox": bbox, "score": score,
         "area": area, "iscrowd": 0}
        for position, (image_id, category_id, bbox, score, area) in enumerate(
            zip(table.image_id.tolist(), table.category_id.tolist(), table.bbox.tolist(), table.score.tolist(),
                table.area.tolist(), strict=True)
        )
    ]
    coco = COCO()
    coco.dataset = {
        "images": list(coco_gt.dataset["images"]),
        "annotations": annotations,
        "categories": list(coco_gt.dataset["categories"]),
    }
    with _quiet():
        coco.createIndex()
    return coco


def _check_class_ids(class_ids: Sequence[int], known: Collection[Any]) -> list[int]:
    """Return ``class_ids`` as a list of ints, all present among the ground-truth categories."""
    ids = [int(c) for c in class_ids]
    if not ids:
        raise ValueError("class_ids: expected at least one class id, got none")
    if len(set(ids)) != len(ids):
        raise ValueError(f"class_ids: expected unique ids, got {ids}")
    unknown = [c for c in ids if c not in known]
    if unknown:
        raise ValueError(f"class_ids: unknown class id(s) {unknown}, expected ids in {sorted(known)}")
    return ids


def _check_image_ids(image_ids: Sequence[int] | None, known: Collection[Any]) -> np.ndarray:
    """The evaluated image ids as COCOeval uses them: (N,) int64, ascending, unique (all
    ground-truth images when None), validated."""
    if image_ids is None:
        return np.unique(np.asarray(list(known), dtype=np.int64))
    ids = [int(i) for i in image_ids]
    if not ids:
        raise ValueError("image_ids: expected at least one image id, got none")
    missing = [i for i in ids if i not in known]
    if missing:
        raise ValueError(f"image_ids: {missing[:5]} not in the ground truth")
    return np.unique(np.asarray(ids, dtype=np.int64))


@dataclass(frozen=True)
class CocoEvaluation:
    """COCO matching (and AP) of one detection set, the same whatever the backend.

    Attributes:
        backend (str): The metrics backend that computed it (``METRICS_BACKENDS``).
        class_ids (list[int]): The evaluated class ids, validated, in the requested order.
        image_ids (np.ndarray): (N,) int64 evaluated image ids, ascending.
        iou_thresholds (np.ndarray): (T,) float64 IoU thresholds.
        matches (tuple[dict[int, ClassMatches], ...]): per area range, ``{class_id:
            ClassMatches}`` in ascending class id order.
        ap (tuple[dict[int, np.ndarray], ...] | None): per area range, ``{class_id: (T,) float64
            AP per IoU threshold}`` (nan where the class has no non-ignored ground truth); None
            when run without ``accumulate``.
    """

    backend: str
    class_ids: list[int]
    image_ids: np.ndarray
    iou_thresholds: np.ndarray
    matches: tuple[dict[int, ClassMatches], ...]
    ap: tuple[dict[int, np.ndarray], ...] | None


def run_cocoeval(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    class_ids: Sequence[int],
    image_ids: Sequence[int] | None = None,
    *,
    area_ranges: Sequence[tuple[float, float]] = (AREA_ALL,),
    iou_thresholds: np.ndarray = IOU_THRESHOLDS,
    accumulate: bool = True,
    gt_areas: Sequence[float] | None = None,
    detection_area: float | None = None,
    backend: str = DEFAULT_BACKEND,
) -> CocoEvaluation:
    """Validate the inputs and run COCO's bbox evaluation with rainbench's parameters.

    The one COCO set-up of rainbench: bbox IoU, maxDets ``MAX_DETECTIONS``, one area range per
    entry of ``area_ranges``, the given IoU thresholds. ``backend`` "numpy" matches with
    :func:`rainbench.eval.metrics.matching.match_boxes` and accumulates with
    :func:`rainbench.eval.metrics.accumulate.interpolated_ap`; "pycocotools" indexes the inputs as
    pycocotools ``COCO`` objects and runs ``COCOeval`` (evaluate, accumulate) quietly, reading
    ``evalImgs`` and ``eval["precision"]`` back. Both give the same matches and AP (the tests
    hold them equal to 1e-9 on every figure).

    Args:
        gt_dict: COCO ground-truth dict (see :func:`coco_ground_truth`); copied, not modified.
        detections: COCO results records (bbox ``[x, y, w, h]`` in pixels, score in [0, 1]);
            copied, not modified; may be empty.
        class_ids: Class ids to evaluate (unique, all ground-truth categories).
        image_ids: Images to evaluate; all ground-truth images when None.
        area_ranges: (lo, hi) area ranges of COCOeval's area-range test, squared pixels.
        iou_thresholds: (T,) float64 IoU thresholds.
        accumulate: Also compute AP (``CocoEvaluation.ap``); the matches are always computed.
        gt_areas: (A,) float areas replacing the annotations' ``area`` (aligned with
            ``gt_dict["annotations"]``), or None to keep them.
        detection_area: One area given to every detection instead of ``w * h``, or None.
        backend: "numpy" (default) or "pycocotools" (the reference), ``METRICS_BACKENDS``.

    Returns:
        The :class:`CocoEvaluation`.
    """
    backend = check_backend(backend)
    validate_gt_dict(gt_dict)
    known_images = {image["id"] for image in gt_dict["images"]}
    known_categories = {category["id"] for category in gt_dict["categories"]}
    class_ids = _check_class_ids(class_ids, known_categories)
    evaluated_images = _check_image_ids(image_ids, known_images)
    table = _detection_table(detections, known_images, known_categories, area_override=detection_area)
    iou_thresholds = np.asarray(iou_thresholds, dtype=np.float64)
    run = _numpy_evaluation if backend == "numpy" else _pycocotools_evaluation
    matches, ap = run(gt_dict, table, sorted(class_ids), evaluated_images, area_ranges=area_ranges,
                      iou_thresholds=iou_thresholds, accumulate=accumulate, gt_areas=gt_areas)
    return CocoEvaluation(backend=backend, class_ids=class_ids, image_ids=evaluated_images,
                          iou_thresholds=iou_thresholds, matches=matches, ap=ap)


def _accumulate_order(
    class_id: int,
    image_ids: np.ndarray,
    iou_thresholds: np.ndarray,
    scores: np.ndarray,
    true_positive: np.ndarray,
    ignored: np.ndarray,
    image_index: np.ndarray,
    n_gt_per_image: np.ndarray,
) -> ClassMatches:
    """:class:`ClassMatches` from one class's detections given image by image (ascending images,
    each image's by descending score): (D,) ``scores``, (T, D) ``true_positive`` / ``ignored``,
    (D,) ``image_index``; puts them in ``COCOeval.accumulate``'s order (a stable sort by
    descending score)."""
    order = np.argsort(-scores, kind="mergesort")
    return ClassMatches(
        class_id=int(class_id),
        image_ids=image_ids,
        iou_thresholds=iou_thresholds,
        scores=scores[order],
        true_positive=true_positive[:, order],
        ignored=ignored[:, order],
        image_index=image_index[order],
        n_gt_per_image=n_gt_per_image,
    )


def _numpy_evaluation(
    gt_dict: Mapping[str, Any],
    table: _DetectionTable,
    class_ids: list[int],
    image_ids: np.ndarray,
    *,
    area_ranges: Sequence[tuple[float, float]],
    iou_thresholds: np.ndarray,
    accumulate: bool,
    gt_areas: Sequence[float] | None,
) -> tuple[tuple[dict[int, ClassMatches], ...], tuple[dict[int, np.ndarray], ...] | None]:
    """The "numpy" backend of :func:`run_cocoeval`: (matches, AP) per area range."""
    annotations = gt_dict["annotations"]
    n_annotations = len(annotations)
    gt_image = np.array([ann["image_id"] for ann in annotations], dtype=np.int64).reshape(n_annotations)
    gt_category = np.array([ann["category_id"] for ann in annotations], dtype=np.int64).reshape(n_annotations)
    gt_boxes = np.array([ann["bbox"] for ann in annotations], dtype=np.float64).reshape(n_annotations, 4)
    gt_crowd = np.array([bool(ann["iscrowd"]) for ann in annotations], dtype=bool).reshape(n_annotations)
    if gt_areas is None:
        gt_area = np.array([ann["area"] for ann in annotations], dtype=np.float64).reshape(n_annotations)
    else:
        gt_area = np.asarray(gt_areas, dtype=np.float64)
        if gt_area.shape != (n_annotations,):
            raise ValueError(f"gt_areas: expected shape ({n_annotations},) aligned with the annotations, "
                             f"got {gt_area.shape}")
    classes = np.asarray(class_ids, dtype=np.int64)
    n_images = len(image_ids)

    def groups(image: np.ndarray, category: np.ndarray) -> np.ndarray:
        """(M,) int64 group ``class_index * n_images + image_index``, -1 outside the evaluation."""
        image_index = np.minimum(np.searchsorted(image_ids, image), n_images - 1)
        class_index = np.minimum(np.searchsorted(classes, category), len(classes) - 1)
        inside = (image_ids[image_index] == image) & (classes[class_index] == category)
        return np.where(inside, class_index * n_images + image_index, -1)

    gt_group = groups(gt_image, gt_category)
    det_group = groups(table.image_id, table.category_id)
    gt_kept, det_kept = gt_group >= 0, np.flatnonzero(det_group >= 0)
    matching = match_boxes(
        gt_group=gt_group[gt_kept], gt_boxes=gt_boxes[gt_kept], gt_area=gt_area[gt_kept],
        gt_crowd=gt_crowd[gt_kept], det_group=det_group[det_kept], det_boxes=table.bbox[det_kept],
        det_score=table.score[det_kept], det_area=table.area[det_kept], n_groups=len(classes) * n_images,
        area_ranges=np.asarray(area_ranges, dtype=np.float64), iou_thresholds=iou_thresholds,
        max_detections=MAX_DETECTIONS,
    )
    scores = table.score[det_kept][matching.source]
    class_starts = np.searchsorted(matching.group, np.arange(len(classes) + 1) * n_images, side="left")
    all_matches, all_ap = [], []
    for a in range(len(area_ranges)):
        by_class, ap_by_class = {}, {}
        for k, class_id in enumerate(class_ids):
            dets = slice(class_starts[k], class_starts[k + 1])
            n_gt_per_image = matching.n_gt[a, k * n_images : (k + 1) * n_images].astype(np.int64)
            match = _accumulate_order(class_id, image_ids, iou_thresholds, scores[dets],
                                      matching.matched[a, :, dets], matching.ignored[a, :, dets],
                                      matching.group[dets] - k * n_images, n_gt_per_image)
            by_class[class_id] = match
            if accumulate:
                n_gt = np.array([float(n_gt_per_image.sum())])
                ap_by_class[class_id] = interpolated_ap(match.true_positive, match.ignored,
                                                        np.ones((1, len(match.scores))), n_gt)[0]
        all_matches.append(by_class)
        all_ap.append(ap_by_class)
    return tuple(all_matches), (tuple(all_ap) if accumulate else None)


def _pycocotools_evaluation(
    gt_dict: Mapping[str, Any],
    table: _DetectionTable,
    class_ids: list[int],
    image_ids: np.ndarray,
    *,
    area_ranges: Sequence[tuple[float, float]],
    iou_thresholds: np.ndarray,
    accumulate: bool,
    gt_areas: Sequence[float] | None,
) -> tuple[tuple[dict[int, ClassMatches], ...], tuple[dict[int, np.ndarray], ...] | None]:
    """The "pycocotools" backend of :func:`run_cocoeval`: (matches, AP) per area range, read from
    ``COCOeval.evalImgs`` and ``COCOeval.eval["precision"]``."""
    coco_gt = _coco_from_gt(gt_dict, area_override=gt_areas)
    coco_dt = _coco_from_detections(coco_gt, table)
    evaluator = COCOeval(coco_gt, coco_dt, iouType="bbox")
    params = evaluator.params
    params.imgIds = image_ids.tolist()
    params.catIds = list(class_ids)
    params.maxDets = [MAX_DETECTIONS]
    params.areaRng = [list(r) for r in area_ranges]
    params.areaRngLbl = [str(i) for i in range(len(area_ranges))]
    params.iouThrs = iou_thresholds
    with _quiet():
        evaluator.evaluate()
        if accumulate:
            evaluator.accumulate()
    matches = tuple(_read_eval_images(evaluator, a) for a in range(len(area_ranges)))
    if not accumulate:
        return matches, None
    ap = tuple({class_id: _read_precision(evaluator, k, a) for k, class_id in enumerate(params.catIds)}
               for a in range(len(area_ranges)))
    return matches, ap


def _read_eval_images(evaluator: COCOeval, area_index: int) -> dict[int, ClassMatches]:
    """Read COCOeval ``evalImgs`` of one area range into one :class:`ClassMatches` per category."""
    params = evaluator.params
    n_images, n_areas = len(params.imgIds), len(params.areaRng)
    n_thresholds = len(params.iouThrs)
    image_ids = np.asarray(params.imgIds, dtype=np.int64)
    iou_thresholds = np.asarray(params.iouThrs, dtype=np.float64)
    result = {}
    for k, class_id in enumerate(params.catIds):
        start = k * n_areas * n_images + area_index * n_images
        entries = evaluator.evalImgs[start : start + n_images]
        scores, true_positive, ignored, image_index = [], [], [], []
        n_gt_per_image = np.zeros(n_images, dtype=np.int64)
        for i, entry in enumerate(entries):
            if entry is None:
                continue
            n_gt_per_image[i] = np.count_nonzero(np.asarray(entry["gtIgnore"]) == 0)
            n_dets = len(entry["dtScores"])
            if n_dets == 0:
                continue
            scores.append(np.asarray(entry["dtScores"], dtype=np.float64))
            true_positive.append(np.asarray(entry["dtMatches"]) > 0)
            ignored.append(np.asarray(entry["dtIgnore"]).astype(bool))
            image_index.append(np.full(n_dets, i, dtype=np.int64))
        if scores:
            arrays = (np.concatenate(scores), np.concatenate(true_positive, axis=1),
                      np.concatenate(ignored, axis=1), np.concatenate(image_index))
        else:
            arrays = (np.zeros(0), np.zeros((n_thresholds, 0), dtype=bool), np.zeros((n_thresholds, 0), dtype=bool),
                      np.zeros(0, dtype=np.int64))
        result[int(class_id)] = _accumulate_order(class_id, image_ids, iou_thresholds, *arrays, n_gt_per_image)
    return result


def _read_precision(evaluator: COCOeval, k: int, area_index: int) -> np.ndarray:
    """(T,) float64 AP per IoU of the k-th category (COCOeval's sorted order) and one area range:
    ``eval["precision"][:, :, k, area_index, 0]`` ((T, R), -1 where the class has no ground truth)
    averaged over the recall thresholds as ``COCOeval.summarize`` does; nan without ground truth."""
    precision = evaluator.eval["precision"][:, :, k, area_index, 0]
    valid = precision > -1
    with np.errstate(invalid="ignore"):
        return np.where(valid.any(axis=1), np.where(valid, precision, 0).sum(axis=1) / valid.sum(axis=1), np.nan)


def class_matches(evaluation: CocoEvaluation, area_index: int = 0) -> dict[int, ClassMatches]:
    """The per-class matches of one area range of an evaluation (COCO's ``evalImgs`` as arrays).

    Args:
        evaluation: The result of :func:`run_cocoeval`.
        area_index: Index of the area range whose matches are read.

    Returns:
        ``{class_id: ClassMatches}`` for every evaluated class, in ascending class id order.
    """
    return evaluation.matches[area_index]


def match_table(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
    iou_thresholds: np.ndarray = IOU_THRESHOLDS,
    *,
    backend: str = DEFAULT_BACKEND,
) -> dict[int, ClassMatches]:
    """Match detections to ground truth (COCO's evaluate) and return the per-class match arrays.

    Args:
        gt_dict: COCO ground-truth dict (see :func:`coco_ground_truth`).
        detections: COCO results records (bbox ``[x, y, w, h]``).
        class_ids: Class ids to match.
        image_ids: Images to evaluate; all ground-truth images when None.
        iou_thresholds: (T,) float64 IoU thresholds.
        backend: Metrics backend, ``METRICS_BACKENDS``.

    Returns:
        ``{class_id: ClassMatches}`` for the "all" area range, maxDets 100, in ``class_ids`` order.
    """
    evaluation = run_cocoeval(gt_dict, detections, class_ids, image_ids, iou_thresholds=iou_thresholds,
                              accumulate=False, backend=backend)
    matches = class_matches(evaluation)
    return {class_id: matches[class_id] for class_id in evaluation.class_ids}


def iou_index(iou_thresholds: np.ndarray, iou: float) -> int:
    """Index of ``iou`` in the (T,) float64 ``iou_thresholds`` (compared with ``np.isclose``)."""
    return int(np.flatnonzero(np.isclose(iou_thresholds, iou))[0])


def ap_per_iou(evaluation: CocoEvaluation, class_id: int, area_index: int = 0) -> np.ndarray:
    """Per-IoU AP of one class and area range of an evaluation run with ``accumulate``.

    COCO's 101-point interpolated precision averaged over the recall thresholds as
    ``COCOeval.summarize`` does.

    Args:
        evaluation: The result of :func:`run_cocoeval` with ``accumulate=True``.
        class_id: One of the evaluated class ids.
        area_index: Index of the area range.

    Returns:
        (T,) float64 AP per IoU threshold, nan where the class has no ground truth.
    """
    if evaluation.ap is None:
        raise ValueError("evaluation: expected a run_cocoeval result with accumulate=True, got one without AP")
    return evaluation.ap[area_index][class_id]
