"""rainbench eval on bad input and failing writes: absurd boxes are refused naming the file, a
failure while writing leaves no report that looks finished and names the file, the detection
strip draws any box, the detection cache is never half-written and a broken one suggests --force."""

import errno
import json
import os
import pathlib
import re

import numpy as np
import pytest
from labelled_shards import write_labelled_shard

from rainbench import cli
from rainbench.eval import backends, pipeline
from rainbench.eval.report.figures import plot_detection_strip
from rainbench.store.locks import directory_lock

RATES = (0.0, 50.0)
FRAMES = [[(0, 0, (10, 10, 20, 40), 1.0, 0.0)], [(2, 1, (30, 30, 60, 50), 1.0, 0.0)]]
GOOD = [{"image_id": 1, "category_id": 0, "bbox": [10, 10, 10, 30], "score": 0.9},
        {"image_id": 2, "category_id": 2, "bbox": [30, 30, 30, 20], "score": 0.8}]
HUGE = {"image_id": 1, "category_id": 2, "bbox": [1e20, 1, 5, 5], "score": 0.9}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    write_labelled_shard(data, FRAMES, rates=RATES)
    return data


def _predictions(root, by_rate):
    for rate, records in by_rate.items():
        path = root / "m" / f"rate_{pipeline.rate_token(rate)}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(records))
    return root


def _eval(data_dir, preds, out):
    return pipeline.run_eval(data_dir, out, predictions_dir=preds, n_boot=3, progress=False)


def _left(out):
    """Report outputs and staging folders under ``out``."""
    if not out.exists():
        return []
    return sorted(p.name for p in out.iterdir() if p.name in pipeline.REPORT_OUTPUTS or p.name.startswith(".report"))


def test_a_huge_box_is_refused_naming_the_file_record_and_value(data_dir, tmp_path, capsys):
    preds = _predictions(tmp_path / "preds", {0.0: GOOD + [HUGE], 50.0: GOOD})
    out = tmp_path / "out"
    where = re.escape(f"{preds / 'm' / 'rate_0.json'}: record 2: bbox [1e+20, 1, 5, 5] is not an image box")
    with pytest.raises(ValueError, match=where + r".*at most 1000000 pixels"):
        _eval(data_dir, preds, out)
    assert not (out / "report.md").exists() and _left(out) == []
    code = cli.main(["eval", "--data", str(data_dir), "--predictions", str(preds), "--out", str(out), "--quiet",
                     "--n-boot", "3"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("rainbench: error: ") and "record 2" in err[0], err
    assert not (out / "report.md").exists()


@pytest.mark.parametrize("bbox, ok", [([1e6, -1e6, 1e6, 1e6], True), ([-1e6 - 1, 0, 5, 5], False),
                                      ([0, 1e6 + 1, 5, 5], False), ([0, 0, 2e6, 5], False),
                                      ([0, 0, 5, 1e300], False)])
def test_the_box_bound_is_a_million_pixels(bbox, ok):
    records = [{"image_id": 1, "category_id": 0, "bbox": bbox, "score": 0.5}]
    if ok:
        assert pipeline.check_detections(records, {1}, "f.json")[0]["bbox"] == bbox
    else:
        with pytest.raises(pipeline.EvalError, match=r"^f\.json: record 0: bbox .* is not an image box"):
            pipeline.check_detections(records, {1}, "f.json")


def _fail_strip_write(monkeypatch):
    real = pathlib.Path.write_bytes

    def write_bytes(self, data):
        if self.name == "detections_strip.png":
            real(self, data[:10])  # half a file, then the disk is full
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)

    monkeypatch.setattr(pathlib.Path, "write_bytes", write_bytes)


def _fail_report_write(monkeypatch):
    real = pathlib.Path.write_text

    def write_text(self, text, *args, **kwargs):
        if self.name == "report.md":
            real(self, text[:20], *args, **kwargs)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, text, *args, **kwargs)

    monkeypatch.setattr(pathlib.Path, "write_text", write_text)


def _fail_plot(monkeypatch):
    def plot(records, metric, out_png, **kwargs):
        if metric == "f1":
            raise OSError(errno.ENOSPC, "No space left on device")
        pathlib.Path(out_png).write_bytes(b"png")
        return out_png

    monkeypatch.setattr(pipeline, "plot_metric_vs_rate", plot)


@pytest.mark.parametrize("fail, name", [(_fail_strip_write, "detections_strip.png"),
                                        (_fail_report_write, "report.md"), (_fail_plot, "f1_vs_rate.png")])
def test_a_failed_write_leaves_no_report_and_names_the_file(data_dir, tmp_path, monkeypatch, capsys, fail, name):
    preds = _predictions(tmp_path / "preds", {0.0: GOOD, 50.0: GOOD})
    out = tmp_path / "out"
    _eval(data_dir, preds, out)  # a finished earlier run: its outputs must not pass for this one's
    assert _left(out) == sorted(pipeline.REPORT_OUTPUTS)
    fail(monkeypatch)
    with pytest.raises(OSError, match=f"^{re.escape(str(out / name))}: No space left on device$") as info:
        _eval(data_dir, preds, out)
    assert info.value.errno == errno.ENOSPC
    assert _left(out) == []
    code = cli.main(["eval", "--data", str(data_dir), "--predictions", str(preds), "--out", str(out), "--quiet",
                     "--n-boot", "3"])
    assert code == 2
    assert capsys.readouterr().err == f"rainbench: error: {out / name}: No space left on device\n"
    assert _left(out) == [] and not (out / "report.md").exists() and not (out / "metrics.json").exists()
    monkeypatch.undo()
    assert _left(out) == []
    _eval(data_dir, preds, out)
    assert _left(out) == sorted(pipeline.REPORT_OUTPUTS)


