"""The label classes: COCO-80 indices, so any COCO-pretrained YOLO matches them directly.

``CLASS_NAMES[class_id]`` is the COCO name of ``class_id`` for ids 0..7; ids 4 (airplane) and
6 (train) are never labelled in our scenes but keep their COCO names so that the ids of bus (5)
and truck (7) are COCO's own. ``PAPER_CLASSES`` are the four classes of the seed paper, which the
evaluator and the paper report use by default.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

CLASS_NAMES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck",
)
PERSON, BICYCLE, CAR, MOTORCYCLE, BUS, TRUCK = 0, 1, 2, 3, 5, 7
LABELLED_CLASSES: tuple[int, ...] = (PERSON, BICYCLE, CAR, MOTORCYCLE, BUS, TRUCK)
PAPER_CLASSES: tuple[int, ...] = (PERSON, BICYCLE, CAR, MOTORCYCLE)
CLASS_COLOURS: tuple[tuple[int, int, int], ...] = (
    (230, 60, 60), (60, 200, 60), (60, 120, 240), (240, 200, 40), (128, 128, 128),
    (240, 130, 30), (128, 128, 128), (170, 80, 220))
"""RGB box colour per class id 0..7 (person, bicycle, car, motorcycle, (airplane), bus, (train),
truck): previews, videos and the evaluator's detection strip draw every class in its colour."""
PAPER_CLASS_NAMES: tuple[str, ...] = tuple(CLASS_NAMES[i] for i in PAPER_CLASSES)
"""Names of the paper's four classes, ids 0..3 (the default categories of :func:`rainbench.eval.metrics.coco.coco_ground_truth`)."""

def class_list(class_ids: Sequence[int]) -> str:
    """``"person (0), car (2), bus (5)"``: class ids with their names, for messages."""
    return ", ".join(f"{CLASS_NAMES[class_id]} ({class_id})" for class_id in class_ids)


def parse_classes(spec: str | Sequence[int | str]) -> tuple[int, ...]:
    """Class ids of a ``--classes`` value, unique and in class-id order.

    Args:
        spec: Comma-separated names or ids (``"person,car,bus,truck"``, ``"0,2,5,7"``, mixed, any
            case), or a sequence of names / ids. Allowed: the labelled classes
            (``LABELLED_CLASSES``: person 0, bicycle 1, car 2, motorcycle 3, bus 5, truck 7).

    Returns:
        (K,) tuple of class ids, K >= 1, ascending.

    Raises a one-line ValueError naming an unknown entry and the allowed names.
    """
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    allowed = f"expected names or ids of {class_list(LABELLED_CLASSES)}"
    ids: set[int] = set()
    for item in items:
        if isinstance(item, str):
            text = item.strip().lower()
            if not text:
                continue
            class_id = int(text) if text.isdigit() else (CLASS_NAMES.index(text) if text in CLASS_NAMES else -1)
        elif isinstance(item, (int, np.integer)) and not isinstance(item, (bool, np.bool_)):
            class_id = int(item)
        else:
            class_id = -1
        if class_id not in LABELLED_CLASSES:
            raise ValueError(f"--classes: unknown class {item!r}; {allowed}")
        ids.add(class_id)
    if not ids:
        raise ValueError(f"--classes: expected at least one class, got {spec!r}; {allowed}")
    return tuple(sorted(ids))
