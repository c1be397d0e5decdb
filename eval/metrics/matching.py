"""COCOeval's bbox matching (``COCOeval.evaluate``) in vectorised numpy: the ``numpy`` metrics backend.

The same greedy matching as pycocotools' ``evaluateImg``, for every image, class, area range and
IoU threshold at once: per image and class, detections (the ``max_detections`` best by score,
ties in input order) are taken by descending score; each takes, among the ground truths whose IoU
with it reaches the threshold and that are not yet taken (crowd ground truths can be taken again),
the one of highest IoU (the last in input order among equals), preferring a non-ignored ground
truth to an ignored one. A detection matched to an ignored ground truth, or unmatched with an area
outside the area range, is ignored. IoU is pycocotools' ``bbIou`` evaluated with the same float64
operations (for a crowd ground truth, intersection over the detection's area).

Vectorisation: only detections whose IoU reaches the lowest threshold with some ground truth of
their image and class can match; those candidates are processed in rounds, round j taking the
j-th candidate of every (image, class) at once, for every (area range, threshold) column.
Conventions of the inputs and outputs: :mod:`rainbench.eval.metrics`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

IOU_CEILING = 1 - 1e-10
"""pycocotools caps each IoU threshold at this value (``min([t, 1 - 1e-10])``)."""


@dataclass(frozen=True)
class BoxMatching:
    """Matches of the kept detections, grouped by (class, image).

    Attributes:
        group (np.ndarray): (D,) int64 ``class_index * n_images + image_index`` of each kept
            detection; detections are sorted by group, then descending score, then input order.
        source (np.ndarray): (D,) int64 position of each kept detection in the input arrays.
        matched (np.ndarray): (A, T, D) bool, matched to a ground truth at area range a and IoU
            threshold t (an ignored ground truth included).
        ignored (np.ndarray): (A, T, D) bool, COCO ``dtIgnore``.
        n_gt (np.ndarray): (A, n_groups) int64 non-ignored ground truths per area range and group.
    """

    group: np.ndarray
    source: np.ndarray
    matched: np.ndarray
    ignored: np.ndarray
    n_gt: np.ndarray


def bbox_iou(det_boxes: np.ndarray, gt_boxes: np.ndarray, crowd: np.ndarray) -> np.ndarray:
    """IoU of P (detection, ground truth) pairs, as pycocotools' ``bbIou`` computes it.

    Args:
        det_boxes: (P, 4) float64 detection boxes ``[x, y, w, h]``.
        gt_boxes: (P, 4) float64 ground-truth boxes ``[x, y, w, h]``.
        crowd: (P,) bool, the ground truth is a crowd box (union = the detection's area).

    Returns:
        (P,) float64 IoU, 0 where the boxes do not overlap.
    """
    dx, dy, dw, dh = det_boxes.T
    gx, gy, gw, gh = gt_boxes.T
    width = np.minimum(dw + dx, gw + gx) - np.maximum(dx, gx)
    height = np.minimum(dh + dy, gh + gy) - np.maximum(dy, gy)
    intersection = width * height
    det_area = dw * dh
    union = np.where(crowd, det_area, det_area + gw * gh - intersection)
    overlap = (width > 0) & (height > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(overlap, intersection / np.where(overlap, union, 1.0), 0.0)


def match_boxes(
    *,
    gt_group: np.ndarray,
    gt_boxes: np.ndarray,
    gt_area: np.ndarray,
    gt_crowd: np.ndarray,
    det_group: np.ndarray,
    det_boxes: np.ndarray,
    det_score: np.ndarray,
    det_area: np.ndarray,
    n_groups: int,
    area_ranges: np.ndarray,
    iou_thresholds: np.ndarray,
    max_detections: int,
) -> BoxMatching:
    """Match detections to ground truth per (class, image) group, as ``COCOeval.evaluate`` does.

    Args:
        gt_group: (G,) int64 group of each ground truth (input order = annotation order).
        gt_boxes: (G, 4) float64 ground-truth boxes ``[x, y, w, h]``.
        gt_area: (G,) float64 area used by the area-range test.
        gt_crowd: (G,) bool crowd (``iscrowd``) flag: ignored, matched by intersection over the
            detection's area, and takeable by several detections.
        det_group: (D,) int64 group of each detection (input order = record order).
        det_boxes: (D, 4) float64 detection boxes ``[x, y, w, h]``.
        det_score: (D,) float64 scores.
        det_area: (D,) float64 area used by the area-range test (nan passes every range).
        n_groups: Number of groups (``n_classes * n_images``).
        area_ranges: (A, 2) float64 inclusive (lo, hi) area ranges.
        iou_thresholds: (T,) float64 IoU thresholds.
        max_detections: Detections kept per group (COCO maxDets).

    Returns:
        The :class:`BoxMatching` of the kept detections.
    """
    area_ranges = np.asarray(area_ranges, dtype=np.float64).reshape(-1, 2)
    thresholds = np.minimum(np.asarray(iou_thresholds, dtype=np.float64), IOU_CEILING)
    n_areas, n_thresholds = len(area_ranges), len(thresholds)
    lo, hi = area_ranges[:, 0], area_ranges[:, 1]

    # Detections: sorted by group, then descending score (stable: input order breaks ties), the
    # first max_detections of each group kept.
    order = np.lexsort((-det_score, det_group))
    group = det_group[order]
    rank = np.arange(len(group)) - np.searchsorted(group, group, side="left")
    order, group = order[rank < max_detections], group[rank < max_detections]
    boxes, area = det_boxes[order], det_area[order]

    # Ground truth: stable-sorted by group (annotation order within a group), plus one padding
    # entry (index G) that never matches.
    gt_order = np.argsort(gt_group, kind="stable")
    n_gt_boxes = len(gt_order)
    gt_start = np.searchsorted(gt_group[gt_order], np.arange(n_groups), side="left")
    gt_count = np.bincount(gt_group, minlength=n_groups)
    gt_ignored = gt_crowd[None, :] | (gt_area[None, :] < lo[:, None]) | (gt_area[None, :] > hi[:, None])

    # Every (detection, ground truth of its group) pair, by detection then annotation order.
    per_det = gt_count[group]
    pair_det = np.repeat(np.arange(len(group)), per_det)
    pair_offset = np.arange(len(pair_det)) - np.repeat(np.cumsum(per_det) - per_det, per_det)
    pair_gt = gt_order[gt_start[group][pair_det] + pair_offset]
    iou = bbox_iou(boxes[pair_det], gt_boxes[pair_gt], gt_crowd[pair_gt])
    reachable = iou >= thresholds.min(initial=np.inf)
    pair_det, pair_gt, iou = pair_det[reachable], pair_gt[reachable], iou[reachable]

    # Candidates (detections with a reachable ground truth): one row each, padded to P columns.
    candidates, first_pair, n_pairs = np.unique(pair_det, return_index=True, return_counts=True)
    width = int(n_pairs.max(initial=1))
    row = np.repeat(np.arange(len(candidates)), n_pairs)
    column = np.arange(len(pair_det)) - np.repeat(first_pair, n_pairs)
    candidate_gt = np.full((len(candidates), width), n_gt_boxes)
    candidate_gt[row, column] = pair_gt
    candidate_iou = np.full((len(candidates), width), -np.inf)
    candidate_iou[row, column] = iou

    # Columns are (area range, threshold) pairs, c = a * T + t.
    column_thresholds = np.tile(thresholds, n_areas)
    ignored_by_column = np.repeat(np.concatenate([gt_ignored, np.ones((n_areas, 1), bool)], axis=1).T, n_thresholds,
                                  axis=1)
    crowd = np.append(gt_crowd, False)
    taken = np.zeros((n_gt_boxes + 1, n_areas * n_thresholds), dtype=bool)
    chosen_gt = np.full((len(candidates), n_areas * n_thresholds), -1)
    candidate_group = group[candidates]
    round_of = np.arange(len(candidates)) - np.searchsorted(candidate_group, candidate_group, side="left")
    by_round = np.argsort(round_of, kind="stable")
    bounds = np.searchsorted(round_of[by_round], np.arange(int(round_of.max(initial=-1)) + 2), side="left")
    for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
        rows = by_round[start:stop]
        gts = candidate_gt[rows]
        ious = candidate_iou[rows][:, :, None]
        free = ~(taken[gts] & ~crowd[gts][:, :, None])
        allowed = (ious >= column_thresholds) & free
        regular = allowed & ~ignored_by_column[gts]
        allowed = np.where(regular.any(axis=1, keepdims=True), regular, allowed)
        value = np.where(allowed, ious, -np.inf)
        best = allowed & (value == value.max(axis=1, keepdims=True))
        last = width - 1 - np.argmax(best[:, ::-1, :], axis=1)
        found = allowed.any(axis=1)
        pick = np.take_along_axis(gts, last, axis=1)
        chosen_gt[rows] = np.where(found, pick, -1)
        hit_row, hit_column = np.nonzero(found)
        taken[pick[hit_row, hit_column], hit_column] = True

    matched = np.zeros((len(group), n_areas * n_thresholds), dtype=bool)
    matched[candidates] = chosen_gt >= 0
    matched_ignored = np.zeros_like(matched)
    matched_ignored[candidates] = ignored_by_column[np.where(chosen_gt >= 0, chosen_gt, n_gt_boxes),
                                                    np.arange(n_areas * n_thresholds)]
    outside = np.repeat((area[:, None] < lo[None, :]) | (area[:, None] > hi[None, :]), n_thresholds, axis=1)
    ignored = np.where(matched, matched_ignored, outside)
    shape = (len(group), n_areas, n_thresholds)
    return BoxMatching(
        group=group,
        source=order,
        matched=matched.reshape(shape).transpose(1, 2, 0),
        ignored=ignored.reshape(shape).transpose(1, 2, 0),
        n_gt=np.stack([np.bincount(gt_group[~gt_ignored[a]], minlength=n_groups) for a in range(n_areas)]),
    )
