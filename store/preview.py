"""Preview montages: one frame of a shard across all its rain rates (the paper's Fig. 7)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np

from .classes import CLASS_COLOURS
from .images import write_image

MAX_SHEET_PIXELS = 1 << 27
"""A montage's largest size (about 400 MB of RGB): four 8192x4096 tiles."""
IGNORE_COLOUR = (150, 150, 150)
"""RGB of ignore regions (actors too small or hidden to be labels) in previews."""


def montage(images: np.ndarray, rates: np.ndarray, columns: int | None = None,
            boxes: np.ndarray | None = None, class_ids: np.ndarray | None = None,
            tile_width: int = 400, ignore_boxes: np.ndarray | None = None) -> np.ndarray:
    """Tile ``images`` (R, H, W, 3) uint8 with "<rate> mm/h" printed on each, each resized to
    ``tile_width`` pixels wide (aspect kept); returns RGB uint8.

    Optional ``boxes`` (M, 4) xyxy pixel-edge and ``class_ids`` (M,) are drawn on every tile in
    their class colours, and ``ignore_boxes`` (N, 4) xyxy pixel-edge (the frame's ignore
    regions) in :data:`IGNORE_COLOUR`, under the labels.
    """
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"images: expected (R, H, W, 3) uint8, got {images.shape} {images.dtype}")
    if rates.shape != (images.shape[0],):
        raise ValueError(f"rates: expected shape ({images.shape[0]},), got {rates.shape}")
    if isinstance(tile_width, bool) or not isinstance(tile_width, (int, np.integer)) or tile_width < 1:
        raise ValueError(f"tile_width: expected a positive integer of pixels, got {tile_width!r}")
    count, height, width = images.shape[:3]
    if count == 0:
        raise ValueError("images: expected at least one image, got none (R = 0)")
    if columns is not None and (isinstance(columns, bool) or not isinstance(columns, (int, np.integer))
                                or columns < 1):
        raise ValueError(f"columns: expected a positive integer or None (up to 4), got {columns!r}")
    if boxes is not None and (class_ids is None or len(class_ids) != len(boxes)):
        got = "none" if class_ids is None else f"{len(class_ids)} for {len(boxes)} boxes"
        raise ValueError(f"class_ids: expected one class id per box with boxes, got {got}")
    columns = columns or min(4, count)
    rows = math.ceil(count / columns)
    scale = tile_width / width
    tile_h = max(1, round(height * scale))
    if rows * tile_h * columns * tile_width > MAX_SHEET_PIXELS:
        raise ValueError(f"tile_width: {tile_width} px tiles of {width}x{height} images make a "
                         f"{columns * tile_width}x{rows * tile_h} sheet, over {MAX_SHEET_PIXELS} "
                         "pixels; choose narrower tiles")
    sheet = np.full((rows * tile_h, columns * tile_width, 3), 255, np.uint8)
    for index, (image, rate) in enumerate(zip(images, rates)):
        tile = cv2.resize(image, (tile_width, tile_h), interpolation=cv2.INTER_AREA)
        drawn = [] if ignore_boxes is None else [(box, IGNORE_COLOUR, "ignore_boxes") for box in ignore_boxes]
        if boxes is not None:
            drawn += [(box, CLASS_COLOURS[int(class_id) % len(CLASS_COLOURS)], "boxes")
                      for box, class_id in zip(boxes, class_ids)]
        for box, colour, name in drawn:
            if not np.all(np.isfinite(box)):
                raise ValueError(f"{name}: expected finite x1, y1, x2, y2, got {np.asarray(box).tolist()}")
            x1, y1, x2, y2 = (np.asarray(box) * scale).round().astype(int)
            cv2.rectangle(tile, (x1, y1), (x2 - 1, y2 - 1), colour, 1)
        label = f"{rate:g} mm/h"
        for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
            cv2.putText(tile, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, thickness,
                        cv2.LINE_AA)
        row, column = divmod(index, columns)
        sheet[row * tile_h:(row + 1) * tile_h, column * tile_width:(column + 1) * tile_width] = tile
    return sheet


def write_png(path, image: np.ndarray) -> None:
    """Write RGB ``image`` as the PNG ``path`` (a ``.png`` name): under a temporary name in the
    same folder, renamed when complete. Failures are one-line OSErrors naming the path."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise OSError(f"{path}: expected a .png file name")
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}.png")
    try:
        write_image(tmp, image)
    except OSError as error:
        tmp.unlink(missing_ok=True)
        raise OSError(str(error).replace(str(tmp), str(path), 1)) from None
    os.replace(tmp, path)
