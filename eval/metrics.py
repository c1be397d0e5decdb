"""Detection metrics for rainbench: COCO AP, YOLO-style F1, robustness arithmetic, bootstrap CIs.

Everything here is a pure function of its arguments (no files, no plotting, no global random
state); writing and plotting live in ``rainbench.eval.report``.

Conventions (fixed by the project):

- Class ids are COCO-80 indices: 0 person, 1 bicycle, 2 car, 3 motorcycle, 5 bus, 7 truck
  (``CLASS_NAMES[i]`` is the name of class id ``i``, :mod:`rainbench.store.classes`; 4 airplane and
  6 train are never labelled). The paper's four classes 0..3 are evaluated by default
  (``PAPER_CLASSES``). COCO category ids are the same numbers, *including 0*:
  pycocotools handles category id 0 (it indexes categories by value and never tests them for
  truth), which the tests pin against a direct ``loadRes``/``COCOeval`` run.
- Dataset boxes are float32 ``x1, y1, x2, y2`` in pixel-edge coordinates (a box covering pixel
  columns 0..9 is ``x1=0, x2=10``); COCO boxes are ``[x, y, w, h]`` with ``w = x2 - x1``.
- Image ids are positive ints. COCO annotation ids must be >= 1, because COCOeval stores the
  matched ground-truth id in ``dtMatches`` and treats 0 as "unmatched".
- Detections are COCO results records ``{"image_id": int, "category_id": int,
  "bbox": [x, y, w, h], "score": float in [0, 1]}``.
- Rates are rainfall rates in mm/h (0, 10, ..., 100); rate 0 is the clean ("Normal") condition.

AP is computed by pycocotools' COCOeval (not re-implemented): bbox IoU, maxDets 100, area range
"all", the 101-point interpolated precision at IoU 0.50 (AP50), 0.75 (AP75) and averaged over
0.50:0.05:0.95 (AP50-95). Precision/recall/F1 follow the YOLO (ultralytics ``ap_per_class``)
convention, fed with the reference TP/FP matches at IoU 0.5 read from COCOeval's ``evalImgs``.
The bootstrap re-uses those per-image matches and re-computes COCO's interpolated AP for many
resamples at once with :func:`interpolated_ap`, which is verified against COCOeval in the tests.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval, Params

from rainbench.store.classes import CLASS_NAMES, LABELLED_CLASSES, PAPER_CLASS_NAMES, PAPER_CLASSES, class_list

IOU_THRESHOLDS: np.ndarray = Params(iouType="bbox").iouThrs.copy()
"""(10,) float64 COCO IoU thresholds 0.50:0.05:0.95, exactly as pycocotools builds them."""

RECALL_THRESHOLDS: np.ndarray = Params(iouType="bbox").recThrs.copy()
"""(101,) float64 COCO recall thresholds 0.00:0.01:1.00, exactly as pycocotools builds them."""

MAX_DETECTIONS = 100
"""Detections kept per image and class (COCO maxDets; the largest of COCO's default [1, 10, 100])."""

AREA_ALL: tuple[float, float] = (0.0, 1e5**2)
"""COCO "all" area range in squared pixels."""

SIZE_RANGES: dict[str, tuple[float, float]] = {
    "small": (0.0, 32.0**2),
    "medium": (32.0**2, 96.0**2),
    "large": (96.0**2, 1e5**2),
}
"""COCO object-size area ranges (squared pixels, bounds inclusive as in pycocotools)."""

CONFIDENCE_GRID: np.ndarray = np.linspace(0.0, 1.0, 1000)
"""(1000,) float64 confidence grid of the YOLO precision/recall/F1 curves (ultralytics)."""

DEFAULT_CONF = 0.25
"""Fixed confidence threshold of the ``*_at_conf`` metrics (ultralytics' predict default)."""

F1_SMOOTH_FRACTION = 0.1
"""Box-filter width (fraction of the grid) used by ultralytics before taking the F1 argmax."""

EPS = 1e-16
"""Epsilon of ultralytics' recall and F1 formulas."""

BOOTSTRAP_METRICS = ("ap50", "ap50_95")
"""Metrics :func:`bootstrap_ci` can resample."""


# --------------------------------------------------------------------------------------------
# Result types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ClassMetrics:
    """Metrics of one class on one evaluation set.

    Attributes:
        class_id (int): COCO-80 class id.
        n_gt (int): Ground-truth boxes that count (not ignored / not crowd).
        n_det (int): Detections of this class on the evaluated images (after maxDets truncation).
        ap50 (float): COCO AP at IoU 0.5; nan when ``n_gt == 0``.
        ap75 (float): COCO AP at IoU 0.75; nan when ``n_gt == 0``.
        ap50_95 (float): COCO AP averaged over IoU 0.50:0.95; nan when ``n_gt == 0``.
        precision (float): Precision at ``best_conf`` (YOLO curves); nan when ``n_gt == 0``.
        recall (float): Recall at ``best_conf``; nan when ``n_gt == 0``.
        f1 (float): F1 at ``best_conf``; nan when ``n_gt == 0``.
        best_conf (float): Grid confidence maximising the smoothed mean F1 over the evaluated
            classes that have ground truth (shared by all classes of one evaluation); nan when no
            class has ground truth.
        precision_at_conf (float): TP / (TP + FP) over detections with score >= ``conf``
            (0 when there are none); nan when ``n_gt == 0``.
        recall_at_conf (float): TP / n_gt at ``conf``; nan when ``n_gt == 0``.
        f1_at_conf (float): 2PR / (P + R) at ``conf`` (0 when P + R == 0); nan when ``n_gt == 0``.
        conf (float): The fixed confidence threshold used for the ``*_at_conf`` values.
    """

    class_id: int
    n_gt: int
    n_det: int
    ap50: float
    ap75: float
    ap50_95: float
    precision: float
    recall: float
    f1: float
    best_conf: float
    precision_at_conf: float
    recall_at_conf: float
    f1_at_conf: float
    conf: float


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


@dataclass(frozen=True)
class BootstrapCI:
    """Percentile bootstrap confidence interval of one metric of one class.

    Attributes:
        class_id (int): COCO-80 class id.
        metric (str): "ap50" or "ap50_95".
        point (float): Metric on the original (non-resampled) images; equals COCOeval's value.
        low (float): Lower bound (``alpha / 2`` quantile of the resampled values).
        high (float): Upper bound (``1 - alpha / 2`` quantile).
        alpha (float): 1 - confidence level.
        n_boot (int): Resamples drawn.
        n_valid (int): Resamples in which the class had ground truth (the others are nan and
            left out of the quantiles).
    """

    class_id: int
    metric: str
    point: float
    low: float
    high: float
    alpha: float
    n_boot: int
    n_valid: int


@dataclass(frozen=True)
class BreakdownAP:
    """AP of one class restricted to one slice of the ground truth (object size or visibility).

    Attributes:
        ap50 (float): COCO AP at IoU 0.5 within the slice; nan when ``n_gt == 0``.
        ap50_95 (float): COCO AP at IoU 0.50:0.95 within the slice; nan when ``n_gt == 0``.
        n_gt (int): Non-ignored ground truths in the slice.
    """

    ap50: float
    ap50_95: float
    n_gt: int


# --------------------------------------------------------------------------------------------
# Building COCO inputs
# --------------------------------------------------------------------------------------------


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
    if np.any((boxes[:, 2] < boxes[:, 0]) | (boxes[:, 3] < boxes[:, 1])):
        raise ValueError("boxes: expected x1 <= x2 and y1 <= y2 (xyxy), got a box with x2 < x1 or y2 < y1")
    xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], axis=1)
    return [
        {"image_id": image_id, "category_id": int(c), "bbox": b, "score": float(s)}
        for b, s, c in zip(xywh.tolist(), scores.tolist(), class_ids.tolist(), strict=True)
    ]


