"""Tests of rainbench.eval.metrics: COCO AP via pycocotools, YOLO F1, robustness, bootstrap."""

from __future__ import annotations

import contextlib
import copy
import io
import math

import numpy as np
import pytest
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from rainbench.eval.metrics.accumulate import RECALL_THRESHOLDS, image_weighted_ap, interpolated_ap
from rainbench.eval.metrics.bootstrap import bootstrap_ci, bootstrap_weights, resample_images, robustness_intervals
from rainbench.eval.metrics.breakdown import SIZE_RANGES, ap_by_size, ap_by_visibility
from rainbench.eval.metrics.coco import (AREA_ALL, METRICS_BACKENDS, coco_detections, coco_ground_truth, match_table,
                                         run_cocoeval)
from rainbench.eval.metrics.evaluation import evaluate
from rainbench.eval.metrics.f1 import pr_confidence_curves
from rainbench.eval.metrics.robustness import half_value_rate, mpc, percent_drop, rpc
from rainbench.store.classes import PAPER_CLASS_NAMES, PAPER_CLASSES

PERSON, BICYCLE, CAR, MOTORCYCLE = 0, 1, 2, 3


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def direct_cocoeval(gt_dict, detections):
    """pycocotools run the textbook way: COCO + loadRes + default-params COCOeval (bbox)."""
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = COCO()
        coco_gt.dataset = copy.deepcopy(gt_dict)
        coco_gt.createIndex()
        coco_dt = coco_gt.loadRes(copy.deepcopy(list(detections)))
        evaluator = COCOeval(coco_gt, coco_dt, "bbox")
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    return evaluator


def direct_ap(evaluator, class_id, area_index=0):
    """(ap50, ap50_95) of one class from a default-params COCOeval (maxDets index 2 = 100)."""
    k = list(evaluator.params.catIds).index(class_id)
    precision = evaluator.eval["precision"][:, :, k, area_index, 2]
    if np.all(precision == -1):
        return math.nan, math.nan
    return float(precision[0].mean()), float(precision.mean())


def det(image_id, class_id, xyxy, score):
    """One COCO results record from an xyxy box."""
    x1, y1, x2, y2 = xyxy
    return {"image_id": image_id, "category_id": class_id, "bbox": [x1, y1, x2 - x1, y2 - y1], "score": score}


def box_row(i):
    """A 10x10 box in row i (disjoint boxes, IoU 0 with each other)."""
    return [20.0 * i, 0.0, 20.0 * i + 10.0, 10.0]


def synthetic_set(rng, n_images, mean_objects=6.0, recall=0.8, n_false=4, with_ignore=False):
    """Random frames with noisy detections: (gt_dict, detections)."""
    images, detections = [], []
    for image_id in range(1, n_images + 1):
        n = int(rng.poisson(mean_objects))
        xy = rng.uniform(0, 600, (n, 2))
        wh = rng.uniform(8, 160, (n, 2))
        boxes = np.concatenate([xy, xy + wh], axis=1).astype(np.float32)
        classes = rng.choice(4, size=n, p=[0.28, 0.06, 0.63, 0.03])
        ignore = (rng.random(n) < 0.08) if with_ignore else np.zeros(n, dtype=bool)
        images.append((image_id, 800, 600, boxes, classes, ignore))
        for box, class_id in zip(boxes.astype(np.float64), classes, strict=True):
            if rng.random() < recall:
                size = np.r_[box[2] - box[0], box[3] - box[1]]
                jitter = rng.normal(0, 0.1, 4) * np.r_[size, size]
                new = box + jitter
                new[2:] = np.maximum(new[2:], new[:2] + 1)
                label = int(class_id) if rng.random() < 0.9 else int(rng.integers(4))
                detections.append(det(image_id, label, new.tolist(), float(rng.uniform(0.15, 1.0))))
        for _ in range(int(rng.poisson(n_false))):
            x, y = rng.uniform(0, 700, 2)
            w, h = rng.uniform(5, 90, 2)
            detections.append(det(image_id, int(rng.integers(4)), [x, y, x + w, y + h], float(rng.uniform(0.0, 0.8))))
    return coco_ground_truth(images), detections


# --------------------------------------------------------------------------------------------
# ground truth building
# --------------------------------------------------------------------------------------------


def test_coco_ground_truth_layout():
    gt = coco_ground_truth(
        [
            (
                1,
                800,
                600,
                np.array([[10, 20, 40, 60], [0, 0, 5, 5]], np.float32),
                np.array([CAR, PERSON]),
                np.array([False, True]),
            ),
            (2, 800, 600, np.zeros((0, 4), np.float32), np.zeros(0, np.int64)),
        ]
    )
    assert [c["id"] for c in gt["categories"]] == [0, 1, 2, 3]
    assert [c["name"] for c in gt["categories"]] == list(PAPER_CLASS_NAMES)
    assert [img["id"] for img in gt["images"]] == [1, 2]
    first, second = gt["annotations"]
    assert first == {
        "id": 1,
        "image_id": 1,
        "category_id": CAR,
        "bbox": [10.0, 20.0, 30.0, 40.0],
        "area": 1200.0,
        "iscrowd": 0,
        "ignore": 0,
    }
    assert (second["id"], second["category_id"], second["iscrowd"], second["ignore"]) == (2, PERSON, 1, 1)


def test_coco_detections_converts_xyxy_to_xywh():
    records = coco_detections(3, np.array([[10, 20, 40, 60]], np.float32), np.array([0.5]), np.array([CAR]))
    assert records == [{"image_id": 3, "category_id": CAR, "bbox": [10.0, 20.0, 30.0, 40.0], "score": 0.5}]
    assert coco_detections(3, np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64)) == []


# --------------------------------------------------------------------------------------------
# AP against known answers and against pycocotools
# --------------------------------------------------------------------------------------------


def test_perfect_predictions_give_ap_one():
    boxes = np.array([box_row(i) for i in range(4)], np.float32)
    classes = np.array([PERSON, BICYCLE, CAR, MOTORCYCLE])
    gt = coco_ground_truth([(1, 100, 100, boxes, classes), (2, 100, 100, boxes, classes[::-1].copy())])
    detections = coco_detections(1, boxes, np.full(4, 0.9), classes) + coco_detections(
        2, boxes, np.full(4, 0.8), classes[::-1].copy()
    )
    result = evaluate(gt, detections)
    for class_id in PAPER_CLASSES:
        metrics = result[class_id]
        assert (metrics.n_gt, metrics.n_det) == (2, 2)
        assert (metrics.ap50, metrics.ap75, metrics.ap50_95) == pytest.approx((1.0, 1.0, 1.0), abs=1e-12)
        assert metrics.precision == pytest.approx(1.0)
        assert metrics.recall == pytest.approx(1.0)
        assert metrics.f1 == pytest.approx(1.0)
        assert (metrics.precision_at_conf, metrics.recall_at_conf, metrics.f1_at_conf) == (1.0, 1.0, 1.0)


