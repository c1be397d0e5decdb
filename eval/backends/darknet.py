"""The Darknet backend: a YOLOv4-style network run by OpenCV DNN.

A Darknet model is ``name.cfg`` and ``name.weights`` side by side (either may be given as the
weights spec). The cfg is parsed here to check the ``.weights`` file's size before OpenCV reads
it, and to learn the class count and input size. Darknet files carry no class names: 80 classes
count as COCO-80, other counts use their class indices as names
(:func:`rainbench.eval.backends.classes.index_names`). Darknet files hold no code.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.eval.backends import BackendError
from rainbench.eval.backends.classes import _lookups, index_names
from rainbench.eval.backends.letterbox import letterbox, select_detections, unletterbox
from rainbench.store.classes import PAPER_CLASSES


@dataclass
class DarknetDetector:
    """A Darknet (YOLOv4-style) network run by OpenCV DNN; see
    :func:`rainbench.eval.backends.load_detector`."""

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
    """Size of a Darknet ``.weights`` file's header (20 bytes from format 0.2 on, else 16); 0
    when the file is too short to hold one."""
    with open(path, "rb") as handle:
        head = handle.read(12)
    if len(head) < 12:
        return 0
    major, minor, _ = np.frombuffer(head, "<i4")
    return 20 if (major * 10 + minor >= 2 and major < 1000 and minor < 1000) else 16


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
