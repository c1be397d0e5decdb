"""Detector backends for ``rainbench eval``: local weights -> boxes in original image pixels.

:func:`load_detector` returns a :class:`Detector` for a weights spec (:func:`resolve_weights`):

- a shipped model by name (``rainbench-yolo11n``): ``rainbench/eval/weights/<name>.onnx`` on
  CPU, ``<name>.pt`` on a CUDA device (:func:`resolve_weights`);
- an ultralytics checkpoint ``.pt`` (YOLOv3u/v5u/v8/v9/v10/11/12...): ``ultralytics.YOLO(path)``;
- an ONNX export ``.onnx`` through onnxruntime: YOLOv5/YOLOv7-style outputs ``(B, N, 5 + nc)``
  (cx, cy, w, h, objectness, class scores) and YOLOv8+-style ``(B, 4 + nc, N)`` (no objectness);
- a Darknet model (YOLOv4) through OpenCV DNN: ``name.cfg`` and ``name.weights`` side by side
  (either may be given).

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

Pre-processing: RGB, letterboxed (aspect kept, grey 114 padding, centred) to ``imgsz`` on the
long side; ONNX models with a dynamic input get the smallest multiple of 32 around the image
(640x480 for 800x600 frames), fixed-size inputs get their own size (``--imgsz`` must equal its
long side). Darknet networks take their ``[net] width/height`` and are stretched, not
letterboxed, unless the cfg says ``letter_box=1`` (how Darknet itself runs them). Post-processing
for ONNX and Darknet: confidence floor, per-class NMS (torchvision), at most ``max_det`` boxes,
letterbox undone, boxes clipped to the image.

Class mapping: rainbench class ids are COCO-80 indices 0 person, 1 bicycle, 2 car, 3 motorcycle,
5 bus, 7 truck (:mod:`rainbench.store.classes`). A model whose names[0..3] are those COCO names
maps each rainbench class it names at its COCO index directly (a COCO-80 model: all six; the
shipped four-class models: 0..3) and drops its other classes (ONNX files without names metadata
and Darknet files with 80 classes count as COCO-80); any other model needs a class map
``"car=2,pedestrian=0"`` (model class name = rainbench class id; models without names use their
class indices as names, ``"0=2"``); model classes left out of the map are dropped. Of the classes
a model can predict (:func:`model_classes`) only the evaluated ones (``classes``, by default the
paper's four) are kept, before NMS and ``max_det``.
"""

from __future__ import annotations

import ast
import json
import os
import pickle
import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from rainbench.store.classes import CLASS_NAMES, LABELLED_CLASSES, PAPER_CLASSES, class_list

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
"""Shipped weights, selectable by name (docs/models.md): ``<name>.pt`` (the ultralytics
checkpoint), ``<name>.onnx`` (the same network exported by :func:`export_onnx`, run on CPU) and
``<name>.json`` (the model's card: ``imgsz``, the letterbox size it is evaluated at)."""
DEFAULT_IMGSZ = 640
"""Letterbox size of models that do not declare their own (ultralytics' default)."""
LETTERBOX_FILL = 114


class BackendError(ValueError):
    """A user-facing backend error with a one-line message."""


