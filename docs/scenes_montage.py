"""Regenerate docs/scenes_montage.png (docs/scenes.md, README):

    python docs/scenes_montage.py [OUT]

Twelve seeds, each as `rainbench generate --seed S` draws it (layout, sky, time of day, actors),
frame 70 of the 200-frame clip at 800x600 and 0 mm/h, shown at 320x240 in 3 rows of 4 and
labelled. The seeds are chosen to show every layout and time of day.
"""

from __future__ import annotations

import sys
import tempfile

import cv2
import h5py
import numpy as np

from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import generate_shard

SEEDS = (3, 8, 0, 15, 4, 2, 38, 27, 17, 6, 23, 18)
WIDTH, HEIGHT = 800, 600
TILE = (320, 240)


def tile(seed: int) -> np.ndarray:
    """(240, 320, 3) uint8 RGB: seed ``seed``'s frame 70 at 0 mm/h as its shard stores it (after
    the camera's response: night noise included), labelled."""
    config = GenerateConfig(seed=seed, frames=1, frame_offset=70, clip_frames=200, width=WIDTH,
                            height=HEIGHT, rates=(0.0,))
    with tempfile.TemporaryDirectory() as out, h5py.File(generate_shard(config, out)) as shard:
        rgb = shard["rgb"][0, 0]
        layout, sky, time_of_day = (shard.attrs[k] for k in ("layout", "sky", "time_of_day"))
    image = cv2.resize(rgb, TILE, interpolation=cv2.INTER_AREA)
    label = f"seed {seed}: {layout}, {sky}, {time_of_day}"
    cv2.putText(image, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                cv2.LINE_AA)
    return image


def montage() -> np.ndarray:
    """(rows x 240, 4 x 320, 3) uint8 RGB: the tiles of :data:`SEEDS` in rows of 4 (3 rows)."""
    if len(SEEDS) % 4:
        raise ValueError(f"SEEDS: expected a multiple of 4 seeds, got {len(SEEDS)}")
    tiles = [tile(seed) for seed in SEEDS]
    return np.vstack([np.hstack(tiles[row:row + 4]) for row in range(0, len(tiles), 4)])


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "docs/scenes_montage.png"
    if not cv2.imwrite(out, cv2.cvtColor(montage(), cv2.COLOR_RGB2BGR)):
        sys.exit(f"scenes_montage: could not write {out}")
