"""The ONNX backend: a YOLO export run by onnxruntime.

Outputs YOLOv5/YOLOv7-style ``(B, N, 5 + nc)`` (cx, cy, w, h, objectness, class scores) and
YOLOv8+-style ``(B, 4 + nc, N)`` (no objectness) are told apart by their shape
(:func:`output_layout`). Class names come from the file's ``names`` metadata (ultralytics
exports); a file without them counts as COCO-80 when it has 80 classes, else its class indices
are its names (:func:`rainbench.eval.backends.classes.index_names`). Letterboxing and
post-processing: :mod:`rainbench.eval.backends.letterbox`. ONNX files hold no code.
"""

from __future__ import annotations

import ast
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.devices import parse_device
from rainbench.eval.backends import BackendError
from rainbench.eval.backends.classes import _lookups, index_names
from rainbench.eval.backends.letterbox import letterbox, rect_shape, select_detections, unletterbox
from rainbench.store.classes import PAPER_CLASSES


CPU_BATCH = 4
"""Images per onnxruntime call on the CPU (a model with a dynamic batch): at 960 px on a 2-core
CPU 11.6 images/s in calls of 4 or 8 against 9.4 in calls of the eval's 32 (smaller activations
stay in cache; bench/RESULTS.md). Other providers take the whole batch."""


@dataclass
class OnnxDetector:
    """A YOLO ONNX export run by onnxruntime; see :func:`rainbench.eval.backends.load_detector`."""

    name: str
    session: Any
    names: list[str] | dict[int, str] | None  # from the file's metadata (ultralytics exports)
    class_map: str | None
    input_shape: tuple[int | None, int | None]  # fixed (h, w), or None where dynamic
    fixed_batch: int | None
    layout: str | None = None  # "v8" or "v5"; decided from the output shape (:meth:`configure`)
    lookup: np.ndarray | None = None  # model class -> rainbench id of the evaluated classes (-1 dropped)
    classes: tuple[int, ...] = PAPER_CLASSES  # the evaluated rainbench ids
    full_lookup: np.ndarray | None = None  # model class -> any rainbench id (:func:`model_classes`)
    trained: tuple[int, ...] | None = None  # the classes its card says it was trained on (None: unknown)

    def configure(self, output_shape: list) -> None:
        """Decide the output layout and class table from an output shape (B, A, C)."""
        nc = len(self.names) if self.names is not None else None
        self.layout, nc = output_layout(output_shape, nc, Path(f"{self.name}.onnx"))
        names = self.names if self.names is not None else index_names(nc)
        self.full_lookup, self.lookup = _lookups(names, self.class_map, f"--weights {self.name}.onnx",
                                                 self.classes, self.trained)

    def _on_cpu(self) -> bool:
        """Whether onnxruntime runs this model on the CPU (its first provider)."""
        return self.session.get_providers()[0] == "CPUExecutionProvider"

    def _shape(self, height: int, width: int, imgsz: int) -> tuple[int, int]:
        fixed_h, fixed_w = self.input_shape
        if fixed_h is None or fixed_w is None:
            return rect_shape(height, width, imgsz)
        if max(fixed_h, fixed_w) != imgsz:
            raise BackendError(f"--imgsz {imgsz}: {self.name}.onnx has a fixed {fixed_w}x{fixed_h} input; "
                               f"pass --imgsz {max(fixed_h, fixed_w)} or export it with a dynamic input")
        return fixed_h, fixed_w

    def predict(self, images, *, imgsz: int, conf: float, iou: float, max_det: int):
        prepared = []
        for image in images:
            image = np.asarray(image)
            height, width = image.shape[:2]
            canvas, gain, pad = letterbox(image, self._shape(height, width, imgsz))
            prepared.append((canvas, gain, pad, width, height))
        outputs: list = [None] * len(prepared)
        groups: dict[tuple[int, int], list[int]] = {}
        for index, item in enumerate(prepared):
            groups.setdefault(item[0].shape[:2], []).append(index)
        step = self.fixed_batch or (CPU_BATCH if self._on_cpu() else len(prepared))
        input_name = self.session.get_inputs()[0].name
        for indices in groups.values():
            for start in range(0, len(indices), step):
                chunk = indices[start:start + step]
                blob = np.stack([prepared[i][0] for i in chunk]).transpose(0, 3, 1, 2)
                blob = np.ascontiguousarray(blob, dtype=np.float32) / 255.0
                raw = self.session.run(None, {input_name: blob})[0]
                if self.layout is None:
                    self.configure(list(raw.shape))
                for i, head in zip(chunk, raw, strict=True):
                    _, gain, pad, width, height = prepared[i]
                    boxes, scores = decode_yolo(head, self.layout)
                    check_decoded(boxes, scores, f"--weights {self.name}.onnx")
                    boxes, kept_scores, ids = select_detections(boxes, scores, self.lookup, conf=conf,
                                                                iou=iou, max_det=max_det)
                    outputs[i] = (unletterbox(boxes, gain, pad, width, height), kept_scores, ids)
        return outputs