# Three cars over two images. Ranked detections and their COCO 101-point AP by hand:
#   TP FP TP FP    -> PR points (1/3, 1) (1/3, .5) (2/3, 2/3) (2/3, .5); recall thresholds
#                     0.00..0.33 (34) take 1, 0.34..0.66 (33) take 2/3, 0.67..1.00 (34) take 0
#                     -> (34 + 33 * 2/3) / 101 = 56 / 101
#   TP FP TP FP TP -> adds (1, .6): the last 34 thresholds take 0.6 -> (34 + 22 + 20.4) / 101
@pytest.mark.parametrize(
    ("outcomes", "expected"),
    [(("tp", "fp", "tp", "fp"), 56 / 101), (("tp", "fp", "tp", "fp", "tp"), 76.4 / 101), (("fp", "fp"), 0.0)],
)
def test_hand_made_pr_curve(outcomes, expected):
    gt = coco_ground_truth(
        [
            (1, 200, 100, np.array([box_row(0), box_row(1)], np.float32), np.array([CAR, CAR])),
            (2, 200, 100, np.array([box_row(0)], np.float32), np.array([CAR])),
            (3, 200, 100, np.zeros((0, 4), np.float32), np.zeros(0, np.int64)),
        ]
    )
    gt_slots = iter([(1, box_row(0)), (2, box_row(0)), (1, box_row(1))])
    detections = []
    for rank, outcome in enumerate(outcomes):
        score = 0.9 - 0.1 * rank
        if outcome == "tp":
            image_id, box = next(gt_slots)
        else:
            image_id, box = 1 + rank % 3, box_row(5 + rank)
        detections.append(det(image_id, CAR, box, score))
    metrics = evaluate(gt, detections)[CAR]
    assert metrics.ap50 == pytest.approx(expected, abs=1e-12)
    assert metrics.ap50_95 == pytest.approx(expected, abs=1e-12)  # TPs are exact boxes, FPs miss entirely
    assert metrics.n_gt == 3


def test_ap_over_iou_thresholds_with_known_iou():
    # IoU = 72 / 100 = 0.72: a TP at 0.50..0.70 (5 thresholds), a miss at 0.75..0.95 (5).
    gt = coco_ground_truth([(1, 100, 100, np.array([[0, 0, 10, 10]], np.float32), np.array([PERSON]))])
    metrics = evaluate(gt, [det(1, PERSON, [0, 0, 10, 7.2], 0.7)])[PERSON]
    assert (metrics.ap50, metrics.ap75) == pytest.approx((1.0, 0.0), abs=1e-12)
    assert metrics.ap50_95 == pytest.approx(0.5, abs=1e-12)


@pytest.mark.parametrize("with_ignore", [False, True])
def test_matches_pycocotools_on_noisy_predictions(with_ignore):
    gt, detections = synthetic_set(np.random.default_rng(7), 120, with_ignore=with_ignore)
    reference = direct_cocoeval(gt, detections)
    result = evaluate(gt, detections)
    for class_id in PAPER_CLASSES:
        ap50, ap50_95 = direct_ap(reference, class_id)
        assert result[class_id].ap50 == pytest.approx(ap50, abs=1e-4)
        assert result[class_id].ap50_95 == pytest.approx(ap50_95, abs=1e-4)
        assert 0.0 < result[class_id].ap50 < 1.0


