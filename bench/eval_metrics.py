"""Benchmark rainbench.eval.metrics: the numpy backend against pycocotools, and the bootstrap.

Workload at the paper's size: 11 rain rates x 200 frames, the paper's Table I instance mix per
rate (838 car, 350 person, 67 bicycle, 10 motorcycle = 1265 boxes over 200 frames), about
``--detections-per-frame`` (default 20) noisy detections per frame whose recall and localisation
degrade with the rate.

Timed, per full sweep of the 11 rates (best of --repeats sweeps, all in the same run):

- numpy: ``rainbench.eval.metrics.evaluation.evaluate(..., backend="numpy")`` (the default:
  validation, vectorised matching and accumulation, AP50/AP75/AP50-95 and the YOLO F1 part);
- pycocotools: the same call with ``backend="pycocotools"`` (``rainbench eval --metrics
  pycocotools``: COCO indexing and ``COCOeval`` with the same parameters) -- the target is
  numpy >= 5x faster than this;
- direct: the textbook pycocotools run on the same data (``COCO``, ``loadRes``, default-params
  ``COCOeval``: evaluate, accumulate, summarize), for continuity with earlier results;
- faster-coco-eval (when installed, ``pip install '.[bench]'``): ``COCOeval_faster`` with our
  parameters, evaluate + accumulate, no matches read back -- the candidate replacement that was
  measured and not adopted; its largest AP difference to pycocotools is reported too;
- bootstrap: ``bootstrap_ci`` AP50 and AP50:95 intervals (--n-boot resamples per rate and metric,
  as ``rainbench eval`` computes them) after (numpy backend, :func:`image_weighted_ap` over all
  resamples at once) and before (pycocotools matching and the per-resample loop rainbench used
  before, kept below as :func:`looped_interpolated_ap`); both draw the same resamples, so the
  intervals must be equal.

Equality checks (reported, not asserted): every figure of ``evaluate`` numpy vs pycocotools, AP50
and AP50-95 vs the textbook run, and the intervals before vs after.

Usage: ``python bench/eval_metrics.py [--json OUT] [--repeats 3] [--n-boot 1000] [--seed 0]
[--detections-per-frame 20] [--boot-repeats 1]``
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import datetime
import io
import json
import math
import os
import platform
import sys
import time

import numpy as np
import pycocotools
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from rainbench.eval.metrics.accumulate import RECALL_THRESHOLDS
from rainbench.eval.metrics.bootstrap import BootstrapCI, bootstrap_ci, bootstrap_weights
from rainbench.eval.metrics.coco import AREA_ALL, IOU_THRESHOLDS, MAX_DETECTIONS, coco_ground_truth, match_table
from rainbench.eval.metrics.evaluation import evaluate

RATES = tuple(float(r) for r in range(0, 101, 10))
N_FRAMES = 200
INSTANCES = {2: 838, 0: 350, 1: 67, 3: 10}  # the paper's Table I, class id -> instances
WIDTH, HEIGHT = 800, 600
BOOTSTRAP_METRICS = ("ap50", "ap50_95")


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


def make_detections(rng: np.random.Generator, frames, rate: float, per_frame: int) -> list[dict]:
    """About ``per_frame`` detections per frame: jittered hits (recall falls with the rate) plus
    background false positives."""
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
        for _ in range(max(0, per_frame - int(hits.sum()))):
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


def run_direct(gt: dict, detections: list[dict]) -> COCOeval:
    """pycocotools COCOeval run the textbook way: 4 area ranges, maxDets [1, 10, 100], evaluate +
    accumulate + summarize."""
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = gt
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(detections)
        evaluator = COCOeval(coco_gt, coco_dt, "bbox")
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    return evaluator


def run_faster_coco_eval(gt: dict, detections: list[dict]):
    """faster-coco-eval's ``COCOeval_faster`` with our parameters (area "all", maxDets 100, the four
    classes): evaluate + accumulate; returns it (``eval["precision"]`` as pycocotools')."""
    from faster_coco_eval import COCO as FasterCOCO
    from faster_coco_eval import COCOeval_faster

    coco_gt = FasterCOCO(gt)
    coco_dt = coco_gt.loadRes(detections)
    evaluator = COCOeval_faster(coco_gt, coco_dt, "bbox", print_function=lambda *args, **kwargs: None)
    evaluator.params.catIds = sorted(INSTANCES)
    evaluator.params.areaRng = [list(AREA_ALL)]
    evaluator.params.areaRngLbl = ["all"]
    evaluator.params.maxDets = [MAX_DETECTIONS]
    evaluator.evaluate()
    evaluator.accumulate()
    return evaluator


def looped_interpolated_ap(true_positive, ignored, det_weights, n_gt) -> np.ndarray:
    """The bootstrap's AP before issue 17, timed as "before": (T, D) bool ``true_positive`` and
    ``ignored``, (B, D) float64 ``det_weights``, (B,) float64 ``n_gt`` -> (B, T) AP, with one
    ``np.searchsorted`` per resample row and threshold."""
    n_thresholds = true_positive.shape[0]
    ap = np.full((len(det_weights), n_thresholds), np.nan)
    valid_rows = np.flatnonzero(n_gt > 0)
    if valid_rows.size == 0:
        return ap
    weights = det_weights[valid_rows]
    counts = n_gt[valid_rows][:, None]
    for t in range(n_thresholds):
        counted = ~ignored[t]
        tp_sum = np.cumsum(weights * (true_positive[t] & counted), axis=1)
        fp_sum = np.cumsum(weights * (~true_positive[t] & counted), axis=1)
        recall = tp_sum / counts
        precision = tp_sum / (fp_sum + tp_sum + np.spacing(1))
        envelope = np.maximum.accumulate(precision[:, ::-1], axis=1)[:, ::-1]
        envelope = np.concatenate([envelope, np.zeros((len(valid_rows), 1))], axis=1)
        for row in range(len(valid_rows)):
            indices = np.searchsorted(recall[row], RECALL_THRESHOLDS, side="left")
            ap[valid_rows[row], t] = envelope[row, indices].mean()
    return ap


def bootstrap_before(gt: dict, detections: list[dict], n_boot: int, rng: np.random.Generator,
                     metric: str) -> dict[int, BootstrapCI]:
    """``bootstrap_ci`` as it was before issue 17: pycocotools matching, then
    :func:`looped_interpolated_ap` in chunks of resamples (the same resamples and quantiles)."""
    matches = match_table(gt, detections, iou_thresholds=IOU_THRESHOLDS[:1] if metric == "ap50" else IOU_THRESHOLDS,
                          backend="pycocotools")
    image_weights = bootstrap_weights(N_FRAMES, n_boot, rng).astype(np.float64)
    result = {}
    for class_id, match in matches.items():
        ones = np.ones((1, len(match.scores)))
        n_gt_total = np.array([match.n_gt_per_image.sum()], float)
        point = float(looped_interpolated_ap(match.true_positive, match.ignored, ones, n_gt_total).mean())
        n_gt = image_weights @ match.n_gt_per_image.astype(np.float64)
        values = np.empty(n_boot)
        chunk = max(1, 2_000_000 // max(1, len(match.scores)))
        for start in range(0, n_boot, chunk):
            rows = slice(start, start + chunk)
            det_weights = image_weights[rows][:, match.image_index]
            values[rows] = looped_interpolated_ap(match.true_positive, match.ignored, det_weights,
                                                  n_gt[rows]).mean(axis=1)
        valid = values[~np.isnan(values)]
        low, high = np.quantile(valid, [0.025, 0.975]) if valid.size else (math.nan, math.nan)
        result[class_id] = BootstrapCI(class_id=class_id, metric=metric, point=point, low=float(low),
                                       high=float(high), alpha=0.05, n_boot=n_boot, n_valid=int(valid.size))
    return result


def best_sweep_seconds(sweep, repeats: int) -> tuple[float, list[float], object]:
    """(best seconds, all seconds, result of the last sweep) of ``repeats`` calls of ``sweep()``."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = sweep()
        times.append(time.perf_counter() - start)
    return min(times), times, result


def largest_difference(first, second) -> float:
    """Largest |a - b| over the float fields of two ``{rate: {class: dataclass}}`` results (nan
    against nan counts 0; nan against a number counts inf)."""
    largest = 0.0
    for rate, per_class in first.items():
        for class_id, value in per_class.items():
            other = second[rate][class_id]
            for name in value.__dataclass_fields__:
                a, b = getattr(value, name), getattr(other, name)
                if isinstance(a, float):
                    if math.isnan(a) or math.isnan(b):
                        largest = max(largest, 0.0 if math.isnan(a) and math.isnan(b) else math.inf)
                    else:
                        largest = max(largest, abs(a - b))
    return largest


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark, print a summary, optionally write JSON; returns the result dict."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", help="write the results as JSON to this path")
    parser.add_argument("--repeats", type=int, default=3, help="timed sweeps per method (best is reported)")
    parser.add_argument("--boot-repeats", type=int, default=1, help="timed bootstrap sweeps (best is reported)")
    parser.add_argument("--n-boot", type=int, default=1000, help="bootstrap resamples per rate and metric")
    parser.add_argument("--detections-per-frame", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    gt, frames = make_ground_truth(rng)
    detections_by_rate = {rate: make_detections(rng, frames, rate, args.detections_per_frame) for rate in RATES}
    n_detections = sum(len(d) for d in detections_by_rate.values())

    def sweep(backend):
        return lambda: {rate: evaluate(gt, dets, backend=backend) for rate, dets in detections_by_rate.items()}

    numpy_s, numpy_all, ours = best_sweep_seconds(sweep("numpy"), args.repeats)
    reference_s, reference_all, reference = best_sweep_seconds(sweep("pycocotools"), args.repeats)
    direct_times, direct = [], {}
    for _ in range(args.repeats):
        # loadRes mutates its inputs
        inputs = {rate: (copy.deepcopy(gt), copy.deepcopy(d)) for rate, d in detections_by_rate.items()}
        start = time.perf_counter()
        direct = {rate: run_direct(*inputs[rate]) for rate in RATES}
        direct_times.append(time.perf_counter() - start)
    direct_s = min(direct_times)
    max_direct_difference = 0.0
    for rate in RATES:
        evaluator = direct[rate]
        for k, class_id in enumerate(evaluator.params.catIds):
            precision = evaluator.eval["precision"][:, :, k, 0, 2]
            max_direct_difference = max(max_direct_difference, abs(ours[rate][class_id].ap50 - precision[0].mean()),
                                        abs(ours[rate][class_id].ap50_95 - precision.mean()))

    faster = None
    try:
        import faster_coco_eval
    except ImportError:
        faster_coco_eval = None
    if faster_coco_eval is not None:
        faster_times, largest = [], 0.0
        for _ in range(args.repeats):
            inputs = {rate: (copy.deepcopy(gt), copy.deepcopy(d)) for rate, d in detections_by_rate.items()}
            start = time.perf_counter()
            evaluated = {rate: run_faster_coco_eval(*inputs[rate]) for rate in RATES}
            faster_times.append(time.perf_counter() - start)
        for rate, evaluator in evaluated.items():
            for k, class_id in enumerate(sorted(INSTANCES)):
                precision = np.asarray(evaluator.eval["precision"])[:, :, k, 0, 0]
                largest = max(largest, abs(reference[rate][class_id].ap50 - precision[0].mean()),
                              abs(reference[rate][class_id].ap50_95 - precision.mean()))
        faster = {"version": faster_coco_eval.__version__, "s": min(faster_times),
                  "ratio_pycocotools_over_it": reference_s / min(faster_times),
                  "max_abs_ap_difference_vs_pycocotools": largest}

    def bootstrap_sweep(run):
        def go():
            boot_rng = np.random.default_rng(args.seed + 1)
            return {(rate, metric): run(gt, dets, args.n_boot, boot_rng, metric)
                    for rate, dets in detections_by_rate.items() for metric in BOOTSTRAP_METRICS}
        return go

    after_s, after_all, after = best_sweep_seconds(
        bootstrap_sweep(lambda g, d, n, r, m: bootstrap_ci(g, d, n, rng=r, metric=m)), args.boot_repeats)
    after_reference_s, _, after_reference = best_sweep_seconds(
        bootstrap_sweep(lambda g, d, n, r, m: bootstrap_ci(g, d, n, rng=r, metric=m, backend="pycocotools")),
        args.boot_repeats)
    before_s, before_all, before = best_sweep_seconds(bootstrap_sweep(bootstrap_before), args.boot_repeats)

    result = {
        "date": datetime.date.today().isoformat(),
        "workload": {
            "rates": len(RATES),
            "frames_per_rate": N_FRAMES,
            "gt_boxes_per_rate": len(gt["annotations"]),
            "detections_total": n_detections,
            "detections_per_frame": n_detections / (len(RATES) * N_FRAMES),
        },
        "numpy_evaluate_s": numpy_s,
        "pycocotools_evaluate_s": reference_s,
        "ratio_pycocotools_over_numpy": reference_s / numpy_s,
        "pycocotools_direct_s": direct_s,
        "ratio_direct_over_numpy": direct_s / numpy_s,
        "numpy_evaluate_all_s": numpy_all,
        "pycocotools_evaluate_all_s": reference_all,
        "pycocotools_direct_all_s": direct_times,
        "max_abs_difference_numpy_vs_pycocotools": largest_difference(ours, reference),
        "max_abs_ap_difference_numpy_vs_direct": max_direct_difference,
        "faster_coco_eval": faster,
        "bootstrap": {
            "n_boot": args.n_boot,
            "metrics": list(BOOTSTRAP_METRICS),
            "after_s": after_s,
            "after_pycocotools_matching_s": after_reference_s,
            "before_s": before_s,
            "ratio_before_over_after": before_s / after_s,
            "after_all_s": after_all,
            "before_all_s": before_all,
            "max_abs_difference_before_vs_after": max(largest_difference({0: after[key]}, {0: before[key]})
                                                      for key in after),
            "max_abs_difference_after_backends": max(largest_difference({0: after[key]}, {0: after_reference[key]})
                                                     for key in after),
        },
        "example": {
            "car_ap50_rate0": ours[0.0][2].ap50,
            "car_ap50_rate0_ci": [after[(0.0, "ap50")][2].low, after[(0.0, "ap50")][2].high],
            "car_ap50_rate100": ours[100.0][2].ap50,
            "car_f1_rate0": ours[0.0][2].f1,
        },
        "environment": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "pycocotools": getattr(pycocotools, "__version__", "2.0.11"),
            "cpus": os.cpu_count(),
            "load_average": os.getloadavg(),
            "repeats": args.repeats,
        },
    }
    boot = result["bootstrap"]
    print(
        f"workload: {len(RATES)} rates x {N_FRAMES} frames, {len(gt['annotations'])} GT boxes/rate, "
        f"{result['workload']['detections_per_frame']:.1f} detections/frame"
    )
    print(f"evaluate, numpy backend:           {numpy_s:.3f} s")
    print(f"evaluate, pycocotools backend:     {reference_s:.3f} s  (pycocotools / numpy: "
          f"{result['ratio_pycocotools_over_numpy']:.2f}x, target >= 5x)")
    print(f"pycocotools COCOeval direct:       {direct_s:.3f} s  "
          f"(direct / numpy: {result['ratio_direct_over_numpy']:.2f}x)")
    if faster is not None:
        print(f"faster-coco-eval {faster['version']}:           {faster['s']:.3f} s  (pycocotools backend / it: "
              f"{faster['ratio_pycocotools_over_it']:.2f}x; max |AP - pycocotools| "
              f"{faster['max_abs_ap_difference_vs_pycocotools']:.3g})")
    print(f"max |figure numpy - pycocotools|:  {result['max_abs_difference_numpy_vs_pycocotools']:.3g}")
    print(f"max |AP numpy - direct|:           {max_direct_difference:.3g}")
    print(f"bootstrap AP50 + AP50:95 CIs ({args.n_boot} resamples x 11 rates): after {after_s:.3f} s "
          f"(pycocotools matching {after_reference_s:.3f} s), before {before_s:.3f} s: "
          f"{boot['ratio_before_over_after']:.2f}x; max |CI after - before| "
          f"{boot['max_abs_difference_before_vs_after']:.3g}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as handle:
            json.dump(result, handle, indent=1)
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
