"""Benchmark of rain rendering on one CPU core, against albumentations RandomRain.

    python bench/rain.py [--frames N] [--repeats R] [--json OUT]

For each of N synthetic 800x600 street frames (tests/testframe.py, with a depth map), and
each rain model, it times:

* sweep: ``render_rain_sweep`` over the 11 rates 0, 10, ..., 100 mm/h (what the dataset
  generator calls), reported per rainy image (total / 11, and total / 10 rainy images when the
  rate-0 copy is not counted);
* single: ``render_rain`` called once per rate (no shared work), per image;
* RandomRain: ``albumentations.RandomRain(p=1)`` (default rain type) on the same frame, per image.

Ratios are ours / RandomRain per image (< 1 means faster). Targets: jeon2022 sweep <= 1x,
physical sweep <= 3x. It also prints SSIM / PSNR of both models at 10 / 50 / 100 mm/h on the
frames (the table in docs/rain.md). albumentations==2.0.8 is a bench-only dependency.
"""

from __future__ import annotations

import os

# one core: set before numpy / OpenCV are imported
for _variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS", "VECLIB_MAXIMUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

from rainbench.rain import RAIN_MODELS, RainConfig, image_quality, render_rain, render_rain_sweep  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from testframe import street_frame  # noqa: E402  -- the tests' synthetic street frame

RATES = tuple(float(rate) for rate in range(0, 101, 10))
QUALITY_RATES = (10.0, 50.0, 100.0)
HEIGHT, WIDTH = 600, 800


def _load_random_rain():
    try:
        import albumentations
    except ImportError:
        return None, None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        transform = albumentations.RandomRain(p=1.0)
    return transform, albumentations.__version__


