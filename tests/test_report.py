"""Tests of rainbench.eval.report: metric records, metrics.json/csv, report.md tables, PNG plots."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from rainbench.eval.metrics.bootstrap import BootstrapCI
from rainbench.eval.metrics.evaluation import ClassMetrics
from rainbench.eval.metrics.robustness import percent_drop
from rainbench.eval.report.figures import plot_detection_strip
from rainbench.eval.report.markdown import render_report_md
from rainbench.eval.report.paper import PAPER_TABLES, TABLE_CLASS_ORDER
from rainbench.eval.report.plots import plot_metric_vs_rate
from rainbench.eval.report.records import RECORD_FIELDS, index_records, metric_records, read_metrics, robustness_records, write_metrics
from rainbench.store.classes import CLASS_COLOURS, PAPER_CLASSES

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
PERSON, CAR = 0, 2
RATES = (0.0, 50.0, 100.0)


def _class_metrics(class_id, ap50, f1, n_gt=10):
    return ClassMetrics(
        class_id=class_id,
        n_gt=n_gt,
        n_det=12,
        ap50=ap50,
        ap75=ap50 / 2,
        ap50_95=ap50 / 2,
        precision=0.8,
        recall=0.7,
        f1=f1,
        best_conf=0.3,
        precision_at_conf=0.8,
        recall_at_conf=0.6,
        f1_at_conf=f1,
        conf=0.25,
    )


def _records(with_ci=True):
    """Two models x three rates x four classes with values that make the tables predictable."""
    results, cis = {}, {}
    for model, scale in (("YOLOv4", 1.0), ("mine", 0.5)):
        for rate in RATES:
            fade = 1.0 - rate / 200.0  # 1.0, 0.75, 0.5
            per_class = {}
            for class_id in PAPER_CLASSES:
                ap50 = scale * (0.4 + 0.1 * class_id) * fade
                per_class[class_id] = _class_metrics(class_id, ap50, 0.8 * fade, n_gt=10 + class_id)
            per_class[PAPER_CLASSES[1]] = (
                _class_metrics(1, float("nan"), float("nan"), n_gt=0) if rate == 50.0 else per_class[1]
            )
            results[(model, rate)] = per_class
            cis[(model, rate)] = {
                c: BootstrapCI(c, "ap50", m.ap50, m.ap50 - 0.05, m.ap50 + 0.05, 0.05, 100, 100)
                for c, m in per_class.items()
            }
    return metric_records(results, cis if with_ci else None)


def test_metrics_json_and_csv_round_trip(tmp_path):
    records = _records()
    json_path, csv_path = write_metrics(records, tmp_path / "out")
    assert (json_path.name, csv_path.name) == ("metrics.json", "metrics.csv")
    text = json_path.read_text()
    assert "NaN" not in text and "null" in text
    assert isinstance(json.loads(text), list) and len(json.loads(text)) == len(records) == 24
    assert csv_path.read_text().splitlines()[0] == ",".join(RECORD_FIELDS)
    for path in (json_path, csv_path):
        back = read_metrics(path)
        assert len(back) == len(records)
        for original, loaded in zip(records, back, strict=True):
            assert list(loaded) == list(original)
            for key, value in original.items():
                if isinstance(value, float) and math.isnan(value):
                    assert isinstance(loaded[key], float) and math.isnan(loaded[key]), (path.suffix, key)
                else:
                    assert loaded[key] == value and type(loaded[key]) is type(value), (path.suffix, key)


def test_read_metrics_rejects_other_suffix(tmp_path):
    with pytest.raises(ValueError, match=r"expected a .json or .csv metrics file, got suffix '.txt'"):
        read_metrics(tmp_path / "metrics.txt")


def test_a_report_without_rate_0_says_what_it_compares():
    """A dataset of 50 and 100 mm/h: the tables called 50 mm/h "Normal", and one of 50 mm/h alone
    compared "Normal vs Normal" while the robustness table printed mPC beside "Normal n/a"."""
    rainy = [record for record in _records() if record["rate"] > 0]
    text = render_report_md(rainy, clean_rate=50.0)
    assert "no rate 0 (no clean frames): the tables compare with its lowest rate, 50 mm/h" in text
    assert "## Table III. AP@0.5 degradation, 50mm/h (lowest) vs 100mm/h" in text
    assert "mPC and rPC need clean frames (rate 0); this dataset has none." in text
    assert "| Model | Class | AP@0.5 Normal |" not in text and "Normal vs" not in text
    one = render_report_md([record for record in rainy if record["rate"] == 50.0], clean_rate=50.0)
    assert "One rate only (50mm/h (lowest)): no degradation to show." in one and "## Table III." not in one
    assert "| Model | Class | AP@0.5 Normal |" in render_report_md(_records())


def test_report_md_has_paper_tables():
    text = render_report_md(_records())
    assert "## Table III. AP@0.5 degradation, Normal vs 100mm/h" in text
    assert "## Table IV. F1 degradation, Normal vs 100mm/h" in text
    assert "| Model | Condition | Car | Person | Bicycle | Motorcycle |" in text
    # YOLOv4 car: 0.6 -> 0.3 (50 % drop); person 0.4 -> 0.2; bicycle 0.5 -> 0.25; motorcycle 0.7 -> 0.35.
    assert "| YOLOv4 | Normal | 0.600 | 0.400 | 0.500 | 0.700 |" in text
    assert "|  | 100mm/h | 0.300 | 0.200 | 0.250 | 0.350 |" in text
    assert "|  | % drop | 50.00 | 50.00 | 50.00 | 50.00 |" in text
    assert "| mine | Normal | 0.300 | 0.200 | 0.250 | 0.350 |" in text
    # Table IV: F1 0.8 -> 0.4 for every class.
    assert "| YOLOv4 | Normal | 0.800 | 0.800 | 0.800 | 0.800 |" in text
    # Rate-by-rate table, nan rendered as n/a (bicycle has no ground truth at 50 mm/h).
    assert "| Model | Class | Normal | 50mm/h | 100mm/h |" in text
    assert "|  | bicycle | 0.500 | n/a | 0.250 |" in text
    # CIs; mPC / rPC (car YOLOv4 AP: P 0.6, mPC (0.45 + 0.3) / 2 = 0.375, rPC 0.625; F1: P 0.8,
    # mPC (0.6 + 0.4) / 2 = 0.5, rPC 0.625; a nan rate makes mPC nan); ground-truth counts.
    assert "| YOLOv4 | car | [0.550, 0.650] | [0.400, 0.500] | [0.250, 0.350] |" in text
    assert "| YOLOv4 | car | 0.600 | 0.375 | 0.625 | 0.800 | 0.500 | 0.625 |" in text
    assert "|  | bicycle | 0.500 | n/a | n/a | 0.800 | n/a | n/a |" in text
    assert "| car | 12 | 12 | 12 |" in text


def test_report_md_paper_rows_when_no_model_is_the_papers():
    """A report of our own models had four '(paper)' columns of n/a in every row."""
    records = [dict(record, model="rainbench-yolo11n") for record in _records(with_ci=False)]
    text = render_report_md(records, paper=PAPER_TABLES)
    table = text.split("## Table III.", 1)[1].split("##", 1)[0]
    assert "(paper) |" not in table.splitlines()[2]  # the header: no paper columns
    assert "| Model | Condition | Car | Person | Bicycle | Motorcycle |" in table
    assert "| YOLOv4 (paper) | Normal | 0.640 | 0.771 | 0.913 | 0.263 |" in table
    assert "|  | 100mm/h | 0.424 | 0.469 | 0.677 | 0.0043 |" in table
    assert "| YOLOv7x (paper) | Normal |" in table and "n/a | n/a | n/a | n/a" not in table
    one_rate = render_report_md([r for r in records if r["rate"] == 0.0], paper=PAPER_TABLES)
    assert "(paper)" not in one_rate  # no table, no note


def test_report_md_paper_columns_beside_ours():
    text = render_report_md(_records(with_ci=False), paper=PAPER_TABLES, paper_models={"mine": "YOLOv7x"})
    assert "| Model | Condition | Car | Car (paper) | Person | Person (paper) |" in text
    # YOLOv4 matched by name; paper values from Table III / IV and their % drop.
    assert "| YOLOv4 | Normal | 0.600 | 0.640 | 0.400 | 0.771 | 0.500 | 0.913 | 0.700 | 0.263 |" in text
    assert "|  | 100mm/h | 0.300 | 0.424 | 0.200 | 0.469 | 0.250 | 0.677 | 0.350 | 0.0043 |" in text
    assert "|  | % drop | 50.00 | 33.75 |" in text
    assert "| mine | Normal | 0.300 | 0.669 |" in text  # mapped to YOLOv7x
    assert "| YOLOv4 | Normal | 0.800 | 0.629 | 0.800 | 0.699 |" in text  # Table IV
    assert "bootstrap" not in text  # no CI section without CIs


def test_paper_tables_transcription():
    assert set(PAPER_TABLES) == {"ap50", "f1"}
    for metric in PAPER_TABLES.values():
        assert set(metric) == {"YOLOv4", "YOLOv5x", "YOLOv7x"}
        for by_rate in metric.values():
            assert set(by_rate) == {0.0, 100.0}
            assert all(set(values) == set(TABLE_CLASS_ORDER) for values in by_rate.values())
    # The paper's text: car AP drops 31.24 % (v7x), 30.67 % (v5x), 33.75 % (v4).
    drops = {m: percent_drop(v[0.0]["car"], v[100.0]["car"]) for m, v in PAPER_TABLES["ap50"].items()}
    assert drops == pytest.approx({"YOLOv7x": 31.24, "YOLOv5x": 30.67, "YOLOv4": 33.75}, abs=0.005)


def test_report_md_errors():
    with pytest.raises(ValueError, match="records: expected at least one metric record, got none"):
        render_report_md([])
    with pytest.raises(
        ValueError, match=r"expected rates present in the records \[0.0, 50.0, 100.0\], got 0.0 and 30.0"
    ):
        render_report_md(_records(), heavy_rate=30.0)


def _assert_png(path, min_height, min_width):
    assert path.read_bytes()[:8] == PNG_MAGIC
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and image.shape[0] >= min_height and image.shape[1] >= min_width
    assert image.std() > 5  # not a blank canvas
    return image


def test_plot_metric_vs_rate_writes_png(tmp_path):
    records = _records()
    path = plot_metric_vs_rate(records, "ap50", tmp_path / "plots" / "ap50.png")
    _assert_png(path, 200, 800)
    path_f1 = plot_metric_vs_rate(records, "f1", tmp_path / "f1.png", ci=False)
    _assert_png(path_f1, 200, 800)
    with pytest.raises(ValueError, match=r"metric: expected a record key such as 'ap50' or 'f1', got 'map'"):
        plot_metric_vs_rate(records, "map", tmp_path / "x.png")


def _grey_text_pixels(image, left, right):
    """Pixels of the 0.4 grey that only the empty-panel note uses, around the middle of columns
    ``left:right`` of a one-row plot (axes lines and labels are black, grids light, lines
    coloured)."""
    middle_row, middle_column = image.shape[0] // 2, (left + right) // 2
    centre = image[middle_row - 25 : middle_row + 25, middle_column - 40 : middle_column + 40].astype(int)
    return int(np.count_nonzero((np.abs(centre - 102) <= 12).all(axis=-1)))


def test_a_class_without_labelled_boxes_gets_a_note_not_an_empty_panel(tmp_path):
    """A class with no labelled boxes at any rate plotted as a blank panel, which reads as a
    plotting fault; its panel now says why it is empty, and the other panels carry no note."""
    records = []
    for record in _records():
        if record["class_id"] == PAPER_CLASSES[1]:
            record = {**record, "n_gt": 0, "ap50": float("nan"), "ap50_ci_low": float("nan"),
                      "ap50_ci_high": float("nan")}
        records.append(record)
    image = cv2.imread(str(plot_metric_vs_rate(records, "ap50", tmp_path / "ap50.png")))
    classes = index_records(records)[2]
    empty = classes.index(next(r["class"] for r in records if r["class_id"] == PAPER_CLASSES[1]))
    panel = image.shape[1] // len(classes)
    counts = [_grey_text_pixels(image, index * panel, (index + 1) * panel) for index in range(len(classes))]
    assert counts[empty] > 30, counts
    assert all(count == 0 for index, count in enumerate(counts) if index != empty), counts


def test_plot_detection_strip_draws_boxes(tmp_path):
    rng = np.random.default_rng(0)
    frames = {rate: rng.integers(0, 40, (60, 80, 3), dtype=np.uint8) for rate in (0.0, 10.0, 20.0, 30.0, 40.0)}
    detections = {
        0.0: [{"image_id": 1, "category_id": 2, "bbox": [10, 10, 30, 30], "score": 0.9}],
        10.0: [{"image_id": 1, "category_id": 0, "bbox": [5, 5, 20, 40], "score": 0.1}],  # below min_score
    }
    path = plot_detection_strip(frames, detections, tmp_path / "strip.png", columns=3)
    image = _assert_png(path, 1, 1)
    banner, gap = 28, 4
    assert image.shape == (2 * (60 + banner) + gap, 3 * 80 + 2 * gap, 3)
    car_bgr = np.array(CLASS_COLOURS[2][::-1])
    first_tile = image[: 60 + banner, :80]
    second_tile = image[: 60 + banner, 80 + gap : 160 + gap]
    person_bgr = np.array(CLASS_COLOURS[0][::-1])
    assert np.any(np.all(first_tile == car_bgr, axis=-1))
    assert not np.any(np.all(second_tile == person_bgr, axis=-1))
    with pytest.raises(
        ValueError,
        match=r"images_by_rate\[10.0\]: expected uint8 \(60, 80, 3\) like the first image, got uint8 \(10, 10, 3\)",
    ):
        plot_detection_strip({0.0: frames[0.0], 10.0: np.zeros((10, 10, 3), np.uint8)}, {}, tmp_path / "bad.png")


# --------------------------------------------------------------------------------------------
# records (moved with the record schema from the metrics tests)
# --------------------------------------------------------------------------------------------


def _metrics(class_id, ap50, f1):
    return ClassMetrics(class_id, 10, 12, ap50, ap50 / 2, ap50 / 2, 0.8, 0.7, f1, 0.3, 0.8, 0.6, f1, 0.25)


def test_metric_records_layout_drops_and_cis():
    results = {
        ("yolo", 100.0): {CAR: _metrics(CAR, 0.4, 0.5)},
        ("yolo", 0.0): {CAR: _metrics(CAR, 0.8, 0.6), PERSON: _metrics(PERSON, 0.5, 0.5)},
    }
    cis = {("yolo", 0.0): {CAR: BootstrapCI(CAR, "ap50", 0.8, 0.7, 0.9, 0.05, 100, 100)}}
    records = metric_records(results, cis)
    assert [(r["rate"], r["class"]) for r in records] == [(0.0, "car"), (0.0, "person"), (100.0, "car")]
    assert all(tuple(r) == RECORD_FIELDS for r in records)
    clean_car, _, rainy_car = records
    assert (clean_car["ap50_ci_low"], clean_car["ap50_ci_high"]) == (0.7, 0.9)
    assert math.isnan(rainy_car["ap50_ci_low"])
    assert clean_car["ap50_drop_pct"] == 0.0
    assert rainy_car["ap50_drop_pct"] == pytest.approx(50.0)
    assert rainy_car["f1_drop_pct"] == pytest.approx(100 * (0.6 - 0.5) / 0.6)
    assert (rainy_car["model"], rainy_car["class_id"], rainy_car["n_gt"]) == ("yolo", CAR, 10)


def test_robustness_records():
    records = [
        {"model": "m", "class": "car", "rate": rate, "ap50": value, "f1": None}
        for rate, value in ((0.0, 0.8), (10.0, 0.6), (20.0, 0.4))
    ]
    ap50, f1 = robustness_records(records)
    assert ap50["clean"] == 0.8 and ap50["worst_rate"] == 20.0 and ap50["at_worst_rate"] == 0.4
    assert ap50["drop_pct"] == pytest.approx(50.0)
    assert ap50["mpc"] == pytest.approx(0.5) and ap50["rpc"] == pytest.approx(0.625)
    assert math.isnan(f1["clean"]) and math.isnan(f1["rpc"])


def test_robustness_section_shows_intervals_and_paired_differences():
    from rainbench.eval.report.markdown import robustness_section

    nan = float("nan")
    base = {"class": "car", "n_gt": 141, "heavy_rate": 100.0, "at_50": 0.3}
    for key, values in (("clean", (0.94, 0.9, 0.97)), ("at_heavy", (0.1, 0.06, 0.16)), ("mpc", (0.25, 0.21, 0.3)),
                        ("rpc", (0.266, 0.226, 0.319))):
        base.update(zip((key, f"{key}_low", f"{key}_high"), values))
    clean = {**base, "model": "clean", "reference": None,
             "mpc_difference": nan, "mpc_difference_low": nan, "mpc_difference_high": nan}
    rain = {**base, "model": "clean-rain", "reference": "clean",
            "mpc_difference": 0.087, "mpc_difference_low": 0.041, "mpc_difference_high": 0.127}
    lines = robustness_section({"physical": [clean, rain]})
    assert robustness_section({}) == []
    assert lines[0].startswith("### Rain robustness with intervals")
    assert "| Model | Class | Boxes | AP@0.5 Normal | 50 mm/h | 100 mm/h | mPC | rPC | mPC difference (paired) |" in lines
    assert "| clean | car | 141 | 0.940 (0.900-0.970) | 0.300 | 0.100 (0.060-0.160) | 0.250 (0.210-0.300) | " \
           "0.266 (0.226-0.319) |  |" in lines
    assert any(line.endswith("| +0.087 (+0.041 to +0.127) vs clean |") for line in lines)

    # rows come per class id (person 0 before car 2); the table lists them in the other tables'
    # order, car first, each model's rows together
    person = {**clean, "class": "person", "n_gt": 57}
    lines = robustness_section({"physical": [person, clean, {**rain, "class": "person"}, rain]})
    cells = [line.split("|")[1:3] for line in lines if line.startswith("| ") and "Model" not in line]
    assert [(model.strip(), name.strip()) for model, name in cells] == [
        ("clean", "car"), ("", "person"), ("clean-rain", "car"), ("", "person")]
