"""Preview videos: every frame of a dataset as one MP4 per rain rate, boxes drawn."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from .classes import CLASS_COLOURS
from .export import ExportError, open_for_export
from .rates import rate_token


def write_videos(data, out_dir, *, rates: Sequence[float] | None = None, boxes: bool = True,
                 fps: float | None = None, overwrite: bool = False) -> list[Path]:
    """Write ``out_dir/rate_<token>.mp4`` (fourcc ``mp4v``) per rain rate; returns the paths.

    Frames: every frame of every shard of ``data`` (a dataset directory, a shard, or a list of
    shards) in image-id order (manifest shard order, then frame order), W x H as stored.
    ``boxes=True`` draws each label's xyxy pixel-edge ``bbox`` (colour
    :data:`rainbench.store.classes.CLASS_COLOURS` by class id) and prints "<rate> mm/h" in the corner; ``boxes=False`` writes the frames
    untouched. ``fps=None`` uses the ``fps`` attribute of the first shard. ``rates=None``: all
    rates of the dataset; a rate not in it raises :class:`ExportError`. An existing
    ``rate_<token>.mp4`` raises unless ``overwrite``. Each file is written under a temporary
    name and renamed when complete; an unavailable codec raises a one-line error.
    """
    dataset = open_for_export(data, rates)
    selected = dataset.rates
    sizes = {dataset.size(shard)[::-1] for shard in range(len(dataset.shards))}
    if fps is None:
        with dataset.open(0) as handle:
            fps = float(handle.attrs.get("fps", 10.0))
    if len(sizes) != 1:
        raise ExportError(f"{data}: shards have different image sizes {sorted(sizes)}; one "
                          "video needs one size")
    if isinstance(fps, (bool, np.bool_)) or not (isinstance(fps, (int, float, np.integer, np.floating))
                                                 and np.isfinite(fps) and fps > 0):
        raise ExportError(f"fps: expected a number > 0, got {fps!r}")
    (width, height), = sizes
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"OUT: {out_dir} exists and is not a directory")
    out_dir.mkdir(parents=True, exist_ok=True)
    finals = [out_dir / f"rate_{rate_token(rate)}.mp4" for rate in selected]
    existing = [path for path in finals if path.exists()]
    if existing and not overwrite:
        raise ExportError(f"{existing[0]}: already exists; use --overwrite or choose another "
                          "directory")
    temps = [path.with_name(f".{path.stem}.tmp-{os.getpid()}.mp4") for path in finals]
    writers = []
    try:
        for temp, final in zip(temps, finals):
            writer = cv2.VideoWriter(str(temp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps),
                                     (width, height))
            writers.append(writer)
            if not writer.isOpened():
                raise ExportError(f"{final}: cannot open an mp4v video writer (codec "
                                  "unavailable in this OpenCV build)")
        for record in dataset.frames():
            labels = record.labels
            for writer, rate, rgb in zip(writers, selected, record.rgb):
                frame = np.ascontiguousarray(rgb[:, :, ::-1])  # BGR for OpenCV
                if boxes:
                    for box, class_id in zip(labels["bbox"], labels["class_id"]):
                        x1, y1, x2, y2 = np.round(np.asarray(box, np.float64)).astype(int)
                        r, g, b = CLASS_COLOURS[int(class_id) % len(CLASS_COLOURS)]
                        cv2.rectangle(frame, (x1, y1), (x2 - 1, y2 - 1), (b, g, r), 1)
                    label = f"{rate:g} mm/h"
                    for colour, thickness in (((0, 0, 0), 3), ((255, 255, 255), 1)):
                        cv2.putText(frame, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour,
                                    thickness, cv2.LINE_AA)
                writer.write(frame)
        for writer in writers:
            writer.release()
        for temp, final in zip(temps, finals):
            os.replace(temp, final)
    finally:
        for writer in writers:
            writer.release()
        for temp in temps:
            temp.unlink(missing_ok=True)
    return finals
