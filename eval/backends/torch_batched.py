"""The batched torch backend: an ultralytics detection checkpoint run as a plain torch network.

What ``ultralytics.YOLO.predict`` does image by image on the CPU (letterbox with OpenCV, NMS in a
Python loop, box mapping), this backend does for a whole batch with torch on the model's device:

- letterbox: (B, H, W, 3) uint8 frames -> (B, 3, h, w) in 0..1, padded with grey 114 to the
  smallest multiple of 32 around the image (ultralytics' rectangular inference shape,
  :func:`rainbench.eval.backends.letterbox.rect_shape`). Frames read from shards
  (:func:`frame_batches`, ``rainbench eval``) are letterboxed by the reader's worker processes
  with OpenCV's own resize, so the network sees exactly the pixels ultralytics' predict gives it
  (:meth:`TorchDetector.predict_canvases`); arrays handed to :meth:`TorchDetector.predict` are
  letterboxed on CUDA on the GPU (:func:`letterbox_batch`: bilinear with half-pixel centres,
  OpenCV's ``INTER_LINEAR`` sampling, rounded to uint8 levels) and on the CPU with OpenCV
  (:func:`letterbox_frames`);
- the network, fused (convolution + batch norm) as ultralytics predicts, channels-last, in fp16 on
  CUDA and fp32 on the CPU;
- NMS (:func:`select_batch`): ultralytics' ``non_max_suppression`` step for step (best class per
  box, confidence floor, evaluated classes, the 30 000 best, per-class NMS with its 7 680 px class
  offset, ``max_det``), on the device;
- boxes mapped back to image pixels and clipped (:func:`unletterbox_boxes`), on the device.

The same code runs on the CPU and on CUDA except the GPU resize of :meth:`TorchDetector.predict`
(the tests run the CPU, and check the GPU's resize against OpenCV's on the CPU). Against
ultralytics' ``predict``: on the CPU the same input pixels, the same fused network (its
convolutions run channels-last, one image per call, so sums are added in another order) and the
same NMS; on CUDA also fp16 instead of predict's default fp32, and for arrays the GPU resize's
float arithmetic (a pixel differs by at most one grey level from OpenCV's fixed point)
(``tests/test_torch_batched.py``, ``tests/test_train_paper.py``, ``bench/backend_agreement.py``).

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

from rainbench.devices import parse_device
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


def network_input(canvases: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(B, h, w, 3) uint8 letterboxed canvases -> (B, 3, h, w) of ``dtype`` in 0..1 on their
    device, channels-last memory (what the network takes)."""
    return canvases.permute(0, 3, 1, 2).to(dtype).div_(255.0)


