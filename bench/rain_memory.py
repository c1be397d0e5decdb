"""Rain memory benchmark: lens water and streaks drawn in runs against all at once.

Each case renders one frame's rain sweep in a fresh process, once as shipped (lens drops
rasterised in runs of at most ``LENS_RASTER_BUDGET`` cells, streaks past
``STREAK_SAMPLE_BUDGET`` samples in runs) and once with both budgets set beyond the case, as
the code drew everything before (the baseline, in the same run). Reported per case: peak
resident memory and seconds of each, their ratios, and whether the images are byte-identical
(they must be). Cases (rates in mm/h):

- ``paper``: jeon2022 at 800x600, 0..100 by 10, the defaults (one run: no change expected).
- ``lens-large-drops``: jeon2022 at 1024x1024, 50 and 100, 100 px drops.
- ``streaks-long-exposure``: physical at 1920x1080, 1000, exposure 1/20 s, no lens water.
- ``physical-lens-1m``: physical at 800x600, 500 and 1000, lens life 1 h (a million lens drops).

Targets: peak memory <= 0.5x the baseline's on the two lens cases and <= 0.7x on the streaks
(there the frame's own float arrays and the dense per-layer sums are the floor: 1.5 GB at
1920x1080), the same bytes everywhere, and the paper's sweep within the noise (<= 1.1x in time
and memory).

Timing: each process draws its sweep once (its peak memory and its bytes), then again until
about a second has passed (at least once, at most 20 times) and reports the median draw's
seconds: the paper's sweep takes about 0.1 s, too short for one draw to time. The shipped and
baseline processes of a case alternate which goes first, ``--repeats`` pairs (default 3); the
reported time ratio is the median pair's (the lower of the middle two for an even count), and
every pair is kept in the JSON. Peak memory is the largest of a mode's runs.

    python bench/rain_memory.py [--cases paper,lens-large-drops,...] [--repeats 3] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CASES = {
    "paper": dict(height=600, width=800, model="jeon2022", rates=[float(r) for r in range(0, 101, 10)], options={}),
    "lens-large-drops": dict(height=1024, width=1024, model="jeon2022", rates=[50.0, 100.0],
                             options={"lens_radius_min_px": 100.0, "lens_radius_max_px": 100.0}),
    "streaks-long-exposure": dict(height=1080, width=1920, model="physical", rates=[1000.0],
                                  options={"exposure_s": 0.05, "lens_drops": False}),
    "physical-lens-1m": dict(height=600, width=800, model="physical", rates=[500.0, 1000.0],
                             options={"lens_life_min_s": 3600.0, "lens_life_max_s": 3600.0, "lens_sweep_speed_m_s": 19.9}),
}

CHILD = r"""
import hashlib, json, resource, sys, time
import numpy as np
from rainbench.rain import LensClock, RainConfig, render_rain_sweep
from rainbench.rain import render as render_module
case, baseline = json.loads(sys.argv[1]), sys.argv[2] == "baseline"
if baseline:  # everything in one run, as before the budgets
    render_module.LENS_RASTER_BUDGET = render_module.STREAK_SAMPLE_BUDGET = 1 << 62
    render_module.LENS_RASTER_KEEP = 1 << 62
height, width = case["height"], case["width"]
rng = np.random.default_rng(0)
rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
depth = np.full((height, width), 30.0, np.float32)
depth[: height // 3] = np.inf
K = np.array([[width / 2, 0, width / 2], [0, width / 2, height / 2], [0, 0, 1.0]])
config = RainConfig(model=case["model"], **case["options"])
def sweep():
    start = time.perf_counter()
    frames = render_rain_sweep(rgb, depth, case["rates"], config=config, K=K,
                               seed_sequence=np.random.SeedSequence(3),
                               lens_clock=LensClock(np.random.SeedSequence([1, 2]), 5, 10.0))
    return frames, time.perf_counter() - start
frames, first = sweep()
digest = hashlib.sha256(b"".join(f.rgb.tobytes() + f.coverage.tobytes() for f in frames)).hexdigest()
peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
del frames
draws = []
while not draws or (sum(draws) < 1.0 and len(draws) < 20):
    draws.append(sweep()[1])
print(json.dumps({"seconds": sorted(draws)[(len(draws) - 1) // 2], "draws": len(draws),
                  "first_draw_s": first, "peak_gb": peak_gb, "sha256": digest}))
"""


def _run(case: dict, mode: str) -> dict:
    result = subprocess.run([sys.executable, "-c", CHILD, json.dumps(case), mode], capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"rain_memory: the {mode} run failed: {result.stderr.strip().splitlines()[-1:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--repeats", type=int, default=3,
                        help="pairs of runs of each case, alternating which mode goes first (default 3)")
    parser.add_argument("--json")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error(f"--repeats: expected an integer >= 1, got {args.repeats}")
    names = [name.strip() for name in args.cases.split(",") if name.strip()]
    unknown = [name for name in names if name not in CASES]
    if unknown or not names:
        parser.error(f"--cases: expected names from {', '.join(CASES)}, got {args.cases!r}")
    report = {}
    for name in names:
        pairs = []
        for repeat in range(args.repeats):
            order = ("shipped", "baseline") if repeat % 2 == 0 else ("baseline", "shipped")
            runs = {mode: _run(CASES[name], mode) for mode in order}
            pairs.append({**runs, "first": order[0],
                          "time_ratio": runs["shipped"]["seconds"] / runs["baseline"]["seconds"]})
        median_pair = sorted(pairs, key=lambda pair: pair["time_ratio"])[(len(pairs) - 1) // 2]
        peak = {mode: max(pair[mode]["peak_gb"] for pair in pairs) for mode in ("shipped", "baseline")}
        digests = {pair[mode]["sha256"] for pair in pairs for mode in ("shipped", "baseline")}
        shipped, baseline = median_pair["shipped"], median_pair["baseline"]
        row = {"shipped": shipped, "baseline": baseline, "pairs": pairs,
               "shipped_peak_gb": peak["shipped"], "baseline_peak_gb": peak["baseline"],
               "memory_ratio": peak["shipped"] / peak["baseline"],
               "time_ratio": median_pair["time_ratio"],
               "same_bytes": len(digests) == 1}
        report[name] = row
        each_ratio = ", ".join(f"{pair['time_ratio']:.2f}" for pair in pairs)
        print(f"{name}: peak {peak['shipped']:.2f} GB against {peak['baseline']:.2f} GB "
              f"({row['memory_ratio']:.2f}x), {shipped['seconds']:.3f} s against {baseline['seconds']:.3f} s "
              f"({row['time_ratio']:.2f}x, the median of {len(pairs)} pair(s): "
              f"{each_ratio}), "
              f"same bytes: {row['same_bytes']}", flush=True)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(report, handle, indent=1)
    if not all(row["same_bytes"] for row in report.values()):
        raise SystemExit("rain_memory: the images differ from the baseline's")


if __name__ == "__main__":
    main()
