"""The batched torch backend: an ultralytics detection checkpoint run as a plain torch network.

What ``ultralytics.YOLO.predict`` does image by image on the CPU (letterbox with OpenCV, NMS in a
Python loop, box mapping), this backend does for a whole batch with torch on the model's device:

- letterbox: (B, H, W, 3) uint8 frames -> (B, 3, h, w) in 0..1, padded with grey 114 to the
  smallest multiple of 32 around the image (ultralytics' rectangular inference shape,
  :func:`rainbench.eval.backends.letterbox.rect_shape`). On CUDA, on the GPU
  (:func:`letterbox_batch`: bilinear with half-pixel centres, OpenCV's ``INTER_LINEAR`` sampling,
  rounded to uint8 levels); on the CPU with OpenCV's own resize (:func:`letterbox_frames`), so the
  network sees exactly the pixels ultralytics' predict gives it;
- the network, fused (convolution + batch norm) as ultralytics predicts, channels-last, in fp16 on
  CUDA and fp32 on the CPU;
- NMS (:func:`select_batch`): ultralytics' ``non_max_suppression`` step for step (best class per
  box, confidence floor, evaluated classes, the 30 000 best, per-class NMS with its 7 680 px class
  offset, ``max_det``), on the device;
- boxes mapped back to image pixels and clipped (:func:`unletterbox_boxes`), on the device.

The same code runs on the CPU and on CUDA except the resize (the tests run the CPU, and check the
GPU's resize against OpenCV's on the CPU). Against ultralytics' ``predict``: on the CPU the same
input pixels, the same fused network (its convolutions run channels-last, one image per call, so
sums are added in another order) and the same NMS; on CUDA the resize's float arithmetic (a pixel
differs by at most one grey level from OpenCV's fixed point) and fp16 instead of predict's default
fp32 (``tests/test_torch_batched.py``, ``tests/test_train_paper.py``, ``bench/backend_agreement.py``).

Models it runs: ultralytics detection models with a ``Detect`` head that needs NMS (YOLOv3u,
v5u, v8, v9, 11, 12). End-to-end heads (YOLOv10, YOLO26) and other model types (RT-DETR) are run
by ultralytics' own predict (:func:`supports`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from rainbench.eval.backends import BackendError
from rainbench.eval.backends.letterbox import LETTERBOX_FILL, letterbox, letterbox_geometry, rect_shape

MAX_NMS = 30_000
"""Candidates kept per image before NMS, best first (ultralytics' ``max_nms``)."""
CPU_BATCH = 1
"""Images per network call on the CPU: one image's activations stay in cache (at 960 px on a
2-core CPU 12 images/s one at a time against 7 in calls of 16; bench/inference.py). CUDA takes
the whole batch in one call."""
MAX_WH = 7680
"""Per-class coordinate offset of class-aware NMS in pixels (ultralytics' ``max_wh``)."""


def supports(network: Any) -> bool:
    """Whether ``network`` (an ultralytics model's ``nn.Module``) is a detection model whose head
    outputs (B, 4 + nc, N) boxes and class scores that need NMS: a ``Detect`` head (not a
    subclass for segments, poses or rotated boxes) that is not end-to-end."""
    from ultralytics.nn.modules.head import Detect
    from ultralytics.nn.tasks import DetectionModel

    layers = getattr(network, "model", None)
    if type(network) is not DetectionModel or layers is None or len(layers) == 0:
        return False
    head = layers[-1]
    return type(head) is Detect and not bool(getattr(head, "end2end", False))


def letterbox_batch(frames: torch.Tensor, shape: tuple[int, int], dtype: torch.dtype
                    ) -> tuple[torch.Tensor, float, tuple[float, float]]:
    """Letterbox a batch of same-sized frames on their device.

    ``frames``: (B, H, W, 3) uint8 RGB. ``shape``: the canvas (h, w). Returns ``(canvas (B, 3, h,
    w) of dtype in 0..1, gain, (pad_x, pad_y))``: a point (x, y) of a frame lands at ``(x * gain +
    pad_x, y * gain + pad_y)`` on the canvas, as in
    :func:`rainbench.eval.backends.letterbox.letterbox` (the numpy twin, with OpenCV's resize).
    """
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != torch.uint8:
        raise ValueError(f"frames: expected (B, H, W, 3) uint8, got {tuple(frames.shape)} {frames.dtype}")
    count, height, width = frames.shape[:3]
    gain, (new_h, new_w), (top, left) = letterbox_geometry(height, width, shape)
    images = frames.permute(0, 3, 1, 2)
    if (new_w, new_h) != (width, height):
        # Half-pixel centres and no antialiasing as INTER_LINEAR, then uint8 levels as OpenCV
        # writes them.
        images = F.interpolate(images.float(), size=(new_h, new_w), mode="bilinear",
                               align_corners=False, antialias=False).round_().clamp_(0, 255)
    # Channels-last memory (a (B, h, w, 3) block seen as (B, 3, h, w)), as the network runs.
    canvas = torch.full((count, shape[0], shape[1], 3), LETTERBOX_FILL / 255.0, dtype=dtype,
                        device=frames.device).permute(0, 3, 1, 2)
    canvas[:, :, top:top + new_h, left:left + new_w] = images.to(dtype) / 255.0
    return canvas, gain, (float(left), float(top))


def letterbox_frames(frames: torch.Tensor, shape: tuple[int, int]) -> tuple[torch.Tensor, float, tuple[float, float]]:
    """:func:`letterbox_batch` on the CPU with OpenCV's resize
    (:func:`rainbench.eval.backends.letterbox.letterbox`, ultralytics' own pixels): ``frames``
    (B, H, W, 3) uint8 CPU tensor -> (canvas (B, 3, h, w) float32 channels-last in 0..1, gain,
    (pad_x, pad_y))."""
    boxed = [letterbox(frame, shape) for frame in frames.numpy()]
    block = torch.from_numpy(np.stack([canvas for canvas, _, _ in boxed]))
    return block.permute(0, 3, 1, 2).float().div_(255.0), boxed[0][1], boxed[0][2]


def select_batch(prediction: torch.Tensor, lookup: torch.Tensor, *, conf: float, iou: float,
                 max_det: int) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Detections of a batch as ultralytics' ``non_max_suppression(..., classes=kept)`` makes them.

    ``prediction``: (B, 4 + nc, N) head output, boxes as cx, cy, w, h in canvas pixels, class
    scores in 0..1. ``lookup``: (nc,) int64 model class -> rainbench id, -1 for a class that is
    not evaluated. Each box takes its best class; boxes whose score is not above ``conf`` or whose
    best class is dropped go; the ``MAX_NMS`` best are kept; NMS per class at ``iou``; the
    ``max_det`` best stay. Returns per image (boxes (K, 4) float32 xyxy on the canvas, scores
    (K,) float32, ids (K,) int64 rainbench ids), on the prediction's device, best first.
    """
    import torchvision

    prediction = prediction.float()
    scores, best = prediction[:, 4:].max(dim=1)  # (B, N)
    mapped = lookup[best]
    keep = (scores > conf) & (mapped >= 0)
    centres = prediction[:, :4].transpose(1, 2)  # (B, N, 4)
    outputs = []
    for image in range(prediction.shape[0]):
        rows = keep[image].nonzero().view(-1)
        image_scores = scores[image, rows]
        order = image_scores.argsort(descending=True)[:MAX_NMS]
        rows, image_scores = rows[order], image_scores[order]
        xywh = centres[image, rows]
        half = xywh[:, 2:] / 2
        boxes = torch.cat((xywh[:, :2] - half, xywh[:, :2] + half), dim=1)
        classes = best[image, rows]
        kept = torchvision.ops.nms(boxes + classes[:, None].float() * MAX_WH, image_scores, iou)[:max_det]
        outputs.append((boxes[kept], image_scores[kept], mapped[image, rows[kept]]))
    return outputs


def unletterbox_boxes(boxes: torch.Tensor, gain: float, pad: tuple[float, float], width: int,
                      height: int) -> torch.Tensor:
    """Boxes (K, 4) xyxy on the canvas -> (K, 4) xyxy in frame pixels, clipped to ``width`` x
    ``height`` (:func:`rainbench.eval.backends.letterbox.unletterbox` on the device)."""
    out = boxes.clone()
    out[:, [0, 2]] = ((out[:, [0, 2]] - pad[0]) / gain).clamp(0, width)
    out[:, [1, 3]] = ((out[:, [1, 3]] - pad[1]) / gain).clamp(0, height)
    return out


@dataclass
class TorchDetector:
    """An ultralytics detection network run in batches by torch; see the module docstring and
    :func:`rainbench.eval.backends.load_detector`."""

    name: str
    network: Any  # the fused DetectionModel, in eval mode, on ``device``
    device: torch.device
    half: bool  # fp16 (CUDA) or fp32
    lookup: np.ndarray  # model class -> rainbench id of the evaluated classes (-1 dropped)
    full_lookup: np.ndarray | None = None  # model class -> any rainbench id (:func:`model_classes`)

    def __post_init__(self) -> None:
        self._lookup = torch.as_tensor(self.lookup, dtype=torch.int64, device=self.device)

    @property
    def names(self) -> dict[int, str]:
        """The model's class names (its checkpoint's ``names``)."""
        return dict(self.network.names)

    @property
    def dtype(self) -> torch.dtype:
        return torch.float16 if self.half else torch.float32

    def predict(self, images, *, imgsz: int, conf: float, iou: float, max_det: int):
        """(H, W, 3) uint8 RGB images -> per image (boxes (K, 4) float32 xyxy in image pixels,
        scores (K,) float32, class ids (K,) int64 rainbench ids). Images of one size go through the
        network together."""
        outputs: list = [None] * len(images)
        groups: dict[tuple[int, ...], list[int]] = {}
        for index, image in enumerate(images):
            groups.setdefault(np.asarray(image).shape, []).append(index)
        for indices in groups.values():
            block = torch.from_numpy(np.stack([np.asarray(images[i]) for i in indices]))
            for i, result in zip(indices, self.predict_frames(block, imgsz=imgsz, conf=conf, iou=iou,
                                                              max_det=max_det), strict=True):
                outputs[i] = result
        return outputs

    def predict_frames(self, frames: torch.Tensor, *, imgsz: int, conf: float, iou: float,
                       max_det: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Detections of a (B, H, W, 3) uint8 RGB batch of same-sized frames (on any device; moved
        to the model's), as :meth:`predict` returns them."""
        height, width = int(frames.shape[1]), int(frames.shape[2])
        shape = rect_shape(height, width, imgsz)
        frames = frames.to(self.device, non_blocking=True)
        step = len(frames) if self.device.type == "cuda" else CPU_BATCH
        results = []
        with torch.inference_mode():
            for start in range(0, len(frames), step):
                if self.device.type == "cuda":
                    canvas, gain, pad = letterbox_batch(frames[start:start + step], shape, self.dtype)
                else:  # OpenCV's resize, as ultralytics' predict: the same input pixels, faster here
                    canvas, gain, pad = letterbox_frames(frames[start:start + step], shape)
                raw = self.network(canvas)
                raw = raw[0] if isinstance(raw, (tuple, list)) else raw
                results += [(unletterbox_boxes(boxes, gain, pad, width, height), scores, ids)
                            for boxes, scores, ids in select_batch(raw, self._lookup, conf=conf, iou=iou,
                                                                   max_det=max_det)]
        return [(boxes.float().cpu().numpy().reshape(-1, 4), scores.float().cpu().numpy(),
                 ids.cpu().numpy().astype(np.int64)) for boxes, scores, ids in results]