class Detector(Protocol):
    name: str

    def predict(self, images: list[np.ndarray], *, imgsz: int, conf: float, iou: float,
                max_det: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(H, W, 3) uint8 RGB images -> per image (boxes (K, 4) float32 xyxy in original pixels,
        scores (K,) float32, class_ids (K,) int64 rainbench ids)."""
        ...


def shipped_models() -> list[str]:
    """Names of the weights shipped with rainbench (``rainbench eval --weights NAME``)."""
    return sorted(p.stem for p in WEIGHTS_DIR.glob("*.pt"))


def _shipped_file(spec: str | Path, suffix: str) -> Path | None:
    """``WEIGHTS_DIR/<spec><suffix>`` when ``spec`` names a shipped model (a bare name whose
    ``.pt`` is shipped) and that file exists; else None."""
    text = str(spec)
    if Path(text).suffix != "" or not (WEIGHTS_DIR / f"{text}.pt").is_file():
        return None
    path = WEIGHTS_DIR / f"{text}{suffix}"
    return path if path.is_file() else None


def cache_dir() -> Path:
    """Where rainbench keeps files it builds on first use: ``$XDG_CACHE_HOME/rainbench``
    (default ``~/.cache/rainbench``)."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "rainbench"


def cached_onnx(checkpoint: Path) -> Path:
    """The ONNX copy of a shipped ``.pt`` that ships without one, exported by
    :func:`export_onnx` on first use into :func:`cache_dir` (named by the checkpoint's sha256, so
    a new checkpoint gets a new copy) and reused afterwards. Written under a temporary name and
    renamed, so a cut-off export never leaves a partial file."""
    import hashlib

    digest = hashlib.sha256(checkpoint.read_bytes()).hexdigest()[:16]
    path = cache_dir() / "onnx" / f"{checkpoint.stem}-{digest}.onnx"
    if path.is_file():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        export_onnx(checkpoint, partial)
        os.replace(partial, path)
    except BackendError:
        raise
    except Exception as error:  # torch/onnx export failures come as many exception types
        raise BackendError(f"--weights: {checkpoint}: could not build its ONNX copy in {path.parent} "
                           f"({type(error).__name__}: {error})") from error
    finally:
        partial.unlink(missing_ok=True)
    return path


def _on_cuda(device: str | None) -> bool:
    """Whether ``device`` (a torch device string; None: CUDA when present) is a CUDA device."""
    if device is None:
        import torch

        return torch.cuda.is_available()
    return str(device).lower() not in ("cpu", "")


def resolve_weights(spec: str | Path, device: str | None = None) -> tuple[Path, str]:
    """``(file, model name)`` for a weights spec: a shipped model's name, or a local file.

    A shipped name resolves to its ONNX copy (``<name>.onnx``, run by onnxruntime: 2.3 to 2.8
    times ultralytics' speed on CPU, the same detections) unless ``device`` is a CUDA device,
    where it resolves to the ``.pt`` (ultralytics on the GPU). The model name is the shipped name
    or the file stem. Darknet models resolve to their ``.weights`` file (the ``.cfg`` must sit
    beside it). Raises :class:`BackendError` for a missing file.
    """
    text = str(spec)
    path = Path(text)
    checkpoint = _shipped_file(text, ".pt")
    if checkpoint is not None:
        if _on_cuda(device):
            return checkpoint, text
        return (_shipped_file(text, ".onnx") or cached_onnx(checkpoint)), text
    if path.suffix.lower() == ".cfg":
        path = path.with_suffix(".weights")
    if not path.is_file():
        hint = ""
        if path.suffix == "":
            hint = f"; shipped models: {', '.join(shipped_models()) or 'none'}"
        raise BackendError(f"--weights: {path} does not exist (weights are loaded from local files only{hint})")
    return path, path.stem


def model_imgsz(spec: str | Path) -> int:
    """The letterbox size a model is evaluated at by default: a shipped model's card ``imgsz``
    (``<name>.json``), else :data:`DEFAULT_IMGSZ`."""
    card = _shipped_file(spec, ".json")
    if card is not None:
        try:
            imgsz = json.loads(card.read_text())["imgsz"]
        except (ValueError, KeyError, TypeError):
            raise BackendError(f"{card}: expected a JSON object with an integer `imgsz`") from None
        if not (isinstance(imgsz, int) and imgsz >= 32):
            raise BackendError(f"{card}: imgsz: expected an integer >= 32, got {imgsz!r}")
        return imgsz
    return DEFAULT_IMGSZ


def export_onnx(weights: str | Path, out: str | Path) -> Path:
    """Export an ultralytics detection checkpoint to ONNX for :func:`load_detector`: an fp32 graph,
    opset 17, dynamic batch and image size (input ``images`` (B, 3, H, W), output ``output0``
    (B, 4 + nc, N)), class names in the ``names`` metadata. Needs the ``onnx`` package.

    Batch norms are exported unfused, so every weight is the checkpoint's own value, and each
    float32 weight that fp16 holds exactly is stored as fp16 behind a Cast to float32
    (:func:`_store_exact_halves`): for a stripped ultralytics checkpoint (fp16 weights, as shipped)
    the file is half the size of a fused fp32 export, with nothing lost. onnxruntime folds the
    casts and fuses the batch norms when it loads the model, so it runs the same optimized graph
    as a fused fp32 export."""
    import onnx
    import torch

    ultralytics = _offline_ultralytics()
    model = ultralytics.YOLO(str(weights))
    net = model.model.float().eval()
    for module in net.modules():
        if hasattr(module, "export"):
            module.export = True
            module.format = "onnx"
        if hasattr(module, "dynamic"):
            module.dynamic = True  # anchors from the input's shape, not the traced one
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        # PRESERVE keeps the (eval-mode) batch norms as nodes instead of folding them into the
        # convolutions, which would make weights that fp16 cannot hold.
        torch.onnx.export(net, torch.zeros(1, 3, 480, 640), str(out), dynamo=False, opset_version=17,
                          training=torch.onnx.TrainingMode.PRESERVE, do_constant_folding=False,
                          input_names=["images"], output_names=["output0"],
                          dynamic_axes={"images": {0: "batch", 2: "height", 3: "width"},
                                        "output0": {0: "batch", 2: "anchors"}})
    proto = _store_exact_halves(onnx.load(str(out)))
    entry = proto.metadata_props.add()
    entry.key, entry.value = "names", str(model.names)
    onnx.checker.check_model(proto)
    onnx.save(proto, str(out))
    return out


def _store_exact_halves(proto: Any) -> Any:
    """Return ``proto`` (an ``onnx.ModelProto``, changed in place) with each float32 initializer
    whose every value fp16 represents exactly stored as fp16, feeding a Cast back to float32 under
    the original name. The graph computes bit for bit what it did; other initializers are kept."""
    import onnx
    from onnx import numpy_helper

    graph = proto.graph
    casts = []
    for initializer in list(graph.initializer):
        values = numpy_helper.to_array(initializer)
        if values.dtype != np.float32 or values.size == 0:
            continue
        halves = values.astype(np.float16)
        if not np.array_equal(halves.astype(np.float32), values):
            continue
        stored = numpy_helper.from_array(halves, f"{initializer.name}__fp16")
        graph.initializer.remove(initializer)
        graph.initializer.append(stored)
        casts.append(onnx.helper.make_node("Cast", [stored.name], [initializer.name], to=onnx.TensorProto.FLOAT,
                                           name=f"{initializer.name}__cast"))
    nodes = casts + list(graph.node)
    del graph.node[:]
    graph.node.extend(nodes)
    return proto


def parse_class_map(spec: str) -> dict[str, int]:
    """``"car=2,pedestrian=0"`` -> ``{"car": 2, "pedestrian": 0}`` (ids must be rainbench class
    ids: 0..3, 5 bus, 7 truck)."""
    mapping: dict[str, int] = {}
    for item in str(spec).split(","):
        item = item.strip()
        if not item:
            continue
        name, sep, value = item.rpartition("=")
        name = name.strip()
        try:
            class_id = int(value)
        except ValueError:
            class_id = None
        if not sep or not name or class_id not in LABELLED_CLASSES:
            raise BackendError(f"--class-map: expected NAME=ID pairs with ID a rainbench class id "
                               f"({class_list(LABELLED_CLASSES)}), got {spec!r}")
        if name in mapping:
            raise BackendError(f"--class-map: class name {name!r} is given twice in {spec!r}")
        mapping[name] = class_id
    if not mapping:
        raise BackendError(f"--class-map: expected NAME=ID pairs such as car=2,pedestrian=0, got {spec!r}")
    return mapping


def class_lookup(names: dict[int, str] | list[str], class_map: str | None, source: str,
                 classes: Sequence[int] = PAPER_CLASSES) -> np.ndarray:
    """Table model class index -> rainbench class id (-1: dropped) for a model's ``names``.

    ``classes``: the rainbench ids to keep (default the paper's four); a model class mapped to
    any other id is dropped too. ``classes=LABELLED_CLASSES`` gives everything the model can
    predict. Returns an (nc,) int64 array.
    """
    wanted = np.asarray(list(classes), dtype=np.int64)
    if isinstance(names, dict):
        size = max(names) + 1 if names else 0
        by_index = {int(k): str(v) for k, v in names.items()}
    else:
        size = len(names)
        by_index = {i: str(v) for i, v in enumerate(names)}
    table = np.full(size, -1, dtype=np.int64)
    if class_map is not None:
        mapping = parse_class_map(class_map)
        index_of = {name: index for index, name in by_index.items()}
        unknown = [name for name in mapping if name not in index_of]
        if unknown:
            shown = ", ".join(map(repr, list(index_of)[:12])) + (", ..." if len(index_of) > 12 else "")
            raise BackendError(f"--class-map: {source} has no class named {unknown[0]!r} (its classes: {shown})")
        for name, class_id in mapping.items():
            table[index_of[name]] = class_id
        table[~np.isin(table, wanted)] = -1
        return table
    if all(by_index.get(i) == CLASS_NAMES[i] for i in PAPER_CLASSES):
        for class_id in wanted.tolist():
            if class_id < size and by_index.get(class_id) == CLASS_NAMES[class_id]:
                table[class_id] = class_id
        return table
    shown = ", ".join(f"{i}={by_index.get(i)!r}" for i in range(min(size, 4)))
    raise BackendError(f"{source}: its class names ({shown}, ...) are not COCO-80; pass --class-map "
                       f"NAME=ID,... mapping its class names to rainbench ids ({class_list(LABELLED_CLASSES)})")


def model_classes(detector: Any) -> tuple[int, ...] | None:
    """The rainbench class ids a loaded detector can predict (whatever it was asked to keep), in
    ascending order; None while unknown (an ONNX file without names metadata and with a dynamic
    output shape learns its class count at its first batch)."""
    full = getattr(detector, "full_lookup", None)
    if full is None:
        return None
    return tuple(sorted({int(c) for c in np.asarray(full).tolist() if c >= 0}))


def _lookups(names, class_map: str | None, source: str, classes: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """(everything the model can predict, the part kept for ``classes``): two :func:`class_lookup`
    tables."""
    return (class_lookup(names, class_map, source, LABELLED_CLASSES),
            class_lookup(names, class_map, source, classes))


def index_names(nc: int) -> list[str]:
    """Class names of a model that carries none: COCO-80 (our eight COCO names first, the rest
    ``coco8`` ...) when it has 80 classes, else its class indices as text (``"0"``, ``"1"``, ...)."""
    if nc == 80:
        return list(CLASS_NAMES) + [f"coco{i}" for i in range(len(CLASS_NAMES), 80)]
    return [str(i) for i in range(nc)]


def _fixed_dim(value: Any) -> int | None:
    """An ONNX dimension as an int, or None when it is symbolic (dynamic)."""
    return value if isinstance(value, int) and value > 0 else None


def preload_torch() -> Any:
    """Import ultralytics (offline) and torch's lazily loaded modules; returns ultralytics.

    torch's triton segfaults when it is first loaded after Mesa's llvmpipe has rendered in the
    same process, so anything that renders and then runs a detector calls this first.
    """
    ultralytics = _offline_ultralytics()
    import torch._dynamo  # noqa: F401

    return ultralytics


def _offline_ultralytics() -> Any:
    """Import ultralytics with downloads off and its settings outside the home folder."""
    os.environ.setdefault("YOLO_OFFLINE", "1")
    os.environ.setdefault("YOLO_CONFIG_DIR", str(Path(tempfile.gettempdir()) / "rainbench-ultralytics"))
    import ultralytics

    return ultralytics


@dataclass
class UltralyticsDetector:
    """An ultralytics YOLO detection model; see :func:`load_detector`."""

    name: str
    model: Any
    lookup: np.ndarray  # model class -> rainbench id of the evaluated classes (-1 dropped)
    device: str | None = None
    full_lookup: np.ndarray | None = None  # model class -> any rainbench id (:func:`model_classes`)

    def predict(self, images, *, imgsz: int, conf: float, iou: float, max_det: int):
        # ultralytics expects BGR numpy arrays; it letterboxes and maps boxes back itself.
        bgr = [np.ascontiguousarray(np.asarray(image)[..., ::-1]) for image in images]
        # classes=: dropped classes go before NMS and max_det, as in the ONNX and Darknet backends.
        kwargs = dict(imgsz=imgsz, conf=conf, iou=iou, max_det=max_det, verbose=False,
                      classes=np.flatnonzero(self.lookup >= 0).tolist())
        if self.device is not None:
            kwargs["device"] = self.device
        results = self.model.predict(bgr, **kwargs)
        outputs = []
        for image, result in zip(images, results, strict=True):
            height, width = np.asarray(image).shape[:2]
            boxes = result.boxes
            xyxy = boxes.xyxy.cpu().numpy().astype(np.float32).reshape(-1, 4)
            scores = boxes.conf.cpu().numpy().astype(np.float32).reshape(-1)
            classes = boxes.cls.cpu().numpy().astype(np.int64).reshape(-1)
            inside = (classes >= 0) & (classes < len(self.lookup))
            mapped = np.full(classes.shape, -1, dtype=np.int64)
            mapped[inside] = self.lookup[classes[inside]]
            keep = mapped >= 0
            xyxy = xyxy[keep]
            xyxy[:, [0, 2]] = np.clip(xyxy[:, [0, 2]], 0, width)
            xyxy[:, [1, 3]] = np.clip(xyxy[:, [1, 3]], 0, height)
            outputs.append((xyxy, scores[keep], mapped[keep]))
        return outputs


def letterbox(image: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Resize ``image`` (H, W, 3) keeping its aspect ratio into a ``shape`` (h, w) canvas, centred,
    padded with grey 114. Returns ``(canvas (h, w, 3) uint8, gain, (pad_x, pad_y))``: a point
    (x, y) of the image lands at ``(x * gain + pad_x, y * gain + pad_y)`` on the canvas."""
    import cv2

    height, width = image.shape[:2]
    gain = min(shape[0] / height, shape[1] / width)
    new_w, new_h = int(round(width * gain)), int(round(height * gain))
    pad_x, pad_y = (shape[1] - new_w) / 2, (shape[0] - new_h) / 2
    resized = image if (new_w, new_h) == (width, height) else cv2.resize(
        image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    top, left = int(round(pad_y - 0.1)), int(round(pad_x - 0.1))
    canvas = np.full((shape[0], shape[1], 3), LETTERBOX_FILL, dtype=np.uint8)
    canvas[top:top + new_h, left:left + new_w] = resized
    return canvas, gain, (float(left), float(top))


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


def decode_yolo(output: np.ndarray, layout: str) -> tuple[np.ndarray, np.ndarray]:
    """One image's raw head output -> (boxes (N, 4) float32 xyxy in input pixels, class scores (N, nc)).

    ``layout``: ``"v8"`` for (4 + nc, N) rows cx, cy, w, h, class scores; ``"v5"`` for
    (N, 5 + nc) columns cx, cy, w, h, objectness, class scores (score = objectness x class).
    """
    if layout == "v8":
        rows = np.asarray(output, np.float32).T
        centres, scores = rows[:, :4], rows[:, 4:]
    elif layout == "v5":
        rows = np.asarray(output, np.float32)
        centres, scores = rows[:, :4], rows[:, 5:] * rows[:, 4:5]
    else:
        raise ValueError(f"layout: expected 'v8' or 'v5', got {layout!r}")
    boxes = np.empty_like(centres)
    boxes[:, :2] = centres[:, :2] - centres[:, 2:4] / 2
    boxes[:, 2:] = centres[:, :2] + centres[:, 2:4] / 2
    return boxes, scores


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


@dataclass
class OnnxDetector:
    """A YOLO ONNX export run by onnxruntime; see :func:`load_detector`."""

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

    def configure(self, output_shape: list) -> None:
        """Decide the output layout and class table from an output shape (B, A, C)."""
        nc = len(self.names) if self.names is not None else None
        self.layout, nc = output_layout(output_shape, nc, Path(f"{self.name}.onnx"))
        names = self.names if self.names is not None else index_names(nc)
        self.full_lookup, self.lookup = _lookups(names, self.class_map, f"--weights {self.name}.onnx",
                                                 self.classes)

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
        step = self.fixed_batch or len(prepared)
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
                    boxes, kept_scores, ids = select_detections(boxes, scores, self.lookup, conf=conf,
                                                                iou=iou, max_det=max_det)
                    outputs[i] = (unletterbox(boxes, gain, pad, width, height), kept_scores, ids)
        return outputs


def _onnx_names(session: Any) -> list[str] | dict[int, str] | None:
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


def _load_onnx(path: Path, class_map: str | None, device: str | None,
               classes: Sequence[int] = PAPER_CLASSES, name: str | None = None) -> OnnxDetector:
    try:
        import onnxruntime
    except ImportError:
        raise BackendError(f"--weights: {path}: ONNX models need onnxruntime (pip install onnxruntime)") from None
    providers = ["CPUExecutionProvider"]
    if device not in (None, "cpu") and "CUDAExecutionProvider" in onnxruntime.get_available_providers():
        providers.insert(0, "CUDAExecutionProvider")
    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
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
                            fixed_batch=_fixed_dim(input_dims[0]), classes=tuple(classes))
    if names is not None:  # a bad --class-map fails now, not at the first batch
        detector.full_lookup, detector.lookup = _lookups(names, class_map, f"--weights {path}", classes)
    if _fixed_dim(output_dims[1]) and _fixed_dim(output_dims[2]):
        detector.configure(output_dims)
    elif names is None and class_map is not None:
        raise BackendError(f"--weights: {path}: --class-map needs class names or a fixed output shape; "
                           "this model has neither")
    return detector


def parse_darknet_cfg(text: str) -> list[tuple[str, dict[str, str]]]:
    """Darknet cfg text -> ``[(section, {key: value})]`` in file order (comments dropped)."""
    sections: list[tuple[str, dict[str, str]]] = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].split(";", 1)[0].strip()
        if not line:
            continue
        if line.startswith("[") and line.endswith("]"):
            sections.append((line[1:-1].strip().lower(), {}))
        elif "=" in line and sections:
            key, value = line.split("=", 1)
            sections[-1][1][key.strip()] = value.strip()
    return sections


def darknet_weight_count(sections: list[tuple[str, dict[str, str]]]) -> int | None:
    """Number of float32 values a Darknet ``.weights`` file must hold for a parsed cfg; None when
    the cfg has a layer type this count does not know (then the file size is not checked)."""
    channels: list[int] = []
    current = int(sections[0][1].get("channels", 3))
    count = 0
    for name, keys in sections[1:]:
        if name in ("convolutional", "conv"):
            filters, size = int(keys.get("filters", 1)), int(keys.get("size", 1))
            groups = int(keys.get("groups", 1))
            batch_norm = int(keys.get("batch_normalize", 0))
            count += filters * (1 + 3 * batch_norm) + filters * (current // groups) * size * size
            current = filters
        elif name == "route":
            indices = [int(v) for v in keys.get("layers", "-1").split(",")]
            total = sum(channels[i if i >= 0 else len(channels) + i] for i in indices)
            current = total // int(keys.get("groups", 1))
        elif name not in ("shortcut", "upsample", "maxpool", "yolo", "region", "dropout", "sam",
                          "scale_channels", "avgpool", "reorg"):
            return None
        elif name == "reorg":
            current *= int(keys.get("stride", 2)) ** 2
        channels.append(current)
    return count


def _darknet_header_bytes(path: Path) -> int:
    with open(path, "rb") as handle:
        head = handle.read(12)
    if len(head) < 12:
        return 0
    major, minor, _ = np.frombuffer(head, "<i4")
    return 20 if (major * 10 + minor >= 2 and major < 1000 and minor < 1000) else 16


@dataclass
class DarknetDetector:
    """A Darknet (YOLOv4-style) network run by OpenCV DNN; see :func:`load_detector`."""

    name: str
    net: Any
    lookup: np.ndarray  # model class -> rainbench id of the evaluated classes (-1 dropped)
    input_size: tuple[int, int]  # (h, w) from the cfg's [net] section
    letterboxed: bool
    full_lookup: np.ndarray | None = None  # model class -> any rainbench id (:func:`model_classes`)

    def predict(self, images, *, imgsz: int, conf: float, iou: float, max_det: int):
        import cv2

        height_in, width_in = self.input_size
        outputs = []
        names = self.net.getUnconnectedOutLayersNames()
        for image in images:
            image = np.asarray(image)
            height, width = image.shape[:2]
            if self.letterboxed:
                canvas, gain, pad = letterbox(image, (height_in, width_in))
                scale = (gain, gain)
            else:
                canvas = cv2.resize(image, (width_in, height_in), interpolation=cv2.INTER_LINEAR)
                scale, pad = (width_in / width, height_in / height), (0.0, 0.0)
            blob = np.ascontiguousarray(canvas.transpose(2, 0, 1)[None], dtype=np.float32) / 255.0
            self.net.setInput(blob)
            raw = np.concatenate([np.asarray(o, np.float32).reshape(-1, o.shape[-1])
                                  for o in self.net.forward(names)])
            boxes, scores = decode_darknet(raw, (height_in, width_in))
            boxes, kept_scores, ids = select_detections(boxes, scores, self.lookup, conf=conf, iou=iou,
                                                        max_det=max_det)
            outputs.append((unletterbox(boxes, scale, pad, width, height), kept_scores, ids))
        return outputs


def decode_darknet(rows: np.ndarray, input_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV DNN YOLO rows (N, 5 + nc): cx, cy, w, h as fractions of the network input,
    objectness, class scores (already objectness x class probability) -> (boxes (N, 4) float32
    xyxy in input pixels, class scores (N, nc))."""
    rows = np.asarray(rows, np.float32)
    height_in, width_in = input_size
    cx, cy = rows[:, 0] * width_in, rows[:, 1] * height_in
    half_w, half_h = rows[:, 2] * width_in / 2, rows[:, 3] * height_in / 2
    boxes = np.stack([cx - half_w, cy - half_h, cx + half_w, cy + half_h], axis=1)
    return boxes, rows[:, 5:]


def _load_darknet(path: Path, class_map: str | None, kept: Sequence[int] = PAPER_CLASSES) -> DarknetDetector:
    import cv2

    cfg = path.with_suffix(".cfg")
    if not cfg.is_file():
        raise BackendError(f"--weights: {path}: the Darknet cfg {cfg.name} must sit beside the .weights file")
    if not hasattr(cv2.dnn, "readNetFromDarknet"):
        raise BackendError(f"--weights: {path}: this OpenCV ({cv2.__version__}) has no Darknet importer; "
                           "install opencv-python-headless<5")
    sections = parse_darknet_cfg(cfg.read_text(errors="replace"))
    net_section = next((keys for name, keys in sections if name in ("net", "network")), None)
    classes = {int(keys.get("classes", -1)) for name, keys in sections if name in ("yolo", "region")}
    if net_section is None or len(classes) != 1 or min(classes) < 1:
        raise BackendError(f"--weights: {cfg} is not a Darknet YOLO cfg (expected a [net] section and "
                           "[yolo] layers with one classes= value)")
    expected = darknet_weight_count(sections)
    size = path.stat().st_size
    header = _darknet_header_bytes(path)
    if header == 0 or (expected is not None and size != header + 4 * expected):
        held = max(size - header, 0) // 4
        raise BackendError(f"--weights: {path} does not load with {cfg.name} (it holds {held} weights, "
                           f"the cfg needs {expected}: truncated, or another network's file)")
    try:
        net = cv2.dnn.readNetFromDarknet(str(cfg), str(path))
    except cv2.error as error:
        reason = " ".join(str(error).split())[-200:]
        raise BackendError(f"--weights: {path} does not load with {cfg.name} ({reason})") from None
    nc = classes.pop()
    full_lookup, lookup = _lookups(index_names(nc), class_map, f"--weights {path}", kept)
    input_size = (int(net_section.get("height", 416)), int(net_section.get("width", 416)))
    return DarknetDetector(name=path.stem, net=net, lookup=lookup, input_size=input_size,
                           letterboxed=net_section.get("letter_box", "0") == "1", full_lookup=full_lookup)


TRUST_PICKLE_ENV = "RAINBENCH_TRUST_PICKLE"


class _SafeLoadRefused(Exception):
    """ultralytics' safe loading refused a global of the checkpoint (``name``)."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


def _load_yolo_safely(ultralytics: Any, path: Path) -> Any:
    """``ultralytics.YOLO(path)`` with the checkpoint read by ultralytics' own safe loading
    (``torch_safe_load(..., safe_only=True)``: ``torch.load(weights_only=True)`` against its
    allow-list of model classes) instead of the full unpickler ``YOLO`` uses by default.

    Raises :class:`_SafeLoadRefused` naming the first global outside the allow-list, and
    whatever ultralytics raises for a file that does not load at all.
    """
    from ultralytics.nn import tasks

    if not getattr(getattr(tasks, "_SafeLoad", None), "SUPPORTED", False):
        raise _SafeLoadRefused("(this torch/ultralytics has no weights_only loading)")
    unsafe_loader = tasks.torch_safe_load

    def safe_loader(weight, safe_only=None):
        return unsafe_loader(weight, safe_only=True)

    tasks.torch_safe_load = safe_loader  # load_checkpoint looks it up when called
    try:
        return ultralytics.YOLO(str(path))
    except TypeError as error:
        cause = error.__cause__
        if isinstance(cause, pickle.UnpicklingError):
            found = re.search(r"GLOBAL ([\w.]+)", str(cause))
            with open(path, "rb") as handle:
                head = handle.read(2)
            if found or head == b"PK" or head[:1] == b"\x80":  # a torch zip or a pickle
                raise _SafeLoadRefused(found.group(1) if found else
                                       "objects that weights_only loading cannot read") from None
        raise  # not a checkpoint at all (garbage, an image renamed .pt): not loadable
    finally:
        tasks.torch_safe_load = unsafe_loader


def load_detector(weights: str | Path, *, class_map: str | None = None,
                  device: str | None = None, trust_pickle: bool | None = None,
                  classes: Sequence[int] = PAPER_CLASSES) -> Detector:
    """Load a detector from a weights spec (:func:`resolve_weights`); ``.name`` is the model name.

    ``classes``: the rainbench class ids it keeps (default the paper's four); the others it can
    predict (:func:`model_classes`) are dropped before NMS and ``max_det``. A class it cannot
    predict is not an error here (see :func:`check_model_classes`).

    A ``.pt`` is read with ultralytics' safe loading; one that needs Python's full unpickler is
    refused unless ``trust_pickle`` (None: the ``RAINBENCH_TRUST_PICKLE=1`` environment
    variable), see the module docstring.

    Raises :class:`BackendError` (one line, naming the file) for a missing file, an unsupported
    format, a file that does not load, a .pt that needs the unsafe loader without trust, a
    non-detection model, or class names that are neither COCO-80 nor covered by ``class_map``.
    """
    if trust_pickle is None:
        trust_pickle = os.environ.get(TRUST_PICKLE_ENV, "") == "1"
    path, name = resolve_weights(weights, device)
    if class_map is not None:
        parse_class_map(class_map)
    suffix = path.suffix.lower()
    if suffix == ".onnx":
        return _load_onnx(path, class_map, device, classes, name)
    if suffix == ".weights":
        return _load_darknet(path, class_map, classes)
    if suffix != ".pt":
        raise BackendError(f"--weights: {path}: unsupported format {path.suffix or '(none)'!r}; expected "
                           "an ultralytics .pt, an .onnx export, Darknet .cfg/.weights, or a shipped model "
                           f"name ({', '.join(shipped_models()) or 'none shipped'})")
    ultralytics = _offline_ultralytics()
    try:
        try:
            model = _load_yolo_safely(ultralytics, path)
        except _SafeLoadRefused as refused:
            if not trust_pickle:
                raise BackendError(
                    f"--weights: {path} cannot be loaded safely: it pickles {refused.name}, which "
                    "is outside ultralytics' allow-list of model classes, and loading it with "
                    "Python's full unpickler runs code from the file; if you trust this file, "
                    f"pass --trust-pickle (or set {TRUST_PICKLE_ENV}=1)") from None
            print(f"rainbench: warning: loading {path} with Python's full unpickler (it pickles "
                  f"{refused.name}; trusted by --trust-pickle): this runs code from the file",
                  file=sys.stderr)
            model = ultralytics.YOLO(str(path))
    except BackendError:
        raise
    except Exception as error:  # ultralytics raises TypeError, RuntimeError, pickle errors, ...
        reason = " ".join(str(error).split())[:200]
        raise BackendError(f"--weights: {path} is not a loadable ultralytics checkpoint ({reason})") from None
    if getattr(model, "task", None) != "detect":
        raise BackendError(f"--weights: {path} is a {getattr(model, 'task', 'unknown')!r} model; "
                           "expected a detection model")
    full_lookup, lookup = _lookups(model.names, class_map, f"--weights {path}", classes)
    return UltralyticsDetector(name=name, model=model, lookup=lookup, device=device, full_lookup=full_lookup)


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
