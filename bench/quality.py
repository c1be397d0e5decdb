"""Clean AP@0.5 and F1 of shipped (or any) weights on unseen evaluation scenes, against the bar.

The quality check of docs/models.md: ``--scenes`` clean scenes from seed ``--seed`` (default
5 scenes from seed 100: evaluation seeds, never trained on), ``--frames`` frames each spread
over the 20 s clip (40 frames at 2 frames/s), the paper's actor mix, 800x600, evaluated with
``rainbench eval`` defaults (each model at its own letterbox size: 960 for both shipped
models' cards) on CPU. Prints a table per model with the issue's quality
bar (AP@0.5 >= 0.80 for car and person, >= 0.60 for bicycle and motorcycle) and exits 0 either
way: it measures, it does not judge.

Usage: ``python bench/quality.py [--weights rainbench-yolo11n ...] [--data data/quality]
[--json OUT] [--seed 100] [--scenes 5] [--frames 40] [--layouts street,highway,...]``
(``--layouts`` checks each road layout on its own data: the bar must hold per layout.)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from rainbench.eval.backends.ultralytics import preload_torch

preload_torch()  # before Mesa renders the frames

QUALITY_BAR = {"car": 0.80, "person": 0.80, "bicycle": 0.60, "motorcycle": 0.60}
CLIP_SECONDS = 20.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", action="append", default=None,
                        help="shipped name or weights file (repeatable; default rainbench-yolo11n)")
    parser.add_argument("--data", default="data/quality", help="dataset directory (made if missing)")
    parser.add_argument("--out", default="results/quality", help="rainbench eval results directory")
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--imgsz", type=int, default=None, help="letterbox size (default: each model's own)")
    parser.add_argument("--layouts", default="seed",
                        help="comma list of road layouts, each checked on its own data (the "
                             "same seeds at that layout, by day); 'seed' (default): each seed "
                             "its own layout and time of day")
    parser.add_argument("--json", default=None, help="write the figures here")
    args = parser.parse_args(argv)
    if args.seed < 0 or args.seed + args.scenes > 1_000_000:
        parser.error("--seed/--scenes: the check must use evaluation seeds (below 1000000)")

    from rainbench.eval.pipeline import run_eval
    from rainbench.gen.config import DatasetConfig
    from rainbench.gen.dataset import run_dataset

    weights = args.weights or ["rainbench-yolo11n"]
    rows, seconds = [], {}
    for layout in args.layouts.split(","):
        chosen = {} if layout == "seed" else {"layout": layout, "time_of_day": "day"}
        data, out = Path(args.data) / layout, Path(args.out) / layout
        config = DatasetConfig(seed=args.seed, scenes=args.scenes, frames=args.frames,
                               fps=args.frames / CLIP_SECONDS, rates=(0.0,), **chosen)
        started = time.perf_counter()
        run_dataset(config, data, workers=1)
        seconds[f"generate {layout}"] = time.perf_counter() - started
        started = time.perf_counter()
        result = run_eval(data, out, weights=weights, imgsz=args.imgsz, n_boot=200,
                          device="cpu", progress=False, force=True)
        seconds[f"eval {layout}"] = time.perf_counter() - started
        rows += [{"layout": layout, **{key: record[key] for key in (
            "model", "class", "n_gt", "ap50", "ap50_ci_low", "ap50_ci_high", "f1")}}
            for record in result.records if record["rate"] == 0]
    print(f"seeds {args.seed}..{args.seed + args.scenes - 1}, {args.frames} frames each over "
          f"{CLIP_SECONDS:g} s, imgsz {args.imgsz or 'per model'} "
          f"({', '.join(f'{k} {v:.0f} s' for k, v in seconds.items())})")
    print("| layout | model | class | boxes | AP@0.5 (95 % CI) | F1 | bar | met |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        bar = QUALITY_BAR[row["class"]]
        print(f"| {row['layout']} | {row['model']} | {row['class']} | {row['n_gt']} | "
              f"{row['ap50']:.3f} ({row['ap50_ci_low']:.3f}-{row['ap50_ci_high']:.3f}) | "
              f"{row['f1']:.3f} | {bar:.2f} | {'yes' if row['ap50'] >= bar else 'no'} |")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"rows": rows, "bar": QUALITY_BAR,
                                               "seconds": seconds, "cpu_count": os.cpu_count()},
                                              indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
