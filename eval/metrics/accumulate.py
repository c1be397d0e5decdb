"""COCO's 101-point interpolated AP (``COCOeval.accumulate``) for many weighted copies at once.

One class's detections, matched once (:class:`rainbench.eval.metrics.coco.ClassMatches`), are
re-scored with each detection counted an integer number of times: once each for COCO's AP, its
image's multiplicity for a bootstrap resample of images. Both entry points reduce the weights to
the cumulative TP and FP weight at each TP detection, as (S, B) arrays (TP-major: each copy a
column, so that cumulative sums and gathers run over contiguous rows), and share
:func:`ap_from_true_positives`, which has no Python loop over copies.

Why only the TP positions matter: recall only grows at a TP, so the first detection whose recall
reaches a threshold is a TP (or, for threshold 0, the first detection, whose envelope value is the
maximum over all TPs); and precision never grows at an FP or an ignored detection, so the
right-to-left maximum of precision (COCO's monotone envelope) at a TP is the maximum over the TPs
from there on. Every sum is a sum of small integers, exact in any order, and every division the
same float64 division, so the numbers are bit for bit those of ``COCOeval.accumulate``'s loop
over every detection.
"""

from __future__ import annotations

import numpy as np
from pycocotools.cocoeval import Params

RECALL_THRESHOLDS: np.ndarray = Params(iouType="bbox").recThrs.copy()
"""(101,) float64 COCO recall thresholds 0.00:0.01:1.00, exactly as pycocotools builds them."""

_CHUNK_ELEMENTS = 2_000_000
"""Copies are processed in chunks of about this many (copy, TP) entries."""


def thresholds_reached(tp_at: np.ndarray, n_gt: np.ndarray, recall_thresholds: np.ndarray) -> np.ndarray:
    """How many recall thresholds each recall ``tp_at / n_gt`` reaches.

    Args:
        tp_at: (S, B) float64 integer-valued TP counts of B copies.
        n_gt: (B,) float64 positive integer-valued ground-truth counts.
        recall_thresholds: (R,) float64 increasing recall thresholds.

    Returns:
        (S, B) int64 ``searchsorted(recall_thresholds, tp_at / n_gt, side="right")``, each
        distinct (count, total) pair divided once: through a table of every count up to the
        largest over the distinct totals when that table is small, else over the distinct pairs.
    """
    totals, column_total = np.unique(n_gt, return_inverse=True)
    top = int(tp_at.max(initial=0.0)) + 1
    keys = column_total.reshape(1, -1) * top + tp_at.astype(np.int64)
    if len(totals) * top <= max(4 * tp_at.size, 1 << 16):
        keys_used, index = np.arange(len(totals) * top), keys
    else:
        keys_used, inverse = np.unique(keys, return_inverse=True)
        index = inverse.reshape(keys.shape)
    counts, total_index = np.divmod(keys_used, top)[::-1]
    return np.searchsorted(recall_thresholds, counts / totals[total_index], side="right")[index]


def ap_from_true_positives(
    tp_at: np.ndarray, fp_at: np.ndarray, n_gt: np.ndarray, recall_thresholds: np.ndarray = RECALL_THRESHOLDS
) -> np.ndarray:
    """COCO interpolated AP of B copies from their cumulative weights at the S TP detections.

    Args:
        tp_at: (S, B) float64 integer-valued cumulative TP weight at each TP detection (in score
            order) of each copy.
        fp_at: (S, B) float64 integer-valued cumulative FP weight before each TP detection.
        n_gt: (B,) float64 positive integer-valued non-ignored ground truths of each copy.
        recall_thresholds: (R,) float64 increasing recall thresholds (COCO's 101).

    Returns:
        (B,) float64 AP: precision ``tp / (tp + fp + spacing(1))`` made monotone from the right,
        sampled at the first TP whose recall ``tp / n_gt`` reaches each threshold (0 where none
        does), averaged over the thresholds.
    """
    n_tp, n_copies = tp_at.shape
    n_thresholds = len(recall_thresholds)
    precision = tp_at / (fp_at + tp_at + np.spacing(1))
    envelope = np.maximum.accumulate(precision[::-1], axis=0)[::-1]
    reached = thresholds_reached(tp_at, n_gt, recall_thresholds)
    first_reached = np.diff(reached, axis=0, prepend=0)  # thresholds each TP is the first to reach
    n_reached = reached[-1] if n_tp else np.zeros(n_copies, dtype=np.int64)
    # Copy b's samples: each TP's envelope value once per threshold it first reaches, then zeros.
    values = np.repeat(envelope.T.ravel(), first_reached.T.ravel())
    row_start = np.arange(n_copies) * n_thresholds
    position = np.arange(len(values)) - np.repeat(np.cumsum(n_reached) - n_reached - row_start, n_reached)
    sampled = np.zeros((n_copies, n_thresholds))
    sampled.ravel()[position] = values
    return sampled.mean(axis=1)


def _check_counts(values: np.ndarray, what: str) -> None:
    """One-line ValueError unless ``values`` are non-negative integers (in float64)."""
    if not (np.all(values >= 0) and np.array_equal(values, np.floor(values))):
        raise ValueError(f"{what}: expected non-negative integer-valued weights, got other values")