def test_max_detections_per_image_is_100():
    # 150 car detections in one image: 50 false positives scored highest, then 100 true positives.
    # COCO keeps the top 100 per image and class, so only 50 of the TPs count.
    n = 100
    boxes = np.array(
        [[20.0 * (i % 40), 20.0 * (i // 40), 20.0 * (i % 40) + 10, 20.0 * (i // 40) + 10] for i in range(n)], np.float32
    )
    gt = coco_ground_truth([(1, 1000, 1000, boxes, np.full(n, CAR))])
    false_positives = [
        det(1, CAR, [900.0, 900.0 + 0.5 * i, 905.0, 901.0 + 0.5 * i], 0.99 - 0.001 * i) for i in range(50)
    ]
    true_positives = [det(1, CAR, box.tolist(), 0.5 - 0.001 * i) for i, box in enumerate(boxes)]
    detections = false_positives + true_positives
    result = evaluate(gt, detections)[CAR]
    assert result.n_det == 100
    assert result.ap50 == pytest.approx(direct_ap(direct_cocoeval(gt, detections), CAR)[0], abs=1e-12)
    assert result.recall_at_conf == pytest.approx(0.5)


def test_image_subset_matches_pycocotools_restricted():
    gt, detections = synthetic_set(np.random.default_rng(8), 60)
    subset = list(range(1, 61, 2))
    sub_gt = {**gt, "images": [img for img in gt["images"] if img["id"] in subset]}
    sub_gt["annotations"] = [ann for ann in gt["annotations"] if ann["image_id"] in subset]
    sub_dets = [d for d in detections if d["image_id"] in subset]
    reference = direct_cocoeval(sub_gt, sub_dets)
    result = evaluate(gt, detections, image_ids=subset)
    for class_id in (PERSON, CAR):
        assert result[class_id].ap50 == pytest.approx(direct_ap(reference, class_id)[0], abs=1e-12)


def test_category_zero_goes_through_load_res():
    # Person is COCO category 0; check loadRes + COCOeval see it like any other id.
    gt, detections = synthetic_set(np.random.default_rng(9), 40)
    person_only = [d for d in detections if d["category_id"] == PERSON]
    reference = direct_cocoeval(gt, person_only)
    result = evaluate(gt, person_only)
    assert result[PERSON].ap50 == pytest.approx(direct_ap(reference, PERSON)[0], abs=1e-12)
    assert result[PERSON].ap50 > 0.3
    assert result[CAR].ap50 == 0.0 and result[CAR].n_det == 0


def test_empty_detections_and_class_without_ground_truth():
    gt = coco_ground_truth(
        [
            (1, 100, 100, np.array([box_row(0), box_row(1)], np.float32), np.array([CAR, PERSON])),
            (2, 100, 100, np.zeros((0, 4)), np.zeros(0, int)),
        ]
    )
    result = evaluate(gt, [])
    assert (result[CAR].ap50, result[CAR].ap50_95, result[CAR].n_det) == (0.0, 0.0, 0)
    assert (result[CAR].precision, result[CAR].recall, result[CAR].f1) == (0.0, 0.0, 0.0)
    assert (result[CAR].precision_at_conf, result[CAR].recall_at_conf, result[CAR].f1_at_conf) == (0.0, 0.0, 0.0)
    assert math.isnan(result[BICYCLE].ap50) and math.isnan(result[BICYCLE].f1) and result[BICYCLE].n_gt == 0
    # A class without ground truth but with (false) detections stays nan; others unaffected.
    with_fp = evaluate(gt, [det(2, BICYCLE, box_row(3), 0.9), det(1, CAR, box_row(0), 0.8)])
    assert math.isnan(with_fp[BICYCLE].ap50) and with_fp[BICYCLE].n_det == 1
    assert with_fp[CAR].ap50 == pytest.approx(1.0, abs=1e-12)


def test_ignored_ground_truth_is_neither_false_negative_nor_false_positive():
    boxes = np.array([box_row(0), [40, 0, 44, 4]], np.float32)
    gt = coco_ground_truth([(1, 100, 100, boxes, np.array([CAR, CAR]), np.array([False, True]))])
    only_real = evaluate(gt, [det(1, CAR, box_row(0), 0.5)])[CAR]
    assert (only_real.n_gt, only_real.recall_at_conf) == (1, 1.0)
    assert only_real.ap50 == pytest.approx(1.0, abs=1e-12)
    # A higher-scored detection on the ignored box would be an FP ranked first (AP 0.5) if counted.
    both = evaluate(gt, [det(1, CAR, box_row(0), 0.5), det(1, CAR, [40, 0, 44, 4], 0.9)])[CAR]
    assert both.precision_at_conf == 1.0
    assert both.ap50 == pytest.approx(1.0, abs=1e-12)


def test_inputs_are_not_mutated():
    gt, detections = synthetic_set(np.random.default_rng(10), 10)
    gt_before, detections_before = copy.deepcopy(gt), copy.deepcopy(detections)
    evaluate(gt, detections)
    bootstrap_ci(gt, detections, 5, rng=np.random.default_rng(0))
    assert gt == gt_before and detections == detections_before


# --------------------------------------------------------------------------------------------
# F1 (YOLO convention)
# --------------------------------------------------------------------------------------------


def test_f1_best_confidence_flat_optimum():
    # car: 2 GT found at 0.9 and 0.6; person: 2 GT, one found at 0.7; bicycle: 1 GT never found.
    # Every curve is at its best for conf <= 0.6, so the smoothed mean-F1 argmax is grid point 0.
    gt = coco_ground_truth(
        [
            (
                1,
                200,
                100,
                np.array([box_row(0), box_row(1), box_row(2), box_row(3), box_row(4)], np.float32),
                np.array([CAR, CAR, PERSON, PERSON, BICYCLE]),
            ),
        ]
    )
    detections = [det(1, CAR, box_row(0), 0.9), det(1, CAR, box_row(1), 0.6), det(1, PERSON, box_row(2), 0.7)]
    result = evaluate(gt, detections, class_ids=(CAR, PERSON, BICYCLE))
    assert result[CAR].best_conf == 0.0
    assert (result[CAR].precision, result[CAR].recall, result[CAR].f1) == pytest.approx((1.0, 1.0, 1.0))
    assert (result[PERSON].precision, result[PERSON].recall, result[PERSON].f1) == pytest.approx((1.0, 0.5, 2 / 3))
    assert (result[BICYCLE].precision, result[BICYCLE].recall, result[BICYCLE].f1) == (0.0, 0.0, 0.0)


def test_f1_best_confidence_interior_optimum():
    # One GT, a TP at 0.9 and an FP at 0.1. Recall is 1 up to 0.9 and 0 above; precision rises
    # linearly from 0.5 (conf 0.1) to 1 (conf 0.9). F1 rises up to grid point 899 (0.8999) and is
    # 0 from 900 on, so the 101-tap box filter peaks with its right edge on 899: centre 849.
    gt = coco_ground_truth([(1, 100, 100, np.array([box_row(0)], np.float32), np.array([CAR]))])
    metrics = evaluate(gt, [det(1, CAR, box_row(0), 0.9), det(1, CAR, box_row(3), 0.1)], class_ids=(CAR,))[CAR]
    best = 849 / 999
    expected_precision = 1 - 0.5 * (0.9 - best) / 0.8
    assert metrics.best_conf == pytest.approx(best, abs=1e-12)
    assert metrics.recall == pytest.approx(1.0)
    assert metrics.precision == pytest.approx(expected_precision, abs=1e-9)
    assert metrics.f1 == pytest.approx(2 * expected_precision / (1 + expected_precision), abs=1e-9)


def test_f1_at_fixed_confidence_counts():
    gt = coco_ground_truth([(1, 200, 100, np.array([box_row(i) for i in range(3)], np.float32), np.array([CAR] * 3))])
    detections = [
        det(1, CAR, box_row(0), 0.9),
        det(1, CAR, box_row(7), 0.8),
        det(1, CAR, box_row(1), 0.3),
        det(1, CAR, box_row(2), 0.2),
    ]
    at_025 = evaluate(gt, detections, conf=0.25)[CAR]
    assert (at_025.precision_at_conf, at_025.recall_at_conf, at_025.f1_at_conf) == pytest.approx((2 / 3, 2 / 3, 2 / 3))
    at_085 = evaluate(gt, detections, conf=0.85)[CAR]
    assert (at_085.precision_at_conf, at_085.recall_at_conf, at_085.f1_at_conf) == pytest.approx((1.0, 1 / 3, 0.5))
    assert at_085.conf == 0.85


def test_f1_matches_ultralytics_ap_per_class(monkeypatch, tmp_path):
    monkeypatch.setenv("YOLO_CONFIG_DIR", str(tmp_path))  # keep ultralytics' settings file out of $HOME
    monkeypatch.setenv("YOLO_OFFLINE", "1")
    import ultralytics.utils.metrics as ultralytics_metrics  # a dependency: never skipped
    gt, detections = synthetic_set(np.random.default_rng(11), 80)
    result = evaluate(gt, detections)
    matches = match_table(gt, detections)
    tp, conf, pred_cls, target_cls = [], [], [], []
    for class_id, match in matches.items():
        kept = ~match.ignored[0]
        tp.append(match.true_positive[:, kept].T)
        conf.append(match.scores[kept])
        pred_cls.append(np.full(kept.sum(), class_id))
        target_cls.append(np.full(match.n_gt_per_image.sum(), class_id))
    out = ultralytics_metrics.ap_per_class(
        np.concatenate(tp), np.concatenate(conf), np.concatenate(pred_cls), np.concatenate(target_cls)
    )
    precision, recall, f1, classes = out[2], out[3], out[4], out[6]
    for i, class_id in enumerate(classes):
        assert result[int(class_id)].precision == pytest.approx(precision[i], abs=1e-9)
        assert result[int(class_id)].recall == pytest.approx(recall[i], abs=1e-9)
        assert result[int(class_id)].f1 == pytest.approx(f1[i], abs=1e-9)


# --------------------------------------------------------------------------------------------
# breakdowns
# --------------------------------------------------------------------------------------------


def test_ap_by_size_matches_pycocotools_area_ranges():
    gt, detections = synthetic_set(np.random.default_rng(12), 100)
    reference = direct_cocoeval(gt, detections)
    result = ap_by_size(gt, detections)
    for area_index, size in enumerate(("small", "medium", "large"), start=1):
        for class_id in (PERSON, CAR):
            ap50, ap50_95 = direct_ap(reference, class_id, area_index)
            assert result[size][class_id].ap50 == pytest.approx(ap50, abs=1e-12)
            assert result[size][class_id].ap50_95 == pytest.approx(ap50_95, abs=1e-12)
    n_cars = sum(1 for ann in gt["annotations"] if ann["category_id"] == CAR)
    assert sum(result[size][CAR].n_gt for size in SIZE_RANGES) == n_cars


@pytest.mark.parametrize(("unmatched", "expected"), [("fp", 0.5), ("ignore", 1.0)])
def test_ap_by_visibility_hand_made(unmatched, expected):
    # Car A visible 0.9, car B visible 0.1. Detections: background FP 0.95, A 0.9, B 0.5.
    # Per bin, the other car's detection is ignored; the FP ranks first when it counts.
    gt = coco_ground_truth([(1, 200, 100, np.array([box_row(0), box_row(1)], np.float32), np.array([CAR, CAR]))])
    detections = [det(1, CAR, box_row(6), 0.95), det(1, CAR, box_row(0), 0.9), det(1, CAR, box_row(1), 0.5)]
    result = ap_by_visibility(
        gt, detections, np.array([0.9, 0.1]), bins=(0.0, 0.5, 1.0), unmatched=unmatched, class_ids=(CAR,)
    )
    assert list(result) == ["0.00-0.50", "0.50-1.00"]
    for label in result:
        assert result[label][CAR].n_gt == 1
        assert result[label][CAR].ap50 == pytest.approx(expected, abs=1e-12)


def test_ap_by_visibility_edges_and_nan():
    gt = coco_ground_truth([(1, 200, 100, np.array([box_row(i) for i in range(4)], np.float32), np.array([CAR] * 4))])
    result = ap_by_visibility(gt, [], np.array([0.0, 0.5, 1.0, np.nan]), bins=(0.0, 0.5, 1.0), class_ids=(CAR,))
    assert [result[label][CAR].n_gt for label in result] == [1, 2]  # 0.5 -> upper bin, 1.0 -> last bin, nan -> none


# --------------------------------------------------------------------------------------------
# robustness arithmetic
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("clean", "rainy", "drop"), [(0.669, 0.46, 31.24), (0.652, 0.452, 30.67), (0.64, 0.424, 33.75)]
)
def test_percent_drop_reproduces_paper_numbers(clean, rainy, drop):
    assert percent_drop(clean, rainy) == pytest.approx(drop, abs=0.005)


def test_percent_drop_edge_cases():
    assert percent_drop(0.5, 0.25) == 50.0
    assert percent_drop(0.5, 0.75) == -50.0
    assert math.isnan(percent_drop(0.0, 0.1))
    assert math.isnan(percent_drop(float("nan"), 0.1))
    np.testing.assert_array_equal(
        percent_drop(np.array([1.0, 0.0, 0.8]), np.array([0.5, 0.0, 0.2])), [50.0, np.nan, 75.0]
    )


def test_mpc_and_rpc():
    values = {0.0: 0.8, 10.0: 0.6, 20.0: 0.4, 30.0: 0.5}
    assert mpc(values) == pytest.approx(0.5)
    assert rpc(values) == pytest.approx(0.625)
    assert math.isnan(rpc({0.0: 0.0, 10.0: 0.3}))
    with pytest.raises(ValueError, match=r"expected at least one rate > 0 mm/h, got \[0.0\]"):
        mpc({0.0: 0.8})
    with pytest.raises(ValueError, match=r"expected exactly one rate 0 \(clean\), got rates \[10.0, 20.0\]"):
        rpc({10.0: 0.6, 20.0: 0.4})
    with pytest.raises(ValueError, match=r"expected finite rates >= 0 mm/h, got \[-10.0, 0.0\]"):
        mpc({-10.0: 0.6, 0.0: 0.4})


# --------------------------------------------------------------------------------------------
# bootstrap
# --------------------------------------------------------------------------------------------


def test_fast_ap_equals_cocoeval_on_original_data():
    gt, detections = synthetic_set(np.random.default_rng(13), 100, with_ignore=True)
    reference = direct_cocoeval(gt, detections)
    matches = match_table(gt, detections)
    for class_id, match in matches.items():
        fast = interpolated_ap(
            match.true_positive,
            match.ignored,
            np.ones((1, len(match.scores))),
            np.array([match.n_gt_per_image.sum()], float),
        )
        k = list(reference.params.catIds).index(class_id)
        expected = reference.eval["precision"][:, :, k, 0, 2].mean(axis=1)
        np.testing.assert_allclose(fast[0], expected, rtol=0, atol=1e-12)


def test_fast_ap_on_resample_with_duplicates_equals_cocoeval_on_reidentified_copies():
    rng = np.random.default_rng(14)
    gt, detections = synthetic_set(rng, 60)
    matches = match_table(gt, detections)
    image_ids = next(iter(matches.values())).image_ids
    for _ in range(3):
        weights = bootstrap_weights(len(image_ids), 1, rng)[0]
        assert weights.max() >= 2  # duplicates present
        sample = np.repeat(image_ids, weights).tolist()
        resampled_gt, resampled_dets = resample_images(gt, detections, sample)
        reference = direct_cocoeval(resampled_gt, resampled_dets)
        for class_id, match in matches.items():
            fast = interpolated_ap(
                match.true_positive,
                match.ignored,
                weights[match.image_index][None, :].astype(float),
                np.array([weights @ match.n_gt_per_image], float),
            )
            k = list(reference.params.catIds).index(class_id)
            precision = reference.eval["precision"][:, :, k, 0, 2]
            expected = np.full(10, np.nan) if np.all(precision == -1) else precision.mean(axis=1)
            np.testing.assert_allclose(fast[0], expected, rtol=0, atol=1e-12)


def test_resample_images_reidentifies_copies():
    gt = coco_ground_truth(
        [
            (5, 100, 100, np.array([box_row(0)], np.float32), np.array([CAR])),
            (9, 100, 100, np.zeros((0, 4)), np.zeros(0, int)),
        ]
    )
    new_gt, new_dets = resample_images(gt, [det(5, CAR, box_row(0), 0.5)], [5, 5, 9])
    assert [img["id"] for img in new_gt["images"]] == [1, 2, 3]
    assert [(ann["id"], ann["image_id"]) for ann in new_gt["annotations"]] == [(1, 1), (2, 2)]
    assert [d["image_id"] for d in new_dets] == [1, 2]


def test_bootstrap_weights_rows_are_resamples():
    weights = bootstrap_weights(7, 50, np.random.default_rng(0))
    assert weights.shape == (50, 7) and weights.dtype == np.int64
    assert np.all(weights.sum(axis=1) == 7)


def test_bootstrap_ci_contains_point_and_is_deterministic():
    gt, detections = synthetic_set(np.random.default_rng(15), 100)
    first = bootstrap_ci(gt, detections, 200, rng=np.random.default_rng(3))
    again = bootstrap_ci(gt, detections, 200, rng=np.random.default_rng(3))
    other = bootstrap_ci(gt, detections, 200, rng=np.random.default_rng(4))
    evaluated = evaluate(gt, detections)
    assert first == again
    assert first[CAR] != other[CAR]
    for class_id in (PERSON, CAR):
        interval = first[class_id]
        assert interval.point == pytest.approx(evaluated[class_id].ap50, abs=1e-12)
        assert interval.low < interval.point < interval.high
        assert interval.n_valid == 200 and interval.metric == "ap50"
    wide = bootstrap_ci(gt, detections, 200, rng=np.random.default_rng(3), metric="ap50_95")
    assert wide[CAR].point == pytest.approx(evaluated[CAR].ap50_95, abs=1e-12)
    assert wide[CAR].low < wide[CAR].point < wide[CAR].high


def test_bootstrap_ci_narrows_with_more_frames():
    rng = np.random.default_rng(16)
    small_gt, small_dets = synthetic_set(rng, 40)
    large_gt, large_dets = synthetic_set(rng, 400)
    small = bootstrap_ci(small_gt, small_dets, 300, rng=np.random.default_rng(0), class_ids=(CAR,))[CAR]
    large = bootstrap_ci(large_gt, large_dets, 300, rng=np.random.default_rng(0), class_ids=(CAR,))[CAR]
    assert (large.high - large.low) < 0.6 * (small.high - small.low)


def _rainy(detections, keep, rng):
    """The detections with each kept with probability ``keep`` (rain costs recall)."""
    return [record for record in detections if rng.random() < keep]


def _rainy_models(seed=21, n_images=60):
    """Ground truth and {model: {rate: detections}} of two models at 0, 50 and 100 mm/h."""
    rng = np.random.default_rng(seed)
    gt, detections = synthetic_set(rng, n_images)
    models = {"clean-trained": {0: detections, 50: _rainy(detections, 0.6, rng), 100: _rainy(detections, 0.3, rng)},
              "rain-trained": {0: detections, 50: _rainy(detections, 0.9, rng), 100: _rainy(detections, 0.8, rng)}}
    return gt, models


def test_robustness_intervals_points_are_cocoeval_and_intervals_contain_them():
    gt, models = _rainy_models()
    result = robustness_intervals(gt, models, 200, rng=np.random.default_rng(0), class_ids=(PERSON, CAR),
                                  references={"rain-trained": "clean-trained"})
    again = robustness_intervals(gt, models, 200, rng=np.random.default_rng(0), class_ids=(PERSON, CAR),
                                 references={"rain-trained": "clean-trained"})
    assert result == again
    for model, by_rate in models.items():
        for class_id in (PERSON, CAR):
            entry = result[model][class_id]
            reference_ap = {rate: direct_ap(direct_cocoeval(gt, records), class_id)[0] for rate, records in by_rate.items()}
            for rate, value in reference_ap.items():
                assert entry.ap50[float(rate)].point == pytest.approx(value, abs=1e-12)
            assert entry.mpc.point == pytest.approx(mpc(reference_ap), abs=1e-12)
            assert entry.rpc.point == pytest.approx(rpc(reference_ap), abs=1e-12)
            for interval in (entry.mpc, entry.rpc, *entry.ap50.values()):
                assert interval.low <= interval.point <= interval.high
    car = result["rain-trained"][CAR]
    assert car.reference == "clean-trained" and result["clean-trained"][CAR].mpc_difference is None
    assert car.mpc_difference.point == pytest.approx(car.mpc.point - result["clean-trained"][CAR].mpc.point)
    assert car.mpc_difference.low > 0  # the rain-trained model keeps far more detections


def test_robustness_intervals_resample_frames_once_for_every_rate_and_model():
    gt, models = _rainy_models()
    same = {"a": models["clean-trained"], "b": models["clean-trained"]}
    result = robustness_intervals(gt, same, 100, rng=np.random.default_rng(1), class_ids=(CAR,), references={"b": "a"})
    difference = result["b"][CAR].mpc_difference
    assert (difference.point, difference.low, difference.high) == (0.0, 0.0, 0.0)  # paired: identical models
    unchanged = {"steady": {rate: models["clean-trained"][0] for rate in (0, 50, 100)}}
    steady = robustness_intervals(gt, unchanged, 100, rng=np.random.default_rng(1), class_ids=(CAR,))["steady"][CAR]
    assert (steady.rpc.low, steady.rpc.point, steady.rpc.high) == pytest.approx((1.0, 1.0, 1.0), abs=1e-12)


def test_robustness_intervals_one_resample_equals_cocoeval_on_that_resample():
    gt, models = _rainy_models(n_images=25)
    by_rate = models["clean-trained"]
    result = robustness_intervals(gt, {"m": by_rate}, 1, rng=np.random.default_rng(5), class_ids=(CAR,))["m"][CAR]
    weights = bootstrap_weights(25, 1, np.random.default_rng(5))[0]
    image_ids = sorted(image["id"] for image in gt["images"])
    sample = np.repeat(image_ids, weights).tolist()
    resampled = {rate: direct_ap(direct_cocoeval(*resample_images(gt, records, sample)), CAR)[0]
                 for rate, records in by_rate.items()}
    assert result.mpc.low == result.mpc.high == pytest.approx(mpc(resampled), abs=1e-12)
    assert result.rpc.low == pytest.approx(rpc(resampled), abs=1e-12)


@pytest.mark.parametrize(
    "detections, references, message",
    [
        ({}, None, r"detections: expected \{model: \{rate: records\}\} with at least one model, got none"),
        ({"a": {0: [], 50: []}, "b": {0: [], 100: []}}, None,
         r"detections\['b'\]: expected the rates \[0.0, 50.0\] of the first model, got \[0.0, 100.0\]"),
        ({"a": {50: [], 100: []}}, None, r"detections: expected rate 0 and at least one rate > 0 mm/h"),
        ({"a": {0: [], 50: []}}, {"a": "clean"}, r"references: 'a' -> 'clean' names a model without detections"),
    ],
)
def test_robustness_intervals_bad_arguments(detections, references, message):
    with pytest.raises(ValueError, match=message):
        robustness_intervals(_GT, detections, 10, rng=np.random.default_rng(0), references=references)


def test_bootstrap_ci_class_without_ground_truth_is_nan():
    gt = coco_ground_truth([(1, 100, 100, np.array([box_row(0)], np.float32), np.array([CAR]))])
    result = bootstrap_ci(
        gt, [det(1, CAR, box_row(0), 0.5)], 20, rng=np.random.default_rng(0), class_ids=(CAR, BICYCLE)
    )
    assert (result[CAR].point, result[CAR].low, result[CAR].high) == pytest.approx((1.0, 1.0, 1.0), abs=1e-12)
    assert math.isnan(result[BICYCLE].point) and math.isnan(result[BICYCLE].low) and result[BICYCLE].n_valid == 0


# --------------------------------------------------------------------------------------------
# metrics backends: the vectorised "numpy" backend against pycocotools, figure by figure
# --------------------------------------------------------------------------------------------


def hard_set(seed, n_images=40):
    """Frames built to stress COCO's matching rules: (gt_dict, detections, visible_fraction).

    Integer boxes, so IoUs tie exactly and hit the thresholds exactly (a half box has IoU 0.5, a
    three-quarter box 0.75); duplicated ground truths (equal IoU with a detection) and two
    persons a detection straddles with equal IoU, the one it takes (the later one) being the only
    match of a lower-scored detection; crowd
    (ignored) boxes, one of them large enough to absorb several detections; scores from a few
    values (ties within and across images, also at the 100-detection cut of the crowded frame);
    empty frames, frames with only ground truth, frames with only false positives; zero-size
    detections; bicycle detections but no bicycle ground truth.
    """
    rng = np.random.default_rng(seed)
    scores = np.array([0.0, 0.2, 0.5, 0.5, 0.8, 1.0])
    images, detections, visible = [], [], []
    for image_id in range(1, n_images + 1):
        kind = image_id % 5
        n = 0 if kind in (0, 2) else int(rng.integers(1, 9))
        xy = rng.integers(0, 300, (n, 2))
        wh = 4 * rng.integers(1, 20, (n, 2))
        boxes = np.concatenate([xy, xy + wh], axis=1).astype(np.float32)
        classes = rng.choice([PERSON, CAR, MOTORCYCLE], size=n, p=[0.3, 0.6, 0.1])
        duplicate = rng.random(n) < 0.15
        boxes = np.concatenate([boxes, boxes[duplicate]])
        classes = np.concatenate([classes, classes[duplicate]])
        ignore = rng.random(len(boxes)) < 0.15
        if kind == 3:  # a large crowd box over a busy area; two persons with a straddling detection
            boxes = np.concatenate([boxes, np.array([[0, 0, 200, 200], [400, 400, 410, 410], [404, 400, 414, 410]],
                                                    np.float32)])
            classes, ignore = np.append(classes, [CAR, PERSON, PERSON]), np.append(ignore, [True, False, False])
            detections += [det(image_id, PERSON, [402, 400, 412, 410], 0.9),
                           det(image_id, PERSON, [404, 400, 414, 410], 0.4)]
        images.append((image_id, 640, 480, boxes, classes, ignore))
        fraction = rng.random(len(boxes))
        fraction[rng.random(len(boxes)) < 0.2] = rng.choice([np.nan, 0.25, 0.5, 1.0])
        visible.append(fraction)
        if kind == 1:
            continue
        for box, class_id in zip(boxes.astype(np.float64), classes, strict=True):
            x1, y1, x2, y2 = box
            variants = [box, [x1, y1, x2, y1 + (y2 - y1) / 2], [x1, y1, x2, y1 + 0.75 * (y2 - y1)],
                        box + rng.integers(-6, 7, 4)]
            for _ in range(int(rng.integers(0, 4))):
                new = np.asarray(variants[int(rng.integers(len(variants)))], np.float64)
                new[2:] = np.maximum(new[2:], new[:2])
                label = int(class_id) if rng.random() < 0.85 else int(rng.choice([PERSON, BICYCLE, CAR]))
                detections.append(det(image_id, label, new.tolist(), float(rng.choice(scores))))
        for _ in range(int(rng.integers(0, 6))):
            x, y = rng.integers(0, 600, 2).astype(float)
            w, h = (0.0 if rng.random() < 0.2 else float(rng.integers(2, 60)), float(rng.integers(2, 60)))
            detections.append(det(image_id, int(rng.integers(4)), [x, y, x + w, y + h], float(rng.choice(scores))))
        if kind == 4 and image_id < 10:  # more than 100 car detections, tied scores across the cut
            for i in range(130):
                x = float(4 * (i % 60))
                detections.append(det(image_id, CAR, [x, 0.0, x + 40.0, 40.0], float(scores[2 + i % 3])))
    return coco_ground_truth(images), detections, np.concatenate(visible)


def assert_same_figures(first, second, path="", tol=1e-9):
    """Recursively equal: dicts, dataclasses, tuples; floats to ``tol`` (nan equals nan)."""
    if isinstance(first, dict):
        assert list(first) == list(second), path
        for key in first:
            assert_same_figures(first[key], second[key], f"{path}[{key!r}]", tol)
    elif hasattr(first, "__dataclass_fields__"):
        assert type(first) is type(second), path
        for name in first.__dataclass_fields__:
            assert_same_figures(getattr(first, name), getattr(second, name), f"{path}.{name}", tol)
    elif isinstance(first, np.ndarray):
        np.testing.assert_array_equal(first, second, err_msg=path)
    elif isinstance(first, float):
        assert (math.isnan(first) and math.isnan(second)) or abs(first - second) <= tol, (path, first, second)
    else:
        assert first == second, path


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_backends_give_identical_matches_and_ap(seed):
    gt, detections, _ = hard_set(seed)
    ranges = [AREA_ALL, *SIZE_RANGES.values()]
    for image_ids, class_ids in ((None, (CAR, PERSON, BICYCLE, MOTORCYCLE)), (list(range(40, 0, -3)), (MOTORCYCLE,))):
        fast, reference = (run_cocoeval(gt, detections, class_ids, image_ids, area_ranges=ranges, backend=backend)
                           for backend in METRICS_BACKENDS)
        assert fast.class_ids == reference.class_ids == list(class_ids)
        np.testing.assert_array_equal(fast.image_ids, reference.image_ids)
        for a in range(len(ranges)):
            assert list(fast.matches[a]) == sorted(class_ids)
            assert_same_figures(fast.matches[a], reference.matches[a])  # the arrays are identical
            for class_id in class_ids:
                np.testing.assert_allclose(fast.ap[a][class_id], reference.ap[a][class_id], rtol=0, atol=1e-9)
    # the hard cases happen: exact threshold IoUs, crowd absorption, the 100-detection cut
    car = run_cocoeval(gt, detections, (CAR,)).matches[0][CAR]
    assert car.ignored.any() and car.true_positive[0].sum() > car.true_positive[5].sum()
    assert len(car.scores) < sum(d["category_id"] == CAR for d in detections)


@pytest.mark.parametrize("seed", [3, 4])
def test_backends_agree_on_every_figure(seed):
    gt, detections, visible = hard_set(seed, n_images=30)
    figures = {}
    for backend in METRICS_BACKENDS:
        rainy = {"m": {0: detections, 50: detections[::2], 100: detections[::3]}}
        figures[backend] = {
            "evaluate": evaluate(gt, detections, backend=backend),
            "by size": ap_by_size(gt, detections, backend=backend),
            "visibility fp": ap_by_visibility(gt, detections, visible, unmatched="fp", backend=backend),
            "visibility ignore": ap_by_visibility(gt, detections, visible, unmatched="ignore", backend=backend),
            "ci50": bootstrap_ci(gt, detections, 50, rng=np.random.default_rng(1), backend=backend),
            "ci50_95": bootstrap_ci(gt, detections, 50, rng=np.random.default_rng(1), metric="ap50_95",
                                    backend=backend),
            "robustness": robustness_intervals(gt, rainy, 50, rng=np.random.default_rng(2), backend=backend),
        }
    assert_same_figures(figures["numpy"], figures["pycocotools"])
    assert math.isnan(figures["numpy"]["evaluate"][BICYCLE].ap50)  # a class without ground truth
    textbook = direct_cocoeval(gt, detections)
    for class_id in (PERSON, CAR, MOTORCYCLE):
        ap50, ap50_95 = direct_ap(textbook, class_id)
        assert figures["numpy"]["evaluate"][class_id].ap50 == pytest.approx(ap50, abs=1e-9)
        assert figures["numpy"]["evaluate"][class_id].ap50_95 == pytest.approx(ap50_95, abs=1e-9)
        assert figures["numpy"]["ci50"][class_id].point == pytest.approx(ap50, abs=1e-9)


def _looped_interpolated_ap(true_positive, ignored, det_weights, n_gt):
    """COCOeval.accumulate's interpolation, one copy (row) at a time: the reference."""
    ap = np.full((len(det_weights), len(true_positive)), np.nan)
    for row, (weights, count) in enumerate(zip(det_weights, n_gt, strict=True)):
        if count == 0:
            continue
        for t in range(len(true_positive)):
            counted = ~ignored[t]
            tp_sum = np.cumsum(weights * (true_positive[t] & counted))
            fp_sum = np.cumsum(weights * (~true_positive[t] & counted))
            recall = tp_sum / count
            precision = (tp_sum / (fp_sum + tp_sum + np.spacing(1))).tolist()
            for i in range(len(precision) - 1, 0, -1):
                precision[i - 1] = max(precision[i - 1], precision[i])
            indices = np.searchsorted(recall, RECALL_THRESHOLDS, side="left")
            ap[row, t] = np.array([precision[i] if i < len(precision) else 0.0 for i in indices]).mean()
    return ap


def test_interpolated_ap_equals_the_per_copy_loop_bit_for_bit():
    rng = np.random.default_rng(11)
    for trial in range(60):
        n_thresholds, n_dets, n_images = int(rng.integers(1, 11)), int(rng.integers(0, 120)), int(rng.integers(1, 25))
        true_positive = rng.random((n_thresholds, n_dets)) < rng.random()
        ignored = rng.random((n_thresholds, n_dets)) < 0.2 * rng.random()
        image_index = rng.integers(0, n_images, n_dets)
        n_gt_per_image = rng.integers(0, 4, n_images) if trial % 6 else np.zeros(n_images, np.int64)
        weights = bootstrap_weights(n_images, int(rng.integers(1, 30)), rng).astype(float)
        weights[0] = 1.0 if trial % 2 else 0.0
        det_weights, n_gt = weights[:, image_index], weights @ n_gt_per_image
        expected = _looped_interpolated_ap(true_positive, ignored, det_weights, n_gt)
        np.testing.assert_array_equal(interpolated_ap(true_positive, ignored, det_weights, n_gt), expected)
        np.testing.assert_array_equal(
            image_weighted_ap(true_positive, ignored, image_index, weights, n_gt_per_image), expected
        )


# --------------------------------------------------------------------------------------------
# bad inputs: one-line errors saying what was expected and what came
# --------------------------------------------------------------------------------------------

_GOOD_BOXES = np.array([box_row(0)], np.float32)


@pytest.mark.parametrize(
    ("images", "message"),
    [
        (
            [(1, 100, 100, np.array([box_row(0), box_row(1)], np.float32), np.array([CAR]))],
            r"image 1 class_ids: expected shape \(2,\) to match boxes, got \(1,\)",
        ),
        (
            [(1, 100, 100, np.zeros((2, 3), np.float32), np.array([CAR, CAR]))],
            r"image 1 boxes: expected shape \(M, 4\), got \(2, 3\)",
        ),
        (
            [(1, 100, 100, _GOOD_BOXES, np.array([7]))],
            r"image 1 class_ids: unknown class id\(s\) \[7\], expected ids in \(0, 1, 2, 3\)",
        ),
        (
            [(1, 100, 100, np.array([[10, 0, 5, 10]], np.float32), np.array([CAR]))],
            r"image 1 box 0: expected x1 <= x2 and y1 <= y2 \(xyxy\), got \[10.0, 0.0, 5.0, 10.0\]",
        ),
        (
            [(1, 100, 100, _GOOD_BOXES, np.array([CAR])), (1, 100, 100, _GOOD_BOXES, np.array([CAR]))],
            r"images\[1\]: image_id 1 is repeated, expected unique ids",
        ),
        ([(0, 100, 100, _GOOD_BOXES, np.array([CAR]))], r"images\[0\] image_id: expected a positive int, got 0"),
        (
            [(1, 100, 100, _GOOD_BOXES, np.array([CAR]), np.array([1]))],
            r"image 1 ignore: expected a bool array of shape \(1,\), got int64 \(1,\)",
        ),
        (
            [(1, 100, 100, _GOOD_BOXES)],
            r"images\[0\]: expected \(image_id, width, height, boxes, class_ids\[, ignore\]\), got a 4-tuple",
        ),
    ],
)
def test_bad_ground_truth_inputs(images, message):
    with pytest.raises(ValueError, match=message) as error:
        coco_ground_truth(images)
    assert "\n" not in str(error.value)


_GT = coco_ground_truth([(1, 100, 100, _GOOD_BOXES, np.array([CAR]))])


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (
            lambda: evaluate(_GT, [det(2, CAR, box_row(0), 0.5)]),
            r"detections\[0\]: image_id 2 is not in the ground truth",
        ),
        (
            lambda: evaluate(_GT, [det(1, 9, box_row(0), 0.5)]),
            r"detections\[0\]: unknown category_id 9, expected one of \[0, 1, 2, 3\]",
        ),
        (
            lambda: evaluate(_GT, [{"image_id": 1, "category_id": CAR, "bbox": [0, 0, -1, 5], "score": 0.5}]),
            r"detections\[0\] bbox: expected finite \[x, y, w, h\] with w, h >= 0, got \[0, 0, -1, 5\]",
        ),
        (
            lambda: evaluate(_GT, [det(1, CAR, box_row(0), 1.5)]),
            r"detections\[0\] score: expected a confidence in \[0, 1\], got 1.5",
        ),
        (
            lambda: evaluate(_GT, [{"image_id": 1, "bbox": [0, 0, 1, 1]}]),
            r"detections\[0\]: expected a dict with image_id, category_id, bbox, score, got",
        ),
        (
            lambda: evaluate(_GT, [], class_ids=(2, 5)),
            r"class_ids: unknown class id\(s\) \[5\], expected ids in \[0, 1, 2, 3\]",
        ),
        (lambda: evaluate(_GT, [], image_ids=[1, 4]), r"image_ids: \[4\] not in the ground truth"),
        (lambda: evaluate(_GT, [], conf=2.0), r"conf: expected a confidence in \[0, 1\], got 2.0"),
        (
            lambda: evaluate({"images": []}, []),
            r"gt_dict: expected keys images/annotations/categories, missing 'annotations'",
        ),
        (
            lambda: evaluate({**_GT, "annotations": [{**_GT["annotations"][0], "id": 0}]}, []),
            r"gt_dict annotations: expected int ids >= 1 \(COCOeval reads id 0 as unmatched\), got others",
        ),
        (
            lambda: evaluate(
                {**_GT, "annotations": [{"id": 1, "image_id": 1, "category_id": 2, "bbox": [0, 0, 1, 1]}]}, []
            ),
            r"gt_dict annotations\[0\]: expected keys \('id', 'image_id', 'category_id', 'bbox', 'area', 'iscrowd'\), missing \['area', 'iscrowd'\]",
        ),
        (
            lambda: coco_detections(1, np.array([[5, 5, 1, 9]]), np.array([0.5]), np.array([CAR])),
            r"boxes: expected x1 <= x2 and y1 <= y2 \(xyxy\), got a box with x2 < x1",
        ),
        (
            lambda: coco_detections(1, np.array([[0, 0, 1, 1]]), np.array([0.5, 0.4]), np.array([CAR])),
            r"scores/class_ids: expected shape \(1,\) to match boxes, got \(2,\) and \(1,\)",
        ),
        (
            lambda: bootstrap_ci(_GT, [], 10, rng=np.random.RandomState(0)),
            r"rng: expected a numpy.random.Generator, got RandomState",
        ),
        (lambda: bootstrap_ci(_GT, [], 0, rng=np.random.default_rng(0)), r"n_boot: expected an int >= 1, got 0"),
        (
            lambda: bootstrap_ci(_GT, [], 10, rng=np.random.default_rng(0), metric="f1"),
            r"metric: expected one of \('ap50', 'ap50_95'\), got 'f1'",
        ),
        (
            lambda: bootstrap_ci(_GT, [], 10, rng=np.random.default_rng(0), alpha=1.5),
            r"alpha: expected a value in \(0, 1\), got 1.5",
        ),
        (
            lambda: ap_by_visibility(_GT, [], np.array([0.5, 0.5])),
            r"visible_fraction: expected shape \(1,\) aligned with the annotations, got \(2,\)",
        ),
        (
            lambda: ap_by_visibility(_GT, [], np.array([1.5])),
            r"visible_fraction: expected values in \[0, 1\] or nan, got values outside",
        ),
        (
            lambda: ap_by_visibility(_GT, [], np.array([0.5]), bins=(0.5, 0.2)),
            r"bins: expected at least two increasing edges, got \[0.5, 0.2\]",
        ),
        (
            lambda: ap_by_visibility(_GT, [], np.array([0.5]), unmatched="drop"),
            r"unmatched: expected 'fp' or 'ignore', got 'drop'",
        ),
        (
            lambda: pr_confidence_curves(np.zeros(3), np.zeros(2, bool), 1),
            r"scores/true_positive: expected matching \(D,\) shapes, got \(3,\) and \(2,\)",
        ),
        (
            lambda: interpolated_ap(np.zeros((1, 3), bool), np.zeros((1, 3), bool), np.ones((2, 4)), np.ones(2)),
            r"det_weights: expected shape \(B, 3\), got \(2, 4\)",
        ),
        (
            lambda: interpolated_ap(np.zeros((1, 3), bool), np.zeros((1, 3), bool), -np.ones((1, 3)), np.ones(1)),
            r"det_weights: expected non-negative integer-valued weights, got other values",
        ),
        (
            lambda: interpolated_ap(np.zeros((1, 3), bool), np.zeros((1, 3), bool), np.full((1, 3), 0.5), np.ones(1)),
            r"det_weights: expected non-negative integer-valued weights, got other values",
        ),
        (
            lambda: evaluate(_GT, [], backend="fast"),
            r"metrics backend: expected one of numpy, pycocotools, got 'fast'",
        ),
        (
            lambda: bootstrap_ci(_GT, [], 10, rng=np.random.default_rng(0), backend="faster-coco-eval"),
            r"metrics backend: expected one of numpy, pycocotools, got 'faster-coco-eval'",
        ),
        (
            lambda: ap_by_size(_GT, [], backend=None),
            r"metrics backend: expected one of numpy, pycocotools, got None",
        ),
        (
            lambda: robustness_intervals(_GT, {"a": {0: [], 50: []}}, 10, rng=np.random.default_rng(0), backend="np"),
            r"metrics backend: expected one of numpy, pycocotools, got 'np'",
        ),
    ],
)
def test_bad_inputs_give_one_line_errors(call, message):
    with pytest.raises(ValueError, match=message) as error:
        call()
    assert "\n" not in str(error.value)


def test_half_value_rate_interpolates_the_crossing():
    # 0.8 -> 0.6 -> 0.2: half of 0.8 (0.4) is crossed halfway between 10 and 20 mm/h.
    assert half_value_rate({0.0: 0.8, 10.0: 0.6, 20.0: 0.2}) == pytest.approx(15.0)
    assert half_value_rate({0.0: 0.8, 10.0: 0.4}) == pytest.approx(10.0)  # exactly half
    assert half_value_rate({20.0: 0.1, 0.0: 0.8, 10.0: 0.7}) == pytest.approx(10 + 10 * 0.3 / 0.6)  # unsorted
    assert math.isinf(half_value_rate({0.0: 0.8, 100.0: 0.5}))
    assert math.isnan(half_value_rate({0.0: 0.0, 100.0: 0.0}))
    assert half_value_rate({0.0: 1.0, 50.0: 0.8, 100.0: 0.7}, fraction=0.75) == pytest.approx(50 + 50 * 0.05 / 0.1)
    with pytest.raises(ValueError, match="expected rate 0"):
        half_value_rate({10.0: 0.5, 20.0: 0.1})
    with pytest.raises(ValueError, match="fraction"):
        half_value_rate({0.0: 0.5}, fraction=1.0)