def _validate_gt_dict(gt_dict: Mapping[str, Any]) -> None:
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


def _coco_from_detections(
    coco_gt: COCO, detections: Sequence[Mapping[str, Any]], area_override: float | None = None
) -> COCO:
    """Validate detections and index them as a COCO results object.

    Equivalent to ``coco_gt.loadRes(detections)`` for bbox results (ids from 1, ``area = w * h``,
    ``iscrowd = 0``) but copies the records instead of mutating them, and accepts an empty list
    (``loadRes`` raises IndexError on one). ``area_override`` replaces every detection's area
    (used by the visibility breakdown).
    """
    known_images = coco_gt.imgs
    known_categories = coco_gt.cats
    annotations = []
    for position, record in enumerate(detections):
        try:
            image_id, category_id, bbox, score = (
                record["image_id"],
                record["category_id"],
                record["bbox"],
                record["score"],
            )
        except (KeyError, TypeError) as error:
            raise ValueError(
                f"detections[{position}]: expected a dict with image_id, category_id, bbox, score, got {record!r}"
            ) from error
        if image_id not in known_images:
            raise ValueError(f"detections[{position}]: image_id {image_id!r} is not in the ground truth")
        if category_id not in known_categories:
            raise ValueError(
                f"detections[{position}]: unknown category_id {category_id!r}, expected one of {sorted(known_categories)}"
            )
        if len(bbox) != 4:
            raise ValueError(f"detections[{position}] bbox: expected [x, y, w, h], got {bbox!r}")
        x, y, w, h = (float(v) for v in bbox)
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(w) and math.isfinite(h)) or w < 0 or h < 0:
            raise ValueError(f"detections[{position}] bbox: expected finite [x, y, w, h] with w, h >= 0, got {bbox!r}")
        score = float(score)
        if not 0.0 <= score <= 1.0:
            raise ValueError(f"detections[{position}] score: expected a confidence in [0, 1], got {score!r}")
        annotations.append(
            {
                "id": position + 1,
                "image_id": int(image_id),
                "category_id": int(category_id),
                "bbox": [x, y, w, h],
                "score": score,
                "area": w * h if area_override is None else area_override,
                "iscrowd": 0,
            }
        )
    coco = COCO()
    coco.dataset = {
        "images": list(coco_gt.dataset["images"]),
        "annotations": annotations,
        "categories": list(coco_gt.dataset["categories"]),
    }
    with _quiet():
        coco.createIndex()
    return coco


def _check_class_ids(class_ids: Sequence[int], coco_gt: COCO) -> list[int]:
    """Return ``class_ids`` as a list of ints, all present among the ground-truth categories."""
    ids = [int(c) for c in class_ids]
    if not ids:
        raise ValueError("class_ids: expected at least one class id, got none")
    if len(set(ids)) != len(ids):
        raise ValueError(f"class_ids: expected unique ids, got {ids}")
    unknown = [c for c in ids if c not in coco_gt.cats]
    if unknown:
        raise ValueError(f"class_ids: unknown class id(s) {unknown}, expected ids in {sorted(coco_gt.cats)}")
    return ids


def _check_image_ids(image_ids: Sequence[int] | None, coco_gt: COCO) -> list[int]:
    """Return the evaluated image ids (all ground-truth images when None), validated."""
    if image_ids is None:
        return sorted(coco_gt.imgs)
    ids = [int(i) for i in image_ids]
    if not ids:
        raise ValueError("image_ids: expected at least one image id, got none")
    missing = [i for i in ids if i not in coco_gt.imgs]
    if missing:
        raise ValueError(f"image_ids: {missing[:5]} not in the ground truth")
    return ids


def _run_cocoeval(
    coco_gt: COCO,
    coco_dt: COCO,
    class_ids: Sequence[int],
    image_ids: Sequence[int],
    area_ranges: Sequence[tuple[float, float]],
    iou_thresholds: np.ndarray = IOU_THRESHOLDS,
    accumulate: bool = True,
) -> COCOeval:
    """Run COCOeval (bbox, maxDets [100]) quietly; ``evalImgs`` and, if asked, ``eval`` filled."""
    evaluator = COCOeval(coco_gt, coco_dt, iouType="bbox")
    params = evaluator.params
    params.imgIds = list(image_ids)
    params.catIds = list(class_ids)
    params.maxDets = [MAX_DETECTIONS]
    params.areaRng = [list(r) for r in area_ranges]
    params.areaRngLbl = [str(i) for i in range(len(area_ranges))]
    params.iouThrs = np.asarray(iou_thresholds, dtype=np.float64)
    with _quiet():
        evaluator.evaluate()
        if accumulate:
            evaluator.accumulate()
    return evaluator


