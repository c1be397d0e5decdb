"""Detector backends for ``rainbench eval``: local weights files -> boxes in original image pixels.

:func:`load_detector` returns a :class:`Detector`. Backend implemented: ultralytics ``.pt``
checkpoints (``ultralytics.YOLO(path)``), loaded from a local file only; nothing is downloaded
(``YOLO_OFFLINE=1``) and ultralytics' settings go to a temporary folder, not the home folder.

WARNING: ``.pt`` checkpoints are Python pickles; loading one executes code from the file. Only
load weights you trust.

Class mapping: rainbench class ids are COCO-80 indices 0 person, 1 bicycle, 2 car, 3 motorcycle.
A model whose names[0..3] are those COCO names maps ids 0..3 directly and drops its other
classes; any other model needs a class map ``"car=2,pedestrian=0"`` (model class name = rainbench
class id); model classes left out of the map are dropped.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from .metrics import CLASS_IDS, CLASS_NAMES


class BackendError(ValueError):
    """A user-facing backend error with a one-line message."""


class Detector(Protocol):
    name: str

    def predict(self, images: list[np.ndarray], *, imgsz: int, conf: float, iou: float,
                max_det: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(H, W, 3) uint8 RGB images -> per image (boxes (K, 4) float32 xyxy in original pixels,
        scores (K,) float32, class_ids (K,) int64 rainbench ids)."""
        ...


def parse_class_map(spec: str) -> dict[str, int]:
    """``"car=2,pedestrian=0"`` -> ``{"car": 2, "pedestrian": 0}`` (ids must be rainbench ids 0..3)."""
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
        if not sep or not name or class_id not in CLASS_IDS:
            raise BackendError(f"--class-map: expected NAME=ID pairs with ID in 0..3 "
                               f"({', '.join(f'{i} {n}' for i, n in enumerate(CLASS_NAMES))}), got {spec!r}")
        if name in mapping:
            raise BackendError(f"--class-map: class name {name!r} is given twice in {spec!r}")
        mapping[name] = class_id
    if not mapping:
        raise BackendError(f"--class-map: expected NAME=ID pairs such as car=2,pedestrian=0, got {spec!r}")
    return mapping


def class_lookup(names: dict[int, str] | list[str], class_map: str | None, source: str) -> np.ndarray:
    """Table model class index -> rainbench class id (-1: dropped) for a model's ``names``."""
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
            shown = ", ".join(list(index_of)[:12]) + (", ..." if len(index_of) > 12 else "")
            raise BackendError(f"--class-map: {source} has no class named {unknown[0]!r} (its classes: {shown})")
        for name, class_id in mapping.items():
            table[index_of[name]] = class_id
        return table
    if all(by_index.get(i) == CLASS_NAMES[i] for i in CLASS_IDS):
        table[: len(CLASS_IDS)] = CLASS_IDS
        return table
    shown = ", ".join(f"{i}={by_index.get(i)}" for i in range(min(size, 4)))
    raise BackendError(f"{source}: its class names ({shown}, ...) are not COCO-80; pass --class-map "
                       "NAME=ID,... mapping its class names to 0 person, 1 bicycle, 2 car, 3 motorcycle")


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
    lookup: np.ndarray
    device: str | None = None

    def predict(self, images, *, imgsz: int, conf: float, iou: float, max_det: int):
        # ultralytics expects BGR numpy arrays; it letterboxes and maps boxes back itself.
        bgr = [np.ascontiguousarray(np.asarray(image)[..., ::-1]) for image in images]
        kwargs = dict(imgsz=imgsz, conf=conf, iou=iou, max_det=max_det, verbose=False)
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


def load_detector(weights: str | Path, *, class_map: str | None = None,
                  device: str | None = None) -> UltralyticsDetector:
    """Load a detector from a local weights file; ``.name`` is the file stem.

    Raises :class:`BackendError` (one line, naming the file) for a missing file, an unsupported
    format, a file that is not a loadable checkpoint, a non-detection model, or class names that
    are neither COCO-80 nor covered by ``class_map``.
    """
    path = Path(weights)
    if not path.is_file():
        raise BackendError(f"--weights: {path} does not exist (weights are loaded from local files only)")
    if path.suffix.lower() != ".pt":
        raise BackendError(f"--weights: {path}: unsupported format {path.suffix or '(none)'!r}; "
                           "expected an ultralytics .pt checkpoint")
    if class_map is not None:
        parse_class_map(class_map)
    ultralytics = _offline_ultralytics()
    try:
        model = ultralytics.YOLO(str(path))
    except Exception as error:  # ultralytics raises TypeError, RuntimeError, pickle errors, ...
        reason = " ".join(str(error).split())[:200]
        raise BackendError(f"--weights: {path} is not a loadable ultralytics checkpoint ({reason})") from None
    if getattr(model, "task", None) != "detect":
        raise BackendError(f"--weights: {path} is a {getattr(model, 'task', 'unknown')!r} model; "
                           "expected a detection model")
    lookup = class_lookup(model.names, class_map, f"--weights {path}")
    return UltralyticsDetector(name=path.stem, model=model, lookup=lookup, device=device)
