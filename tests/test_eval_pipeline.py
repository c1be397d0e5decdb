"""rainbench eval: the pipeline on a tiny shard, prediction files, caching, backends, CLI errors."""

import json
import math
import shutil

import numpy as np
import pytest
from labelled_shards import write_labelled_shard

from rainbench import cli
from rainbench.eval import backends, pipeline
from rainbench.eval.backends.classes import class_lookup, parse_class_map
from rainbench.eval.backends.ultralytics import _offline_ultralytics
from rainbench.store.classes import CLASS_NAMES, PAPER_CLASSES, PAPER_CLASS_NAMES
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import generate_shard
from rainbench.store.shard import open_shard, read_frame_labels

# torch (through torch._dynamo) loads triton, whose bundled LLVM segfaults when it is loaded
# after Mesa's llvmpipe has rendered in the same process (seen here: generate a shard, then
# import triton -> SIGSEGV). Loaded at collection, before any fixture renders, it is fine.
_offline_ultralytics()
import torch._dynamo  # noqa: E402,F401
import ultralytics  # noqa: E402,F401

RATES = (0.0, 50.0)
RECORD_KEYS = {"model", "rate", "class", "ap50", "ap50_95", "precision", "recall", "f1", "n_gt"}


def _images(data_dir):
    """(image id, shard path, frame) of every image, through the evaluator's dataset reader."""
    return [(image.image_id, image.shard, image.frame) for image in pipeline.open_dataset(data_dir).images]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("data")
    # the residential street: its parked cars are near enough to label at 96x72
    generate_shard(GenerateConfig(frames=2, width=96, height=72, rates=RATES, layout="residential",
                                  time_of_day="day"), out)
    return out


def _perfect_records(data_dir):
    """COCO results equal to the shard's own labels, score 1."""
    records = []
    for image_id, shard, frame in _images(data_dir):
        with open_shard(shard) as handle:
            labels = read_frame_labels(handle, frame)
        for box, class_id in zip(labels["bbox"].tolist(), labels["class_id"].tolist()):
            records.append({"image_id": image_id, "category_id": int(class_id),
                            "bbox": [box[0], box[1], box[2] - box[0], box[3] - box[1]], "score": 1.0})
    return records


def _write_predictions(root, model, records, rates=RATES):
    for rate in rates:
        path = root / model / f"rate_{pipeline.rate_token(rate)}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(records))


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _one_line_error(err, *fragments):
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("rainbench: error: "), err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, err)


@pytest.mark.parametrize("rate, token", [(0, "0"), (0.0, "0"), (12.5, "12.5"), (100, "100"),
                                         (np.float32(0.1), "0.1"), (10.0, "10"), (2.25, "2.25")])
def test_rate_token_is_the_shortest_decimal(rate, token):
    assert pipeline.rate_token(rate) == token


@pytest.mark.parametrize("rate", [-1.0, math.nan, math.inf])
def test_rate_token_rejects_bad_rates(rate):
    with pytest.raises(ValueError, match=rf"^rate: expected a finite rate >= 0 mm/h, got {rate!r}$"):
        pipeline.rate_token(rate)


def test_dataset_images_numbering_and_errors(data_dir, tmp_path):
    images = _images(data_dir)
    assert [(i, s.name, f) for i, s, f in images] == [(1, "scene000000_f00000.h5", 0),
                                                      (2, "scene000000_f00000.h5", 1)]
    assert list(pipeline.open_dataset(data_dir).rates) == list(RATES)
    # A second shard sorts after the first: ids continue in shard order.
    two = tmp_path / "two"
    two.mkdir()
    shutil.copy(data_dir / "scene000000_f00000.h5", two / "scene000000_f00002.h5")
    shutil.copy(data_dir / "scene000000_f00000.h5", two / "scene000000_f00000.h5")
    assert [(i, s.name, f) for i, s, f in _images(two)] == [
        (1, "scene000000_f00000.h5", 0), (2, "scene000000_f00000.h5", 1),
        (3, "scene000000_f00002.h5", 0), (4, "scene000000_f00002.h5", 1)]
    (tmp_path / "empty").mkdir()
    with pytest.raises(pipeline.EvalError, match="no shard"):
        _images(tmp_path / "empty")
    with pytest.raises(pipeline.EvalError, match="not a directory"):
        _images(tmp_path / "missing")
    gt = pipeline.ground_truth(pipeline.open_dataset(data_dir))
    assert [im["id"] for im in gt["images"]] == [1, 2]
    assert gt["images"][0]["width"] == 96 and gt["images"][0]["height"] == 72