def _class_matches(evaluator: COCOeval, area_index: int = 0) -> dict[int, ClassMatches]:
    """Read COCOeval ``evalImgs`` into one :class:`ClassMatches` per category (accumulate's order)."""
    params = evaluator.params
    n_images, n_areas = len(params.imgIds), len(params.areaRng)
    n_thresholds = len(params.iouThrs)
    image_ids = np.asarray(params.imgIds, dtype=np.int64)
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
            all_scores = np.concatenate(scores)
            order = np.argsort(-all_scores, kind="mergesort")
            all_scores = all_scores[order]
            all_tp = np.concatenate(true_positive, axis=1)[:, order]
            all_ignored = np.concatenate(ignored, axis=1)[:, order]
            all_index = np.concatenate(image_index)[order]
        else:
            all_scores = np.zeros(0)
            all_tp = np.zeros((n_thresholds, 0), dtype=bool)
            all_ignored = np.zeros((n_thresholds, 0), dtype=bool)
            all_index = np.zeros(0, dtype=np.int64)
        result[int(class_id)] = ClassMatches(
            class_id=int(class_id),
            image_ids=image_ids,
            iou_thresholds=np.asarray(params.iouThrs, dtype=np.float64),
            scores=all_scores,
            true_positive=all_tp,
            ignored=all_ignored,
            image_index=all_index,
            n_gt_per_image=n_gt_per_image,
        )
    return result


def match_table(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
    iou_thresholds: np.ndarray = IOU_THRESHOLDS,
) -> dict[int, ClassMatches]:
    """Match detections to ground truth with COCOeval and return the per-class match arrays.

    Args:
        gt_dict: COCO ground-truth dict (see :func:`coco_ground_truth`).
        detections: COCO results records (bbox ``[x, y, w, h]``).
        class_ids: Class ids to match.
        image_ids: Images to evaluate; all ground-truth images when None.
        iou_thresholds: (T,) float64 IoU thresholds.

    Returns:
        ``{class_id: ClassMatches}`` for the "all" area range, maxDets 100.
    """
    _validate_gt_dict(gt_dict)
    coco_gt = _coco_from_gt(gt_dict)
    class_ids = _check_class_ids(class_ids, coco_gt)
    image_ids = _check_image_ids(image_ids, coco_gt)
    coco_dt = _coco_from_detections(coco_gt, detections)
    evaluator = _run_cocoeval(coco_gt, coco_dt, class_ids, image_ids, [AREA_ALL], iou_thresholds, accumulate=False)
    matches = _class_matches(evaluator)
    return {class_id: matches[class_id] for class_id in class_ids}


# --------------------------------------------------------------------------------------------
# YOLO-style precision / recall / F1
# --------------------------------------------------------------------------------------------


