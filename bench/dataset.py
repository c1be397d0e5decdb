"""Dataset benchmark (issue: datasets at scale). Three measurements, each against a baseline
run in the same process and the same run:

1. end to end: ``rainbench generate`` of the paper's clip (1 scene, 200 frames, 800x600,
   RATES=0:100:10) against a bare ``mujoco.Renderer`` RGB-only pass over the same 200 frames
   (the mean of one loop before the generation and one after), ``--e2e-repeats`` times (default
   3, alternated: loop, generate, loop, generate, ...); the ratio is the median run's. The
   generate side is the whole process (interpreter, imports, scene, GL contexts, the shard's
   hash and rename: about 4 s of a 24 s run here); the bare loop's timer holds its renders only.
   Target: ratio <= 3 (jeon2022 keeps <= 2.5).
   With the weather following the rate (``--rain-model physical``): against a bare renderer
   rendering 11 images per frame of the same scene, bracketed the same way,
   ``--weather-repeats`` times (default 1: each run takes minutes). Target: ratio <= 1.6.
   ``--workers N`` generates both with N workers (more workers than the clip's one shard:
   the clip in pieces, docs/datasets.md); default: ``rainbench generate``'s own default.
   ``--device`` passes ``rainbench generate --device`` (where the statistics run) to both.
2. scaling: 2 scenes with 2 workers against 1 worker (``--scaling-workers N``: N scenes with N
   workers against 1 worker on 2 scenes, in images/s), once with each worker on one core
   (one Mesa render thread, ``LP_NUM_THREADS=1``, and ``--threads 1``: no rain or compression
   threads beside the render; target >= 1.6x) and once with the defaults (Mesa's threads on
   every core, rain and compression threads = cores / workers). ``--scaling-device`` passes
   ``--device`` to its runs. Each setting runs ``--scaling-repeats`` pairs (default 3),
   alternating which of the two goes first; the median pair's speed-up is reported.
3. reader: images/s through ``ShardDataset`` + ``DataLoader(num_workers=2)`` (second epoch of
   persistent workers, as in training) against reading the same images from PNG files with
   ``cv2.imread`` in one process (warm cache too; target >= 2x, the figure recorded since), and
   against the same PNGs through the same DataLoader (2 workers, RGB tensors: like for like,
   ``ratio_same_dataloader``, no target; bench/train_reader.py compares with ultralytics' own
   loader of the exported PNGs).

    python bench/dataset.py [--frames 200] [--e2e-repeats 3] [--workers N] [--device auto] [--scaling-frames 40]
        [--scaling-workers 2] [--scaling-rates 0,50,100] [--scaling-device auto] [--scaling-repeats 3] [--json OUT]
        [--skip e2e,...]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
from rainbench.gl import mujoco  # imported once the GL backend is chosen

from rainbench.gen import sim
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene
from rainbench.store.rates import parse_rates


def bare_render_seconds(frames: int, width: int, height: int, images_per_frame: int = 1) -> float:
    """A bare ``mujoco.Renderer`` loop over the paper clip (seed 0, the cloudy street by day,
    what ``rainbench generate`` makes given no scene flag): ``images_per_frame`` RGB renders of
    each of ``frames`` frames."""
    config = GenerateConfig(frames=frames, width=width, height=height, sky="cloudy",
                            layout="street", time_of_day="day")
    setup = build_scene(config)
    data = mujoco.MjData(setup.model)
    driver = sim.ActorDriver(setup.model, setup.layout)
    renderer = mujoco.Renderer(setup.model, height, width)
    renderer.update_scene(data, "ego")
    renderer.render()
    start = time.perf_counter()
    previous = 0.0
    for index in range(frames):
        sim.advance(setup.model, data, driver, previous, index / config.fps)
        previous = index / config.fps
        for _ in range(images_per_frame):
            renderer.update_scene(data, "ego")
            renderer.render()
    elapsed = time.perf_counter() - start
    renderer.close()
    return elapsed


def cli_seconds(args: list[str], env: dict | None = None) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "rainbench.cli", "generate", "--quiet", *args],
                   check=True, env={**os.environ, **(env or {})}, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def _workers_args(workers: int | None, device: str | None = None) -> list[str]:
    return ([] if workers is None else ["--workers", str(workers)]) + ([] if device is None else ["--device", device])


def _bracketed_runs(tmp: Path, name: str, frames: int, generate_args: list[str],
                    images_per_frame: int, repeats: int) -> dict:
    """``rainbench generate`` of the paper clip with ``generate_args``, ``repeats`` times, each run
    between two bare loops of ``images_per_frame`` images a frame (one before, one after, shared
    with the neighbouring runs) and measured against their mean: this machine's speed drifts by
    20 % or more within minutes (a bare loop took 16.8 s in one run and 22.8 s in the next), so
    one loop on one side of a run could fall in a fast or a slow spell that the generation did
    not share. Returns the median run (by ratio; the lower middle one of an even count) at the
    top level, every run under ``runs``."""
    bare_loops = [bare_render_seconds(frames, 800, 600, images_per_frame)]
    runs = []
    for index in range(repeats):
        out = tmp / f"{name}{index}"
        seconds = cli_seconds(["--out", str(out), "--frames", str(frames), "--rates", "0:100:10",
                               *generate_args])
        shutil.rmtree(out, ignore_errors=True)
        bare_loops.append(bare_render_seconds(frames, 800, 600, images_per_frame))
        before, after = bare_loops[-2], bare_loops[-1]
        runs.append({"generate_s": seconds, "bare_render_s": (before + after) / 2,
                     "bare_render_before_s": before, "bare_render_after_s": after,
                     "ratio": seconds / ((before + after) / 2)})
    return {**sorted(runs, key=lambda run: run["ratio"])[(len(runs) - 1) // 2], "runs": runs}


def end_to_end(tmp: Path, frames: int, workers: int | None = None, device: str | None = None,
               repeats: int = 1) -> dict:
    """The paper clip's ``rainbench generate`` (the default rain model) against the bare RGB loop,
    bracketed (:func:`_bracketed_runs`) ``repeats`` times. The reported ratio is the median of the
    runs' ratios (one run's moved by +-5 % between runs of the same code: 2.41 to 2.66)."""
    return {"frames": frames, "workers": workers, "device": device or "auto", "repeats": repeats,
            **_bracketed_runs(tmp, "e2e", frames, _workers_args(workers, device), 1, repeats),
            "target_ratio": 3.0, "target_ratio_jeon2022": 2.5}


def weather_end_to_end(tmp: Path, frames: int, workers: int | None = None, device: str | None = None,
                       repeats: int = 1) -> dict:
    """The 11-rate paper clip with the weather following the rate (physical rain) against a
    bare renderer that renders as many images (11 per frame) of the same scene, bracketed as the
    end-to-end runs are (:func:`_bracketed_runs`), ``repeats`` times; the median run is
    reported (its ``bare_render_*`` seconds are of the 11 images a frame)."""
    return {"frames": frames, "workers": workers, "device": device or "auto", "repeats": repeats,
            **_bracketed_runs(tmp, "weather", frames,
                              ["--rain-model", "physical", *_workers_args(workers, device)], 11, repeats),
            "target_ratio": 1.6}


def scaling(tmp: Path, frames: int, workers: int = 2, rates: str = "0,50,100", device: str | None = None,
            repeats: int = 1) -> dict:
    """``workers`` workers on ``workers`` scenes against one worker on 2 scenes (the same scenes'
    first two), in images per second; with 2 workers both runs do the same work. ``device``:
    ``rainbench generate --device`` (where the statistics run; None: its default, ``auto``).
    Each setting runs ``repeats`` pairs, alternating which of the two goes first; its figures are
    the median pair's by speed-up (the lower of the middle two for an even count), every pair
    kept under ``pairs``."""
    num_rates = len(parse_rates(rates))
    result = {"frames_per_scene": frames, "rates": rates, "workers": workers, "device": device or "auto",
              "repeats": repeats}
    device_args = [] if device is None else ["--device", device]
    for label, env, threads in (("one_core_per_worker", {"LP_NUM_THREADS": "1"}, ["--threads", "1"]),
                                ("default_threads", {}, [])):
        pairs = []
        for repeat in range(repeats):
            runs = {}
            order = ((1, 2), (workers, workers))
            for count, scenes in (order if repeat % 2 == 0 else order[::-1]):
                out = tmp / f"s{count}{label}"
                seconds = cli_seconds(["--out", str(out), "--workers", str(count),
                                       "--scenes", str(scenes), "--frames", str(frames),
                                       "--rates", rates, *threads, *device_args], env)
                shutil.rmtree(out, ignore_errors=True)
                runs[count] = (seconds, scenes * frames * num_rates / seconds)
            pairs.append({"one_worker_s": runs[1][0], "n_workers_s": runs[workers][0],
                          "one_worker_images_per_s": runs[1][1],
                          "n_workers_images_per_s": runs[workers][1],
                          "speedup": runs[workers][1] / runs[1][1],
                          "first": "one_worker" if repeat % 2 == 0 else "n_workers"})
        median_pair = sorted(pairs, key=lambda pair: pair["speedup"])[(len(pairs) - 1) // 2]
        result[label] = {**median_pair, "pairs": pairs}
    return result


READER_REPEATS = 7
"""Timed passes of each reader; the medians are reported."""


class _PngImages:
    """The PNG files as a torch dataset: (3, H, W) uint8 RGB tensors (what ShardDataset yields,
    without its targets), for the like-for-like baseline through the same DataLoader."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int):
        import torch

        image = cv2.imread(str(self.paths[index]), cv2.IMREAD_COLOR)[:, :, ::-1]
        return torch.from_numpy(image.copy()).permute(2, 0, 1)


