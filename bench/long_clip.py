"""Long-clip benchmark (issue 15: a clip may be an hour long).

The last ``--frames`` frames of a ``--minutes``-long highway clip (seed 0, cloudy day: the
layout with the most road per second) against the last frames of a 20 s clip of the same seed,
in the same run: the clean frame with every label pass (``render_clip``, the physics between
frames included), from the second frame on (each scene built and its renderer started first). Reported: build seconds of each scene, seconds per
frame of each, their ratio, and the same ratio with the far scenery drawn
(``FrameRenderer.hidden_geoms`` off: what a long clip's frame cost before). The two clips'
blocks alternate ``--repeats`` times; the figures are the median block's (by ratio; the lower
of the middle two for an even count). Target: a long clip's
frame <= 1.25x a short clip's.

    python bench/long_clip.py [--minutes 10] [--frames 10] [--repeats 3] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from rainbench.gen import render as gr
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene, render_clip


def _config(seconds: float, frames: int) -> GenerateConfig:
    clip = int(round(seconds * 10))
    return GenerateConfig(frames=frames, frame_offset=clip - frames, seed=0, layout="highway",
                          sky="cloudy", time_of_day="day", rates=(0.0,))


def _seconds_per_frame(config: GenerateConfig, setup) -> float:
    """Seconds per frame after the first (the renderer's start, which uploads the scene once per
    piece, is left out)."""
    start = None
    for index, _, _ in render_clip(config, setup):
        if index == 0:
            start = time.perf_counter()
    return (time.perf_counter() - start) / (config.frames - 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json")
    args = parser.parse_args()
    if not (2 <= args.frames <= 200 and args.repeats >= 1 and 20 < 60 * args.minutes <= 3600):
        parser.error(f"expected --frames 2..200, --repeats >= 1 and --minutes above 1/3 and at "
                     f"most 60; got {args.frames}, {args.repeats}, {args.minutes:g}")
    long_config, short_config = _config(60 * args.minutes, args.frames), _config(20.0, args.frames)
    start = time.perf_counter()
    long_setup = build_scene(long_config)
    long_build = time.perf_counter() - start
    start = time.perf_counter()
    short_setup = build_scene(short_config)
    short_build = time.perf_counter() - start
    hidden = gr.FrameRenderer.hidden_geoms
    blocks = []
    for _ in range(args.repeats):
        short = _seconds_per_frame(short_config, short_setup)
        long = _seconds_per_frame(long_config, long_setup)
        gr.FrameRenderer.hidden_geoms = lambda self, *args: np.zeros(self.model.ngeom, bool)
        try:
            drawn = _seconds_per_frame(long_config, long_setup)
        finally:
            gr.FrameRenderer.hidden_geoms = hidden
        blocks.append({"short_s_per_frame": short, "long_s_per_frame": long,
                       "long_all_drawn_s_per_frame": drawn, "ratio": long / short,
                       "ratio_all_drawn": drawn / short})
    median = sorted(blocks, key=lambda block: block["ratio"])[(len(blocks) - 1) // 2]
    result = {"minutes": args.minutes, "frames": args.frames, "layout": "highway",
              "long_build_s": long_build, "short_build_s": short_build,
              "long_geoms": int(long_setup.model.ngeom), "short_geoms": int(short_setup.model.ngeom),
              **median,
              "blocks": blocks, "target_ratio": 1.25}
    print(f"highway, {args.minutes:g} min ({result['long_geoms']} geoms) against 20 s "
          f"({result['short_geoms']}): build {long_build:.1f} s against {short_build:.1f} s; "
          f"a frame {median['long_s_per_frame'] * 1000:.0f} ms against "
          f"{median['short_s_per_frame'] * 1000:.0f} ms: ratio {result['ratio']:.2f} (target <= 1.25; "
          f"with the far scenery drawn {median['ratio_all_drawn']:.2f})")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(result, handle, indent=1)


if __name__ == "__main__":
    main()
