"""The batched torch backend against ultralytics' predict on a whole dataset: AP per class per rate.

Runs ``rainbench eval`` on ``--data`` (default ``data/paper/jeon2022``, the paper clip that
``make paper`` writes; generated there first when missing) twice with the same ``.pt``
(``--weights``, default the shipped ``rainbench-yolo11n.pt`` at its card's 960 px): once with
``--pt-backend ultralytics`` (the baseline) and once with the default batched backend, on
``--device`` (default: CUDA when present, else the CPU). Reports, per class and rate, the two
AP@0.5 and AP@0.5:0.95 and their largest absolute difference (the issue's bar: AP@0.5 within
0.002 per class), plus the wall time and images/s of each run (inference and metrics; the
ratio is the batched run's speed over the baseline's, measured in the same process).

Usage: ``python bench/backend_agreement.py [--data DIR] [--weights rainbench-yolo11n]
[--device cpu] [--json OUT]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from rainbench.eval.backends.ultralytics import preload_torch

preload_torch()  # before Mesa renders (when the paper clip has to be generated)
import torch  # noqa: E402

from rainbench.eval import pipeline, weights as registry  # noqa: E402


def paper_clip(folder: Path) -> Path:
    """The paper clip with ``jeon2022`` rain at 0:100:10 (what ``make paper`` writes), generated into
    ``folder`` unless complete there."""
    from dataclasses import replace

    from rainbench.experiments.paper import PaperConfig
    from rainbench.gen.dataset import run_dataset

    run_dataset(replace(PaperConfig().dataset, rain_model="jeon2022", weather_follows_rate=False), folder, workers=1)
    return folder


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="data/paper/jeon2022")
    parser.add_argument("--weights", default="rainbench-yolo11n", help="shipped model name or a .pt")
    parser.add_argument("--device", default=None)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    device = args.device or ("0" if torch.cuda.is_available() else "cpu")
    data = Path(args.data)
    if not (data / "manifest.json").is_file():
        paper_clip(data)
    checkpoint = registry.checkpoint_file(args.weights)
    imgsz = registry.model_imgsz(args.weights)
    dataset = pipeline.open_dataset(data)
    images = len(dataset.images) * len(dataset.rates)
    runs, seconds = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for pt_backend in ("ultralytics", "batched"):
            start = time.perf_counter()
            outputs = pipeline.run_eval(data, Path(tmp) / pt_backend, weights=[checkpoint], imgsz=imgsz,
                                        device=device, n_boot=1, progress=False, pt_backend=pt_backend)
            seconds[pt_backend] = time.perf_counter() - start
            runs[pt_backend] = {(r["class"], r["rate"]): r for r in outputs.records}
    rows = []
    for key, reference in runs["ultralytics"].items():
        ours = runs["batched"][key]
        if reference["ap50"] is None:
            continue
        rows.append({"class": key[0], "rate": key[1], "n_gt": reference["n_gt"],
                     "ap50_ultralytics": reference["ap50"], "ap50_batched": ours["ap50"],
                     "ap50_95_ultralytics": reference["ap50_95"], "ap50_95_batched": ours["ap50_95"]})
    largest = {metric: max(abs(row[f"{metric}_batched"] - row[f"{metric}_ultralytics"]) for row in rows)
               for metric in ("ap50", "ap50_95")}
    by_class = {}
    for row in rows:
        entry = by_class.setdefault(row["class"], 0.0)
        by_class[row["class"]] = max(entry, abs(row["ap50_batched"] - row["ap50_ultralytics"]))
    result = {
        "benchmark": "backend_agreement", "data": str(data), "weights": str(checkpoint), "imgsz": imgsz,
        "device": device, "cuda": torch.cuda.is_available(), "machine": platform.machine(), "cpus": os.cpu_count(),
        "images": images, "seconds": {k: round(v, 1) for k, v in seconds.items()},
        "images_per_s": {k: round(images / v, 2) for k, v in seconds.items()},
        "ratio_batched_vs_ultralytics": round(seconds["ultralytics"] / seconds["batched"], 3),
        "largest_abs_difference": {k: round(v, 5) for k, v in largest.items()},
        "largest_abs_ap50_difference_by_class": {k: round(v, 5) for k, v in by_class.items()},
        "rows": rows,
    }
    print(json.dumps({k: v for k, v in result.items() if k != "rows"}, indent=1))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