def test_a_run_killed_while_writing_leaves_no_staging_behind_the_next(data_dir, tmp_path):
    preds = _predictions(tmp_path / "preds", {0.0: GOOD, 50.0: GOOD})
    out = tmp_path / "out"
    stale = out / ".report.tmp-killed"
    stale.mkdir(parents=True)
    (stale / "report.md").write_text("half")
    _eval(data_dir, preds, out)
    assert not stale.exists() and _left(out) == sorted(pipeline.REPORT_OUTPUTS)


def test_a_failed_cache_write_leaves_no_half_file(tmp_path, monkeypatch):
    path = tmp_path / "predictions" / "m" / "rate_0.json"
    real = pathlib.Path.write_text

    def write_text(self, text, *args, **kwargs):
        real(self, text[:5], *args, **kwargs)  # half a file, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pathlib.Path, "write_text", write_text)
    with pytest.raises(OSError, match=f"^{re.escape(str(path))}: No space left on device$"):
        pipeline._write_json(path, GOOD)
    assert list(path.parent.iterdir()) == []
    monkeypatch.undo()
    pipeline._write_json(path, GOOD)
    assert json.loads(path.read_text()) == GOOD and [p.name for p in path.parent.iterdir()] == ["rate_0.json"]


def test_the_strip_draws_boxes_far_outside_the_image(tmp_path):
    frame = np.full((40, 60, 3), 100, np.uint8)
    far = [[1e9, 5, 10, 10], [5, 5, 1e9, 1e9], [-1e9, -1e9, 2e9, 2e9], [1e308, 1, 1e308, 5],
           [float("nan"), 0, 5, 5], [-1e9, 5, 10, 10]]
    detections = [{"image_id": 1, "category_id": 2, "bbox": box, "score": 0.9} for box in far]
    path = plot_detection_strip({0.0: frame, 50.0: frame}, {0.0: detections}, tmp_path / "strip.png")
    assert path.is_file() and path.stat().st_size > 0
    import cv2

    drawn = cv2.imread(str(path))
    assert (drawn[28 + 5 : 28 + 40, 5] != 100).any()  # the box from (5, 5) to far away: its left edge is drawn


def _fake_load(weights, *, class_map=None, device=None, **_):
    class Detector:
        name = weights.stem

        def predict(self, images, *, imgsz, conf, iou, max_det):
            return [(np.array([[10, 10, 20, 40]], np.float32), np.array([0.9], np.float32), np.array([0]))
                    for _ in images]

    return Detector()


def test_a_broken_cache_file_suggests_force(data_dir, tmp_path, monkeypatch):
    monkeypatch.setattr(backends, "load_detector", _fake_load)
    weights = tmp_path / "fake.onnx"
    weights.write_bytes(b"not used")
    out = tmp_path / "out"
    first = pipeline.run_eval(data_dir, out, weights=[weights], n_boot=3, device="cpu", progress=False)
    assert first.inference_runs == len(RATES)
    cache = out / "predictions" / "fake" / "rate_50.json"
    assert sorted(p.name for p in cache.parent.iterdir()) == ["rate_0.json", "rate_50.json", "settings.json"]
    cache.write_text('[{"image_id": 1')
    with pytest.raises(pipeline.EvalError, match=re.escape(f"{cache} is not valid JSON") + r".*add --force to infer it again"):
        pipeline.run_eval(data_dir, out, weights=[weights], n_boot=3, device="cpu", progress=False)
    forced = pipeline.run_eval(data_dir, out, weights=[weights], n_boot=3, device="cpu", force=True, progress=False)
    assert forced.inference_runs == len(RATES) and (out / "report.md").is_file()
    # a user's predictions file gets no such hint: --force does not rewrite it
    preds = _predictions(tmp_path / "preds", {0.0: GOOD, 50.0: GOOD})
    (preds / "m" / "rate_50.json").write_text("[{")
    with pytest.raises(pipeline.EvalError, match="is not valid JSON") as info:
        _eval(data_dir, preds, tmp_path / "other")
    assert "--force" not in str(info.value)


def test_a_second_eval_into_a_busy_out_is_refused_and_leaves_the_first_s_files(data_dir, tmp_path, capsys):
    """Two evals into one --out removed each other's staging folder and crashed; the second is
    now refused in one line naming the holder, before any inference or write."""
    preds = _predictions(tmp_path / "preds", {0.0: GOOD, 50.0: GOOD})
    out = tmp_path / "out"
    out.mkdir()
    staging = out / ".report.tmp-first"  # the first run's files being written
    staging.mkdir()
    with directory_lock(out, "eval", option="--out", error=ValueError):
        code = cli.main(["eval", "--data", str(data_dir), "--predictions", str(preds), "--out", str(out), "--quiet",
                         "--n-boot", "3"])
        assert staging.is_dir()
    assert code == 2
    assert capsys.readouterr().err == (f"rainbench: error: --out: {out} is being written by another rainbench eval "
                                       f"(pid {os.getpid()}); wait for it to finish or choose another --out\n")
    assert _left(out) == [".report.tmp-first"]
    staging.rmdir()
    _eval(data_dir, preds, out)  # released
    assert _left(out) == sorted(pipeline.REPORT_OUTPUTS) and not (out / ".rainbench.lock").exists()