def letterbox_frames(frames: torch.Tensor, shape: tuple[int, int]) -> tuple[torch.Tensor, float, tuple[float, float]]:
    """:func:`letterbox_batch` on the CPU with OpenCV's resize
    (:func:`rainbench.eval.backends.letterbox.letterbox`, ultralytics' own pixels): ``frames``
    (B, H, W, 3) uint8 CPU tensor -> (canvas (B, 3, h, w) float32 channels-last in 0..1, gain,
    (pad_x, pad_y))."""
    boxed = [letterbox(frame, shape) for frame in frames.numpy()]
    block = torch.from_numpy(np.stack([canvas for canvas, _, _ in boxed]))
    return network_input(block, torch.float32), boxed[0][1], boxed[0][2]


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
    # every image's candidate rows at once (one wait for the device, not one an image)
    image_of, candidate_rows = keep.nonzero(as_tuple=True)  # by image, rows ascending
    counts = torch.bincount(image_of, minlength=prediction.shape[0]).tolist()
    outputs = []
    start = 0
    for image, count in enumerate(counts):
        rows = candidate_rows[start:start + count]
        start += count
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
        if self.device.type == "cuda":
            canvases, gain, pad = letterbox_batch(frames, shape, self.dtype)
            return self._detect(lambda start, stop: canvases[start:stop], len(frames), gain, pad, width, height,
                                conf=conf, iou=iou, max_det=max_det)
        # OpenCV's resize, as ultralytics' predict: the same input pixels, faster here
        gain, _, (top, left) = letterbox_geometry(height, width, shape)
        return self._detect(lambda start, stop: letterbox_frames(frames[start:stop], shape)[0], len(frames), gain,
                            (float(left), float(top)), width, height, conf=conf, iou=iou, max_det=max_det)

    def predict_canvases(self, canvases: torch.Tensor, frame_size: tuple[int, int], *, conf: float, iou: float,
                         max_det: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Detections of frames already letterboxed: ``canvases`` (B, h, w, 3) uint8 on any device,
        each a ``frame_size`` (H, W) frame on its canvas as
        :func:`rainbench.eval.backends.letterbox.letterbox` draws it (OpenCV's resize: the pixels
        ultralytics' predict feeds its network; :func:`frame_batches` with ``imgsz``). Returns what
        :meth:`predict` returns, boxes in frame pixels."""
        if canvases.ndim != 4 or canvases.shape[-1] != 3 or canvases.dtype != torch.uint8:
            raise ValueError(f"canvases: expected (B, h, w, 3) uint8, got {tuple(canvases.shape)} {canvases.dtype}")
        height, width = (int(side) for side in frame_size)
        gain, _, (top, left) = letterbox_geometry(height, width, (int(canvases.shape[1]), int(canvases.shape[2])))
        canvases = canvases.to(self.device, non_blocking=True)
        return self._detect(lambda start, stop: network_input(canvases[start:stop], self.dtype), len(canvases),
                            gain, (float(left), float(top)), width, height, conf=conf, iou=iou, max_det=max_det)

    def _detect(self, canvas, count: int, gain: float, pad: tuple[float, float], width: int, height: int, *,
                conf: float, iou: float, max_det: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The network, NMS and box mapping of ``count`` letterboxed images; ``canvas(start, stop)``
        gives images start..stop as (n, 3, h, w) of the network's dtype in 0..1 on its device
        (channels-last memory). CUDA takes all in one call, the CPU ``CPU_BATCH`` at a time."""
        step = count if self.device.type == "cuda" else CPU_BATCH
        results = []
        with torch.inference_mode():
            for start in range(0, count, step):
                raw = self.network(canvas(start, start + step))
                raw = raw[0] if isinstance(raw, (tuple, list)) else raw
                results += [(unletterbox_boxes(boxes, gain, pad, width, height), scores, ids)
                            for boxes, scores, ids in select_batch(raw, self._lookup, conf=conf, iou=iou,
                                                                   max_det=max_det)]
        return _to_host(results)


def _to_host(results: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
             ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per image (boxes (K, 4), scores (K,), ids (K,)) tensors on any device -> NumPy (float32,
    float32, int64), copied to the host in one transfer of each kind for the whole batch."""
    if not results:
        return []
    ends = np.cumsum([len(scores) for _, scores, _ in results])[:-1]
    boxes = np.split(torch.cat([b.reshape(-1, 4) for b, _, _ in results]).float().cpu().numpy(), ends)
    scores = np.split(torch.cat([s for _, s, _ in results]).float().cpu().numpy(), ends)
    ids = np.split(torch.cat([i for _, _, i in results]).cpu().numpy().astype(np.int64), ends)
    return list(zip(boxes, scores, ids, strict=True))


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
    """A torch device of a ``--device`` string (:func:`rainbench.devices.parse_device`):
    ``"cpu"``, ``"0"`` / ``"0,1"`` (the first CUDA index), ``"cuda"``, ``"cuda:1"``; None, ``""``
    or ``"auto"``: CUDA 0 when present, else the CPU. Anything else, or a CUDA device without
    CUDA, raises :class:`BackendError` naming it."""
    parsed = parse_device(device, BackendError)
    if parsed is None:
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    kind, indices = parsed
    if kind == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise BackendError(f"--device {device}: CUDA is not available on this machine")
    return torch.device(f"cuda:{indices[0]}" if indices else "cuda")



class _FrameChunks(torch.utils.data.Dataset):
    """Frames of a :class:`rainbench.store.Dataset` read in chunks: the key ``(rate, (i, j, ...))``
    (indices of ``dataset.images``, one shard) gives ``(image ids, (n, H, W, 3) uint8 RGB)``, or
    with ``imgsz`` the frames letterboxed on their ``rect_shape`` canvas with OpenCV
    (:func:`rainbench.eval.backends.letterbox.letterbox`): (n, h, w, 3) uint8. Shards are opened
    once per process (:meth:`rainbench.store.Dataset.handle`), so it is safe in ``DataLoader``
    workers."""

    def __init__(self, dataset: Any, imgsz: int | None = None) -> None:
        self.dataset, self.imgsz = dataset, imgsz

    def __getitem__(self, key: tuple[float, tuple[int, ...]]) -> tuple[list[int], torch.Tensor] | Exception:
        """The chunk of ``key``; a file that cannot be read (a corrupt chunk, a missing or
        unreadable shard: ValueError, OSError) comes back as its exception, which
        :func:`frame_batches` raises in the reading process with its own one-line message (a
        ``DataLoader`` worker's exception would carry the worker's traceback in its message)."""
        rate, indices = key
        images = [self.dataset.images[index] for index in indices]
        try:
            handle = self.dataset.handle(images[0].shard_index)
            frames = [self.dataset.read_rgb(handle, image, rate) for image in images]
        except (ValueError, OSError) as error:
            return error
        if self.imgsz is not None:
            shape = rect_shape(frames[0].shape[0], frames[0].shape[1], self.imgsz)
            frames = [letterbox(frame, shape)[0] for frame in frames]
        return [image.image_id for image in images], torch.from_numpy(np.stack(frames))


def _as_read(chunk: tuple[list[int], torch.Tensor] | Exception) -> tuple[list[int], torch.Tensor] | Exception:
    """The ``DataLoader``'s collate function: a chunk is already one block (or its read error)."""
    return chunk


def _one_thread_worker(_worker_id: int) -> None:
    """A reader worker's OpenCV on one thread (torch's already is, in a ``DataLoader`` worker):
    the workers are the parallelism, and each one's resize on every core would oversubscribe
    them."""
    import cv2

    cv2.setNumThreads(1)


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


def frame_batches(dataset: Any, rates: Sequence[float], batch: int, workers: int, *, imgsz: int | None = None,
                  device: torch.device | str | None = None):
    """Yield ``(rate, image_ids, block)`` for every frame of ``dataset``
    (:class:`rainbench.store.Dataset`) at each of ``rates`` in turn, in image-id order, in batches
    of at most ``batch`` frames of one shard (:func:`shard_batches`).

    ``block``: (B, H, W, 3) uint8 RGB frames; with ``imgsz``, the frames letterboxed for a network
    of that size (:class:`_FrameChunks`; for :meth:`TorchDetector.predict_canvases`), (B, h, w, 3)
    uint8. On ``device`` when given (default the CPU).

    ``workers`` > 0: that many ``DataLoader`` worker processes, started once for all the rates,
    decode (and letterbox); each batch is split into chunks of ``ceil(batch / workers)`` frames
    so that all workers decode the frames of one batch at once, and the chunks are joined here
    (on ``device``: each chunk is copied there from pinned memory, then joined). 0: all in this
    process."""
    device = torch.device("cpu") if device is None else torch.device(device)
    chunk = batch if workers == 0 else max(1, -(-batch // workers))
    keys, groups = [], []  # the DataLoader's keys, and the batch each one belongs to
    batches = shard_batches(dataset.images, batch)  # the same at every rate
    for rate in rates:
        for group, indices in enumerate(batches):
            for start in range(0, len(indices), chunk):
                keys.append((float(rate), tuple(indices[start:start + chunk])))
                groups.append((float(rate), group))
    loader = torch.utils.data.DataLoader(
        _FrameChunks(dataset, imgsz), batch_size=None, sampler=keys, num_workers=workers, collate_fn=_as_read,
        pin_memory=device.type == "cuda", prefetch_factor=2 if workers else None,
        worker_init_fn=_one_thread_worker if workers else None)
    pending_ids: list[int] = []
    pending: list[torch.Tensor] = []
    try:
        for position, chunk_read in enumerate(loader):
            if isinstance(chunk_read, Exception):
                raise chunk_read
            image_ids, block = chunk_read
            pending_ids += image_ids
            pending.append(block.to(device, non_blocking=True))
            if position + 1 == len(groups) or groups[position + 1] != groups[position]:
                yield groups[position][0], pending_ids, pending[0] if len(pending) == 1 else torch.cat(pending)
                pending_ids, pending = [], []
    finally:
        dataset.close()