def _time_call(function) -> float:
    start = time.perf_counter()
    function()
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=3, help="number of synthetic frames (default 3)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats per frame (default 3)")
    parser.add_argument("--hfov", type=float, default=90.0, help="horizontal field of view in degrees (default 90, CARLA's)")
    parser.add_argument("--json", dest="json_path", default=None, help="write the figures to this JSON file")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.repeats < 1:
        parser.error(f"--frames and --repeats must be >= 1, got {args.frames} and {args.repeats}")

    random_rain, albumentations_version = _load_random_rain()
    if random_rain is None:
        print("albumentations is not installed: RandomRain ratios are skipped (pip install albumentations==2.0.8)", file=sys.stderr)

    frames = [street_frame(np.random.default_rng(1000 + index), HEIGHT, WIDTH, args.hfov) for index in range(args.frames)]
    configs = {model: RainConfig(model=model) for model in RAIN_MODELS}

    sweep_ms: dict[str, list[float]] = {model: [] for model in RAIN_MODELS}
    single_ms: dict[str, list[float]] = {model: [] for model in RAIN_MODELS}
    baseline_ms: list[float] = []
    quality: dict[str, dict[float, list[tuple[float, float]]]] = {model: {rate: [] for rate in QUALITY_RATES} for model in RAIN_MODELS}
    drop_counts: dict[str, dict[float, list[int]]] = {model: {rate: [] for rate in QUALITY_RATES} for model in RAIN_MODELS}

    for frame_index, (rgb, depth, K) in enumerate(frames):
        seed = np.random.SeedSequence([0, frame_index, 0])
        # warm-up (imports, caches) outside the timing
        for model, config in configs.items():
            render_rain_sweep(rgb, depth, RATES, config=config, K=K, seed_sequence=seed)
        if random_rain is not None:
            random_rain(image=rgb)
        for _ in range(args.repeats):
            # interleave the methods so that machine-load drift hits all of them alike
            if random_rain is not None:
                baseline_ms.append(1e3 * _time_call(lambda: random_rain(image=rgb)))
            for model, config in configs.items():
                sweep_ms[model].append(1e3 * _time_call(lambda: render_rain_sweep(rgb, depth, RATES, config=config, K=K, seed_sequence=seed)))
                single_ms[model].append(1e3 * sum(_time_call(lambda rate=rate: render_rain(rgb, depth, rate, config=config, K=K, seed_sequence=seed)) for rate in RATES))
                if random_rain is not None:
                    baseline_ms.append(1e3 * _time_call(lambda: random_rain(image=rgb)))
        for model, config in configs.items():
            rendered = render_rain_sweep(rgb, depth, QUALITY_RATES, config=config, K=K, seed_sequence=seed)
            for rate, rain_frame in zip(QUALITY_RATES, rendered):
                quality[model][rate].append(image_quality(rgb, rain_frame.rgb))
                drop_counts[model][rate].append(rain_frame.drop_count)

    baseline = statistics.median(baseline_ms) if baseline_ms else None
    report: dict[str, object] = {
        "image": f"{WIDTH}x{HEIGHT}",
        "hfov_deg": args.hfov,
        "frames": args.frames,
        "repeats": args.repeats,
        "rates_mm_h": list(RATES),
        "threads": 1,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "albumentations": albumentations_version,
        "random_rain_ms_per_image": baseline,
        "models": {},
    }
    print(f"rain benchmark: {args.frames} frame(s) {WIDTH}x{HEIGHT}, hfov {args.hfov:g} deg, rates 0..100 step 10, 1 thread, median of {args.repeats} repeat(s)")
    if baseline is not None:
        print(f"albumentations {albumentations_version} RandomRain (default): {baseline:.2f} ms per image")
    header = f"{'model':10s} {'sweep ms/frame':>15s} {'ms/image (11)':>14s} {'ms/image (10)':>14s} {'single ms/image':>16s} {'ratio sweep':>12s} {'ratio single':>13s}"
    print(header)
    print("-" * len(header))
    for model in RAIN_MODELS:
        sweep = statistics.median(sweep_ms[model])
        single = statistics.median(single_ms[model])
        per_image = sweep / len(RATES)
        per_rainy_image = sweep / (len(RATES) - 1)
        single_per_image = single / len(RATES)
        ratio = per_image / baseline if baseline else None
        ratio_single = single_per_image / baseline if baseline else None
        ratio_text = f"{ratio:.2f}x" if ratio is not None else "n/a"
        ratio_single_text = f"{ratio_single:.2f}x" if ratio_single is not None else "n/a"
        print(f"{model:10s} {sweep:15.1f} {per_image:14.2f} {per_rainy_image:14.2f} {single_per_image:16.2f} {ratio_text:>12s} {ratio_single_text:>13s}")
        report["models"][model] = {
            "sweep_ms_per_frame": sweep,
            "sweep_ms_per_image": per_image,
            "sweep_ms_per_rainy_image": per_rainy_image,
            "single_ms_per_image": single_per_image,
            "ratio_sweep_vs_random_rain": ratio,
            "ratio_rainy_image_vs_random_rain": per_rainy_image / baseline if baseline else None,
            "ratio_single_vs_random_rain": ratio_single,
            "quality": {
                str(rate): {
                    "ssim": statistics.mean(q[0] for q in quality[model][rate]),
                    "psnr_db": statistics.mean(q[1] for q in quality[model][rate]),
                    "drop_count": statistics.mean(drop_counts[model][rate]),
                }
                for rate in QUALITY_RATES
            },
        }
    print()
    print(f"{'model':10s} {'rate mm/h':>9s} {'SSIM':>7s} {'PSNR dB':>8s} {'drops':>8s}")
    for model in RAIN_MODELS:
        for rate in QUALITY_RATES:
            figures = report["models"][model]["quality"][str(rate)]
            print(f"{model:10s} {rate:9.0f} {figures['ssim']:7.4f} {figures['psnr_db']:8.2f} {figures['drop_count']:8.0f}")
    if args.json_path:
        with open(args.json_path, "w", encoding="utf-8") as handle:
            json.dump(report, handle, indent=2)
        print(f"\nwrote {args.json_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
