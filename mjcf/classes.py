"""The label classes: COCO-80 indices, so any COCO-pretrained YOLO matches them directly.

``CLASS_NAMES[class_id]`` is the COCO name of ``class_id`` for ids 0..7; ids 4 (airplane) and
6 (train) are never labelled in our scenes but keep their COCO names so that the ids of bus (5)
and truck (7) are COCO's own. ``PAPER_CLASSES`` are the four classes of the seed paper, which the
evaluator and the paper report use by default.
"""

from __future__ import annotations

CLASS_NAMES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck",
)
PERSON, BICYCLE, CAR, MOTORCYCLE, BUS, TRUCK = 0, 1, 2, 3, 5, 7
LABELLED_CLASSES: tuple[int, ...] = (PERSON, BICYCLE, CAR, MOTORCYCLE, BUS, TRUCK)
PAPER_CLASSES: tuple[int, ...] = (PERSON, BICYCLE, CAR, MOTORCYCLE)
