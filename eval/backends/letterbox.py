"""Pre- and post-processing that the ONNX and Darknet backends share (ultralytics does its own).

Pre-processing: RGB, letterboxed (aspect kept, grey 114 padding, centred) to ``imgsz`` on the
long side; ONNX models with a dynamic input get the smallest multiple of 32 around the image
(640x480 for 800x600 frames, :func:`rect_shape`), fixed-size inputs get their own size
(``--imgsz`` must equal its long side). Darknet networks take their ``[net] width/height`` and
are stretched, not letterboxed, unless the cfg says ``letter_box=1`` (how Darknet itself runs
them). Post-processing: confidence floor, per-class NMS (torchvision), at most ``max_det`` boxes
(:func:`select_detections`), letterbox undone, boxes clipped to the image (:func:`unletterbox`).
"""

from __future__ import annotations

import numpy as np

LETTERBOX_FILL = 114
"""Grey level of the letterbox padding (ultralytics' value)."""


def letterbox(image: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Resize ``image`` (H, W, 3) keeping its aspect ratio into a ``shape`` (h, w) canvas, centred,
    padded with grey 114. Returns ``(canvas (h, w, 3) uint8, gain, (pad_x, pad_y))``: a point
    (x, y) of the image lands at ``(x * gain + pad_x, y * gain + pad_y)`` on the canvas."""
    import cv2

    height, width = image.shape[:2]
    gain, (new_h, new_w), (top, left) = letterbox_geometry(height, width, shape)
    resized = image if (new_w, new_h) == (width, height) else cv2.resize(
        image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    canvas = np.full((shape[0], shape[1], 3), LETTERBOX_FILL, dtype=np.uint8)
    canvas[top:top + new_h, left:left + new_w] = resized
    return canvas, gain, (float(left), float(top))


def letterbox_geometry(height: int, width: int, shape: tuple[int, int]
                       ) -> tuple[float, tuple[int, int], tuple[int, int]]:
    """Where a ``height`` x ``width`` image goes on a ``shape`` (h, w) letterbox canvas (ultralytics'
    LetterBox): ``(gain, (new_h, new_w) resized size, (top, left) offset)``."""
    gain = min(shape[0] / height, shape[1] / width)
    new_w, new_h = int(round(width * gain)), int(round(height * gain))
    pad_x, pad_y = (shape[1] - new_w) / 2, (shape[0] - new_h) / 2
    return gain, (new_h, new_w), (int(round(pad_y - 0.1)), int(round(pad_x - 0.1)))


def rect_shape(height: int, width: int, imgsz: int, stride: int = 32) -> tuple[int, int]:
    """The smallest ``stride`` multiple (h, w) holding the image scaled to ``imgsz`` on its long
    side (ultralytics' rectangular inference shape): 800x600 at 640 -> (480, 640)."""
    gain = imgsz / max(height, width)
    return (int(np.ceil(round(height * gain) / stride) * stride),
            int(np.ceil(round(width * gain) / stride) * stride))


def unletterbox(boxes: np.ndarray, gain: float | tuple[float, float], pad: tuple[float, float],
                width: int, height: int) -> np.ndarray:
    """Boxes (K, 4) xyxy on the letterboxed canvas -> (K, 4) float32 xyxy in original pixels,
    clipped to the ``width`` x ``height`` image. ``gain``: one scale, or (x, y) scales of a
    stretched (not letterboxed) resize."""
    gain_x, gain_y = gain if isinstance(gain, tuple) else (gain, gain)
    out = np.asarray(boxes, np.float64).reshape(-1, 4).copy()
    out[:, [0, 2]] = np.clip((out[:, [0, 2]] - pad[0]) / gain_x, 0, width)
    out[:, [1, 3]] = np.clip((out[:, [1, 3]] - pad[1]) / gain_y, 0, height)
    return out.astype(np.float32)


def select_detections(boxes: np.ndarray, scores: np.ndarray, lookup: np.ndarray, *, conf: float,
                      iou: float, max_det: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidates -> detections as ultralytics predicts with ``classes=``: each box takes its best
    class; boxes whose best class is dropped, or whose score is not above ``conf``, go; then
    per-class NMS at ``iou`` and the ``max_det`` best. ``boxes`` (N, 4) xyxy, ``scores`` (N, nc),
    ``lookup`` (nc,) model class -> rainbench id (-1 dropped). Returns (boxes (K, 4) float32,
    scores (K,) float32, ids (K,) int64)."""
    import torch
    import torchvision

    best = scores.argmax(axis=1)
    best_scores = scores[np.arange(len(scores)), best]
    mapped = lookup[best]
    rows = np.flatnonzero((best_scores > conf) & (mapped >= 0))
    candidate_boxes = boxes[rows]
    candidate_scores = best_scores[rows]
    candidate_ids = mapped[rows]
    order = torchvision.ops.batched_nms(torch.from_numpy(np.ascontiguousarray(candidate_boxes, np.float32)),
                                        torch.from_numpy(np.ascontiguousarray(candidate_scores, np.float32)),
                                        torch.from_numpy(candidate_ids.astype(np.int64)), iou).numpy()[:max_det]
    return (candidate_boxes[order].astype(np.float32).reshape(-1, 4),
            candidate_scores[order].astype(np.float32), candidate_ids[order].astype(np.int64))
