"""One frame's per-rate statistics (SSIM, PSNR, per-box rain labels of the 10 rainy rates of
0:100:10) on a torch device against the CPU path, in the same run (issue 17, item 3).

    python bench/stats_device.py [--device auto] [--frames 5] [--repeats 3] [--threads N]
        [--json OUT]

The frames are the tests' synthetic 800x600 street (tests/testframe.py) with ``jeon2022`` rain
drawn over them once, and 20 boxes. Timed per frame, interleaved, after a warm-up:

* ``cpu``: what ``generate_shard`` does on the CPU, the clean references then the rates over
  ``--threads`` threads (default: every core), as :class:`~rainbench.rain.SsimReference` and
  :class:`~rainbench.rain.BoxRainReference`;
* ``device``: :meth:`~rainbench.rain.metrics_torch.TorchRateStatistics.frame` on ``--device``
  (``auto``: the CUDA GPU where torch sees one, else the CPU; the CPU's torch path is the GPU
  path's twin, not a path generation uses), the images' copy to the device and the figures'
  copy back included.

It prints the median ms per frame of each, the ratio cpu / device (> 1: the device is faster),
and the largest difference between the two paths' figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from rainbench.gen.config import stats_device_for
from rainbench.rain import BoxRainReference, RainConfig, SsimReference, render_rain_sweep

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from testframe import street_frame  # noqa: E402  -- the tests' synthetic street frame

RATES = tuple(float(rate) for rate in range(10, 101, 10))
HEIGHT, WIDTH = 600, 800


def _boxes(rng: np.random.Generator, count: int = 20) -> np.ndarray:
    """(count, 4) float32 x1, y1, x2, y2: boxes of 10-200 px anywhere in the frame."""
    size = rng.uniform(10, 200, (count, 2))
    corner = rng.uniform(0, 1, (count, 2)) * (np.array([WIDTH, HEIGHT]) - size)
    return np.concatenate([corner, corner + size], axis=1).astype(np.float32)


def cpu_statistics(pool: ThreadPoolExecutor, clean, rainy, coverage, boxes):
    """The CPU path of one frame, as ``rainbench.gen.generate`` runs it: (ssim, psnr,
    rain_coverage, contrast_loss), one row per rainy image."""
    references = pool.submit(lambda: (SsimReference(clean), BoxRainReference(clean, boxes))).result()

    def row(index):
        ssim, psnr = references[0].quality(rainy[index])
        cover, contrast = references[1].labels(rainy[index], coverage[index])
        return ssim, psnr, cover, contrast

    rows = list(pool.map(row, range(len(rainy))))
    return (np.array([r[0] for r in rows], np.float32), np.array([r[1] for r in rows], np.float32),
            np.stack([r[2] for r in rows]), np.stack([r[3] for r in rows]))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="auto", help="as rainbench generate --device; "
                        "auto: a CUDA GPU where torch sees one, else the CPU's torch path")
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None, help="CPU path threads (default: cores)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.frames < 1 or args.repeats < 1:
        parser.error(f"--frames and --repeats must be >= 1, got {args.frames} and {args.repeats}")
    device = stats_device_for(args.device)
    from rainbench.rain.metrics_torch import TorchRateStatistics  # noqa: PLC0415 -- imports torch

    threads = args.threads or os.cpu_count() or 1
    device_statistics = TorchRateStatistics(device, HEIGHT, WIDTH)
    cpu_ms, device_ms, differences = [], [], {"ssim": 0.0, "psnr": 0.0, "rain_coverage": 0.0,
                                              "contrast_loss": 0.0}
    with ThreadPoolExecutor(threads) as pool:
        for index in range(args.frames):
            rng = np.random.default_rng(2000 + index)
            clean, _, _ = street_frame(rng, HEIGHT, WIDTH)
            drawn = render_rain_sweep(clean, None, RATES, config=RainConfig(model="jeon2022"), K=None,
                                      seed_sequence=np.random.SeedSequence([0, index, 0]))
            rainy = [frame.rgb for frame in drawn]
            coverage = [frame.coverage for frame in drawn]
            boxes = _boxes(rng)
            expected = cpu_statistics(pool, clean, rainy, coverage, boxes)  # warm-up
            got = device_statistics.frame(clean, rainy, coverage, boxes)
            for name, a, b in zip(differences, expected, got):
                finite = np.isfinite(a) & np.isfinite(b)
                if finite.any():
                    differences[name] = max(differences[name], float(np.abs(a[finite] - b[finite]).max()))
            for _ in range(args.repeats):  # interleaved: load drift hits both alike
                start = time.perf_counter()
                cpu_statistics(pool, clean, rainy, coverage, boxes)
                cpu_ms.append(1e3 * (time.perf_counter() - start))
                start = time.perf_counter()
                device_statistics.frame(clean, rainy, coverage, boxes)
                device_ms.append(1e3 * (time.perf_counter() - start))
    cpu, on_device = statistics.median(cpu_ms), statistics.median(device_ms)
    import torch  # noqa: PLC0415

    report = {
        "benchmark": "stats_device", "image": f"{WIDTH}x{HEIGHT}", "rainy_rates": len(RATES),
        "boxes": 20, "frames": args.frames, "repeats": args.repeats, "cpu_threads": threads,
        "device": device, "device_name": (torch.cuda.get_device_name(torch.device(device))
                                          if device.startswith("cuda") else platform.processor() or "cpu"),
        "cpu_ms_per_frame": cpu, "device_ms_per_frame": on_device, "cpu_over_device": cpu / on_device,
        "largest_difference": differences,
    }
    print(f"statistics of one frame (10 rainy rates, 20 boxes, {WIDTH}x{HEIGHT}): CPU path "
          f"{cpu:.1f} ms ({threads} threads), torch on {device} {on_device:.1f} ms: "
          f"{cpu / on_device:.2f}x; largest differences "
          + ", ".join(f"{name} {value:.2g}" for name, value in differences.items()))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
