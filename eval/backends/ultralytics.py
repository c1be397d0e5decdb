"""The ultralytics backend: an ultralytics checkpoint ``.pt`` (YOLOv3u/v5u/v8/v9/v10/11/12...)
run by ``ultralytics.YOLO``, which letterboxes and maps boxes back itself.

Safe loading: ``.pt`` checkpoints are Python pickles, and Python's full unpickler runs code from
the file. They are read with ultralytics' safe loading (:func:`_load_yolo_safely`:
``torch.load(weights_only=True)`` against ultralytics' allow-list of torch and ultralytics model
classes); a file that needs anything else is refused unless trusted (:data:`TRUST_PICKLE_ENV`,
``--trust-pickle``).

ultralytics is imported offline (:func:`_offline_ultralytics`): nothing is downloaded and its
settings go to a temporary folder, not the home folder.
"""

from __future__ import annotations

import os
import pickle
import re
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.devices import ultralytics_device
from rainbench.eval.backends import BackendError
from rainbench.eval.backends.classes import _lookups
from rainbench.store.classes import PAPER_CLASSES

TRUST_PICKLE_ENV = "RAINBENCH_TRUST_PICKLE"
"""Set to ``1``, ``.pt`` files that safe loading refuses are loaded with the full unpickler."""


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
    """An ultralytics YOLO detection model; see :func:`rainbench.eval.backends.load_detector`."""

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
        import torch

        threads = torch.get_num_threads()
        try:
            results = self.model.predict(bgr, **kwargs)
        finally:  # ultralytics sets torch's threads to cores - 1 for CPU work; not for the rest of the run
            torch.set_num_threads(threads)
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


_CHECKPOINT_HEADS = (b"PK\x03\x04", b"\x80")
"""How a file ``torch.load`` reads begins: a zip archive (``torch.save``'s format since torch 1.6,
what ultralytics writes) or a pickle (protocol 2 or later: the legacy format)."""
_OTHER_FORMATS = ((b"\x89PNG", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
                  (b"\x89HDF", "an HDF5 file"), (b"\x1f\x8b", "a gzip file"), (b"GIF8", "a GIF image"))


def _not_a_checkpoint(path: Path) -> str | None:
    """What ``path`` is instead, when its first bytes show that it is not a PyTorch checkpoint
    ("an empty file", "a text file", "a PNG image", ...); None when it may be one."""
    with open(path, "rb") as handle:
        head = handle.read(512)
    if head.startswith(_CHECKPOINT_HEADS):
        return None
    if not head:
        return "an empty file"
    for magic, kind in _OTHER_FORMATS:
        if head.startswith(magic):
            return kind
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as error:  # a character cut at the 512th byte is still text
        text = head[:error.start].decode("utf-8") if error.start >= len(head) - 3 else None
    if text is not None and all(c.isprintable() or c in "\t\n\r\f\v" for c in text):
        return "a text file"
    return f"a file whose first bytes are {head[:8].hex(' ')}"


def _load_ultralytics(path: Path, class_map: str | None, device: str | None, trust_pickle: bool | None,
                      classes: Sequence[int] = PAPER_CLASSES, name: str | None = None,
                      trained: Sequence[int] | None = None) -> UltralyticsDetector:
    """An :class:`UltralyticsDetector` for the checkpoint ``path``, read safely (full unpickler
    only when ``trust_pickle``; None: the :data:`TRUST_PICKLE_ENV` environment variable).
    ``trained``: the classes its card names (None: unknown), the only ones it is taken to predict."""
    trusted_by = "--trust-pickle"
    if trust_pickle is None:
        trust_pickle, trusted_by = os.environ.get(TRUST_PICKLE_ENV, "") == "1", f"{TRUST_PICKLE_ENV}=1"
    try:
        other = _not_a_checkpoint(path)
    except OSError as error:
        raise BackendError(f"--weights: {path} cannot be read ({error.strerror or error})") from None
    if other is not None:
        raise BackendError(f"--weights: {path} is not a loadable ultralytics checkpoint: expected a PyTorch "
                           f"checkpoint file (a zip archive written by torch.save, as ultralytics saves), got {other}")
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
                  f"{refused.name}; trusted by {trusted_by}): this runs code from the file",
                  file=sys.stderr)
            model = ultralytics.YOLO(str(path))
    except BackendError:
        raise
    except Exception as error:  # ultralytics raises TypeError, RuntimeError, pickle errors, ...
        reason = " ".join(str(error).split())
        if not any(c.isalpha() for c in reason):  # a bare KeyError: 101 from the unpickler
            reason = f"{type(error).__name__}: {reason}".rstrip(": ")
        if len(reason) > 200:  # ultralytics' advice runs on; keep its first sentence, whole words
            reason = reason[:200].rsplit(" ", 1)[0] + " ..."
        raise BackendError(f"--weights: {path} is not a loadable ultralytics checkpoint ({reason})") from None
    if getattr(model, "task", None) != "detect":
        raise BackendError(f"--weights: {path} is a {getattr(model, 'task', 'unknown')!r} model; "
                           "expected a detection model")
    full_lookup, lookup = _lookups(model.names, class_map, f"--weights {path}", classes, trained)
    return UltralyticsDetector(name=name or path.stem, model=model, lookup=lookup,
                               device=ultralytics_device(device, BackendError),
                               full_lookup=full_lookup)