def smooth(values: np.ndarray, fraction: float = F1_SMOOTH_FRACTION) -> np.ndarray:
    """Box-filter a curve as ultralytics ``smooth`` does before taking the F1 argmax.

    Args:
        values: (G,) float array.
        fraction: Filter width as a fraction of G (the filter has
            ``round(G * fraction * 2) // 2 + 1`` taps, 101 for G = 1000 and 0.1; edges padded
            with the end values).

    Returns:
        (G,) float64 smoothed curve.
    """
    values = np.asarray(values, dtype=np.float64)
    n_taps = round(len(values) * fraction * 2) // 2 + 1
    pad = np.ones(n_taps // 2)
    padded = np.concatenate((pad * values[0], values, pad * values[-1]), 0)
    return np.convolve(padded, np.ones(n_taps) / n_taps, mode="valid")


def pr_confidence_curves(
    scores: np.ndarray, true_positive: np.ndarray, n_gt: int, grid: np.ndarray = CONFIDENCE_GRID
) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall of one class as functions of the confidence threshold (ultralytics).

    Args:
        scores: (D,) float array of detection confidences (ignored detections already removed).
        true_positive: (D,) bool array, detection is a TP at the chosen IoU threshold.
        n_gt: Non-ignored ground truths of the class (> 0).
        grid: (G,) float array of confidence thresholds, increasing.

    Returns:
        precision (G,) float64, recall (G,) float64: the cumulative precision / recall of the
        detections sorted by descending score, linearly interpolated in confidence; above the
        highest score precision is 1 and recall 0, below the lowest score they hold their final
        values; with no detections both are 0 (as in ultralytics ``ap_per_class``).
    """
    scores = np.asarray(scores, dtype=np.float64)
    true_positive = np.asarray(true_positive, dtype=bool)
    if scores.shape != true_positive.shape or scores.ndim != 1:
        raise ValueError(
            f"scores/true_positive: expected matching (D,) shapes, got {scores.shape} and {true_positive.shape}"
        )
    if n_gt < 1:
        raise ValueError(f"n_gt: expected at least one ground truth, got {n_gt}")
    grid = np.asarray(grid, dtype=np.float64)
    if len(scores) == 0:
        return np.zeros_like(grid), np.zeros_like(grid)
    order = np.argsort(-scores, kind="mergesort")
    scores, true_positive = scores[order], true_positive[order]
    tp_cumsum = np.cumsum(true_positive).astype(np.float64)
    fp_cumsum = np.cumsum(~true_positive).astype(np.float64)
    recall = tp_cumsum / (n_gt + EPS)
    precision = tp_cumsum / (tp_cumsum + fp_cumsum)
    recall_curve = np.interp(-grid, -scores, recall, left=0)
    precision_curve = np.interp(-grid, -scores, precision, left=1)
    return precision_curve, recall_curve


def _yolo_f1(
    matches: Mapping[int, ClassMatches], iou_index: int, conf: float
) -> dict[int, tuple[float, float, float, float, float, float, float]]:
    """Per class (precision, recall, f1, best_conf, precision@conf, recall@conf, f1@conf)."""
    class_ids = list(matches)
    curves, with_gt = [], []
    at_conf = {}
    for class_id in class_ids:
        match = matches[class_id]
        n_gt = int(match.n_gt_per_image.sum())
        counted = ~match.ignored[iou_index]
        scores = match.scores[counted]
        true_positive = match.true_positive[iou_index][counted]
        if n_gt == 0:
            curves.append(None)
            continue
        precision_curve, recall_curve = pr_confidence_curves(scores, true_positive, n_gt)
        f1_curve = 2 * precision_curve * recall_curve / (precision_curve + recall_curve + EPS)
        curves.append((precision_curve, recall_curve, f1_curve))
        with_gt.append(f1_curve)
        kept = scores >= conf
        n_tp = int(np.count_nonzero(true_positive[kept]))
        n_fp = int(np.count_nonzero(kept)) - n_tp
        precision_at = n_tp / (n_tp + n_fp) if n_tp + n_fp else 0.0
        recall_at = n_tp / n_gt
        f1_at = 2 * precision_at * recall_at / (precision_at + recall_at) if precision_at + recall_at else 0.0
        at_conf[class_id] = (precision_at, recall_at, f1_at)
    nan = float("nan")
    if not with_gt:
        return {class_id: (nan,) * 7 for class_id in class_ids}
    best = int(smooth(np.mean(with_gt, axis=0)).argmax())
    best_conf = float(CONFIDENCE_GRID[best])
    result = {}
    for class_id, curve in zip(class_ids, curves, strict=True):
        if curve is None:
            result[class_id] = (nan, nan, nan, best_conf, nan, nan, nan)
        else:
            precision_curve, recall_curve, f1_curve = curve
            result[class_id] = (
                float(precision_curve[best]),
                float(recall_curve[best]),
                float(f1_curve[best]),
                best_conf,
                *at_conf[class_id],
            )
    return result


# --------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------


def _ap_from_precision(precision: np.ndarray) -> np.ndarray:
    """Per-IoU AP from a COCOeval precision slice.

    Args:
        precision: (T, R) float64 slice ``eval["precision"][:, :, k, a, m]`` (-1 = no ground truth).

    Returns:
        (T,) float64 AP per IoU threshold (mean over recall thresholds), nan where absent.
    """
    valid = precision > -1
    with np.errstate(invalid="ignore"):
        return np.where(valid.any(axis=1), np.where(valid, precision, 0).sum(axis=1) / valid.sum(axis=1), np.nan)


def evaluate(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
    conf: float = DEFAULT_CONF,
) -> dict[int, ClassMetrics]:
    """Per-class COCO AP (pycocotools) and YOLO-convention precision / recall / F1.

    One COCOeval run (bbox, area range "all", maxDets 100, IoU 0.50:0.95) over all requested
    classes provides AP50 / AP75 / AP50-95 (its accumulated 101-point interpolated precision,
    averaged as COCOeval.summarize does) and the TP/FP matches at IoU 0.5 (``evalImgs``). From
    those matches, as ultralytics ``ap_per_class`` does: precision and recall curves of every
    class over a 1000-point confidence grid, F1 = 2PR / (P + R + 1e-16), mean F1 over the
    classes with ground truth, box-smoothed (10 %), argmax -> one ``best_conf`` shared by all
    classes; each class reports P, R, F1 at that grid point. Classes with ground truth but no
    detections contribute zero curves to the mean. Differences from YOLO val: ignored ground
    truths (crowd) do not count in ``n_gt`` and detections COCOeval ignores are dropped, and
    matching is COCO's (greedy by score, best IoU) instead of ultralytics' IoU-matrix matching.

    Args:
        gt_dict: COCO ground-truth dict (see :func:`coco_ground_truth`).
        detections: COCO results records ``{"image_id", "category_id", "bbox": [x, y, w, h],
            "score"}``; may be empty; images without detections are fine.
        class_ids: Class ids to evaluate (must be ground-truth categories).
        image_ids: Images to evaluate; all ground-truth images when None.
        conf: Fixed confidence threshold of the ``*_at_conf`` values, in [0, 1].

    Returns:
        ``{class_id: ClassMetrics}`` in ``class_ids`` order. A class without (non-ignored)
        ground truth gets ``n_gt = 0`` and nan for AP, precision, recall and F1.
    """
    if not 0.0 <= conf <= 1.0:
        raise ValueError(f"conf: expected a confidence in [0, 1], got {conf!r}")
    _validate_gt_dict(gt_dict)
    coco_gt = _coco_from_gt(gt_dict)
    class_ids = _check_class_ids(class_ids, coco_gt)
    image_ids = _check_image_ids(image_ids, coco_gt)
    coco_dt = _coco_from_detections(coco_gt, detections)
    evaluator = _run_cocoeval(coco_gt, coco_dt, class_ids, image_ids, [AREA_ALL])
    matches = _class_matches(evaluator)
    iou50 = int(np.flatnonzero(np.isclose(IOU_THRESHOLDS, 0.5))[0])
    iou75 = int(np.flatnonzero(np.isclose(IOU_THRESHOLDS, 0.75))[0])
    f1_values = _yolo_f1({c: matches[c] for c in class_ids}, iou50, conf)
    sorted_ids = list(evaluator.params.catIds)
    result = {}
    for class_id in class_ids:
        k = sorted_ids.index(class_id)
        ap_per_iou = _ap_from_precision(evaluator.eval["precision"][:, :, k, 0, 0])
        match = matches[class_id]
        precision, recall, f1, best_conf, precision_at, recall_at, f1_at = f1_values[class_id]
        result[class_id] = ClassMetrics(
            class_id=class_id,
            n_gt=int(match.n_gt_per_image.sum()),
            n_det=len(match.scores),
            ap50=float(ap_per_iou[iou50]),
            ap75=float(ap_per_iou[iou75]),
            ap50_95=float(np.mean(ap_per_iou)),
            precision=precision,
            recall=recall,
            f1=f1,
            best_conf=best_conf,
            precision_at_conf=precision_at,
            recall_at_conf=recall_at,
            f1_at_conf=f1_at,
            conf=float(conf),
        )
    return result


def _breakdown(
    evaluator: COCOeval, class_ids: Sequence[int], labels: Sequence[str]
) -> dict[str, dict[int, BreakdownAP]]:
    """Read per-(area range, class) AP50 / AP50-95 / n_gt out of an accumulated COCOeval."""
    matches_by_range = [_class_matches(evaluator, a) for a in range(len(labels))]
    sorted_ids = list(evaluator.params.catIds)
    iou50 = int(np.flatnonzero(np.isclose(evaluator.params.iouThrs, 0.5))[0])
    result: dict[str, dict[int, BreakdownAP]] = {}
    for a, label in enumerate(labels):
        per_class = {}
        for class_id in class_ids:
            ap_per_iou = _ap_from_precision(evaluator.eval["precision"][:, :, sorted_ids.index(class_id), a, 0])
            per_class[class_id] = BreakdownAP(
                ap50=float(ap_per_iou[iou50]),
                ap50_95=float(np.mean(ap_per_iou)),
                n_gt=int(matches_by_range[a][class_id].n_gt_per_image.sum()),
            )
        result[label] = per_class
    return result


def ap_by_size(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
) -> dict[str, dict[int, BreakdownAP]]:
    """COCO AP by object size (small < 32², medium 32²..96², large > 96² px², box area).

    Standard COCOeval area-range logic: ground truths outside the range are ignored, detections
    matched to them are ignored, and unmatched detections whose own box area is outside the
    range are ignored (so a small false positive does not hurt AP-large).

    Args:
        gt_dict: COCO ground-truth dict; ``area`` of each annotation is used (box area when built
            by :func:`coco_ground_truth`).
        detections: COCO results records.
        class_ids: Class ids to evaluate.
        image_ids: Images to evaluate; all when None.

    Returns:
        ``{"small" | "medium" | "large": {class_id: BreakdownAP}}``.
    """
    _validate_gt_dict(gt_dict)
    coco_gt = _coco_from_gt(gt_dict)
    class_ids = _check_class_ids(class_ids, coco_gt)
    image_ids = _check_image_ids(image_ids, coco_gt)
    coco_dt = _coco_from_detections(coco_gt, detections)
    evaluator = _run_cocoeval(coco_gt, coco_dt, class_ids, image_ids, list(SIZE_RANGES.values()))
    return _breakdown(evaluator, class_ids, list(SIZE_RANGES))


def ap_by_visibility(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    visible_fraction: np.ndarray,
    bins: Sequence[float] = (0.0, 0.25, 0.5, 0.75, 1.0),
    unmatched: str = "fp",
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
) -> dict[str, dict[int, BreakdownAP]]:
    """COCO AP by ground-truth visible fraction, one COCOeval run with one "area range" per bin.

    Each ground truth is put in exactly one bin (half-open ``[lo, hi)``, the last bin closed);
    within a bin the others are ignored exactly like COCO's out-of-area-range ground truths: they
    are not false negatives, and a detection matched to one of them is neither TP nor FP (COCO
    prefers a match to an in-bin ground truth when both qualify). A detection matching no ground
    truth has no visible fraction, so its bin is unknown; ``unmatched`` decides:

    - ``"fp"`` (default): it is a false positive in every bin (conservative; per-bin APs are
      comparable to the overall AP, but every bin pays for all background false positives);
    - ``"ignore"``: it is ignored in every bin (per-bin AP then measures only how well objects
      of that visibility are found and ranked against the other detections).

    Implementation: COCOeval's area-range test is applied to a replaced ``area`` (ground truth:
    its bin index, or -1 when its visible fraction is nan; detection: nan for "fp", which every
    ``<``/``>`` comparison lets through, or -inf for "ignore").

    Args:
        gt_dict: COCO ground-truth dict.
        detections: COCO results records.
        visible_fraction: (A,) float array in [0, 1] aligned with ``gt_dict["annotations"]``;
            nan leaves the annotation out of every bin (ignored).
        bins: Increasing bin edges in [0, 1], at least two.
        unmatched: "fp" or "ignore", see above.
        class_ids: Class ids to evaluate.
        image_ids: Images to evaluate; all when None.

    Returns:
        ``{"lo-hi": {class_id: BreakdownAP}}`` with labels like ``"0.25-0.50"``.
    """
    _validate_gt_dict(gt_dict)
    visible_fraction = np.asarray(visible_fraction, dtype=np.float64)
    n_annotations = len(gt_dict["annotations"])
    if visible_fraction.shape != (n_annotations,):
        raise ValueError(
            f"visible_fraction: expected shape ({n_annotations},) aligned with the annotations, got {visible_fraction.shape}"
        )
    finite = visible_fraction[~np.isnan(visible_fraction)]
    if np.any((finite < 0) | (finite > 1)):
        raise ValueError("visible_fraction: expected values in [0, 1] or nan, got values outside")
    edges = np.asarray(bins, dtype=np.float64)
    if edges.ndim != 1 or len(edges) < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"bins: expected at least two increasing edges, got {list(bins)}")
    if unmatched not in ("fp", "ignore"):
        raise ValueError(f"unmatched: expected 'fp' or 'ignore', got {unmatched!r}")
    bin_index = np.searchsorted(edges, visible_fraction, side="right") - 1
    bin_index[visible_fraction == edges[-1]] = len(edges) - 2
    outside = np.isnan(visible_fraction) | (bin_index < 0) | (bin_index > len(edges) - 2)
    gt_area = np.where(outside, -1.0, bin_index.astype(np.float64))
    coco_gt = _coco_from_gt(gt_dict, area_override=gt_area)
    class_ids = _check_class_ids(class_ids, coco_gt)
    image_ids = _check_image_ids(image_ids, coco_gt)
    coco_dt = _coco_from_detections(coco_gt, detections, area_override=math.nan if unmatched == "fp" else -math.inf)
    labels = [f"{lo:.2f}-{hi:.2f}" for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    ranges = [(float(i), float(i)) for i in range(len(labels))]
    evaluator = _run_cocoeval(coco_gt, coco_dt, class_ids, image_ids, ranges)
    return _breakdown(evaluator, class_ids, labels)


# --------------------------------------------------------------------------------------------
# Robustness arithmetic (Michaelis et al. 2019, "Benchmarking Robustness in Object Detection")
# --------------------------------------------------------------------------------------------


def percent_drop(clean: float | np.ndarray, value: float | np.ndarray) -> float | np.ndarray:
    """Relative degradation in percent: ``100 * (clean - value) / clean``.

    Positive means worse than clean (the paper's "% drop"); nan where ``clean == 0`` or either
    input is nan.

    Args:
        clean: Scalar or (...) float array, the metric at rate 0.
        value: Scalar or array broadcastable with ``clean``, the metric under rain.

    Returns:
        float for scalar inputs, else float64 array of the broadcast shape.
    """
    clean_array = np.asarray(clean, dtype=np.float64)
    value_array = np.asarray(value, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        drop = np.where(clean_array == 0, np.nan, 100.0 * (clean_array - value_array) / clean_array)
    return float(drop) if drop.ndim == 0 else drop


def _rates_and_values(values_by_rate: Mapping[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(R,) float64 rates and (R,) float64 values of a ``{rate: value}`` mapping, validated."""
    if not values_by_rate:
        raise ValueError("values_by_rate: expected {rate_mm_h: value} with at least one rate, got an empty mapping")
    rates = np.array([float(r) for r in values_by_rate], dtype=np.float64)
    values = np.array([float(v) for v in values_by_rate.values()], dtype=np.float64)
    if np.any(rates < 0) or not np.all(np.isfinite(rates)):
        raise ValueError(f"values_by_rate: expected finite rates >= 0 mm/h, got {rates.tolist()}")
    return rates, values


def mpc(values_by_rate: Mapping[float, float]) -> float:
    """Mean performance under corruption: the mean of the metric over rates > 0.

    Args:
        values_by_rate: ``{rate_mm_h: metric}``; rates > 0 are averaged with equal weight
            (nan propagates).

    Returns:
        mPC as a float.
    """
    rates, values = _rates_and_values(values_by_rate)
    rainy = rates > 0
    if not rainy.any():
        raise ValueError(f"values_by_rate: expected at least one rate > 0 mm/h, got {rates.tolist()}")
    return float(np.mean(values[rainy]))


def rpc(values_by_rate: Mapping[float, float]) -> float:
    """Relative performance under corruption: ``mPC / P`` with P the metric at rate 0.

    Args:
        values_by_rate: ``{rate_mm_h: metric}`` including rate 0.

    Returns:
        rPC as a float; nan when P is 0 or nan.
    """
    rates, values = _rates_and_values(values_by_rate)
    clean = values[rates == 0]
    if len(clean) != 1:
        raise ValueError(f"values_by_rate: expected exactly one rate 0 (clean), got rates {rates.tolist()}")
    performance_clean = float(clean[0])
    if performance_clean == 0 or math.isnan(performance_clean):
        return float("nan")
    return mpc(values_by_rate) / performance_clean


def half_value_rate(values_by_rate: Mapping[float, float], fraction: float = 0.5) -> float:
    """The rain rate at which a metric first falls to ``fraction`` of its clean (rate 0) value.

    Linear interpolation between the two measured rates around the crossing. Returns inf when
    the metric stays above ``fraction x clean`` at every measured rate, and nan when the clean
    value is 0 or nan.

    Args:
        values_by_rate: ``{rate_mm_h: metric}`` including rate 0.
        fraction: Level, in (0, 1), relative to the clean value.
    """
    if not 0 < fraction < 1:
        raise ValueError(f"fraction: expected a value in (0, 1), got {fraction}")
    rates, values = _rates_and_values(values_by_rate)
    order = np.argsort(rates)
    rates, values = rates[order], values[order]
    if rates[0] != 0:
        raise ValueError(f"values_by_rate: expected rate 0 (clean), got rates {rates.tolist()}")
    clean = values[0]
    if clean == 0 or math.isnan(clean):
        return float("nan")
    level = fraction * clean
    for index in range(1, len(rates)):
        if values[index] <= level:
            previous, current = values[index - 1], values[index]
            if previous == current:
                return float(rates[index])
            step = (previous - level) / (previous - current)
            return float(rates[index - 1] + step * (rates[index] - rates[index - 1]))
    return float("inf")


# --------------------------------------------------------------------------------------------
# Bootstrap
# --------------------------------------------------------------------------------------------


def interpolated_ap(
    true_positive: np.ndarray,
    ignored: np.ndarray,
    det_weights: np.ndarray,
    n_gt: np.ndarray,
    recall_thresholds: np.ndarray = RECALL_THRESHOLDS,
) -> np.ndarray:
    """COCO 101-point interpolated AP for B weighted copies of one class's detections at once.

    Weighted version of ``COCOeval.accumulate``: detection d counts ``det_weights[b, d]`` times in
    copy b (its image's multiplicity in a bootstrap resample; 1 everywhere gives COCOeval's AP
    exactly). Cumulative TP / FP sums over the score-sorted detections give recall
    ``tp / n_gt`` and precision ``tp / (tp + fp + spacing(1))``; precision is made monotone from
    the right, sampled at the first index whose recall reaches each threshold (0 past the
    final recall), and averaged. Zero-weight detections only repeat the previous PR point, which
    changes neither the envelope nor the sampled values.

    Args:
        true_positive: (T, D) bool, detection d is matched at IoU threshold t (COCO order:
            sorted by descending score, see :class:`ClassMatches`).
        ignored: (T, D) bool, COCO ``dtIgnore`` (neither TP nor FP).
        det_weights: (B, D) float64 non-negative integer-valued weights.
        n_gt: (B,) float64 non-ignored ground truths in each copy.
        recall_thresholds: (R,) float64 increasing recall thresholds (COCO's 101).

    Returns:
        (B, T) float64 AP; nan where ``n_gt == 0`` (COCO leaves such a class out).
    """
    true_positive = np.asarray(true_positive, dtype=bool)
    ignored = np.asarray(ignored, dtype=bool)
    det_weights = np.asarray(det_weights, dtype=np.float64)
    n_gt = np.asarray(n_gt, dtype=np.float64)
    if true_positive.ndim != 2 or ignored.shape != true_positive.shape:
        raise ValueError(
            f"true_positive/ignored: expected matching (T, D) shapes, got {true_positive.shape} and {ignored.shape}"
        )
    n_thresholds, n_dets = true_positive.shape
    if det_weights.ndim != 2 or det_weights.shape[1] != n_dets:
        raise ValueError(f"det_weights: expected shape (B, {n_dets}), got {det_weights.shape}")
    n_copies = det_weights.shape[0]
    if n_gt.shape != (n_copies,):
        raise ValueError(f"n_gt: expected shape ({n_copies},), got {n_gt.shape}")
    ap = np.full((n_copies, n_thresholds), np.nan)
    valid_rows = np.flatnonzero(n_gt > 0)
    if valid_rows.size == 0:
        return ap
    weights = det_weights[valid_rows]
    counts = n_gt[valid_rows][:, None]
    for t in range(n_thresholds):
        counted = ~ignored[t]
        tp_sum = np.cumsum(weights * (true_positive[t] & counted), axis=1)
        fp_sum = np.cumsum(weights * (~true_positive[t] & counted), axis=1)
        recall = tp_sum / counts
        precision = tp_sum / (fp_sum + tp_sum + np.spacing(1))
        envelope = np.maximum.accumulate(precision[:, ::-1], axis=1)[:, ::-1]
        envelope = np.concatenate([envelope, np.zeros((len(valid_rows), 1))], axis=1)
        for row in range(len(valid_rows)):
            indices = np.searchsorted(recall[row], recall_thresholds, side="left")
            ap[valid_rows[row], t] = envelope[row, indices].mean()
    return ap


def bootstrap_weights(n_images: int, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """Image multiplicities of ``n_boot`` bootstrap resamples of ``n_images`` frames.

    Each resample draws ``n_images`` image indices uniformly with replacement.

    Args:
        n_images: Frames in the evaluation set (>= 1).
        n_boot: Resamples (>= 1).
        rng: Source of randomness.

    Returns:
        (n_boot, n_images) int64 counts, each row summing to ``n_images``.
    """
    draws = rng.integers(0, n_images, size=(n_boot, n_images))
    offsets = np.arange(n_boot)[:, None] * n_images
    return np.bincount((draws + offsets).ravel(), minlength=n_boot * n_images).reshape(n_boot, n_images)


def bootstrap_ci(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    n_boot: int = 1000,
    *,
    rng: np.random.Generator,
    alpha: float = 0.05,
    metric: str = "ap50",
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
) -> dict[int, BootstrapCI]:
    """Percentile bootstrap CI of per-class AP over frames (images resampled with replacement).

    Approach: COCOeval matches detections once per image (``evalImgs``); matching is per image,
    so a resample that contains an image k times contains its matches k times. Each resample is
    therefore a vector of image multiplicities, and its AP is :func:`interpolated_ap` with each
    detection weighted by its image's multiplicity and ``n_gt`` the weighted ground-truth count.
    This equals running COCOeval on the resampled set with the duplicated images re-numbered
    (pycocotools keys everything by image id; see :func:`resample_images`), which the tests check
    on explicit resamples, except for the order of exactly tied scores within one image (COCO
    breaks ties by copy, this by detection). 1000 resamples of 200 frames take well under a
    second, versus minutes for 1000 COCOeval runs.

    Args:
        gt_dict: COCO ground-truth dict.
        detections: COCO results records.
        n_boot: Number of resamples (>= 1).
        rng: Random generator (required; pass ``np.random.default_rng(seed)``).
        alpha: 1 - confidence level, in (0, 1); 0.05 gives a 95 % interval.
        metric: "ap50" (COCOeval run at IoU 0.5 only) or "ap50_95".
        class_ids: Class ids.
        image_ids: Frames to resample; all ground-truth images when None.

    Returns:
        ``{class_id: BootstrapCI}``; classes without ground truth get nan point and bounds.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    if isinstance(n_boot, bool) or not isinstance(n_boot, (int, np.integer)) or n_boot < 1:
        raise ValueError(f"n_boot: expected an int >= 1, got {n_boot!r}")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha: expected a value in (0, 1), got {alpha!r}")
    if metric not in BOOTSTRAP_METRICS:
        raise ValueError(f"metric: expected one of {BOOTSTRAP_METRICS}, got {metric!r}")
    iou_thresholds = IOU_THRESHOLDS[:1] if metric == "ap50" else IOU_THRESHOLDS
    matches = match_table(gt_dict, detections, class_ids, image_ids, iou_thresholds)
    n_images = len(next(iter(matches.values())).image_ids)
    image_weights = bootstrap_weights(n_images, int(n_boot), rng).astype(np.float64)
    result = {}
    for class_id, match in matches.items():
        ones = np.ones((1, len(match.scores)))
        point = float(
            interpolated_ap(
                match.true_positive, match.ignored, ones, np.array([match.n_gt_per_image.sum()], float)
            ).mean()
        )
        n_gt = image_weights @ match.n_gt_per_image.astype(np.float64)
        values = np.empty(n_boot)
        chunk = max(1, 2_000_000 // max(1, len(match.scores)))
        for start in range(0, n_boot, chunk):
            rows = slice(start, start + chunk)
            det_weights = image_weights[rows][:, match.image_index]
            values[rows] = interpolated_ap(match.true_positive, match.ignored, det_weights, n_gt[rows]).mean(axis=1)
        valid = values[~np.isnan(values)]
        if valid.size:
            low, high = np.quantile(valid, [alpha / 2, 1 - alpha / 2])
        else:
            low = high = float("nan")
        result[class_id] = BootstrapCI(
            class_id=class_id,
            metric=metric,
            point=point,
            low=float(low),
            high=float(high),
            alpha=float(alpha),
            n_boot=int(n_boot),
            n_valid=int(valid.size),
        )
    return result


def resample_images(
    gt_dict: Mapping[str, Any], detections: Sequence[Mapping[str, Any]], image_ids: Sequence[int]
) -> tuple[dict[str, list[dict]], list[dict[str, Any]]]:
    """Materialise a resample of images (with repeats) as a new COCO set, re-numbering images.

    pycocotools keys images, annotations and matches by image id, so a frame drawn twice must
    appear under two ids. The k-th entry of ``image_ids`` becomes image ``k + 1``; annotation ids
    are re-numbered from 1; detections are copied onto every copy of their image.

    Args:
        gt_dict: COCO ground-truth dict.
        detections: COCO results records.
        image_ids: (N,) sequence of ground-truth image ids, repeats allowed.

    Returns:
        (ground-truth dict, detection records) of the resampled set.
    """
    _validate_gt_dict(gt_dict)
    images = {image["id"]: image for image in gt_dict["images"]}
    annotations_by_image: dict[int, list[dict]] = {}
    for ann in gt_dict["annotations"]:
        annotations_by_image.setdefault(ann["image_id"], []).append(ann)
    detections_by_image: dict[int, list[Mapping[str, Any]]] = {}
    for record in detections:
        detections_by_image.setdefault(record["image_id"], []).append(record)
    new_images, new_annotations, new_detections = [], [], []
    for position, image_id in enumerate(image_ids):
        if image_id not in images:
            raise ValueError(f"image_ids[{position}]: {image_id!r} is not in the ground truth")
        new_id = position + 1
        new_images.append({**images[image_id], "id": new_id})
        for ann in annotations_by_image.get(image_id, []):
            new_annotations.append({**ann, "id": len(new_annotations) + 1, "image_id": new_id})
        for record in detections_by_image.get(image_id, []):
            new_detections.append({**record, "image_id": new_id, "bbox": list(record["bbox"])})
    categories = [dict(category) for category in gt_dict["categories"]]
    return {"images": new_images, "annotations": new_annotations, "categories": categories}, new_detections


# --------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------

RECORD_FIELDS: tuple[str, ...] = (
    "model",
    "rate",
    "class",
    "class_id",
    "n_gt",
    "n_det",
    "ap50",
    "ap75",
    "ap50_95",
    "precision",
    "recall",
    "f1",
    "best_conf",
    "precision_at_conf",
    "recall_at_conf",
    "f1_at_conf",
    "conf",
    "ap50_ci_low",
    "ap50_ci_high",
    "ap50_95_ci_low",
    "ap50_95_ci_high",
    "ap50_drop_pct",
    "ap50_95_drop_pct",
    "f1_drop_pct",
    "f1_at_conf_drop_pct",
)
"""Keys of every :func:`metric_records` record, in column order."""

DROP_METRICS = ("ap50", "ap50_95", "f1", "f1_at_conf")
"""Metrics that get a ``<metric>_drop_pct`` column (percent drop from the clean rate)."""


def metric_records(
    results: Mapping[tuple[str, float], Mapping[int, ClassMetrics]],
    cis: Mapping[tuple[str, float], Mapping[int, BootstrapCI]]
    | Sequence[Mapping[tuple[str, float], Mapping[int, BootstrapCI]]]
    | None = None,
    *,
    clean_rate: float = 0.0,
    class_names: Sequence[str] = CLASS_NAMES,
) -> list[dict[str, Any]]:
    """Flatten evaluations into one record per (model, rate, class).

    Args:
        results: ``{(model, rate_mm_h): {class_id: ClassMetrics}}`` (e.g. :func:`evaluate`
            outputs).
        cis: Optional bootstrap intervals ``{(model, rate): {class_id: BootstrapCI}}``, or a
            sequence of such mappings (one per metric); fills ``<metric>_ci_low/high``.
        clean_rate: The reference rate of the ``*_drop_pct`` columns.
        class_names: ``class_names[class_id]`` is written as ``class``.

    Returns:
        Records with exactly the keys of ``RECORD_FIELDS``, ordered by model (first appearance),
        rate (ascending), then class (mapping order). Missing values are nan, e.g. the CI columns
        without ``cis`` and the drop columns when the model has no clean-rate result.
    """
    if cis is None:
        ci_maps: list[Mapping] = []
    elif isinstance(cis, Mapping):
        ci_maps = [cis]
    else:
        ci_maps = list(cis)
    models: list[str] = []
    for model, _rate in results:
        if model not in models:
            models.append(model)
    nan = float("nan")
    records = []
    for model in models:
        rates = sorted(float(rate) for m, rate in results if m == model)
        keys = {float(rate): (m, rate) for m, rate in results if m == model}
        clean_key = keys.get(float(clean_rate))
        clean = results[clean_key] if clean_key is not None else {}
        for rate in rates:
            key = keys[rate]
            for class_id, metrics in results[key].items():
                if not 0 <= class_id < len(class_names):
                    raise ValueError(
                        f"results[{key}]: class id {class_id} has no name in class_names {tuple(class_names)}"
                    )
                record = {field: nan for field in RECORD_FIELDS}
                values = dataclasses.asdict(metrics)
                record.update({name: values[name] for name in RECORD_FIELDS if name in values})
                record.update({"model": model, "rate": rate, "class": class_names[class_id], "class_id": class_id})
                for ci_map in ci_maps:
                    interval = ci_map.get(key, {}).get(class_id)
                    if interval is not None:
                        record[f"{interval.metric}_ci_low"] = interval.low
                        record[f"{interval.metric}_ci_high"] = interval.high
                reference = clean.get(class_id)
                for name in DROP_METRICS:
                    record[f"{name}_drop_pct"] = (
                        percent_drop(getattr(reference, name), values[name]) if reference is not None else nan
                    )
                records.append({field: record[field] for field in RECORD_FIELDS})
    return records


def robustness_records(
    records: Sequence[Mapping[str, Any]], metrics: Sequence[str] = ("ap50", "f1")
) -> list[dict[str, Any]]:
    """mPC / rPC per (model, class, metric) from :func:`metric_records` records.

    Args:
        records: Records with at least ``model``, ``rate`` (mm/h), ``class`` and the ``metrics``
            keys; values may be nan or None (JSON null).
        metrics: Record keys to summarise.

    Returns:
        Records ``{model, class, metric, clean, worst_rate, at_worst_rate, drop_pct, mpc, rpc}``
        in first-appearance order: ``clean`` is P, the value at rate 0 (nan without one),
        ``worst_rate`` the highest rate present, ``drop_pct`` the percent drop there, mPC the
        mean over rates > 0 (nan without any), rPC = mPC / P.
    """
    groups: dict[tuple[str, str], dict[float, Mapping[str, Any]]] = {}
    for record in records:
        groups.setdefault((record["model"], record["class"]), {})[float(record["rate"])] = record
    nan = float("nan")
    summary = []
    for (model, class_name), by_rate in groups.items():
        for metric in metrics:
            values = {rate: _as_float(by_rate[rate][metric]) for rate in sorted(by_rate)}
            worst_rate = max(values)
            clean = values.get(0.0, nan)
            has_rain = worst_rate > 0
            summary.append(
                {
                    "model": model,
                    "class": class_name,
                    "metric": metric,
                    "clean": clean,
                    "worst_rate": worst_rate,
                    "at_worst_rate": values[worst_rate],
                    "drop_pct": percent_drop(clean, values[worst_rate]),
                    "mpc": mpc(values) if has_rain else nan,
                    "rpc": rpc(values) if has_rain and 0.0 in values else nan,
                }
            )
    return summary


def _as_float(value: Any) -> float:
    """float(value), with None (a JSON null) read as nan."""
    return float("nan") if value is None else float(value)
