"""Bus and truck end to end: shards, check_labels, --classes in eval, model classes, exports."""

import contextlib
import io
import json
import re

import numpy as np
import pytest
import yaml
from labelled_shards import OLD_CLASS_NAMES, write_labelled_shard
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from rainbench import cli
from rainbench.eval import backends, pipeline
from rainbench.eval.backends.classes import class_lookup, index_names, parse_class_map
from rainbench.eval.backends.ultralytics import _offline_ultralytics
from rainbench.store.shard import open_checked
from rainbench.store.export import export_coco, export_yolo, read_yolo_labels
from rainbench.store.shard import ShardFormatError
from rainbench.mjcf import layout
from rainbench.store.classes import CLASS_NAMES, parse_classes

# torch's triton segfaults when first loaded after Mesa rendered in the same process (see
# tests/test_eval_pipeline.py); `rainbench paper` below loads it, so load it at collection.
_offline_ultralytics()
import torch._dynamo  # noqa: E402,F401

PERSON, BICYCLE, CAR, MOTORCYCLE, BUS, TRUCK = 0, 1, 2, 3, 5, 7
RATES = (0.0, 50.0)
# Three frames: every class id of interest, boxes in 100x80 images.
FRAMES = [
    [(PERSON, 1, (2, 2, 12, 30), 1.0, 0.0), (CAR, 2, (20, 40, 50, 60), 0.9, 0.0),
     (BUS, 3, (55, 10, 95, 50), 0.8, 0.0)],
    [(CAR, 2, (22, 40, 52, 60), 0.9, 0.0), (TRUCK, 4, (60, 20, 98, 70), 1.0, 0.1),
     (BICYCLE, 5, (5, 50, 15, 70), 0.7, 0.0)],
    [(BUS, 3, (50, 10, 90, 50), 0.8, 0.0), (TRUCK, 4, (10, 5, 40, 35), 1.0, 0.0),
     (MOTORCYCLE, 6, (70, 60, 85, 78), 0.6, 0.0)],
]
FRAMES_OF_OLD_SHARD = [[(PERSON, 1, (2, 2, 12, 30), 1.0, 0.0), (CAR, 2, (20, 40, 50, 60), 0.9, 0.0)],
                       [(CAR, 2, (22, 40, 52, 60), 0.9, 0.0)]]


def xywh(box, shift=0.0):
    x1, y1, x2, y2 = box
    return [x1 + shift, y1, x2 - x1, y2 - y1]


def predictions(frames, rate):
    """COCO results: each label found (score 0.9, shifted by 3 px at 50 mm/h) except the second
    truck; a false bus and a false truck; bus/truck confusions on frame 1."""
    shift = 0.0 if rate == 0 else 3.0
    records = []
    for image_id, labels in enumerate(frames, start=1):
        for class_id, instance_id, box, _, _ in labels:
            if image_id == 3 and class_id == TRUCK:
                continue
            records.append({"image_id": image_id, "category_id": class_id, "bbox": xywh(box, shift),
                            "score": 0.9 - 0.1 * instance_id / 10})
    records += [{"image_id": 1, "category_id": BUS, "bbox": [0, 60, 20, 18], "score": 0.95},
                {"image_id": 2, "category_id": TRUCK, "bbox": [30, 0, 20, 20], "score": 0.5},
                {"image_id": 2, "category_id": BUS, "bbox": xywh((60, 20, 98, 70)), "score": 0.7}]
    return records


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("classes")
    data = root / "data"
    write_labelled_shard(data, FRAMES, rates=RATES)
    preds = root / "preds"
    for rate in RATES:
        path = preds / "coco-model" / f"rate_{pipeline.rate_token(rate)}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(predictions(FRAMES, rate)))
    return data, preds


def reference_ap(frames, records, class_id):
    """(AP50, AP50-95) of one class by pycocotools on hand-built COCO dicts (no rainbench code)."""
    annotations = []
    for image_id, labels in enumerate(frames, start=1):
        for label_class, _, box, _, _ in labels:
            x, y, w, h = xywh(box)
            annotations.append({"id": len(annotations) + 1, "image_id": image_id, "category_id": label_class,
                                "bbox": [x, y, w, h], "area": w * h, "iscrowd": 0})
    truth = COCO()
    truth.dataset = {"images": [{"id": i} for i in range(1, len(frames) + 1)], "annotations": annotations,
                     "categories": [{"id": i, "name": n} for i, n in enumerate(CLASS_NAMES)]}
    with contextlib.redirect_stdout(io.StringIO()):
        truth.createIndex()
        evaluator = COCOeval(truth, truth.loadRes([dict(r) for r in records]), "bbox")
        evaluator.params.catIds = [class_id]
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    return evaluator.stats[1], evaluator.stats[0]


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_class_definitions_are_shared():
    assert layout.CLASS_NAMES is CLASS_NAMES
    assert CLASS_NAMES[BUS] == "bus" and CLASS_NAMES[TRUCK] == "truck" and len(CLASS_NAMES) == 8
    assert parse_classes("Car, bus,7") == (CAR, BUS, TRUCK)
    assert parse_classes([TRUCK, "person", TRUCK]) == (PERSON, TRUCK)


