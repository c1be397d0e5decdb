"""Detector backends for ``rainbench eval``: local weights -> boxes in original image pixels.

:func:`load_detector` returns a :class:`Detector` for a weights spec
(:func:`rainbench.eval.weights.resolve_weights`), one backend family per module:

- a shipped model by name (``rainbench-yolo11n``, :mod:`rainbench.eval.weights`): its ONNX copy
  on CPU (``<name>.onnx`` beside the checkpoint, or built on first use into the user cache,
  :func:`rainbench.eval.weights.cached_onnx`), ``<name>.pt`` on a CUDA device;
- an ultralytics checkpoint ``.pt`` (YOLOv3u/v5u/v8/v9/v10/11/12...): read by
  ``ultralytics.YOLO(path)`` (:mod:`rainbench.eval.backends.ultralytics`) and run in batches by
  torch, letterbox and NMS on the model's device, fp16 on CUDA
  (:mod:`rainbench.eval.backends.torch_batched`), or by ultralytics' own predict
  (``pt_backend="ultralytics"``, and for heads the batched path does not run: end-to-end YOLOv10
  and YOLO26, RT-DETR);
- an ONNX export ``.onnx`` through onnxruntime: YOLOv5/YOLOv7-style outputs ``(B, N, 5 + nc)``
  (cx, cy, w, h, objectness, class scores) and YOLOv8+-style ``(B, 4 + nc, N)`` (no objectness)
  (:mod:`rainbench.eval.backends.onnx`);
- a Darknet model (YOLOv4) through OpenCV DNN: ``name.cfg`` and ``name.weights`` side by side
  (either may be given) (:mod:`rainbench.eval.backends.darknet`).

Weights are loaded from local files only; nothing is downloaded (``YOLO_OFFLINE=1``) and
ultralytics' settings go to a temporary folder, not the home folder.

``.pt`` checkpoints are Python pickles, and Python's full unpickler runs code from the file.
rainbench loads them with ultralytics' safe loading (``torch.load(weights_only=True)`` against
ultralytics' allow-list of torch and ultralytics model classes), which reads ordinary
ultralytics checkpoints (the shipped ones, anything ``ultralytics`` trained or exported). A file
that pickles anything else (a custom module, a YOLOv5-repository checkpoint, a global such as
``os.system``) is refused, naming the global, unless ``trust_pickle=True``
(``rainbench eval --trust-pickle`` or ``RAINBENCH_TRUST_PICKLE=1``): only then is it loaded with
the full unpickler, with a warning. Only trust files you would run as code. ONNX and Darknet
files hold no code.

Pre- and post-processing of the ONNX and Darknet backends (letterbox, confidence floor,
per-class NMS, ``max_det``): :mod:`rainbench.eval.backends.letterbox`; ultralytics does its own.

Class mapping (:mod:`rainbench.eval.backends.classes`): rainbench class ids are COCO-80
indices 0 person, 1 bicycle, 2 car, 3 motorcycle, 5 bus, 7 truck (:mod:`rainbench.store.classes`).
A model whose names[0..3] are those COCO names maps each rainbench class it names at its COCO
index directly (a COCO-80 model: all six; the shipped four-class models: 0..3) and drops its
other classes (ONNX files without names metadata and Darknet files with 80 classes count as
COCO-80); any other model needs a class map ``"car=2,pedestrian=0"`` (model class name =
rainbench class id; models without names use their class indices as names, ``"0=2"``); model
classes left out of the map are dropped. Of the classes a model can predict
(:func:`model_classes`) only the evaluated ones (``classes``, by default the paper's four) are
kept, before NMS and ``max_det``.

The backend modules import :class:`BackendError` from here, so this module imports them (and
:mod:`rainbench.eval.weights`, which imports them) only inside :func:`load_detector`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from rainbench.store.classes import CLASS_NAMES, PAPER_CLASSES


class BackendError(ValueError):
    """A user-facing backend error with a one-line message."""


class Detector(Protocol):
    name: str

    def predict(self, images: list[np.ndarray], *, imgsz: int, conf: float, iou: float,
                max_det: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(H, W, 3) uint8 RGB images -> per image (boxes (K, 4) float32 xyxy in original pixels,
        scores (K,) float32, class_ids (K,) int64 rainbench ids)."""
        ...


