"""The detection strip (the seed paper's Fig. 12): one frame across rain rates with its detections,
drawn with OpenCV (built-in Hershey fonts, nothing fetched). OpenCV is imported when a strip is
drawn, not with this module.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.store.classes import CLASS_COLOURS, CLASS_NAMES

from rainbench.store.images import write_image


def plot_detection_strip(
    images_by_rate: Mapping[float, np.ndarray],
    detections_by_rate: Mapping[float, Sequence[Mapping[str, Any]]],
    out_png: str | Path,
    *,
    class_names: Sequence[str] = CLASS_NAMES,
    min_score: float = 0.25,
    columns: int | None = None,
) -> Path:
    """Draw one frame across rain rates with its detections, tiled into one PNG (Fig. 12).

    Args:
        images_by_rate: ``{rate_mm_h: image}``, each image (H, W, 3) uint8 RGB, all the same shape.
        detections_by_rate: ``{rate_mm_h: records}``, COCO results records of that frame
            (bbox ``[x, y, w, h]`` in pixels, ``category_id`` a class id, ``score``); rates
            missing here are drawn without boxes.
        out_png: Output PNG path (parent folders created).
        class_names: ``class_names[category_id]`` labels the boxes.
        min_score: Detections below this confidence are not drawn.
        columns: Tiles per row; ``ceil(sqrt(n))`` when None.

    Boxes are clipped to the tile before drawing, and a box that misses the image (or is not
    finite) is not drawn, so no detection, however far outside the frame, can make OpenCV fail.

    Returns:
        The PNG path.

    Raises:
        OSError: one line naming ``out_png`` when it cannot be written.
    """
    import cv2

    if not images_by_rate:
        raise ValueError("images_by_rate: expected at least one {rate: image}, got none")
    rates = sorted(images_by_rate, key=float)
    first = np.asarray(images_by_rate[rates[0]])
    if first.ndim != 3 or first.shape[2] != 3 or first.dtype != np.uint8:
        raise ValueError(
            f"images_by_rate[{rates[0]}]: expected an (H, W, 3) uint8 RGB image, got {first.dtype} {first.shape}"
        )
    height, width = first.shape[:2]
    banner = 28
    tiles = []
    for rate in rates:
        image = np.asarray(images_by_rate[rate])
        if image.shape != first.shape or image.dtype != np.uint8:
            raise ValueError(
                f"images_by_rate[{rate}]: expected uint8 {first.shape} like the first image, got {image.dtype} {image.shape}"
            )
        tile = np.full((height + banner, width, 3), 255, dtype=np.uint8)
        tile[banner:] = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR)
        cv2.putText(
            tile, f"{float(rate):g} mm/h", (6, banner - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 2, cv2.LINE_AA
        )
        for record in detections_by_rate.get(rate, ()):
            score = float(record["score"])
            if not score >= min_score:  # nan too
                continue
            corners = _visible_corners(record["bbox"], width, height)
            if corners is None:
                continue
            x1, y1, x2, y2 = corners
            class_id = int(record["category_id"])
            color = CLASS_COLOURS[class_id % len(CLASS_COLOURS)][::-1]  # BGR
            top_left = (x1, y1 + banner)
            bottom_right = (x2, y2 + banner)
            cv2.rectangle(tile, top_left, bottom_right, color, 2)
            name = class_names[class_id] if 0 <= class_id < len(class_names) else str(class_id)
            label = f"{name} {score:.2f}"
            (text_width, text_height), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
            label_top = max(banner, top_left[1] - text_height - 4)
            label_left = max(0, min(top_left[0], width - text_width - 2))
            cv2.rectangle(
                tile, (label_left, label_top), (label_left + text_width + 2, label_top + text_height + 4), color, -1
            )
            cv2.putText(
                tile,
                label,
                (label_left + 1, label_top + text_height + 1),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.45,
                (255, 255, 255),
                1,
                cv2.LINE_AA,
            )
        tiles.append(tile)
    n_columns = columns if columns is not None else math.ceil(math.sqrt(len(tiles)))
    if n_columns < 1:
        raise ValueError(f"columns: expected an int >= 1, got {columns!r}")
    n_rows = math.ceil(len(tiles) / n_columns)
    gap = 4
    canvas = np.full(
        (n_rows * (height + banner) + (n_rows - 1) * gap, n_columns * width + (n_columns - 1) * gap, 3),
        255,
        dtype=np.uint8,
    )
    for position, tile in enumerate(tiles):
        row, column = divmod(position, n_columns)
        top, left = row * (height + banner + gap), column * (width + gap)
        canvas[top : top + height + banner, left : left + width] = tile
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    return write_image(out_png, canvas[:, :, ::-1])  # the canvas is BGR


def _visible_corners(bbox: Sequence[float], width: int, height: int) -> tuple[int, int, int, int] | None:
    """The integer corners ``(x1, y1, x2, y2)`` of a ``[x, y, w, h]`` box clipped to just outside
    a ``width`` x ``height`` image (an edge beyond the image is not drawn), or None for a box
    that misses the image or is not finite: whatever a model reports, OpenCV gets small ints."""
    x, y, w, h = (float(v) for v in bbox)
    x1, y1, x2, y2 = x, y, x + w, y + h  # inf where x + w overflows: not finite, not drawn
    if not all(math.isfinite(v) for v in (x1, y1, x2, y2)):
        return None
    x1, x2 = sorted((x1, x2))
    y1, y2 = sorted((y1, y2))
    if x2 < 0 or y2 < 0 or x1 > width or y1 > height:
        return None
    return _clip(x1, width), _clip(y1, height), _clip(x2, width), _clip(y2, height)


def _clip(value: float, size: int) -> int:
    """``value`` rounded into -2 .. size + 2 (a clipped edge lies just outside the image)."""
    return int(round(min(max(value, -2.0), size + 2.0)))
