"""Regenerate docs/time_of_day.jpg (docs/rain.md, "Time of day"):

    python docs/time_of_day.py [OUT]

Seed 0's street, cloudy, 8 s into the 200-frame clip at 800x600: day, dusk and night at 0 mm/h
(top row) and at 50 mm/h with the weather only (bottom row: the wet road, its mirror and streaks,
the light, the glow around lights after dark and the camera's response; no drops). Each image
goes through the camera's response of its weather, the night's sensor noise included (one noise
field, seed 0).
"""

from __future__ import annotations

import sys

import cv2
import numpy as np

from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene, render_clip
from rainbench.rain import weather as wx

SKY = "cloudy"
PANELS = (("day", 0.0), ("dusk", 0.0), ("night", 0.0), ("day", 50.0), ("dusk", 50.0),
          ("night", 50.0))
WIDTH, HEIGHT = 800, 600


def panel(time_of_day: str, rate: float, noise: np.ndarray) -> np.ndarray:
    """(HEIGHT, WIDTH, 3) uint8 RGB: the frame at 8 s in ``time_of_day`` under the weather of
    ``rate`` mm/h, after the camera's response."""
    config = GenerateConfig(seed=0, frames=1, frame_offset=80, clip_frames=200, width=WIDTH,
                            height=HEIGHT, rates=(0.0,), sky=SKY, layout="street",
                            time_of_day=time_of_day)
    weather = wx.weather_at(SKY, rate, time_of_day=time_of_day)
    _, frame, _ = next(render_clip(config, build_scene(config), weathers=(weather,)))
    return wx.camera_response(frame.rgb_by_weather.get(weather, frame.rgb), weather, noise)


def montage() -> np.ndarray:
    """(HEIGHT, 3 * WIDTH / 2, 3) uint8 RGB: the six panels at half size, labelled, 2 rows of 3."""
    noise = wx.noise_field(np.random.default_rng(0), HEIGHT, WIDTH)
    tiles = []
    for time_of_day, rate in PANELS:
        image = cv2.resize(panel(time_of_day, rate, noise), (WIDTH // 2, HEIGHT // 2),
                           interpolation=cv2.INTER_AREA)
        label = f"{time_of_day}, {rate:.0f} mm/h" + (" (weather only)" if rate else "")
        cv2.putText(image, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1,
                    cv2.LINE_AA)
        tiles.append(image)
    return np.vstack([np.hstack(tiles[:3]), np.hstack(tiles[3:])])


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "docs/time_of_day.jpg"
    quality = [cv2.IMWRITE_JPEG_QUALITY, 90] if out.lower().endswith((".jpg", ".jpeg")) else []
    if not cv2.imwrite(out, cv2.cvtColor(montage(), cv2.COLOR_RGB2BGR), quality):
        sys.exit(f"time_of_day: could not write {out}")