def test_bus_and_truck_evaluate_as_pycocotools(dataset, tmp_path, capsys):
    data, preds = dataset
    out = tmp_path / "out"
    code, stdout, err = _run(capsys, "eval", "--data", data, "--predictions", preds, "--out", out,
                             "--classes", "car,bus,truck", "--n-boot", 20, "--quiet")
    assert code == 0, err
    records = json.loads((out / "metrics.json").read_text())
    assert [(r["rate"], r["class"], r["class_id"]) for r in records] == [
        (rate, name, class_id) for rate in RATES for name, class_id in (("car", CAR), ("bus", BUS), ("truck", TRUCK))]
    for record in records:
        ap50, ap50_95 = reference_ap(FRAMES, predictions(FRAMES, record["rate"]), record["class_id"])
        assert record["ap50"] == pytest.approx(ap50, abs=1e-12)
        assert record["ap50_95"] == pytest.approx(ap50_95, abs=1e-12)
    by_key = {(r["rate"], r["class"]): r for r in records}
    assert (by_key[(0.0, "bus")]["n_gt"], by_key[(0.0, "truck")]["n_gt"]) == (2, 2)
    assert by_key[(0.0, "truck")]["ap50"] < 0.6 and by_key[(0.0, "bus")]["ap50"] < 1.0  # the misses count
    report = (out / "report.md").read_text()
    assert "| Model | Condition | Car | Bus | Truck |" in report  # only the requested classes
    # no evaluated model is one of the paper's: its models follow as rows, n/a for bus and truck
    assert "| YOLOv4 (paper) | Normal | 0.640 | n/a | n/a |" in report
    assert "Person" not in report and "| person |" not in report
    assert (out / "ap50_vs_rate.png").stat().st_size > 1000


def test_default_evaluation_reports_only_the_paper_classes(dataset, tmp_path):
    data, preds = dataset
    result = pipeline.run_eval(data, tmp_path / "out", predictions_dir=preds, n_boot=5, progress=False)
    assert {r["class"] for r in result.records} == {"person", "bicycle", "car", "motorcycle"}
    person = next(r for r in result.records if r["class"] == "person" and r["rate"] == 50.0)
    assert person["ap50_95"] == pytest.approx(reference_ap(FRAMES, predictions(FRAMES, 50.0), PERSON)[1],
                                              abs=1e-12)
    # the bus and truck detections of the files were read and left out
    car = next(r for r in result.records if r["class"] == "car" and r["rate"] == 0.0)
    assert (car["n_gt"], car["n_det"]) == (2, 2)


def test_an_old_four_name_shard_reads_verifies_exports_and_evaluates(tmp_path, capsys):
    data = tmp_path / "old"
    shard = write_labelled_shard(data, FRAMES_OF_OLD_SHARD, class_names=OLD_CLASS_NAMES, rates=RATES)
    open_checked(shard).close()
    preds = tmp_path / "preds"
    for rate in RATES:
        path = preds / "m" / f"rate_{pipeline.rate_token(rate)}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(predictions(FRAMES_OF_OLD_SHARD, rate)))
    result = pipeline.run_eval(data, tmp_path / "out", predictions_dir=preds, n_boot=5, progress=False)
    car = next(r for r in result.records if r["class"] == "car" and r["rate"] == 0.0)
    assert car["ap50"] == pytest.approx(1.0) and car["n_gt"] == 2
    with_bus = pipeline.run_eval(data, tmp_path / "bus", predictions_dir=preds, n_boot=5, progress=False,
                                 classes="car,bus")
    bus = next(r for r in with_bus.records if r["class"] == "bus" and r["rate"] == 0.0)
    assert bus["n_gt"] == 0 and bus["ap50"] != bus["ap50"]  # no bus in an old shard: nan
    data_yaml = export_yolo(data, tmp_path / "yolo", rates=[0])[0]
    assert yaml.safe_load(data_yaml.read_text())["names"] == dict(enumerate(OLD_CLASS_NAMES))
    # an old and a new shard side by side export together (names are prefixes of one list)
    write_labelled_shard(data, FRAMES, scene_seed=1, rates=RATES)
    data_yaml = export_yolo(data, tmp_path / "mixed", rates=[0])[0]
    assert yaml.safe_load(data_yaml.read_text())["nc"] == 8


