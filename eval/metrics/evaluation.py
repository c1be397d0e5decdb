"""Per-class evaluation of one detection set: COCO AP and YOLO-style P / R / F1."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rainbench.store.classes import PAPER_CLASSES

from .coco import DEFAULT_BACKEND, IOU_THRESHOLDS, ap_per_iou, class_matches, iou_index, run_cocoeval
from .f1 import DEFAULT_CONF, yolo_f1

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


def evaluate(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
    conf: float = DEFAULT_CONF,
    *,
    backend: str = DEFAULT_BACKEND,
) -> dict[int, ClassMetrics]:
    """Per-class COCO AP and YOLO-convention precision / recall / F1.

    One COCO evaluation (:func:`.coco.run_cocoeval`: bbox, area range "all", maxDets 100, IoU
    0.50:0.95) over all requested classes provides AP50 / AP75 / AP50-95 (the accumulated
    101-point interpolated precision, averaged as COCOeval.summarize does) and the TP/FP matches
    at IoU 0.5 (COCO's ``evalImgs``). From
    those matches, as ultralytics ``ap_per_class`` does: precision and recall curves of every
    class over a 1000-point confidence grid, F1 = 2PR / (P + R + 1e-16), mean F1 over the
    classes with ground truth, box-smoothed (10 %), argmax -> one ``best_conf`` shared by all
    classes; each class reports P, R, F1 at that grid point. Classes with ground truth but no
    detections contribute zero curves to the mean. Differences from YOLO val: ignored ground
    truths (crowd) do not count in ``n_gt`` and detections COCOeval ignores are dropped, and
    matching is COCO's (greedy by score, best IoU) instead of ultralytics' IoU-matrix matching.

    Args:
        gt_dict: COCO ground-truth dict (see :func:`.coco.coco_ground_truth`).
        detections: COCO results records ``{"image_id", "category_id", "bbox": [x, y, w, h],
            "score"}``; may be empty; images without detections are fine.
        class_ids: Class ids to evaluate (must be ground-truth categories).
        image_ids: Images to evaluate; all ground-truth images when None.
        conf: Fixed confidence threshold of the ``*_at_conf`` values, in [0, 1].
        backend: Metrics backend, ``METRICS_BACKENDS`` ("numpy" or the reference "pycocotools";
            the same values).

    Returns:
        ``{class_id: ClassMetrics}`` in ``class_ids`` order. A class without (non-ignored)
        ground truth gets ``n_gt = 0`` and nan for AP, precision, recall and F1.
    """
    if not 0.0 <= conf <= 1.0:
        raise ValueError(f"conf: expected a confidence in [0, 1], got {conf!r}")
    evaluation = run_cocoeval(gt_dict, detections, class_ids, image_ids, backend=backend)
    class_ids = evaluation.class_ids
    matches = class_matches(evaluation)
    iou50 = iou_index(IOU_THRESHOLDS, 0.5)
    iou75 = iou_index(IOU_THRESHOLDS, 0.75)
    f1_values = yolo_f1({c: matches[c] for c in class_ids}, iou50, conf)
    result = {}
    for class_id in class_ids:
        ap_by_iou = ap_per_iou(evaluation, class_id)
        match = matches[class_id]
        precision, recall, f1, best_conf, precision_at, recall_at, f1_at = f1_values[class_id]
        result[class_id] = ClassMetrics(
            class_id=class_id,
            n_gt=int(match.n_gt_per_image.sum()),
            n_det=len(match.scores),
            ap50=float(ap_by_iou[iou50]),
            ap75=float(ap_by_iou[iou75]),
            ap50_95=float(np.mean(ap_by_iou)),
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
