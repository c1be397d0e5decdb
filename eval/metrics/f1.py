"""YOLO-convention precision, recall and F1 (ultralytics ``ap_per_class``) from COCO matches.

Fed with :class:`rainbench.eval.metrics.coco.ClassMatches` (COCOeval's TP/FP matches): the
precision and recall of every class as functions of the confidence threshold over a 1000-point
grid, the confidence maximising the smoothed mean F1 over classes, and the values at a fixed
confidence.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .coco import ClassMatches

CONFIDENCE_GRID: np.ndarray = np.linspace(0.0, 1.0, 1000)
"""(1000,) float64 confidence grid of the YOLO precision/recall/F1 curves (ultralytics)."""

DEFAULT_CONF = 0.25
"""Fixed confidence threshold of the ``*_at_conf`` metrics (ultralytics' predict default)."""

F1_SMOOTH_FRACTION = 0.1
"""Box-filter width (fraction of the grid) used by ultralytics before taking the F1 argmax."""

EPS = 1e-16
"""Epsilon of ultralytics' recall and F1 formulas."""


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


def yolo_f1(
    matches: Mapping[int, ClassMatches], iou_index: int, conf: float
) -> dict[int, tuple[float, float, float, float, float, float, float]]:
    """YOLO precision / recall / F1 of every class, at the shared best-F1 confidence and at ``conf``.

    Detections COCOeval ignores at the IoU threshold are dropped; a class's ``n_gt`` is its
    non-ignored ground truths. The mean F1 curve over the classes with ground truth is
    box-smoothed (:func:`smooth`) and its argmax on ``CONFIDENCE_GRID`` is ``best_conf``.

    Args:
        matches: ``{class_id: ClassMatches}`` of the evaluated classes.
        iou_index: Row of the matches' IoU thresholds that decides TP / FP (IoU 0.5 in
            :func:`rainbench.eval.metrics.evaluation.evaluate`).
        conf: Fixed confidence threshold of the ``@conf`` values, in [0, 1].

    Returns:
        ``{class_id: (precision, recall, f1, best_conf, precision@conf, recall@conf, f1@conf)}``;
        nan for a class without ground truth (``best_conf`` too when no class has any).
    """
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