def test_unknown_class_is_a_one_line_error(dataset, tmp_path, capsys):
    data, preds = dataset
    allowed = re.escape("expected names or ids of person (0), bicycle (1), car (2), motorcycle (3), bus (5), "
                        "truck (7)")
    with pytest.raises(pipeline.EvalError, match=r"^--classes: unknown class 'van'; " + allowed + "$"):
        pipeline.run_eval(data, tmp_path / "out", predictions_dir=preds, classes="car,van", progress=False)
    with pytest.raises(ValueError, match=r"^--classes: unknown class '4'; " + allowed):
        parse_classes("4")  # airplane: a COCO id that is never labelled
    with pytest.raises(ValueError, match=r"^--classes: expected at least one class, got ' , '; " + allowed):
        parse_classes(" , ")
    code, out, err = _run(capsys, "eval", "--data", data, "--predictions", preds, "--out", tmp_path / "o",
                          "--classes", "car,lorry")
    assert code == 2 and out == "" and err == "rainbench: error: --classes: unknown class 'lorry'; " \
        "expected names or ids of person (0), bicycle (1), car (2), motorcycle (3), bus (5), truck (7)\n"
    assert not (tmp_path / "o").exists()


def test_a_model_that_cannot_predict_a_requested_class_is_an_error(dataset, tmp_path, capsys):
    data, _ = dataset
    # the weak control has the paper's four classes (the retrained nano model also has bus and truck)
    code, out, err = _run(capsys, "eval", "--data", data, "--weights", "rainbench-yolo11n-weak", "--out",
                          tmp_path / "out", "--classes", "car,bus", "--quiet")
    assert code == 2 and out == ""
    assert err == ("rainbench: error: --classes: model 'rainbench-yolo11n-weak' cannot predict 'bus' (class 5); "
                   "it predicts person, bicycle, car, motorcycle\n")
    assert not list((tmp_path / "out").rglob("rate_*.json"))  # refused before any inference


def test_paper_refuses_a_model_without_a_requested_class_before_generating(tmp_path, capsys):
    code, out, err = _run(capsys, "paper", "--classes", "person,truck", "--frames", 1, "--width", 64, "--height",
                          48, "--rates", "0", "--data", tmp_path / "data", "--out", tmp_path / "out", "--quiet")
    assert code == 2 and out == ""
    # the default models: the nano model predicts trucks, its weak control does not
    assert err.startswith("rainbench: error: --classes: model 'rainbench-yolo11n-weak' cannot predict 'truck' (class 7)")
    assert not (tmp_path / "data").exists() and len(err.splitlines()) == 1
    code, _, err = _run(capsys, "paper", "--classes", "tram", "--data", tmp_path / "data", "--out", tmp_path / "out")
    assert code == 2 and err.startswith("rainbench: error: --classes: unknown class 'tram'; expected names or ids")


def test_paper_report_shows_the_requested_classes():
    from rainbench.eval.report.markdown import render_paper_md  # noqa: PLC0415

    records = [{"model": "coco", "rate": rate, "class": name, "ap50": ap, "f1": ap}
               for rate, scale in ((0.0, 1.0), (100.0, 0.5)) for name, ap in (("car", 0.8 * scale), ("bus", 0.6 * scale))]
    text = render_paper_md(setup_lines=["setup"], table_one={"car": (2, 10), "bus": (1, 4)},
                           records_by_rain={"jeon2022": records}, half_rates={("jeon2022", "coco", "bus"): 100.0},
                           breakdowns={}, breakdown_model="coco")
    table_one = text.split("## Table I.", 1)[1].split("##", 1)[0]
    assert "| car | 2 | 10 | 6 | 838 |" in table_one and "| bus | 1 | 4 | n/a | n/a |" in table_one
    assert "person" not in table_one
    assert "| coco | Normal | 0.800 | 0.600 |" in text  # Table III: Car, Bus
    assert "|  | bus | 100 |" in text  # the half-AP rate table


def test_class_tables_of_coco_and_four_class_models():
    coco = ["person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat"]
    assert class_lookup(coco, None, "m").tolist() == [0, 1, 2, 3, -1, -1, -1, -1, -1]
    assert class_lookup(coco, None, "m", (CAR, BUS, TRUCK)).tolist() == [-1, -1, 2, -1, -1, 5, -1, 7, -1]
    darknet80 = class_lookup(index_names(80), None, "m", (BUS, TRUCK))  # no names: COCO-80
    assert np.flatnonzero(darknet80 >= 0).tolist() == [5, 7] and darknet80[[5, 7]].tolist() == [5, 7]
    four = class_lookup(coco[:4], None, "m", (CAR, BUS, TRUCK))
    assert four.tolist() == [-1, -1, 2, -1]  # nothing to map bus and truck to
    assert class_lookup(["lkw", "auto"], "lkw=7,auto=2", "m", (TRUCK,)).tolist() == [7, -1]
    assert parse_class_map("lkw=7,omnibus=5") == {"lkw": 7, "omnibus": 5}
    with pytest.raises(backends.BackendError, match=r"--class-map: expected NAME=ID pairs with ID a rainbench "
                                                    r"class id \(person \(0\), .*truck \(7\)\), got 'plane=4'"):
        parse_class_map("plane=4")