def decode_yolo(output: np.ndarray, layout: str) -> tuple[np.ndarray, np.ndarray]:
    """One image's raw head output -> (boxes (N, 4) float32 xyxy in input pixels, class scores (N, nc)).

    ``layout``: ``"v8"`` for (4 + nc, N) rows cx, cy, w, h, class scores; ``"v5"`` for
    (N, 5 + nc) columns cx, cy, w, h, objectness, class scores (score = objectness x class).
    """
    if layout not in ("v8", "v5"):
        raise ValueError(f"layout: expected 'v8' or 'v5', got {layout!r}")
    # a broken export's huge values overflow to inf here, quietly: check_decoded reports them
    with np.errstate(over="ignore", invalid="ignore"):
        if layout == "v8":
            rows = np.asarray(output, np.float32).T
            centres, scores = rows[:, :4], rows[:, 4:]
        else:
            rows = np.asarray(output, np.float32)
            centres, scores = rows[:, :4], rows[:, 5:] * rows[:, 4:5]
        boxes = np.empty_like(centres)
        boxes[:, :2] = centres[:, :2] - centres[:, 2:4] / 2
        boxes[:, 2:] = centres[:, :2] + centres[:, 2:4] / 2
    return boxes, scores


SCORE_TOLERANCE = 1e-3
"""How far outside [0, 1] a decoded score may be (float rounding in an export's sigmoid)."""


def check_decoded(boxes: np.ndarray, scores: np.ndarray, what: str) -> None:
    """Refuse a head output that no working detector gives: boxes (N, 4) or scores (N, nc) not
    finite, or scores outside [0, 1] (an export without its sigmoid, or a broken graph).

    Raises:
        BackendError: one line naming ``what`` and the values found.
    """
    if not (np.isfinite(boxes).all() and np.isfinite(scores).all()):
        raise BackendError(f"{what}: its output holds inf or nan; expected a YOLO detection "
                           "head's finite boxes and scores")
    if scores.size and (scores.min() < -SCORE_TOLERANCE or scores.max() > 1 + SCORE_TOLERANCE):
        raise BackendError(f"{what}: its scores span {scores.min():.3g} to {scores.max():.3g}; "
                           "expected probabilities in [0, 1] (an export with its sigmoid, as "
                           "ultralytics writes)")


def _fixed_dim(value: Any) -> int | None:
    """An ONNX dimension as an int, or None when it is symbolic (dynamic)."""
    return value if isinstance(value, int) and value > 0 else None


def _onnx_names(session: Any) -> list[str] | dict[int, str] | None:
    """Class names from an onnxruntime session's ``names`` metadata (ultralytics exports); None
    when the file has none or they do not read as a dict or list."""
    metadata = session.get_modelmeta().custom_metadata_map or {}
    if "names" not in metadata:
        return None
    try:
        names = ast.literal_eval(metadata["names"])
    except (ValueError, SyntaxError):
        return None
    return names if isinstance(names, (dict, list)) else None