def _counted(true_positive: np.ndarray, ignored: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
    """(S,) positions of the TP detections and (F,) positions of the FP detections at IoU row t
    (ignored detections are neither)."""
    counted = ~ignored[t]
    return np.flatnonzero(true_positive[t] & counted), np.flatnonzero(~true_positive[t] & counted)


def interpolated_ap(
    true_positive: np.ndarray,
    ignored: np.ndarray,
    det_weights: np.ndarray,
    n_gt: np.ndarray,
    recall_thresholds: np.ndarray = RECALL_THRESHOLDS,
) -> np.ndarray:
    """COCO 101-point interpolated AP for B weighted copies of one class's detections at once.

    Weighted version of ``COCOeval.accumulate``: detection d counts ``det_weights[b, d]`` times in
    copy b (1 everywhere gives COCOeval's AP exactly). Cumulative TP / FP sums over the
    score-sorted detections give recall ``tp / n_gt`` and precision ``tp / (tp + fp +
    spacing(1))``; precision is made monotone from the right, sampled at the first index whose
    recall reaches each threshold (0 past the final recall), and averaged
    (:func:`ap_from_true_positives`).

    Args:
        true_positive: (T, D) bool, detection d is matched at IoU threshold t (COCO order:
            sorted by descending score, see :class:`.coco.ClassMatches`).
        ignored: (T, D) bool, COCO ``dtIgnore`` (neither TP nor FP).
        det_weights: (B, D) float64 non-negative integer-valued weights (copies of detections).
        n_gt: (B,) float64 non-negative integer-valued non-ignored ground truths in each copy.
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
    _check_counts(det_weights, "det_weights")
    _check_counts(n_gt, "n_gt")
    ap = np.full((n_copies, n_thresholds), np.nan)
    valid_rows = np.flatnonzero(n_gt > 0)
    if valid_rows.size == 0:
        return ap
    weights = det_weights[valid_rows].T  # (D, B)
    for t in range(n_thresholds):
        tp_positions, fp_positions = _counted(true_positive, ignored, t)
        fp_weights = np.zeros_like(weights)
        fp_weights[fp_positions] = weights[fp_positions]
        tp_at = np.cumsum(weights[tp_positions], axis=0)
        fp_at = np.cumsum(fp_weights, axis=0)[tp_positions]
        ap[valid_rows, t] = ap_from_true_positives(tp_at, fp_at, n_gt[valid_rows], recall_thresholds)
    return ap


def image_weighted_ap(
    true_positive: np.ndarray,
    ignored: np.ndarray,
    image_index: np.ndarray,
    image_weights: np.ndarray,
    n_gt_per_image: np.ndarray,
    recall_thresholds: np.ndarray = RECALL_THRESHOLDS,
) -> np.ndarray:
    """:func:`interpolated_ap` with every detection weighted by its image's multiplicity.

    Equal to ``interpolated_ap(true_positive, ignored, image_weights[:, image_index],
    image_weights @ n_gt_per_image)`` but without (B, D) arrays: the FP weight between two
    consecutive TPs is a sum over the (image, count) pairs of the FPs there, so the work is
    (S + P, B) for S TPs and P such pairs (sums of small integers: exact).

    Args:
        true_positive: (T, D) bool, detection d matched at IoU threshold t (COCO order).
        ignored: (T, D) bool, COCO ``dtIgnore``.
        image_index: (D,) int64 image of each detection, in [0, N).
        image_weights: (B, N) float64 non-negative integer-valued image multiplicities.
        n_gt_per_image: (N,) int64 non-ignored ground truths per image.
        recall_thresholds: (R,) float64 increasing recall thresholds (COCO's 101).

    Returns:
        (B, T) float64 AP; nan where a copy holds no ground truth.
    """
    n_thresholds = true_positive.shape[0]
    n_copies, n_images = image_weights.shape
    n_gt = image_weights @ np.asarray(n_gt_per_image, dtype=np.float64)
    ap = np.full((n_copies, n_thresholds), np.nan)
    valid_rows = np.flatnonzero(n_gt > 0)
    for t in range(n_thresholds):
        tp_positions, fp_positions = _counted(true_positive, ignored, t)
        n_tp = len(tp_positions)
        tp_images = image_index[tp_positions]
        # The FPs between TP s - 1 and TP s ("segment" s) as (segment, image, count) triples,
        # sorted by segment; an FP after the last TP counts for none.
        segment = np.searchsorted(tp_positions, fp_positions)
        keep = segment < n_tp
        pairs, pair_count = np.unique(segment[keep] * n_images + image_index[fp_positions[keep]], return_counts=True)
        pair_segment, pair_image = np.divmod(pairs, n_images)
        segments, segment_start = np.unique(pair_segment, return_index=True)
        chunk = max(1, _CHUNK_ELEMENTS // max(1, n_tp + len(pairs)))
        for start in range(0, len(valid_rows), chunk):
            rows = valid_rows[start : start + chunk]
            weights = np.ascontiguousarray(image_weights[rows].T)  # (N, B)
            fp_between = np.zeros((n_tp, len(rows)))
            if len(segments):
                fp_weights = weights[pair_image]
                if np.any(pair_count > 1):
                    fp_weights *= pair_count[:, None]
                fp_between[segments] = np.add.reduceat(fp_weights, segment_start, axis=0)
            tp_at = np.cumsum(weights[tp_images], axis=0)
            ap[rows, t] = ap_from_true_positives(tp_at, np.cumsum(fp_between, axis=0), n_gt[rows], recall_thresholds)
    return ap