def test_exports_keep_coco_ids_for_bus_and_truck(dataset, tmp_path):
    from ultralytics.data.utils import check_det_dataset  # noqa: PLC0415

    data, _ = dataset
    data_yaml = export_yolo(data, tmp_path / "yolo", rates=[0])[0]
    checked = check_det_dataset(str(data_yaml))
    assert checked["nc"] == 8 and checked["names"] == dict(enumerate(CLASS_NAMES))
    assert checked["names"][5] == "bus" and checked["names"][7] == "truck"
    _, class_ids = read_yolo_labels(data_yaml.parent / "labels" / "000002.txt", 100, 80)
    assert class_ids.tolist() == [CAR, TRUCK, BICYCLE]
    _, class_ids = read_yolo_labels(data_yaml.parent / "labels" / "000003.txt", 100, 80)
    assert class_ids.tolist() == [BUS, TRUCK, MOTORCYCLE]
    paper_only = export_yolo(data, tmp_path / "paper", rates=[0], classes=(0, 1, 2, 3))[0]
    assert yaml.safe_load(paper_only.read_text())["names"] == dict(enumerate(OLD_CLASS_NAMES))
    assert read_yolo_labels(paper_only.parent / "labels" / "000003.txt", 100, 80)[1].tolist() == [MOTORCYCLE]
    coco = json.loads(export_coco(data, tmp_path / "coco", rates=[50], images=False)[0].read_text())
    assert [(c["id"], c["name"]) for c in coco["categories"]] == [
        (0, "person"), (1, "bicycle"), (2, "car"), (3, "motorcycle"), (5, "bus"), (7, "truck")]
    assert [a["category_id"] for a in coco["annotations"]] == [
        c for labels in FRAMES for c, *_ in labels]


def test_check_labels_refuses_foreign_names_and_unlabelled_ids(tmp_path):
    renamed = write_labelled_shard(tmp_path / "a", FRAMES_OF_OLD_SHARD, class_names=["car", "person"])
    with pytest.raises(ShardFormatError, match=r"scene000000_f00000.h5: class_names \['car', 'person'\] are not "
                                               r"the rainbench classes \(the first names of \['person', "):
        open_checked(renamed)
    airplane = write_labelled_shard(tmp_path / "b", [[(4, 1, (1, 1, 9, 9), 1.0, 0.0)]])
    with pytest.raises(ShardFormatError, match=r"frame 0: label 0 has class_id 4 \(airplane\), which rainbench "
                                               r"never labels"):
        open_checked(airplane)
    truck_in_old = write_labelled_shard(tmp_path / "c", [[(TRUCK, 1, (1, 1, 9, 9), 1.0, 0.0)]],
                                        class_names=OLD_CLASS_NAMES)
    with pytest.raises(ShardFormatError, match=r"frame 0: label 0 has a class_id outside 0\.\.3"):
        open_checked(truck_in_old)


def test_paper_report_says_the_visibility_bins_count_no_false_positives_and_explains_a_negative_share():
    """A new user read AP 0.96 in a visibility bin beside an overall AP of 0.70 and a weather
    share of -147 % without a word on either."""
    from types import SimpleNamespace

    from rainbench.eval.report.markdown import render_paper_md  # noqa: PLC0415

    def records(heavy_car):
        return [{"model": "m", "rate": rate, "class": "car", "ap50": ap, "f1": ap}
                for rate, ap in ((0.0, 0.9), (100.0, heavy_car))]

    entry = SimpleNamespace(ap50=0.95, n_gt=12)
    text = render_paper_md(setup_lines=["setup"], table_one={"car": (2, 10)},
                           records_by_rain={"jeon2022": records(0.7), "physical": records(0.7),
                                            "physical-fixed-weather": records(0.3)},
                           half_rates={}, breakdown_model="m",
                           breakdowns={"visible fraction": {0.0: {"0.75-1.00": {"car": entry}}},
                                       "box size": {0.0: {"large": {"car": entry}}}})
    visibility = text.split("### AP@0.5 by visible fraction", 1)[1].split("###", 1)[0]
    assert "count no false positives" in visibility
    size = text.split("### AP@0.5 by box size", 1)[1]
    assert "count no false positives" not in size
    share = text.split("How much of the AP loss is the weather?", 1)[1].split("###", 1)[0]
    assert "a negative share means the rain over the unchanged base weather cost more" in share
    assert "| -200 % |" in share  # (0.2 - 0.6) / 0.2