def torch_detector(yolo: Any, name: str, device: str | None, lookups: tuple[np.ndarray, np.ndarray]
                   ) -> TorchDetector:
    """A :class:`TorchDetector` of a loaded ``ultralytics.YOLO`` (its network is fused in place).

    ``device``: a torch device string (``"cpu"``, ``"0"``, ``"cuda:1"``); None: CUDA when present,
    else the CPU. ``lookups``: (full, evaluated) class tables
    (:func:`rainbench.eval.backends.classes._lookups`).
    """
    target = torch_device(device)
    half = target.type == "cuda"
    network = yolo.model.float().fuse(verbose=False) if hasattr(yolo.model, "fuse") else yolo.model.float()
    # Channels-last convolutions: 1.8x the images/s of NCHW on a 2-core CPU (bench/inference.py),
    # and what cuDNN's fp16 tensor-core kernels take.
    network = network.to(target).to(memory_format=torch.channels_last).eval()
    if half:
        network = network.half()
    for parameter in network.parameters():
        parameter.requires_grad_(False)
    full_lookup, lookup = lookups
    return TorchDetector(name=name, network=network, device=target, half=half, lookup=lookup,
                         full_lookup=full_lookup)


def torch_device(device: str | None) -> torch.device:
    """A torch device of a device string: ``"cpu"``, ``"0"`` / ``"0,1"`` (the first CUDA index),
    ``"cuda"``, ``"cuda:1"``; None: CUDA 0 when present, else the CPU. Anything else, or a CUDA
    device without CUDA, raises :class:`BackendError` naming it."""
    if device is None or str(device).strip() == "":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    text = str(device).strip().lower()
    if text == "cpu":
        return torch.device("cpu")
    index = text.split(",")[0]
    if index.isdigit():
        text = f"cuda:{index}"
    if not text.startswith("cuda"):
        raise BackendError(f"--device: expected cpu, a CUDA index (0) or cuda:N, got {device!r}")
    if not torch.cuda.is_available():
        raise BackendError(f"--device {device}: CUDA is not available on this machine")
    return torch.device(text)



