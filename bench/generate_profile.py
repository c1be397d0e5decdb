"""Where a shard's generation time goes (issue 17): the paper clip generated in this process
with a timer around each stage, summed over the threads that run it.

On the 16-core H100 machine the paper clip's `rainbench generate` took 16.9 s (`jeon2022`) and
72.1 s (`physical`, the weather following the rate) against 1.1 s and 7.3 s of bare renders
(bench/RESULTS.md): the GPU idles and the time goes to CPU work whose split `bench/dataset.py`
cannot show. This runs :func:`rainbench.gen.generate.generate_shard` on the clip as
`rainbench generate` does (seed 0, rates 0:100:10, the rain model's default weather) with
timers wrapped around:

- ``scene build``: the MJCF scene and its layout (once);
- ``GL renderer start``: the renderer's GL context, textures and buffers (once);
- ``simulate``: stepping the scene to each frame (main thread);
- ``render: ...``: each GL pass with its read-back (main thread): RGB, segmentation (+ depth),
  the weather re-renders' passes (``physical``) and their lamps' state, and the labels'
  per-actor passes;
- ``weather images' array work``: the re-renders' wet road, puddles and lamp glow (statistics
  threads; a glowing image's time holds that of the render it glows over);
- ``rain sweep``: the drops and lens water of every rate of a frame (frame threads), and for
  ``physical`` with weather, ``weather rain`` (spray, rain in each weather's light, camera
  response; holds the sweep);
- ``statistics: ...``: the clean image's SSIM and per-box references, then each rate's SSIM /
  PSNR and per-box rain labels (statistics threads); with ``--device cuda`` (the default where
  torch sees a GPU) ``statistics: torch, all rates of a frame`` instead (frame threads: the
  images' copy to the device, the batched filters and the figures' copy back);
- ``compress``: igzip of every image (the writer's threads); ``write``: the writer
  thread's whole :meth:`~rainbench.store.shard.ShardWriter.write_frame` (it waits for the
  compression); ``commit``: the tables and the rename (once).

A stage's seconds (wall) and CPU seconds (the calling thread's own CPU time: GL work done in the
driver's threads, such as Mesa's llvmpipe, is not in it) are summed over the threads that ran
it, so stages run in parallel add up to more than the wall time; wall seconds well above CPU
seconds in a pool stage mean its threads waited for a core or for the GIL. ``main thread
waiting`` is what the main thread spent neither in setup nor in its own stages: waiting for
frames in flight (back-pressure) and handing frames over.
``cores busy`` is the process's CPU time over the wall time; the time from the process's start
to the generation (interpreter and imports, what every worker process pays) is printed too.
``--threads 1 --frames 13`` is one of 16 pieces of the paper clip, as a worker renders it;
``--workers 16`` makes the clip in 16 pieces and shows the parent's side: when the pieces were
joined and what copying them into the shard cost.

    python bench/generate_profile.py [--rain-model jeon2022] [--frames 200] [--threads N]
        [--frames-in-flight K] [--workers N] [--device auto] [--out DIR] [--json OUT]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import tempfile
import threading
import time
from pathlib import Path

from rainbench import rain
from rainbench.gen import generate, sim
from rainbench.gen.config import DatasetConfig, stats_device_for
from rainbench.gen.dataset import run_dataset
from rainbench.gen.render import FrameRenderer, PendingImage
from rainbench.rain import weather as wx
from rainbench.store import shard


def process_age_s() -> float | None:
    """Seconds since this process started (the interpreter's start and the imports so far, when
    called first thing), from Linux's /proc; None elsewhere."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return uptime - start_ticks / os.sysconf("SC_CLK_TCK")


class StageTimers:
    """Wall seconds, the calling thread's CPU seconds and calls per stage, summed over threads
    (thread-safe)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.cpu_seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._lock = threading.Lock()

    def wrap(self, owner, attribute: str, stage: str) -> None:
        """Replace ``owner.attribute`` (a function or method) by a timed one."""
        original = getattr(owner, attribute)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            start, cpu_start = time.perf_counter(), time.thread_time()
            try:
                return original(*args, **kwargs)
            finally:
                elapsed, cpu = time.perf_counter() - start, time.thread_time() - cpu_start
                with self._lock:
                    self.seconds[stage] = self.seconds.get(stage, 0.0) + elapsed
                    self.cpu_seconds[stage] = self.cpu_seconds.get(stage, 0.0) + cpu
                    self.calls[stage] = self.calls.get(stage, 0) + 1

        setattr(owner, attribute, timed)


MAIN_THREAD_STAGES = ("scene build", "GL renderer start", "simulate", "render: RGB",
                      "render: segmentation", "render: weather re-renders", "render: lamp glow",
                      "render: labels' actor passes", "labels (total, incl. actor passes)", "commit")
"""Stages that run on the main thread, one after the other (the rest run in pool threads);
the labels' total holds its actor passes, so only the total counts towards the main thread."""


