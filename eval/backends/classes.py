"""Class maps: a model's own class names -> rainbench class ids.

rainbench class ids are COCO-80 indices (:mod:`rainbench.store.classes`). A model whose
names[0..3] are the COCO names person, bicycle, car, motorcycle maps each rainbench class it
names at its COCO index directly; any other model needs a class map ``"car=2,pedestrian=0"``
(:func:`parse_class_map`). The tables built here (:func:`class_lookup`) are what every backend
uses to turn model class indices into rainbench ids.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rainbench.eval.backends import BackendError
from rainbench.store.classes import CLASS_NAMES, LABELLED_CLASSES, PAPER_CLASSES, class_list


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


def _lookups(names: dict[int, str] | list[str], class_map: str | None, source: str,
             classes: Sequence[int], trained: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(everything the model can predict, the part kept for ``classes``): two :func:`class_lookup`
    tables; ``trained`` (:func:`rainbench.eval.weights.trained_classes`), when known, leaves out
    the classes the model was not trained on."""
    everything = LABELLED_CLASSES if trained is None else [c for c in LABELLED_CLASSES if c in trained]
    kept = classes if trained is None else [c for c in classes if c in trained]
    return (class_lookup(names, class_map, source, everything),
            class_lookup(names, class_map, source, kept))


def index_names(nc: int) -> list[str]:
    """Class names of a model that carries none: COCO-80 (our eight COCO names first, the rest
    ``coco8`` ...) when it has 80 classes, else its class indices as text (``"0"``, ``"1"``, ...)."""
    if nc == 80:
        return list(CLASS_NAMES) + [f"coco{i}" for i in range(len(CLASS_NAMES), 80)]
    return [str(i) for i in range(nc)]
