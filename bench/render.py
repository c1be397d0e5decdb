"""Render benchmark (issue: generator core).

Frames/s of the full per-frame work of a clip -- one frame interval of physics (1 / fps of the
clip, 0.1 s at the default 10 fps), RGB + depth, segmentation, actor-alone passes and labels --
at 800x600 on seed 0's scene of every road layout (and the street at night), each against a
bare ``mujoco.Renderer`` RGB-only loop (update_scene + render, nothing else timed) on the same
model in the same run. The measured frames are spread over the 20 s clip; the physics between
them beyond the frame's own interval is stepped untimed in both loops. Blocks of the two loops
alternate so that machine noise hits both. Target: full / bare time ratio <= 2.0 on every scene.

    python bench/render.py [--frames 40] [--width 800 --height 600] [--scenes street:day,...]
                           [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np

from rainbench.gen import sim
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene, render_frame
from rainbench.gen.render import FrameRenderer


def measure(layout: str, time_of_day: str, frames: int, width: int, height: int) -> dict:
    """Full per-frame work against the bare renderer on seed 0's ``layout`` scene at
    ``time_of_day`` (cloudy, the paper's sky), ``frames`` frames spread over the 20 s clip."""
    config = GenerateConfig(width=width, height=height, sky="cloudy", layout=layout,
                            time_of_day=time_of_day)
    setup = build_scene(config)
    model = setup.model
    times = np.linspace(0.0, 19.9, frames)
    frame_interval = 1.0 / config.fps  # the physics one frame of the clip steps

    data_full, data_bare = mujoco.MjData(model), mujoco.MjData(model)
    driver = sim.ActorDriver(model, setup.layout)
    full_s = bare_s = 0.0
    labels_total = 0
    bare = mujoco.Renderer(model, height, width)
    with FrameRenderer(model, width, height, setup.geom_instance,
                       base_weather=setup.base_weather) as renderer:
        # Warm-up (shader compilation, texture upload) for both.
        renderer.update(data_full)
        renderer.render_rgb_depth()
        bare.update_scene(data_bare, "ego")
        bare.render()
        previous_full = previous_bare = 0.0
        for block in np.array_split(np.arange(frames), max(1, frames // 5)):
            for index in block:
                # Untimed: the clip frames between the measured ones.
                frame_start = max(previous_full, times[index] - frame_interval)
                sim.advance(model, data_full, driver, previous_full, frame_start)
                start = time.perf_counter()
                sim.advance(model, data_full, driver, frame_start, times[index])
                previous_full = times[index]
                frame = render_frame(renderer, data_full, setup, config.label_filter)
                full_s += time.perf_counter() - start
                labels_total += len(frame.labels)
            for index in block:  # the bare loop is timed on rendering alone
                sim.advance(model, data_bare, driver, previous_bare, times[index])
                previous_bare = times[index]
                start = time.perf_counter()
                bare.update_scene(data_bare, "ego")
                bare.render()
                bare_s += time.perf_counter() - start
    bare.close()
    return {
        "layout": layout, "time_of_day": time_of_day, "ngeom": int(model.ngeom),
        "full_frames_per_s": frames / full_s,
        "bare_rgb_frames_per_s": frames / bare_s,
        "ratio_full_over_bare": full_s / bare_s,
        "labels_per_frame": labels_total / frames,
    }


SCENES = ("street:day", "intersection:day", "curved:day", "highway:day", "residential:day",
          "street:night")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--width", type=int, default=800)
    parser.add_argument("--height", type=int, default=600)
    parser.add_argument("--scenes", default=",".join(SCENES),
                        help="comma list of LAYOUT:TIME (default: every layout by day, the "
                             "street at night)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    rows = []
    for scene in args.scenes.split(","):
        layout, _, time_of_day = scene.partition(":")
        rows.append(measure(layout, time_of_day or "day", args.frames, args.width, args.height))
        row = rows[-1]
        print(f"{layout:>12} {row['time_of_day']:>5}: full {row['full_frames_per_s']:.2f} "
              f"frames/s, bare RGB {row['bare_rgb_frames_per_s']:.2f} frames/s, ratio "
              f"{row['ratio_full_over_bare']:.2f} (target <= 2.0), {row['ngeom']} geoms, "
              f"{row['labels_per_frame']:.1f} labels/frame", flush=True)
    result = {
        "benchmark": "render",
        "width": args.width, "height": args.height, "frames": args.frames,
        "gl_backend": os.environ.get("MUJOCO_GL", ""), "machine": platform.node(),
        "cpu_count": os.cpu_count(), "target_ratio": 2.0, "scenes": rows,
        "worst_ratio_full_over_bare": max(row["ratio_full_over_bare"] for row in rows),
    }
    print(f"worst ratio full/bare time: {result['worst_ratio_full_over_bare']:.2f} "
          "(target <= 2.0)")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(result, handle, indent=2)


if __name__ == "__main__":
    main()
