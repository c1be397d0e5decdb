"""Render benchmark (issue: generator core).

Frames/s of the full per-frame work -- physics step, RGB + depth, segmentation, actor-alone
passes and labels -- at 800x600 on the default scene, against a bare ``mujoco.Renderer``
RGB-only loop (update_scene + render, nothing else timed) on the same model in the same run. Blocks of the two loops alternate so that
machine noise hits both. Target: full / bare time ratio <= 2.0.

    python bench/render.py [--frames 40] [--width 800 --height 600] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import rainbench  # noqa: F401  -- chooses MUJOCO_GL before mujoco is imported

import mujoco
import numpy as np

from rainbench.gen import sim
from rainbench.gen.generate import GenerateConfig, build_scene, render_frame
from rainbench.gen.render import FrameRenderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--width", type=int, default=800)
    parser.add_argument("--height", type=int, default=600)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    config = GenerateConfig(width=args.width, height=args.height)
    setup = build_scene(config)
    model = setup.model
    times = np.linspace(0.0, 19.9, args.frames)

    data_full, data_bare = mujoco.MjData(model), mujoco.MjData(model)
    driver = sim.ActorDriver(model, setup.layout)
    full_s = bare_s = 0.0
    labels_total = 0
    bare = mujoco.Renderer(model, args.height, args.width)
    with FrameRenderer(model, args.width, args.height, setup.geom_instance) as renderer:
        # Warm-up (shader compilation, texture upload) for both.
        renderer.update(data_full)
        renderer.render_rgb_depth()
        bare.update_scene(data_bare, "ego")
        bare.render()
        previous_full = previous_bare = 0.0
        for block in np.array_split(np.arange(args.frames), max(1, args.frames // 5)):
            start = time.perf_counter()
            for index in block:
                sim.advance(model, data_full, driver, previous_full, times[index])
                previous_full = times[index]
                frame = render_frame(renderer, data_full, setup, config.label_filter)
                labels_total += len(frame.labels)
            full_s += time.perf_counter() - start
            for index in block:  # the bare loop is timed on rendering alone
                sim.advance(model, data_bare, driver, previous_bare, times[index])
                previous_bare = times[index]
                start = time.perf_counter()
                bare.update_scene(data_bare, "ego")
                bare.render()
                bare_s += time.perf_counter() - start
    bare.close()
    result = {
        "benchmark": "render",
        "width": args.width, "height": args.height, "frames": args.frames,
        "gl_backend": os.environ.get("MUJOCO_GL", ""), "machine": platform.node(),
        "cpu_count": os.cpu_count(),
        "full_frames_per_s": args.frames / full_s,
        "bare_rgb_frames_per_s": args.frames / bare_s,
        "ratio_full_over_bare": full_s / bare_s,
        "target_ratio": 2.0,
        "labels_per_frame": labels_total / args.frames,
    }
    print(f"full pipeline : {result['full_frames_per_s']:.2f} frames/s "
          f"(RGB+depth, segmentation, alone passes, labels, physics)")
    print(f"bare Renderer : {result['bare_rgb_frames_per_s']:.2f} frames/s (RGB only)")
    print(f"ratio full/bare time: {result['ratio_full_over_bare']:.2f} (target <= 2.0)")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(result, handle, indent=2)


if __name__ == "__main__":
    main()
