"""COCO set-up and matching: the one place rainbench builds pycocotools objects and runs COCOeval.

:func:`coco_ground_truth` and :func:`coco_detections` turn per-image arrays into COCO dicts and
results records; :func:`run_cocoeval` validates them, indexes them as pycocotools ``COCO``
objects and runs ``COCOeval`` with rainbench's parameters (bbox, maxDets 100, the given area
ranges and IoU thresholds). Every metric that needs COCO (AP, the YOLO F1 matches, the AP
breakdowns, the bootstrap) goes through it; :func:`class_matches` and :func:`ap_per_iou` read its
results back as arrays. Conventions: see :mod:`rainbench.eval.metrics`.
"""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval, Params

from rainbench.store.classes import PAPER_CLASS_NAMES, PAPER_CLASSES

IOU_THRESHOLDS: np.ndarray = Params(iouType="bbox").iouThrs.copy()
"""(10,) float64 COCO IoU thresholds 0.50:0.05:0.95, exactly as pycocotools builds them."""

RECALL_THRESHOLDS: np.ndarray = Params(iouType="bbox").recThrs.copy()
"""(101,) float64 COCO recall thresholds 0.00:0.01:1.00, exactly as pycocotools builds them."""

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
) -> tuple[COCOeval, list[int]]:
    """Validate the inputs, index them as pycocotools ``COCO`` objects and run COCOeval quietly.

    The one COCO set-up of rainbench: bbox IoU, ``maxDets = [MAX_DETECTIONS]``, one area range
    per entry of ``area_ranges`` (labelled "0", "1", ...), the given IoU thresholds.

    Args:
        gt_dict: COCO ground-truth dict (see :func:`coco_ground_truth`); copied, not modified.
        detections: COCO results records (bbox ``[x, y, w, h]`` in pixels, score in [0, 1]);
            copied, not modified; may be empty.
        class_ids: Class ids to evaluate (unique, all ground-truth categories).
        image_ids: Images to evaluate; all ground-truth images when None.
        area_ranges: (lo, hi) area ranges of COCOeval's area-range test, squared pixels.
        iou_thresholds: (T,) float64 IoU thresholds.
        accumulate: Also run ``accumulate`` (fills ``eval``); ``evalImgs`` is always filled.
        gt_areas: (A,) float areas replacing the annotations' ``area`` (aligned with
            ``gt_dict["annotations"]``), or None to keep them.
        detection_area: One area given to every detection instead of ``w * h``, or None.

    Returns:
        (the evaluated COCOeval, ``class_ids`` as a validated list of ints in the given order).
    """
    validate_gt_dict(gt_dict)
    coco_gt = _coco_from_gt(gt_dict, area_override=gt_areas)
    class_ids = _check_class_ids(class_ids, coco_gt)
    image_ids = _check_image_ids(image_ids, coco_gt)
    coco_dt = _coco_from_detections(coco_gt, detections, area_override=detection_area)
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
    return evaluator, class_ids


def class_matches(evaluator: COCOeval, area_index: int = 0) -> dict[int, ClassMatches]:
    """Read COCOeval ``evalImgs`` into one :class:`ClassMatches` per category (accumulate's order).

    Args:
        evaluator: COCOeval after ``evaluate`` (see :func:`run_cocoeval`).
        area_index: Index of the area range whose matches are read.

    Returns:
        ``{class_id: ClassMatches}`` for every evaluated class, in COCOeval's sorted order.
    """
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
    evaluator, class_ids = run_cocoeval(
        gt_dict, detections, class_ids, image_ids, iou_thresholds=iou_thresholds, accumulate=False
    )
    matches = class_matches(evaluator)
    return {class_id: matches[class_id] for class_id in class_ids}


def iou_index(iou_thresholds: np.ndarray, iou: float) -> int:
    """Index of ``iou`` in the (T,) float64 ``iou_thresholds`` (compared with ``np.isclose``)."""
    return int(np.flatnonzero(np.isclose(iou_thresholds, iou))[0])


def ap_per_iou(evaluator: COCOeval, class_id: int, area_index: int = 0) -> np.ndarray:
    """Per-IoU AP of one class and area range from an accumulated COCOeval.

    Reads the slice ``eval["precision"][:, :, k, area_index, 0]`` ((T, R) float64, -1 where the
    class has no ground truth) of the class's position ``k`` among COCOeval's sorted category ids,
    and averages it over the recall thresholds as ``COCOeval.summarize`` does.

    Args:
        evaluator: COCOeval after ``evaluate`` and ``accumulate`` (see :func:`run_cocoeval`).
        class_id: One of the evaluated class ids.
        area_index: Index of the area range.

    Returns:
        (T,) float64 AP per IoU threshold, nan where the class has no ground truth.
    """
    k = list(evaluator.params.catIds).index(class_id)
    precision = evaluator.eval["precision"][:, :, k, area_index, 0]
    valid = precision > -1
    with np.errstate(invalid="ignore"):
        return np.where(valid.any(axis=1), np.where(valid, precision, 0).sum(axis=1) / valid.sum(axis=1), np.nan)
