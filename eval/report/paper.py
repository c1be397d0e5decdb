"""The seed paper's published numbers and presentation constants (its Tables I, III and IV, the
class order of its tables and the line colours of its Figs. 8-11), set beside ours by the reports.
"""

from __future__ import annotations

PAPER_TABLES: dict[str, dict[str, dict[float, dict[str, float]]]] = {
    # Table III, "AP score" (YOLO val's per-class AP, read here as AP@0.5).
    "ap50": {
        "YOLOv4": {
            0.0: {"car": 0.64, "person": 0.771, "bicycle": 0.913, "motorcycle": 0.263},
            100.0: {"car": 0.424, "person": 0.469, "bicycle": 0.677, "motorcycle": 0.0043},
        },
        "YOLOv5x": {
            0.0: {"car": 0.652, "person": 0.738, "bicycle": 0.813, "motorcycle": 0.425},
            100.0: {"car": 0.452, "person": 0.427, "bicycle": 0.614, "motorcycle": 0.0031},
        },
        "YOLOv7x": {
            0.0: {"car": 0.669, "person": 0.731, "bicycle": 0.936, "motorcycle": 0.198},
            100.0: {"car": 0.46, "person": 0.51, "bicycle": 0.693, "motorcycle": 0.00025},
        },
    },
    # Table IV, "F1 score".
    "f1": {
        "YOLOv4": {
            0.0: {"car": 0.629, "person": 0.699, "bicycle": 0.802, "motorcycle": 0.179},
            100.0: {"car": 0.477, "person": 0.414, "bicycle": 0.627, "motorcycle": 0.0},
        },
        "YOLOv5x": {
            0.0: {"car": 0.623, "person": 0.746, "bicycle": 0.724, "motorcycle": 0.415},
            100.0: {"car": 0.514, "person": 0.485, "bicycle": 0.535, "motorcycle": 0.0},
        },
        "YOLOv7x": {
            0.0: {"car": 0.663, "person": 0.786, "bicycle": 0.859, "motorcycle": 0.159},
            100.0: {"car": 0.533, "person": 0.549, "bicycle": 0.522, "motorcycle": 0.0},
        },
    },
}
"""Published numbers of the seed paper, ``{metric: {model: {rate_mm_h: {class: value}}}}``.

Transcribed from Tables III (AP) and IV (F1), CARLA data, Normal (0 mm/h) and 100 mm/h. The
paper reports YOLO's "AP score" without naming the IoU; it is mapped to our ``ap50``. (Table II
repeats the Normal values, with one discrepancy: YOLOv4 car F1 is 0.628 there, 0.629 here.)
"""

TABLE_CLASS_ORDER: tuple[str, ...] = ("car", "person", "bicycle", "motorcycle")
"""Column order of the paper's Tables III and IV (other classes, e.g. bus and truck, follow in
class-id order)."""

PAPER_COLORS: dict[str, str] = {"yolov7x": "tab:red", "yolov5x": "tab:green", "yolov4": "tab:blue"}
"""Line colours of the paper's Figs. 8-11 (YOLOv7x red, YOLOv5x green, YOLOv4 blue)."""

PAPER_TABLE_I: dict[str, tuple[int, int]] = {
    "car": (6, 838), "person": (8, 350), "bicycle": (2, 67), "motorcycle": (1, 10),
}
"""The seed paper's Table I: (objects placed, labelled instances over the 200 frames) per class."""
