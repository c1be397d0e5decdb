"""The labels of one frame as writer and reader share them (the rows of ``/labels``).

Boxes are float32 ``x1, y1, x2, y2`` in pixel-edge coordinates: a box covering columns 10..19
has ``x1 = 10, x2 = 20`` (``x2 = last column + 1``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FrameLabels:
    """Labels of one frame; M labelled instances, sorted by instance id.

    bbox, bbox_amodal: (M, 4) float32 xyxy pixel-edge; class_id, instance_id: (M,) int32;
    visible_fraction, truncation: (M,) float32 in [0, 1].
    """

    bbox: np.ndarray
    bbox_amodal: np.ndarray
    class_id: np.ndarray
    instance_id: np.ndarray
    visible_fraction: np.ndarray
    truncation: np.ndarray

    def __len__(self) -> int:
        return int(self.instance_id.shape[0])