def install(timers: StageTimers, stats_device: str = "cpu") -> None:
    """Wrap every stage's function where ``generate_shard`` looks it up (the torch statistics'
    too when ``stats_device`` is not ``"cpu"``)."""
    stages = (
        (generate, "build_scene", "scene build"),
        (FrameRenderer, "__init__", "GL renderer start"),
        (sim, "advance", "simulate"),
        (FrameRenderer, "render_rgb", "render: RGB"),
        (FrameRenderer, "_segmentation_pass", "render: segmentation"),
        (FrameRenderer, "start_weather", "render: weather re-renders"),
        (FrameRenderer, "start_glow", "render: lamp glow"),
        (PendingImage, "result", "weather images' array work"),
        (FrameRenderer, "render_alone", "render: labels' actor passes"),
        (generate, "frame_labels", "labels (total, incl. actor passes)"),
        (generate, "_weather_rain", "weather rain (spray, sweeps, camera response)"),
        (rain, "render_rain_sweep", "rain sweep"),
        (wx, "camera_response", "camera response"),
        (rain.SsimReference, "quality", "statistics: SSIM / PSNR per rate"),
        (rain.BoxRainReference, "labels", "statistics: box rain labels per rate"),
        # the constructors after their methods: the classes' names then point to timed functions
        (rain, "SsimReference", "statistics: clean references (SSIM)"),
        (rain, "BoxRainReference", "statistics: clean references (boxes)"),
        (shard, "_deflate", "compress"),
        (shard.ShardWriter, "write_frame", "write (writer thread, incl. compress)"),
        (shard.ShardWriter, "commit", "commit"),
    )
    if stats_device != "cpu":
        from rainbench.rain.metrics_torch import TorchRateStatistics  # noqa: PLC0415 -- torch

        stages += ((TorchRateStatistics, "frame", "statistics: torch, all rates of a frame"),)
    for owner, attribute, stage in stages:
        timers.wrap(owner, attribute, stage)


def profile(rain_model: str, frames: int, threads: int | None, frames_in_flight: int | None,
            started_s: float | None = None, stats_device: str = "cpu",
            out_dir: str | None = None) -> dict:
    config = DatasetConfig(frames=frames, clip_frames=max(frames, 200), rain_model=rain_model,
                           rates=tuple(float(rate) for rate in range(0, 101, 10)),
                           stats_device=stats_device).tasks()[0]
    timers = StageTimers()
    install(timers, stats_device)
    threads = threads or os.cpu_count() or 1
    in_flight = frames_in_flight or generate.default_frames_in_flight(threads)
    with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
        cpu_start, wall_start = time.process_time(), time.perf_counter()
        generate.generate_shard(config, Path(tmp), threads=threads, frames_in_flight=in_flight)
        wall = time.perf_counter() - wall_start
        cpu = time.process_time() - cpu_start
    main_stages = sum(timers.seconds.get(stage, 0.0) for stage in MAIN_THREAD_STAGES
                      if not stage.startswith("render: labels'"))
    return {
        "benchmark": "generate_profile", "rain_model": rain_model, "frames": frames,
        "rates": len(config.rates), "weather_follows_rate": config.follows_rate,
        "width": config.width, "height": config.height, "threads": threads,
        "frames_in_flight": in_flight, "stats_device": stats_device, "cpu_count": os.cpu_count(),
        "out_dir": str(Path(out_dir or tempfile.gettempdir()).resolve()),
        "gl_backend": os.environ.get("MUJOCO_GL", ""), "process_start_to_generate_s": started_s,
        "wall_s": wall, "cpu_s": cpu,
        "cores_busy": cpu / wall, "main_thread_waiting_s": max(0.0, wall - main_stages),
        "stages": {stage: {"seconds": seconds, "cpu_seconds": timers.cpu_seconds[stage],
                           "calls": timers.calls[stage],
                           "ms_per_frame": 1000 * seconds / frames,
                           "thread": "main" if stage in MAIN_THREAD_STAGES else "pool"}
                   for stage, seconds in timers.seconds.items()},
    }