def _images_only(batch):
    return tuple(batch)


def reader(tmp: Path, frames: int) -> dict:
    from torch.utils.data import DataLoader

    from rainbench import ShardDataset

    data = tmp / "reader"
    cli_seconds(["--out", str(data), "--frames", str(frames), "--rates", "0,50"])
    dataset = ShardDataset(data)
    pngs = tmp / "pngs"
    pngs.mkdir()
    for index in range(len(dataset)):
        image, _ = dataset.reader.sample(index)
        cv2.imwrite(str(pngs / f"{index:06d}.png"), image[:, :, ::-1])
    loader = DataLoader(dataset, batch_size=16, num_workers=2, persistent_workers=True,
                        collate_fn=ShardDataset.collate_fn)
    sum(len(images) for images, _ in loader)  # first epoch: worker start-up, page cache
    paths = sorted(pngs.iterdir())
    for path in paths:  # the same warm page cache for the PNG files
        cv2.imread(str(path))
    # The like-for-like baseline: the same PNGs through the same DataLoader (2 worker processes,
    # batches of 16, second epoch), as RGB tensors; the one-process imread loop is kept for the
    # figures recorded before it (its ratio credits the workers to the shards).
    png_loader = DataLoader(_PngImages(paths), batch_size=16, num_workers=2, persistent_workers=True,
                            collate_fn=_images_only)
    sum(len(images) for images in png_loader)
    # One pass is about half a second on this machine: the medians of REPEATS interleaved passes
    # of each reader (a single pass swung the ratio between 1.6 and 2.9 on a quiet machine).
    shard_runs, png_runs, png_loader_runs = [], [], []
    for _ in range(READER_REPEATS):
        start = time.perf_counter()
        count = sum(len(images) for images, _ in loader)
        shard_runs.append(time.perf_counter() - start)
        start = time.perf_counter()
        for path in paths:
            cv2.imread(str(path))
        png_runs.append(time.perf_counter() - start)
        start = time.perf_counter()
        png_count = sum(len(images) for images in png_loader)
        png_loader_runs.append(time.perf_counter() - start)
    shard_s, png_s = statistics.median(shard_runs), statistics.median(png_runs)
    png_loader_s = statistics.median(png_loader_runs)
    return {"images": count, "repeats": READER_REPEATS,
            "shard_dataset_images_per_s": count / shard_s,
            "png_imread_images_per_s": len(paths) / png_s,
            "png_dataloader_images_per_s": png_count / png_loader_s,
            "ratio": (count / shard_s) / (len(paths) / png_s), "target_ratio": 2.0,
            "ratio_same_dataloader": (count / shard_s) / (png_count / png_loader_s)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--workers", type=int, default=None,
                        help="workers of the end-to-end runs (default: rainbench generate's)")
    parser.add_argument("--device", default=None,
                        help="rainbench generate --device of the end-to-end runs (default: its own, auto)")
    parser.add_argument("--scaling-frames", type=int, default=40)
    parser.add_argument("--scaling-workers", type=int, default=2,
                        help="workers (and scenes) against one worker on 2 scenes (default 2)")
    parser.add_argument("--scaling-rates", default="0,50,100")
    parser.add_argument("--scaling-repeats", type=int, default=3,
                        help="pairs of scaling runs per setting, alternating their order; the median's reported (default 3)")
    parser.add_argument("--scaling-device", default=None,
                        help="rainbench generate --device of the scaling runs (default: its own, auto)")
    parser.add_argument("--weather-frames", type=int, default=200)
    parser.add_argument("--weather-repeats", type=int, default=1,
                        help="bracketed weather runs (each about 4 minutes here; default 1)")
    parser.add_argument("--reader-frames", type=int, default=100)
    parser.add_argument("--e2e-repeats", type=int, default=3,
                        help="end-to-end runs, each between two bare loops; the ratio is their median (default 3)")
    parser.add_argument("--skip", default="", help="comma list of e2e,weather,scaling,reader")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    if args.workers is not None and args.workers < 1:
        parser.error(f"--workers: expected an integer >= 1, got {args.workers}")
    if args.e2e_repeats < 1:
        parser.error(f"--e2e-repeats: expected an integer >= 1, got {args.e2e_repeats}")
    if args.scaling_repeats < 1:
        parser.error(f"--scaling-repeats: expected an integer >= 1, got {args.scaling_repeats}")
    if args.scaling_workers < 2:
        parser.error(f"--scaling-workers: expected an integer >= 2, got {args.scaling_workers}")
    skip = set(filter(None, args.skip.split(",")))
    tmp = Path(tempfile.mkdtemp(prefix="rainbench-bench-"))
    results: dict = {"benchmark": "dataset", "cpu_count": os.cpu_count(),
                     "gl_backend": os.environ.get("MUJOCO_GL", "")}
    try:
        if "e2e" not in skip:
            results["end_to_end"] = e2e = end_to_end(tmp, args.frames, args.workers, args.device,
                                                     args.e2e_repeats)
            for index, run in enumerate(e2e["runs"]):
                print(f"end to end, run {index + 1} of {len(e2e['runs'])}: generate {run['generate_s']:.1f} s,"
                      f" bare RGB {run['bare_render_s']:.1f} s (mean of {run['bare_render_before_s']:.1f} s"
                      f" before and {run['bare_render_after_s']:.1f} s after), ratio {run['ratio']:.2f}")
            print(f"end to end: ratio {e2e['ratio']:.2f}, the median of {len(e2e['runs'])} run(s) (target "
                  f"<= 3; jeon2022, the default rain model, <= 2.5)")
        if "weather" not in skip:
            results["weather_end_to_end"] = weather = weather_end_to_end(tmp, args.weather_frames, args.workers,
                                                                         args.device, args.weather_repeats)
            for index, run in enumerate(weather["runs"]):
                print(f"weather following the rate (physical, 11 rates), run {index + 1} of "
                      f"{len(weather['runs'])}: generate {run['generate_s']:.1f} s, bare RGB x11 "
                      f"{run['bare_render_s']:.1f} s (mean of {run['bare_render_before_s']:.1f} s before "
                      f"and {run['bare_render_after_s']:.1f} s after), ratio {run['ratio']:.2f}")
            print(f"weather following the rate: ratio {weather['ratio']:.2f}, the median of "
                  f"{len(weather['runs'])} run(s) (target <= 1.6)")
        if "scaling" not in skip:
            results["scaling"] = scale = scaling(tmp, args.scaling_frames, args.scaling_workers,
                                                 args.scaling_rates, args.scaling_device,
                                                 args.scaling_repeats)
            for label in ("one_core_per_worker", "default_threads"):
                row = scale[label]
                print(f"scaling ({label}, --device {scale['device']}): 1 worker {row['one_worker_images_per_s']:.0f} images/s"
                      f" ({row['one_worker_s']:.1f} s), {args.scaling_workers} workers "
                      f"{row['n_workers_images_per_s']:.0f} images/s ({row['n_workers_s']:.1f} s),"
                      f" speed-up {row['speedup']:.2f}x (the median of {len(row['pairs'])} pair(s): "
                      f"{', '.join(format(pair['speedup'], '.2f') for pair in row['pairs'])})")
        if "reader" not in skip:
            results["reader"] = read = reader(tmp, args.reader_frames)
            print(f"reader: ShardDataset {read['shard_dataset_images_per_s']:.0f} images/s, "
                  f"PNG imread in one process {read['png_imread_images_per_s']:.0f} images/s, ratio "
                  f"{read['ratio']:.2f} (target >= 2); the PNGs through the same DataLoader "
                  f"{read['png_dataloader_images_per_s']:.0f} images/s, ratio {read['ratio_same_dataloader']:.2f}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