def output_layout(dims: list, nc: int | None, path: Path) -> tuple[str, int]:
    """(layout ``"v8"``/``"v5"``, class count) of an ONNX output shape ``(B, A, C)``; symbolic
    dimensions are allowed where ``nc`` (from names metadata) decides."""
    rows, cols = (_fixed_dim(d) for d in dims[1:3])
    if nc is not None and rows == 4 + nc:
        layout = "v8"
    elif nc is not None and cols == 5 + nc:
        layout = "v5"
    elif nc is None and rows and (not cols or rows < cols):
        layout, nc = "v8", rows - 4
    elif nc is None and cols:
        layout, nc = "v5", cols - 5
    else:
        raise BackendError(f"--weights: {path}: output {list(dims)} is neither YOLOv8-style (B, 4 + nc, N) "
                           "nor YOLOv5/v7-style (B, N, 5 + nc)")
    if nc < 1:
        raise BackendError(f"--weights: {path}: output {list(dims)} leaves no class scores")
    return layout, nc


def onnx_cuda_device(path: Path, device: str | None, onnxruntime=None) -> int | None:
    """The CUDA device index an ONNX model at ``path`` runs on for ``--device`` ``device``
    (:func:`rainbench.devices.parse_device`: "0", "0,1", "cuda", "cuda:1", any case; the first
    index; None, "auto" or "cpu": None, the CPU). A value it does not read, or a CUDA device where
    onnxruntime has no CUDA provider (the CPU wheel rainbench installs), is a one-line
    :class:`BackendError`, not a silent run on the CPU."""
    parsed = parse_device(device, BackendError)
    if parsed is None or parsed[0] == "cpu":
        return None
    if onnxruntime is None:
        import onnxruntime  # noqa: PLC0415
    if "CUDAExecutionProvider" not in onnxruntime.get_available_providers():
        raise BackendError(f"--device {device}: {path} is an ONNX model and this onnxruntime has no "
                           "CUDA provider (the CPU wheel rainbench installs); use --device cpu, or "
                           "install onnxruntime-gpu")
    indices = parsed[1]
    return indices[0] if indices else 0


def _load_onnx(path: Path, class_map: str | None, device: str | None,
               classes: Sequence[int] = PAPER_CLASSES, name: str | None = None,
               trained: Sequence[int] | None = None) -> OnnxDetector:
    try:
        import onnxruntime
    except ImportError:
        raise BackendError(f"--weights: {path}: ONNX models need onnxruntime (pip install onnxruntime)") from None
    providers: list = ["CPUExecutionProvider"]
    cuda_index = onnx_cuda_device(path, device, onnxruntime)
    if cuda_index is not None:
        providers.insert(0, ("CUDAExecutionProvider", {"device_id": cuda_index}))
    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    # No busy-waiting between operators: beside the run's decoding threads (or another process)
    # spinning workers took 1.6x longer an image (bench/RESULTS.md), and alone they gain nothing.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.add_session_config_entry("session.inter_op.allow_spinning", "0")
    try:
        session = onnxruntime.InferenceSession(str(path), options, providers=providers)
    except Exception as error:  # onnxruntime raises its own exception types (Fail, InvalidGraph, ...)
        reason = " ".join(str(error).split())[:200]
        raise BackendError(f"--weights: {path} is not a loadable ONNX model ({reason})") from None
    inputs, outputs = session.get_inputs(), session.get_outputs()
    input_dims = list(inputs[0].shape)
    output_dims = list(outputs[0].shape)
    if len(input_dims) != 4 or len(output_dims) != 3:
        raise BackendError(f"--weights: {path}: expected a YOLO detection model with an (N, 3, H, W) input "
                           f"and an (N, A, B) output, got input {input_dims} and output {output_dims}")

    names = _onnx_names(session)
    detector = OnnxDetector(name=name or path.stem, session=session, names=names, class_map=class_map,
                            input_shape=(_fixed_dim(input_dims[2]), _fixed_dim(input_dims[3])),
                            fixed_batch=_fixed_dim(input_dims[0]), classes=tuple(classes),
                            trained=None if trained is None else tuple(trained))
    if names is not None:  # a bad --class-map fails now, not at the first batch
        detector.full_lookup, detector.lookup = _lookups(names, class_map, f"--weights {path}", classes, trained)
    if _fixed_dim(output_dims[1]) and _fixed_dim(output_dims[2]):
        detector.configure(output_dims)
    elif names is None and class_map is not None:
        raise BackendError(f"--weights: {path}: --class-map needs class names or a fixed output shape; "
                           "this model has neither")
    return detector