def test_mixed_rates_are_an_error(data_dir, tmp_path):
    other = tmp_path / "other"
    generate_shard(GenerateConfig(seed=1, frames=1, width=96, height=72, rates=(0.0, 100.0)), other)
    shutil.copy(data_dir / "scene000000_f00000.h5", other / "scene000000_f00000.h5")
    with pytest.raises(pipeline.EvalError, match="same rates"):
        _images(other)


def test_predictions_mode_end_to_end_perfect_predictions(data_dir, tmp_path, capsys):
    records = _perfect_records(data_dir)
    assert records, "the tiny shard should hold at least one label"
    preds = tmp_path / "preds"
    _write_predictions(preds, "perfect", records)
    out = tmp_path / "results"
    code, stdout, err = _run(capsys, "eval", "--data", data_dir, "--predictions", preds, "--out", out,
                             "--n-boot", "20", "--quiet")
    assert code == 0, err
    assert stdout.strip() == str(out / "report.md")
    for name in ("metrics.json", "metrics.csv", "images.json", "report.md", "ap50_vs_rate.png",
                 "f1_vs_rate.png", "detections_strip.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    metrics = json.loads((out / "metrics.json").read_text())
    assert len(metrics) == len(RATES) * len(PAPER_CLASS_NAMES)  # the paper's classes by default
    assert {(m["model"], m["rate"], m["class"]) for m in metrics} == {
        ("perfect", rate, name) for rate in RATES for name in PAPER_CLASS_NAMES}
    for record in metrics:
        assert RECORD_KEYS <= set(record)
        if record["n_gt"] > 0:
            assert record["ap50"] == pytest.approx(1.0) and record["ap50_95"] == pytest.approx(1.0)
            assert record["f1"] == pytest.approx(1.0, abs=1e-3)
        else:
            assert record["ap50"] is None  # nan -> null
    present = {r["category_id"] for r in records}
    assert {m["class"] for m in metrics if m["n_gt"] > 0} == {CLASS_NAMES[c] for c in present if c in PAPER_CLASSES}
    assert json.loads((out / "images.json").read_text()) == [
        {"id": 1, "shard": "scene000000_f00000.h5", "frame": 0},
        {"id": 2, "shard": "scene000000_f00000.h5", "frame": 1}]
    report = (out / "report.md").read_text()
    assert "## Table III. AP@0.5 degradation, Normal vs 50mm/h" in report
    assert "## Table IV. F1 degradation" in report
    assert "| perfect | Normal | 1.000 |" in report and "|  | % drop | 0.00 |" in report


def test_a_detection_of_an_ignore_region_is_neither_right_nor_wrong(tmp_path, capsys):
    # one person label, and a person too small to be one: an ignore region (KITTI's DontCare)
    data = tmp_path / "data"
    write_labelled_shard(data, [[(0, 0, (10, 10, 20, 40), 1.0, 0.0)]], rates=RATES,
                         ignore=[[(0, 1, (60, 20, 63, 27))]])
    found = {"image_id": 1, "category_id": 0, "bbox": [10, 10, 10, 30], "score": 0.5}
    # the detector sees the small person too, a little larger than its pixels, more confidently
    small = {"image_id": 1, "category_id": 0, "bbox": [59.5, 19.0, 4.0, 9.0], "score": 0.9}
    preds = tmp_path / "preds"
    _write_predictions(preds, "model", [found, small])
    person_ap = {}
    for flag in ((), ("--no-ignore-regions",)):
        out = tmp_path / ("strict" if flag else "default")
        code, _, err = _run(capsys, "eval", "--data", data, "--predictions", preds, "--out", out,
                            "--n-boot", "5", "--quiet", *flag)
        assert code == 0, err
        person_ap[flag] = [(m["ap50"], m["n_gt"]) for m in json.loads((out / "metrics.json").read_text())
                           if m["class"] == "person" and m["rate"] == 0.0]
    assert person_ap[()] == [(pytest.approx(1.0), 1)]  # ignored: not a false positive, never missed
    assert "COCO crowd boxes: a detection of one is neither right nor wrong, docs/eval.md): car 0, person 1," \
        in (tmp_path / "default" / "report.md").read_text()
    assert "Ignore regions were left out (`--no-ignore-regions`)" in (tmp_path / "strict" / "report.md").read_text()
    assert person_ap[("--no-ignore-regions",)] == [(pytest.approx(0.5), 1)]  # a false positive first


def test_labels_outside_the_scored_difficulty_become_ignore_regions(tmp_path, capsys):
    # a person 30 px tall and one 12 px tall, half hidden; only the small one is missed
    data = tmp_path / "data"
    write_labelled_shard(data, [[(0, 0, (10, 10, 20, 40), 1.0, 0.0), (0, 1, (50, 10, 55, 22), 0.5, 0.0)]],
                         rates=RATES)
    found = {"image_id": 1, "category_id": 0, "bbox": [10, 10, 10, 30], "score": 0.5}
    preds = tmp_path / "preds"
    _write_predictions(preds, "model", [found])
    person = {}
    for flags in ((), ("--min-height", "25"), ("--min-visible", "0.6"), ("--max-truncation", "0.3")):
        out = tmp_path / "out" / "-".join(flags or ("all",))
        code, _, err = _run(capsys, "eval", "--data", data, "--predictions", preds, "--out", out, "--n-boot", "5",
                            "--quiet", *flags)
        assert code == 0, err
        person[flags] = next((m["ap50"], m["n_gt"]) for m in json.loads((out / "metrics.json").read_text())
                             if m["class"] == "person" and m["rate"] == 0.0)
        report = (out / "report.md").read_text()
        assert ("Scored labels:" in report) == bool(flags)
    assert person[()] == (pytest.approx(51 / 101), 2)  # the small person is a miss: recall 0.5
    assert person[("--min-height", "25")] == person[("--min-visible", "0.6")] == (pytest.approx(1.0), 1)
    assert person[("--max-truncation", "0.3")] == person[()]  # neither is truncated
    assert "Scored labels: height >= 25 px; the other labels are ignore regions" in \
        (tmp_path / "out" / "--min-height-25" / "report.md").read_text()
    with pytest.raises(SystemExit) as exit_info:
        _run(capsys, "eval", "--data", data, "--predictions", preds, "--out", tmp_path / "bad", "--min-visible", "2")
    assert exit_info.value.code == 2
    assert "MIN_VISIBLE: expected a number in [0, 1], got '2'" in capsys.readouterr().err
    with pytest.raises(pipeline.EvalError, match=r"--min-height: expected a number in 0\.\.100000, got -1"):
        pipeline.TargetFilter(min_height=-1)


def test_robustness_rows_pair_models_and_bad_compare_is_refused_first(data_dir, tmp_path, capsys):
    records = _perfect_records(data_dir)
    present = sorted({r["category_id"] for r in records if r["category_id"] in PAPER_CLASSES})
    preds = tmp_path / "preds"
    _write_predictions(preds, "base", records)
    _write_predictions(preds, "base-blind", records, rates=(0.0,))  # sees nothing in the rain
    _write_predictions(preds, "base-blind", [], rates=(50.0,))
    out = tmp_path / "results"
    code, _, err = _run(capsys, "eval", "--data", data_dir, "--predictions", preds, "--out", out,
                        "--n-boot", "20", "--quiet", "--compare", "base-blind=nobody")
    _one_line_error(err, "--compare: 'nobody' is not an evaluated model (models: base, base-blind)")
    assert code == 2 and not out.exists()
    code, _, err = _run(capsys, "eval", "--data", data_dir, "--predictions", preds, "--out", out,
                        "--n-boot", "20", "--quiet")
    assert code == 0, err
    rows = {(row["model"], row["class"]): row for row in json.loads((out / "robustness.json").read_text())}
    for class_id in present:
        base, blind = rows[("base", CLASS_NAMES[class_id])], rows[("base-blind", CLASS_NAMES[class_id])]
        assert (base["clean"], base["mpc"], base["rpc"], base["reference"]) == (1.0, 1.0, 1.0, None)
        assert (blind["clean"], blind["mpc"], blind["rpc"], blind["reference"]) == (1.0, 0.0, 0.0, "base")
        assert (blind["mpc_difference"], blind["mpc_difference_low"], blind["mpc_difference_high"]) == (-1.0, -1.0, -1.0)
    assert "## Rain robustness with intervals" in (out / "report.md").read_text()


def _noisy_records(data_dir, seed):
    """The shard's labels, jittered, duplicated and with false positives, scores with ties."""
    rng = np.random.default_rng(seed)
    records = []
    for record in _perfect_records(data_dir) * 2:
        x, y, w, h = record["bbox"]
        jitter = rng.normal(0, 0.15, 4) * [w, h, w, h]
        box = [x + jitter[0], y + jitter[1], max(0.0, w + jitter[2]), max(0.0, h + jitter[3])]
        records.append(dict(record, bbox=box, score=float(rng.choice([0.3, 0.6, 0.9]))))
    for image_id, _, _ in _images(data_dir):
        for _ in range(5):
            x, y = rng.uniform(0, 80, 2)
            records.append({"image_id": image_id, "category_id": int(rng.integers(4)), "bbox": [x, y, 8.0, 6.0],
                            "score": float(rng.choice([0.3, 0.6]))})
    return records


def test_metrics_backends_write_the_same_figures(data_dir, tmp_path, capsys):
    preds = tmp_path / "preds"
    _write_predictions(preds, "noisy", _noisy_records(data_dir, 0))
    _write_predictions(preds, "noisy-rain", _noisy_records(data_dir, 1))
    outputs = {}
    for metrics in ("numpy", "pycocotools"):
        out = tmp_path / metrics
        code, _, err = _run(capsys, "eval", "--data", data_dir, "--predictions", preds, "--out", out,
                            "--n-boot", "30", "--quiet", "--metrics", metrics)
        assert code == 0, err
        outputs[metrics] = [json.loads((out / name).read_text()) for name in ("metrics.json", "robustness.json")]
    for fast, reference in zip(outputs["numpy"], outputs["pycocotools"], strict=True):
        assert len(fast) == len(reference)
        for fast_row, reference_row in zip(fast, reference, strict=True):
            assert list(fast_row) == list(reference_row)  # same keys, same order
            for key, value in fast_row.items():
                if isinstance(value, float):
                    assert reference_row[key] == pytest.approx(value, abs=1e-9), key
                else:
                    assert reference_row[key] == value, key
    assert any(0.0 < row["ap50"] < 1.0 for row in outputs["numpy"][0] if row["ap50"] is not None)
    with pytest.raises(SystemExit) as exit_info:  # argparse refuses it, in one line
        cli.main(["eval", "--data", str(data_dir), "--predictions", str(preds), "--out", str(tmp_path / "x"),
                  "--metrics", "fast"])
    assert exit_info.value.code == 2
    _one_line_error(capsys.readouterr().err, "--metrics", "'fast'")
    with pytest.raises(pipeline.EvalError, match=r"--metrics: expected one of numpy, pycocotools, got 'fast'"):
        pipeline.run_eval(data_dir, tmp_path / "y", predictions_dir=preds, n_boot=5, progress=False, metrics="fast")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_bad_prediction_files_name_the_file(data_dir, tmp_path):
    records = _perfect_records(data_dir)
    preds = tmp_path / "preds"
    _write_predictions(preds, "m", records, rates=(0.0,))
    with pytest.raises(pipeline.EvalError, match="rate_50.json is missing"):
        pipeline.run_eval(data_dir, tmp_path / "out", predictions_dir=preds, n_boot=5, progress=False)
    (preds / "m" / "rate_50.json").write_text("[{not json")
    with pytest.raises(pipeline.EvalError, match="rate_50.json is not valid JSON"):
        pipeline.run_eval(data_dir, tmp_path / "out", predictions_dir=preds, n_boot=5, progress=False)
    bad_class = [dict(records[0], category_id=9)]
    (preds / "m" / "rate_50.json").write_text(json.dumps(bad_class))
    with pytest.raises(pipeline.EvalError, match="rate_50.json: record 0: category_id 9"):
        pipeline.run_eval(data_dir, tmp_path / "out", predictions_dir=preds, n_boot=5, progress=False)
    (preds / "m" / "rate_50.json").write_text(json.dumps([dict(records[0], image_id=99)]))
    with pytest.raises(pipeline.EvalError, match="image_id 99 is not an image"):
        pipeline.run_eval(data_dir, tmp_path / "out", predictions_dir=preds, n_boot=5, progress=False)


class _FakeDetector:
    """Returns the frame's own labels (found by image equality) as detections; counts calls."""

    def __init__(self, name, truth):
        self.name, self.truth, self.calls = name, truth, 0

    def predict(self, images, *, imgsz, conf, iou, max_det):
        self.calls += 1
        outputs = []
        for image in images:
            boxes, class_ids = self.truth(image)
            outputs.append((boxes, np.full(len(boxes), 0.9, np.float32), class_ids))
        return outputs


def test_the_cache_knows_weights_by_their_bytes_and_a_darknet_cfg(tmp_path):
    """Weights were known by path, size and mtime: a same-size file copied in with its time
    (`cp -p`, `rsync -a`) served the old model's detections; a Darknet .cfg was not looked at."""
    import os

    weights = tmp_path / "m.weights"
    weights.write_bytes(b"a" * 64)
    (tmp_path / "m.cfg").write_text("[net]\nwidth=64\n")
    settings = dict(imgsz=64, conf=0.25, iou=0.7, max_det=300, class_map=None, classes=[0, 2])
    before = pipeline._cache_settings(weights, **settings)
    stat = weights.stat()
    weights.write_bytes(b"b" * 64)
    os.utime(weights, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    after_weights = pipeline._cache_settings(weights, **settings)
    assert after_weights != before and after_weights["weights"] == before["weights"]
    (tmp_path / "m.cfg").write_text("[net]\nwidth=128\n")
    assert pipeline._cache_settings(weights, **settings) != after_weights
    assert pipeline._cache_settings(weights, **settings) == pipeline._cache_settings(weights, **settings)


def test_backend_detections_are_cached_and_reused(data_dir, tmp_path, monkeypatch):
    by_bytes = {}
    for _, shard, frame in _images(data_dir):
        with open_shard(shard) as handle:
            labels = read_frame_labels(handle, frame)
            for rate_index in range(len(RATES)):
                by_bytes[handle["rgb"][rate_index, frame].tobytes()] = (labels["bbox"], labels["class_id"])
    loads = []

    def fake_load(weights, *, class_map=None, device=None, pt_backend="batched"):
        detector = _FakeDetector(weights.stem, lambda image: by_bytes[np.asarray(image).tobytes()])
        loads.append(detector)
        return detector

    monkeypatch.setattr(backends, "load_detector", fake_load)
    weights = tmp_path / "fake.pt"
    weights.write_bytes(b"not used")
    out = tmp_path / "out"
    first = pipeline.run_eval(data_dir, out, weights=[weights], n_boot=5, batch=1, progress=False)
    assert first.inference_runs == len(RATES) and len(loads) == 1 and loads[0].calls == 2 * len(RATES)
    for rate in RATES:
        assert (out / "predictions" / "fake" / f"rate_{pipeline.rate_token(rate)}.json").is_file()
    assert all(r["ap50"] == pytest.approx(1.0) for r in first.records if r["n_gt"] > 0)
    second = pipeline.run_eval(data_dir, out, weights=[weights], n_boot=5, progress=False)
    assert second.inference_runs == 0 and len(loads) == 1
    assert json.dumps(second.records) == json.dumps(first.records)
    forced = pipeline.run_eval(data_dir, out, weights=[weights], n_boot=5, force=True, progress=False)
    assert forced.inference_runs == len(RATES) and len(loads) == 2
    # Other settings invalidate the cache.
    pipeline.run_eval(data_dir, out, weights=[weights], n_boot=5, conf=0.2, progress=False)
    assert len(loads) == 3
    # So does the way a .pt runs (its detections differ slightly).
    pipeline.run_eval(data_dir, out, weights=[weights], n_boot=5, conf=0.2, pt_backend="ultralytics",
                      progress=False)
    assert len(loads) == 4
    settings = json.loads((out / "predictions" / "fake" / "settings.json").read_text())
    assert settings["pt_backend"] == "ultralytics" and settings["cuda"] is False


def test_a_dataset_regenerated_in_place_is_inferred_again(tmp_path, monkeypatch):
    # make dataset SEED=1; make eval; make dataset SEED=2; make eval: the same folders, other images
    loads = []

    def fake_load(weights, *, class_map=None, device=None, pt_backend="batched"):
        detector = _FakeDetector(weights.stem, lambda image: (np.zeros((0, 4), np.float32), np.zeros(0, np.int64)))
        loads.append(detector)
        return detector

    monkeypatch.setattr(backends, "load_detector", fake_load)
    weights = tmp_path / "fake.pt"
    weights.write_bytes(b"not used")
    data, out = tmp_path / "data", tmp_path / "out"
    config = dict(frames=2, width=64, height=48, rates=RATES)
    generate_shard(GenerateConfig(seed=1, **config), data)
    pipeline.run_eval(data, out, weights=[weights], n_boot=5, batch=1, progress=False)
    assert pipeline.run_eval(data, out, weights=[weights], n_boot=5, progress=False).inference_runs == 0
    generate_shard(GenerateConfig(seed=1, rain_seed=7, **config), data)  # other drops, same clean frames
    again = pipeline.run_eval(data, out, weights=[weights], n_boot=5, batch=1, progress=False)
    assert again.inference_runs == 1 and loads[-1].calls == 2  # only 50 mm/h: its two images changed
    generate_shard(GenerateConfig(seed=2, **config), data)  # another scene under the same file name
    assert pipeline.run_eval(data, out, weights=[weights], n_boot=5, progress=False).inference_runs == len(RATES)
    settings = json.loads((out / "predictions" / "fake" / "settings.json").read_text())
    assert set(settings["images"]) == {"0", "50"}


def test_class_map_logic_with_fake_names():
    coco = {i: n for i, n in enumerate(["person", "bicycle", "car", "motorcycle", "airplane", "bus"])}
    assert class_lookup(coco, None, "m").tolist() == [0, 1, 2, 3, -1, -1]
    other = {0: "pedestrian", 1: "car", 2: "truck"}
    with pytest.raises(backends.BackendError, match="not COCO-80; pass --class-map"):
        class_lookup(other, None, "m")
    assert class_lookup(other, "car=2,pedestrian=0", "m").tolist() == [0, 2, -1]
    assert class_lookup(["a", "b"], "b=3", "m").tolist() == [-1, 3]
    with pytest.raises(backends.BackendError, match="no class named 'bus'"):
        class_lookup(other, "bus=2", "m")
    assert parse_class_map(" car = 2 , pedestrian=0") == {"car": 2, "pedestrian": 0}
    for spec in ("car", "car=9", "car=x", "=2", "", "car=2,car=1"):
        with pytest.raises(backends.BackendError, match="--class-map"):
            parse_class_map(spec)


COCO_NAMES = ["person", "bicycle", "car", "motorcycle"] + [f"coco{i}" for i in range(4, 80)]


@pytest.fixture(scope="module")
def tiny_yolo(tmp_path_factory):
    """A yolo11n with random weights and COCO-80 names, saved as a .pt (no download)."""
    _offline_ultralytics()
    from ultralytics import YOLO

    path = tmp_path_factory.mktemp("weights") / "tiny11n.pt"
    model = YOLO("yolo11n.yaml")
    model.model.names = dict(enumerate(COCO_NAMES))
    model.save(str(path))
    return path


@pytest.mark.parametrize("pt_backend", ["batched", "ultralytics"])
def test_ultralytics_backend_end_to_end(data_dir, tiny_yolo, tmp_path, pt_backend):
    from rainbench.eval.backends.torch_batched import TorchDetector
    from rainbench.eval.backends.ultralytics import UltralyticsDetector

    detector = backends.load_detector(tiny_yolo, device="cpu", pt_backend=pt_backend)
    assert isinstance(detector, TorchDetector if pt_backend == "batched" else UltralyticsDetector)
    assert detector.name == "tiny11n"
    images = []
    for _, shard, frame in _images(data_dir):
        with open_shard(shard) as handle:
            images.append(handle["rgb"][1, frame])
    outputs = detector.predict(images, imgsz=96, conf=0.0001, iou=0.7, max_det=50)
    assert len(outputs) == 2
    for boxes, scores, class_ids in outputs:
        assert boxes.dtype == np.float32 and boxes.ndim == 2 and boxes.shape[1] == 4
        assert scores.shape == class_ids.shape == (len(boxes),) and len(boxes) <= 50
        assert set(class_ids.tolist()) <= {0, 1, 2, 3}
        assert (boxes[:, 0] >= 0).all() and (boxes[:, 2] <= 96).all()
        assert (boxes[:, 1] >= 0).all() and (boxes[:, 3] <= 72).all()
        assert (boxes[:, 2] >= boxes[:, 0]).all() and (boxes[:, 3] >= boxes[:, 1]).all()
    # The whole pipeline on the real backend.
    result = pipeline.run_eval(data_dir, tmp_path / "out", weights=[tiny_yolo], imgsz=96, n_boot=5,
                               device="cpu", progress=False, pt_backend=pt_backend, workers=1)
    assert result.inference_runs == len(RATES)
    assert {r["model"] for r in result.records} == {"tiny11n"}
    # Non-COCO names need a class map.
    with pytest.raises(backends.BackendError, match="not COCO-80"):
        class_lookup(dict(enumerate(COCO_NAMES)) | {0: "ped"}, None, "x")


def test_cli_one_line_errors(data_dir, tmp_path, capsys):
    out = tmp_path / "out"
    code, _, err = _run(capsys, "eval", "--data", data_dir, "--weights", tmp_path / "nope.pt", "--out", out)
    assert code == 2
    _one_line_error(err, "nope.pt does not exist")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"garbage")
    code, _, err = _run(capsys, "eval", "--data", data_dir, "--weights", garbage, "--out", out, "--quiet")
    assert code == 2
    _one_line_error(err, "garbage.pt is not a loadable ultralytics checkpoint")
    code, _, err = _run(capsys, "eval", "--data", data_dir, "--weights", garbage, "--out", out,
                        "--class-map", "car=4")
    assert code == 2
    _one_line_error(err, "--class-map")
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = _run(capsys, "eval", "--data", empty, "--predictions", tmp_path, "--out", out)
    assert code == 2
    _one_line_error(err, "no shard", str(empty))
    preds = tmp_path / "preds"
    _write_predictions(preds, "m", [], rates=(0.0,))
    code, _, err = _run(capsys, "eval", "--data", data_dir, "--predictions", preds, "--out", out)
    assert code == 2
    _one_line_error(err, "rate_50.json is missing")
    code, _, err = _run(capsys, "eval", "--data", data_dir, "--out", out)
    assert code == 2
    _one_line_error(err, "exactly one of --weights")
    for flags, message in ((["--workers", "-1"], "WORKERS: expected >= 0, got -1"),
                           (["--pt-backend", "onnx"], "--pt-backend: invalid choice: 'onnx'")):
        with pytest.raises(SystemExit) as exit_info:  # argparse refuses it, in one line
            _run(capsys, "eval", "--data", data_dir, "--weights", garbage, "--out", out, *flags)
        assert exit_info.value.code == 2
        _one_line_error(capsys.readouterr().err, message)


def test_cli_refuses_a_device_it_cannot_use(data_dir, tiny_yolo, tmp_path, capsys):
    code, _, err = _run(capsys, "eval", "--data", data_dir, "--weights", tiny_yolo, "--out", tmp_path / "out",
                        "--device", "tpu", "--quiet")
    assert code == 2
    _one_line_error(err, "--device: expected auto, cpu, cuda, cuda:N or CUDA indices (0 or 0,1), got 'tpu'")
    assert not (tmp_path / "out" / "metrics.json").exists()