class _RateImages(torch.utils.data.Dataset):
    """The frames of a :class:`rainbench.store.Dataset` at one rate, in image-id order: item i is
    ``(image_id, (H, W, 3) uint8 RGB)``. Shards are opened once per process
    (:meth:`rainbench.store.Dataset.handle`), so it is safe in ``DataLoader`` workers."""

    def __init__(self, dataset: Any, rate: float) -> None:
        self.dataset, self.rate = dataset, rate

    def __len__(self) -> int:
        return len(self.dataset.images)

    def __getitem__(self, index: int) -> tuple[int, np.ndarray]:
        image = self.dataset.images[index]
        return image.image_id, self.dataset.read_rgb(self.dataset.handle(image.shard_index), image, self.rate)


def _collate_frames(batch: list[tuple[int, np.ndarray]]) -> tuple[list[int], torch.Tensor]:
    """One (B, H, W, 3) block per batch: one shared-memory segment crosses from a worker."""
    return [image_id for image_id, _ in batch], torch.from_numpy(np.stack([frame for _, frame in batch]))


def shard_batches(images: Sequence[Any], batch: int) -> list[list[int]]:
    """Indices of ``images`` (:class:`rainbench.store.dataset.Image`, in image-id order) in batches
    of at most ``batch`` frames of one shard (so each batch has one frame size)."""
    batches: list[list[int]] = []
    for index, image in enumerate(images):
        if batches and len(batches[-1]) < batch and images[batches[-1][0]].shard_index == image.shard_index:
            batches[-1].append(index)
        else:
            batches.append([index])
    return batches


def frame_batches(dataset: Any, rate: float, batch: int, workers: int, pin_memory: bool = False):
    """Yield ``(image_ids, (B, H, W, 3) uint8 tensor)`` of every frame of ``dataset``
    (:class:`rainbench.store.Dataset`) at ``rate``, in image-id order, in batches of at most
    ``batch`` frames of one shard. ``workers`` > 0 decode in that many ``DataLoader`` worker
    processes (0: in this process)."""
    frames = _RateImages(dataset, rate)
    loader = torch.utils.data.DataLoader(
        frames, batch_sampler=shard_batches(dataset.images, batch), num_workers=workers,
        collate_fn=_collate_frames, pin_memory=pin_memory, prefetch_factor=2 if workers else None)
    try:
        yield from loader
    finally:
        dataset.close()
