"""COCO AP of one class restricted to a slice of the ground truth: by object size or by visibility."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rainbench.store.classes import PAPER_CLASSES

from .coco import DEFAULT_BACKEND, CocoEvaluation, ap_per_iou, class_matches, iou_index, run_cocoeval, validate_gt_dict

SIZE_RANGES: dict[str, tuple[float, float]] = {
    "small": (0.0, 32.0**2),
    "medium": (32.0**2, 96.0**2),
    "large": (96.0**2, 1e5**2),
}
"""COCO object-size area ranges (squared pixels, bounds inclusive as in pycocotools)."""


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


def _breakdown(evaluation: CocoEvaluation, labels: Sequence[str]) -> dict[str, dict[int, BreakdownAP]]:
    """Read per-(area range, class) AP50 / AP50-95 / n_gt out of an accumulated evaluation, the
    classes in the evaluation's order."""
    matches_by_range = [class_matches(evaluation, a) for a in range(len(labels))]
    iou50 = iou_index(evaluation.iou_thresholds, 0.5)
    result: dict[str, dict[int, BreakdownAP]] = {}
    for a, label in enumerate(labels):
        per_class = {}
        for class_id in evaluation.class_ids:
            ap_by_iou = ap_per_iou(evaluation, class_id, a)
            per_class[class_id] = BreakdownAP(
                ap50=float(ap_by_iou[iou50]),
                ap50_95=float(np.mean(ap_by_iou)),
                n_gt=int(matches_by_range[a][class_id].n_gt_per_image.sum()),
            )
        result[label] = per_class
    return result


def ap_by_size(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
    *,
    backend: str = DEFAULT_BACKEND,
) -> dict[str, dict[int, BreakdownAP]]:
    """COCO AP by object size (small < 32², medium 32²..96², large > 96² px², box area).

    Standard COCOeval area-range logic: ground truths outside the range are ignored, detections
    matched to them are ignored, and unmatched detections whose own box area is outside the
    range are ignored (so a small false positive does not hurt AP-large).

    Args:
        gt_dict: COCO ground-truth dict; ``area`` of each annotation is used (box area when built
            by :func:`.coco.coco_ground_truth`).
        detections: COCO results records.
        class_ids: Class ids to evaluate.
        image_ids: Images to evaluate; all when None.
        backend: Metrics backend, ``METRICS_BACKENDS``.

    Returns:
        ``{"small" | "medium" | "large": {class_id: BreakdownAP}}``.
    """
    evaluation = run_cocoeval(
        gt_dict, detections, class_ids, image_ids, area_ranges=list(SIZE_RANGES.values()), backend=backend
    )
    return _breakdown(evaluation, list(SIZE_RANGES))


def ap_by_visibility(
    gt_dict: Mapping[str, Any],
    detections: Sequence[Mapping[str, Any]],
    visible_fraction: np.ndarray,
    bins: Sequence[float] = (0.0, 0.25, 0.5, 0.75, 1.0),
    unmatched: str = "fp",
    class_ids: Sequence[int] = PAPER_CLASSES,
    image_ids: Sequence[int] | None = None,
    *,
    backend: str = DEFAULT_BACKEND,
) -> dict[str, dict[int, BreakdownAP]]:
    """COCO AP by ground-truth visible fraction, one COCO evaluation with one "area range" per bin.

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
        backend: Metrics backend, ``METRICS_BACKENDS``.

    Returns:
        ``{"lo-hi": {class_id: BreakdownAP}}`` with labels like ``"0.25-0.50"``.
    """
    validate_gt_dict(gt_dict)
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
    labels = [f"{lo:.2f}-{hi:.2f}" for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    ranges = [(float(i), float(i)) for i in range(len(labels))]
    evaluation = run_cocoeval(
        gt_dict,
        detections,
        class_ids,
        image_ids,
        area_ranges=ranges,
        gt_areas=gt_area,
        detection_area=math.nan if unmatched == "fp" else -math.inf,
        backend=backend,
    )
    return _breakdown(evaluation, labels)
