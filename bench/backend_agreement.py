"""The batched torch backend against ultralytics' predict on a whole dataset: AP per class per rate.

Runs ``rainbench eval`` on ``--data`` (default ``data/paper/jeon2022``, the paper clip that
``make paper`` writes; generated there first when missing) twice with the same ``.pt``
(``--weights``, default the shipped ``rainbench-yolo11n.pt`` at its card's 960 px): once with
``--pt-backend ultralytics`` (the baseline) and once with the default batched backend, on
``--device`` (default: CUDA when present, else the CPU). Reports, per class and rate, the two
AP@0.5 and AP@0.5:0.95 and their largest absolute difference (the issue's bar: AP@0.5 within
0.002 per class), plus the wall time and images/s of each run (inference and metrics; the
ratio is the batched run's speed over the baseline's, measured in the same process). With
``--fp32`` on CUDA a third run keeps the batched backend's network in fp32 (its default there is
fp16), so that what fp16 makes of the difference shows apart from the rest.

Usage: ``python bench/backend_agreement.py [--data DIR] [--weights rainbench-yolo11n]
[--device cpu] [--json OUT] [--fp32]``
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

from rainbench.eval.backends.ultralytics import preload_torch

preload_torch()  # before Mesa renders (when the paper clip has to be generated)
import numpy as np  # noqa: E402
import torch  # noqa: E402

from rainbench.eval import backends, pipeline, weights as registry  # noqa: E402
from rainbench.eval.backends import torch_batched  # noqa: E402

_torch_detector = torch_batched.torch_detector


def paper_clip(folder: Path) -> Path:
    """The paper clip with ``jeon2022`` rain at 0:100:10 (what ``make paper`` writes), generated into
    ``folder`` unless complete there."""
    from dataclasses import replace

    from rainbench.experiments.paper import PaperConfig
    from rainbench.gen.dataset import run_dataset

    run_dataset(replace(PaperConfig().dataset, rain_model="jeon2022", weather_follows_rate=False), folder, workers=1)
    return folder


def _fp32_detector(*args, **kwargs):
    """``torch_detector`` with the network kept in fp32 on CUDA too (``--fp32``)."""
    detector = _torch_detector(*args, **kwargs)
    return dataclasses.replace(detector, network=detector.network.float(), half=False)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="data/paper/jeon2022")
    parser.add_argument("--weights", default="rainbench-yolo11n", help="shipped model name or a .pt")
    parser.add_argument("--device", default=None)
    parser.add_argument("--json", default=None)
    parser.add_argument("--fp32", action="store_true",
                        help="on CUDA, also run the batched backend in fp32: what of the difference fp16 makes")
    args = parser.parse_args(argv)
    device = args.device or ("0" if torch.cuda.is_available() else "cpu")
    data = Path(args.data)
    if not (data / "manifest.json").is_file():
        paper_clip(data)
    checkpoint = registry.checkpoint_file(args.weights)
    imgsz = registry.model_imgsz(args.weights)
    dataset = pipeline.open_dataset(data)
    images = len(dataset.images) * len(dataset.rates)
    variants = ["ultralytics", "batched"] + (["batched_fp32"] if args.fp32 and device != "cpu" else [])
    runs, seconds = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        # untimed warm-up of both backends (first-use torch kernels; the baseline ran cold before)
        blank = [np.full((600, 800, 3), 128, np.uint8)] * 8  # the paper clip's size
        for variant in ("ultralytics", "batched"):
            backends.load_detector(checkpoint, device=device, pt_backend=variant).predict(
                blank, imgsz=imgsz, conf=0.001, iou=0.7, max_det=300)
        for variant in variants:
            start = time.perf_counter()
            with contextlib.ExitStack() as stack:
                if variant == "batched_fp32":
                    stack.enter_context(mock.patch.object(torch_batched, "torch_detector", _fp32_detector))
                outputs = pipeline.run_eval(data, Path(tmp) / variant, weights=[checkpoint], imgsz=imgsz,
                                            device=device, n_boot=1, progress=False,
                                            pt_backend=variant.split("_")[0])
            seconds[variant] = time.perf_counter() - start
            runs[variant] = {(r["class"], r["rate"]): r for r in outputs.records}
    rows = []
    for key, reference in runs["ultralytics"].items():
        if reference["ap50"] is None:
            continue
        row = {"class": key[0], "rate": key[1], "n_gt": reference["n_gt"]}
        for variant in variants:
            row[f"ap50_{variant}"] = runs[variant][key]["ap50"]
            row[f"ap50_95_{variant}"] = runs[variant][key]["ap50_95"]
        rows.append(row)

    def largest(variant: str) -> tuple[dict, dict]:
        overall = {metric: max(abs(row[f"{metric}_{variant}"] - row[f"{metric}_ultralytics"]) for row in rows)
                   for metric in ("ap50", "ap50_95")}
        by_class: dict[str, float] = {}
        for row in rows:
            by_class[row["class"]] = max(by_class.get(row["class"], 0.0),
                                         abs(row[f"ap50_{variant}"] - row["ap50_ultralytics"]))
        return ({k: round(v, 5) for k, v in overall.items()}, {k: round(v, 5) for k, v in by_class.items()})

    overall, by_class = largest("batched")
    result = {
        "benchmark": "backend_agreement", "data": str(data), "weights": str(checkpoint), "imgsz": imgsz,
        "device": device, "cuda": torch.cuda.is_available(), "machine": platform.machine(), "cpus": os.cpu_count(),
        "images": images, "seconds": {k: round(v, 1) for k, v in seconds.items()},
        "images_per_s": {k: round(images / v, 2) for k, v in seconds.items()},
        "ratio_batched_vs_ultralytics": round(seconds["ultralytics"] / seconds["batched"], 3),
        "largest_abs_difference": overall,
        "largest_abs_ap50_difference_by_class": by_class,
    }
    if "batched_fp32" in variants:
        overall, by_class = largest("batched_fp32")
        result["largest_abs_difference_fp32"] = overall
        result["largest_abs_ap50_difference_by_class_fp32"] = by_class
    result["rows"] = rows
    print(json.dumps({k: v for k, v in result.items() if k != "rows"}, indent=1))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