PT_BACKENDS = ("batched", "ultralytics")
"""How an ultralytics ``.pt`` runs (``--pt-backend``): ``batched``, the network in batches by torch
with letterbox and NMS on its device (:mod:`rainbench.eval.backends.torch_batched`; models it does
not support fall back to ultralytics); ``ultralytics``, ``ultralytics.YOLO.predict`` (the reference)."""


def load_detector(weights: str | Path, *, class_map: str | None = None,
                  device: str | None = None, trust_pickle: bool | None = None,
                  classes: Sequence[int] = PAPER_CLASSES, pt_backend: str = "batched") -> Detector:
    """Load a detector from a weights spec (:func:`rainbench.eval.weights.resolve_weights`);
    ``.name`` is the model name.

    ``classes``: the rainbench class ids it keeps (default the paper's four); the others it can
    predict (:func:`model_classes`) are dropped before NMS and ``max_det``. A class it cannot
    predict is not an error here (see :func:`check_model_classes`).

    A ``.pt`` is read with ultralytics' safe loading; one that needs Python's full unpickler is
    refused unless ``trust_pickle`` (None: the ``RAINBENCH_TRUST_PICKLE=1`` environment
    variable), see the module docstring.

    ``pt_backend``: how a ``.pt`` runs (:data:`PT_BACKENDS`): "batched" (default; fp16 on CUDA,
    fp32 on the CPU) or "ultralytics" (its own predict).

    Raises :class:`BackendError` (one line, naming the file) for a missing file, an unsupported
    format, a file that does not load, a .pt that needs the unsafe loader without trust, a
    non-detection model, or class names that are neither COCO-80 nor covered by ``class_map``.
    """
    from rainbench.eval import weights as registry
    from rainbench.eval.backends.classes import parse_class_map
    from rainbench.eval.backends.darknet import _load_darknet
    from rainbench.eval.backends.onnx import _load_onnx
    from rainbench.eval.backends.ultralytics import _load_ultralytics

    path, name = registry.resolve_weights(weights, device)
    if class_map is not None:
        parse_class_map(class_map)
    trained = registry.trained_classes(weights)
    suffix = path.suffix.lower()
    if suffix == ".onnx":
        return _load_onnx(path, class_map, device, classes, name, trained)
    if suffix == ".weights":
        return _load_darknet(path, class_map, classes)
    if suffix != ".pt":
        raise BackendError(f"--weights: {path}: unsupported format {path.suffix or '(none)'!r}; expected "
                           "an ultralytics .pt, an .onnx export, Darknet .cfg/.weights, or a shipped model "
                           f"name ({', '.join(registry.shipped_models()) or 'none shipped'})")
    if pt_backend not in PT_BACKENDS:
        raise BackendError(f"--pt-backend: expected one of {', '.join(PT_BACKENDS)}, got {pt_backend!r}")
    detector = _load_ultralytics(path, class_map, device, trust_pickle, classes, name, trained)
    if pt_backend == "batched":
        from rainbench.eval.backends.torch_batched import supports, torch_detector

        if supports(detector.model.model):
            return torch_detector(detector.model, detector.name, device, (detector.full_lookup, detector.lookup))
    return detector


def model_classes(detector: Any) -> tuple[int, ...] | None:
    """The rainbench class ids a loaded detector can predict (whatever it was asked to keep), in
    ascending order; None while unknown (an ONNX file without names metadata and with a dynamic
    output shape learns its class count at its first batch)."""
    full = getattr(detector, "full_lookup", None)
    if full is None:
        return None
    return tuple(sorted({int(c) for c in np.asarray(full).tolist() if c >= 0}))


def check_model_classes(detector: Any, model: str, classes: Sequence[int]) -> None:
    """Refuse a model that cannot predict one of ``classes`` (rainbench ids): a one-line
    :class:`BackendError` naming the model and the class. Does nothing while the detector's
    classes are unknown (:func:`model_classes` is None)."""
    available = model_classes(detector)
    if available is None:
        return
    for class_id in classes:
        if class_id not in available:
            shown = ", ".join(CLASS_NAMES[c] for c in available) or "none of the rainbench classes"
            raise BackendError(f"--classes: model {model!r} cannot predict {CLASS_NAMES[class_id]!r} "
                               f"(class {class_id}); it predicts {shown}")
