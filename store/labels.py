"""The labels of one frame as writer and reader share them (the rows of ``/labels``).

Boxes are float32 ``x1, y1, x2, y2`` in pixel-edge coordinates: a box covering columns 10..19
has ``x1 = 10, x2 = 20`` (``x2 = last column + 1``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _no_boxes() -> np.ndarray:
    return np.zeros((0, 4), np.float32)


def _no_ids() -> np.ndarray:
    return np.zeros(0, np.int32)


@dataclass(frozen=True)
class FrameLabels:
    """Labels of one frame; M labelled instances, sorted by instance id.

    bbox, bbox_amodal: (M, 4) float32 xyxy pixel-edge; class_id, instance_id: (M,) int32;
    visible_fraction, truncation: (M,) float32 in [0, 1].

    The N actors with visible pixels that the label filter leaves out (too small, too hidden)
    are the frame's ignore regions (``/ignore`` in a shard): ignore_bbox (N, 4) float32 xyxy
    pixel-edge, the union of the actor's visible and unoccluded in-image boxes; ignore_class_id,
    ignore_instance_id (N,) int32. An evaluator counts a detection of one neither right nor
    wrong (KITTI's DontCare, COCO's crowd). ``len()`` counts the labels only.
    """

    bbox: np.ndarray
    bbox_amodal: np.ndarray
    class_id: np.ndarray
    instance_id: np.ndarray
    visible_fraction: np.ndarray
    truncation: np.ndarray
    ignore_bbox: np.ndarray = field(default_factory=_no_boxes)
    ignore_class_id: np.ndarray = field(default_factory=_no_ids)
    ignore_instance_id: np.ndarray = field(default_factory=_no_ids)

    def __len__(self) -> int:
        return int(self.instance_id.shape[0])
