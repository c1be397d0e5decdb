"""Benchmark rainbench.eval.metrics against running pycocotools' COCOeval directly.

Workload at the paper's size: 11 rain rates x 200 frames, the paper's Table I instance mix per
rate (838 car, 350 person, 67 bicycle, 10 motorcycle = 1265 boxes over 200 frames), about 20
noisy detections per frame whose recall and localisation degrade with the rate.

Timed, per full sweep of the 11 rates (best of --repeats sweeps):

- ours: ``rainbench.eval.metrics.evaluation.evaluate`` (COCO indexing, one COCOeval over all
  classes with area range "all" and maxDets 100, AP50/AP75/AP50-95 and the YOLO
  precision/recall/F1 part);
- direct: the textbook pycocotools run on the same data: ``COCO`` from the dict, ``loadRes``,
  ``COCOeval(..., "bbox")`` with default params, ``evaluate(); accumulate(); summarize()``;
- same params (reference point, not the target): pycocotools with our params (area "all" only,
  maxDets [100]), evaluate + accumulate, no F1 -- shows what our F1 / indexing part costs;
- bootstrap: ``rainbench.eval.metrics.bootstrap.bootstrap_ci`` (AP50, --n-boot resamples per
  rate), timed separately.

Usage: ``python bench/eval_metrics.py [--json OUT] [--repeats 3] [--n-boot 1000] [--seed 0]``
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import io
import json
import os
import platform
import sys
import time

import numpy as np
import pycocotools
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from rainbench.eval.metrics.bootstrap import bootstrap_ci
from rainbench.eval.metrics.coco import AREA_ALL, MAX_DETECTIONS, coco_ground_truth
from rainbench.eval.metrics.evaluation import evaluate

RATES = tuple(float(r) for r in range(0, 101, 10))
N_FRAMES = 200
INSTANCES = {2: 838, 0: 350, 1: 67, 3: 10}  # the paper's Table I, class id -> instances
DETECTIONS_PER_FRAME = 20
WIDTH, HEIGHT = 800, 600


def make_ground_truth(rng: np.random.Generator) -> tuple[dict, list[tuple[np.ndarray, np.ndarray]]]:
    """The 200-frame ground truth shared by all rates: (COCO dict, per-frame (boxes (M,4) xyxy float32, classes (M,)))."""
    class_of_instance = np.concatenate([np.full(n, c) for c, n in INSTANCES.items()])
    frame_of_instance = rng.integers(0, N_FRAMES, len(class_of_instance))
    frames = []
    for frame in range(N_FRAMES):
        classes = class_of_instance[frame_of_instance == frame]
        size = np.where(
            classes[:, None] == 2, rng.uniform(30, 220, (len(classes), 2)), rng.uniform(12, 120, (len(classes), 2))
        )
        xy = rng.uniform(0, [WIDTH - 230, HEIGHT - 230], (len(classes), 2))
        frames.append((np.concatenate([xy, xy + size], axis=1).astype(np.float32), classes.astype(np.int64)))
    gt = coco_ground_truth([(i + 1, WIDTH, HEIGHT, boxes, classes) for i, (boxes, classes) in enumerate(frames)])
    return gt, frames


def make_detections(rng: np.random.Generator, frames, rate: float) -> list[dict]:
    """~20 detections per frame: jittered hits (recall falls with the rate) plus background false positives."""
    severity = rate / 100.0
    detections = []
    for i, (boxes, classes) in enumerate(frames):
        image_id = i + 1
        hits = rng.random(len(boxes)) < 0.9 - 0.35 * severity
        for box, class_id in zip(boxes[hits].astype(np.float64), classes[hits], strict=True):
            size = np.r_[box[2:] - box[:2], box[2:] - box[:2]]
            new = box + rng.normal(0, 0.06 + 0.06 * severity, 4) * size
            new[2:] = np.maximum(new[2:], new[:2] + 1)
            label = int(class_id) if rng.random() > 0.05 + 0.1 * severity else int(rng.integers(4))
            score = float(np.clip(rng.normal(0.75 - 0.25 * severity, 0.15), 0.001, 1.0))
            detections.append(
                {
                    "image_id": image_id,
                    "category_id": label,
                    "bbox": [new[0], new[1], new[2] - new[0], new[3] - new[1]],
                    "score": score,
                }
            )
        for _ in range(max(0, DETECTIONS_PER_FRAME - int(hits.sum()))):
            x, y = rng.uniform(0, [WIDTH - 60, HEIGHT - 60])
            w, h = rng.uniform(6, 60, 2)
            detections.append(
                {
                    "image_id": image_id,
                    "category_id": int(rng.choice(4, p=[0.4, 0.1, 0.4, 0.1])),
                    "bbox": [x, y, w, h],
                    "score": float(rng.uniform(0.001, 0.5)),
                }
            )
    return detections


def run_direct(gt: dict, detections: list[dict], *, matched_params: bool = False) -> COCOeval:
    """pycocotools COCOeval run directly. By default the textbook evaluation (4 area ranges,
    maxDets [1, 10, 100], evaluate + accumulate + summarize); ``matched_params``: our params
    (area range "all" only, maxDets [100]), evaluate + accumulate."""
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = gt
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(detections)
        evaluator = COCOeval(coco_gt, coco_dt, "bbox")
        if matched_params:
            evaluator.params.areaRng = [list(AREA_ALL)]
            evaluator.params.areaRngLbl = ["all"]
            evaluator.params.maxDets = [MAX_DETECTIONS]
        evaluator.evaluate()
        evaluator.accumulate()
        if not matched_params:
            evaluator.summarize()
    return evaluator


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark, print a summary, optionally write JSON; returns the result dict."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the results as JSON to this path")
    parser.add_argument("--repeats", type=int, default=3, help="timed sweeps per method (best is reported)")
    parser.add_argument("--n-boot", type=int, default=1000, help="bootstrap resamples per rate")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    gt, frames = make_ground_truth(rng)
    detections_by_rate = {rate: make_detections(rng, frames, rate) for rate in RATES}
    n_detections = sum(len(d) for d in detections_by_rate.values())

    ours_times, direct_times, matched_times = [], [], []
    max_ap_difference = 0.0
    for _ in range(args.repeats):
        start = time.perf_counter()
        ours = {rate: evaluate(gt, detections) for rate, detections in detections_by_rate.items()}
        ours_times.append(time.perf_counter() - start)

        inputs = {
            rate: (copy.deepcopy(gt), copy.deepcopy(d)) for rate, d in detections_by_rate.items()
        }  # loadRes mutates
        start = time.perf_counter()
        direct = {rate: run_direct(*inputs[rate]) for rate in RATES}
        direct_times.append(time.perf_counter() - start)

        inputs = {rate: (copy.deepcopy(gt), copy.deepcopy(d)) for rate, d in detections_by_rate.items()}
        start = time.perf_counter()
        for rate in RATES:
            run_direct(*inputs[rate], matched_params=True)
        matched_times.append(time.perf_counter() - start)

    for rate in RATES:
        evaluator = direct[rate]
        for k, class_id in enumerate(evaluator.params.catIds):
            precision = evaluator.eval["precision"][:, :, k, 0, 2]
            max_ap_difference = max(
                max_ap_difference,
                abs(ours[rate][class_id].ap50 - precision[0].mean()),
                abs(ours[rate][class_id].ap50_95 - precision.mean()),
            )

    boot_rng = np.random.default_rng(args.seed + 1)
    start = time.perf_counter()
    intervals = {rate: bootstrap_ci(gt, d, args.n_boot, rng=boot_rng) for rate, d in detections_by_rate.items()}
    bootstrap_seconds = time.perf_counter() - start

    result = {
        "workload": {
            "rates": len(RATES),
            "frames_per_rate": N_FRAMES,
            "gt_boxes_per_rate": len(gt["annotations"]),
            "detections_total": n_detections,
            "detections_per_frame": n_detections / (len(RATES) * N_FRAMES),
        },
        "ours_evaluate_s": min(ours_times),
        "pycocotools_direct_s": min(direct_times),
        "ratio_ours_over_direct": min(ours_times) / min(direct_times),
        "pycocotools_same_params_s": min(matched_times),
        "ratio_ours_over_same_params": min(ours_times) / min(matched_times),
        "ours_evaluate_all_s": ours_times,
        "pycocotools_direct_all_s": direct_times,
        "bootstrap_s": bootstrap_seconds,
        "bootstrap_n_boot": args.n_boot,
        "bootstrap_s_per_rate": bootstrap_seconds / len(RATES),
        "max_abs_ap_difference_vs_direct": max_ap_difference,
        "example": {
            "car_ap50_rate0": ours[0.0][2].ap50,
            "car_ap50_rate0_ci": [intervals[0.0][2].low, intervals[0.0][2].high],
            "car_ap50_rate100": ours[100.0][2].ap50,
            "car_f1_rate0": ours[0.0][2].f1,
        },
        "environment": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "pycocotools": getattr(pycocotools, "__version__", "2.0.11"),
            "cpus": os.cpu_count(),
            "repeats": args.repeats,
        },
    }
    print(
        f"workload: {len(RATES)} rates x {N_FRAMES} frames, {len(gt['annotations'])} GT boxes/rate, "
        f"{result['workload']['detections_per_frame']:.1f} detections/frame"
    )
    print(f"ours (evaluate incl. F1):          {result['ours_evaluate_s']:.3f} s")
    print(f"pycocotools COCOeval direct:       {result['pycocotools_direct_s']:.3f} s")
    print(f"ratio ours / direct:               {result['ratio_ours_over_direct']:.3f}")
    print(
        f"pycocotools, our params, no F1:    {result['pycocotools_same_params_s']:.3f} s (ours / it: {result['ratio_ours_over_same_params']:.3f})"
    )
    print(f"bootstrap ({args.n_boot} resamples x 11 rates): {bootstrap_seconds:.3f} s")
    print(f"max |AP ours - AP direct|:         {max_ap_difference:.3g}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump(result, handle, indent=1)
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