def profile_pieces(rain_model: str, frames: int, workers: int, stats_device: str = "cpu",
                   out_dir: str | None = None) -> dict:
    """The clip made by ``workers`` processes in pieces (``run_dataset``, as ``rainbench
    generate --workers N``), seen from the parent: when each piece's shard was joined into the
    clip's shard, and what copying the pieces and committing cost (the workers' own stages are
    in their processes: profile one piece with ``--threads 1 --frames <its length>``)."""
    config = DatasetConfig(frames=frames, clip_frames=max(frames, 200), rain_model=rain_model,
                           rates=tuple(float(rate) for rate in range(0, 101, 10)),
                           stats_device=stats_device)
    timers = StageTimers()
    timers.wrap(generate.ShardAssembler, "add", "join: copy a piece's chunks (parent)")
    timers.wrap(generate.ShardAssembler, "commit", "join: commit the shard (parent)")
    joined: list[float] = []
    add = generate.ShardAssembler.add

    def noted_add(self, piece):
        add(self, piece)
        joined.append(time.perf_counter() - wall_start)

    generate.ShardAssembler.add = noted_add
    with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
        wall_start = time.perf_counter()
        run_dataset(config, Path(tmp) / "clip", workers=workers)
        wall = time.perf_counter() - wall_start
        size = sum(path.stat().st_size for path in (Path(tmp) / "clip").glob("*.h5"))
    return {
        "benchmark": "generate_profile", "mode": "pieces", "rain_model": rain_model,
        "frames": frames, "rates": len(config.rates), "workers": workers,
        "stats_device": stats_device,
        "out_dir": str(Path(out_dir or tempfile.gettempdir()).resolve()),
        "pieces": len(generate.piece_configs(config.tasks()[0], workers)),
        "cpu_count": os.cpu_count(), "gl_backend": os.environ.get("MUJOCO_GL", ""),
        "wall_s": wall, "shard_bytes": size, "joined_at_s": joined,
        "stages": {stage: {"seconds": seconds, "cpu_seconds": timers.cpu_seconds[stage],
                           "calls": timers.calls[stage]}
                   for stage, seconds in timers.seconds.items()},
    }


def pieces_table(result: dict) -> str:
    joined = result["joined_at_s"]
    lines = [f"{result['rain_model']}, {result['frames']} frames x {result['rates']} rates in "
             f"{result['pieces']} pieces by {result['workers']} workers, written in "
             f"{result['out_dir']}: wall {result['wall_s']:.1f} s, "
             f"shard {result['shard_bytes'] / 1e9:.2f} GB; pieces joined from {joined[0]:.1f} s to "
             f"{joined[-1]:.1f} s" if joined else "no piece was joined (one piece: the shard itself)"]
    for stage, row in result["stages"].items():
        lines.append(f"{stage:<52} {row['calls']:>6} {row['seconds']:>8.2f} s {row['cpu_seconds']:>7.2f} CPU s")
    return "\n".join(lines)


def table(result: dict) -> str:
    lines = [f"{result['rain_model']}, {result['frames']} frames x {result['rates']} rates, "
             f"{result['width']}x{result['height']}, {result['threads']} threads, "
             f"{result['frames_in_flight']} frames in flight, statistics on {result['stats_device']}, "
             f"shard written in {result['out_dir']}, "
             f"{result['gl_backend'] or 'default'} GL: "
             f"wall {result['wall_s']:.1f} s, CPU {result['cpu_s']:.1f} s "
             f"({result['cores_busy']:.1f} cores busy); process start and imports before it: "
             + (f"{result['process_start_to_generate_s']:.1f} s"
                if result["process_start_to_generate_s"] is not None else "unknown"),
             f"{'stage':<52} {'thread':>6} {'calls':>6} {'seconds':>8} {'CPU s':>7} {'ms/frame':>9}"]
    for stage, row in sorted(result["stages"].items(), key=lambda item: -item[1]["seconds"]):
        lines.append(f"{stage:<52} {row['thread']:>6} {row['calls']:>6} {row['seconds']:>8.2f} "
                     f"{row['cpu_seconds']:>7.2f} {row['ms_per_frame']:>9.1f}")
    lines.append(f"{'main thread waiting (frames in flight, hand-over)':<52} {'main':>6} {'':>6} "
                 f"{result['main_thread_waiting_s']:>8.2f} {'':>7} "
                 f"{1000 * result['main_thread_waiting_s'] / result['frames']:>9.1f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rain-model", default="jeon2022", choices=("jeon2022", "physical"))
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--threads", type=int, default=None, help="default: one per core")
    parser.add_argument("--frames-in-flight", type=int, default=None,
                        help="default: generate_shard's own (one per 4 threads, 2 to 8)")
    parser.add_argument("--workers", type=int, default=None,
                        help="profile the clip made in pieces by this many worker processes "
                             "(the parent's view: when the pieces were joined, what joining cost)")
    parser.add_argument("--device", default="auto",
                        help="the statistics' device, as rainbench generate --device (default: "
                             "auto, a CUDA GPU where torch sees one)")
    parser.add_argument("--out", default=None,
                        help="write the shard (a temporary folder) under this directory (default: "
                             "the system's temporary directory; /dev/shm keeps it off the disk)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.out is not None and not Path(args.out).is_dir():
        parser.error(f"--out: {args.out} is not a directory")
    stats_device = stats_device_for(args.device)
    if args.frames < 1:
        parser.error(f"--frames: expected an integer >= 1, got {args.frames}")
    if args.workers is not None and args.workers < 2:
        parser.error(f"--workers: expected an integer >= 2 (pieces), got {args.workers}")
    if args.workers is not None:
        result = profile_pieces(args.rain_model, args.frames, args.workers, stats_device, args.out)
        print(pieces_table(result), flush=True)
    else:
        result = profile(args.rain_model, args.frames, args.threads, args.frames_in_flight,
                         started_s=process_age_s(), stats_device=stats_device, out_dir=args.out)
        print(table(result), flush=True)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
