"""Bad inputs to the library's own functions (not the CLI): one-line errors naming the thing,
never a silent wrong answer. Found by an audit of the docstrings against the code."""

import h5py
import numpy as np
import pytest
from labelled_shards import write_labelled_shard

from rainbench import store
from rainbench.gen.config import DatasetConfig, GenerateConfig
from rainbench.gen.labels import LabelFilter
from rainbench.mjcf.layout import ScenarioConfig
from rainbench.rain import physical
from rainbench.rain.weather import weather_at
from rainbench.store.labels import FrameLabels
from rainbench.store.rates import parse_rates
from rainbench.store.shard import ShardWriter, read_frame_ignore, read_frame_labels

FRAMES = [[(2, 0, (1, 1, 9, 9), 1.0, 0.0), (0, 1, (20, 2, 30, 40), 1.0, 0.0)],
          [(2, 0, (2, 1, 10, 9), 1.0, 0.0)]]


def test_a_frame_outside_the_shard_is_an_error_naming_the_file(tmp_path):
    """A negative frame read the rows offsets[-1]:offsets[0], an empty slice: no labels, silently."""
    path = write_labelled_shard(tmp_path, FRAMES)
    with h5py.File(path, "r") as handle:
        assert read_frame_labels(handle, 0)["class_id"].tolist() == [2, 0]
        assert read_frame_labels(handle, np.int64(1))["bbox"].shape == (1, 4)
        for frame in (-1, 2, 1.0, True):
            with pytest.raises(IndexError, match=rf"{path.name}: frame {frame!r} is outside its 2 frames "
                                                 r"\(expected an int in 0\.\.1\)"):
                read_frame_labels(handle, frame)
            with pytest.raises(IndexError, match=r"outside its 2 frames"):
                read_frame_ignore(handle, frame)


def test_frames_of_classes_take_names_and_refuse_what_is_not_labelled(tmp_path):
    """``classes=[9]`` or ``[]`` gave every frame without labels, ``['car']`` a raw int() error."""
    path = write_labelled_shard(tmp_path, FRAMES)
    dataset = store.Dataset(path)
    by_name = [frame.labels["class_id"].tolist() for frame in dataset.frames(classes=["car"])]
    by_id = [frame.labels["class_id"].tolist() for frame in dataset.frames(classes=[2])]
    assert by_name == by_id == [[2], [2]]
    for classes, message in (([9], r"classes: .*9"), ([], r"classes"), ("car", r"classes: expected a list"),
                             (["lorry"], r"classes: .*lorry")):
        with pytest.raises(store.DatasetError, match=message):
            next(iter(dataset.frames(classes=classes)))


def _writer(tmp_path, **kwargs):
    return ShardWriter(tmp_path / "x.h5", attrs={"class_names": '["person"]'}, rates=np.zeros(2, np.float32),
                       num_frames=1, width=16, height=12, K=np.eye(3), **kwargs)


def test_the_writer_refuses_wrong_shapes_when_written_not_when_read(tmp_path):
    """Per-box rain labels of another shape were committed and then refused by every reader."""
    labels = FrameLabels(bbox=np.array([[1, 1, 5, 5]], np.float32), bbox_amodal=np.array([[1, 1, 5, 5]], np.float32),
                         class_id=np.zeros(1, np.int32), instance_id=np.zeros(1, np.int32),
                         visible_fraction=np.ones(1, np.float32), truncation=np.zeros(1, np.float32))
    rgb = np.zeros((2, 12, 16, 3), np.uint8)
    with _writer(tmp_path, threads=1) as writer:
        with pytest.raises(ValueError, match=r"rain_coverage: expected \(2, 1\) \(rates, labels of frame 0\), "
                                             r"got \(2, 3\)"):
            writer.write_frame(0, rgb, labels, np.eye(4), rain_coverage=np.zeros((2, 3)))
        with pytest.raises(ValueError, match=r"T_world_cam: expected a \(4, 4\) pose, got \(3, 4\)"):
            writer.write_frame(0, rgb, labels, np.eye(4)[:3])
        # nothing of the refused frame was stored: the frame is still missing
        with pytest.raises(RuntimeError, match=r"shard x\.h5: frames \[0\] were never written"):
            writer.commit()
    assert list(tmp_path.iterdir()) == []  # the aborted writer's temporary file is gone
    for threads in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match=r"threads: expected an integer >= 1 or None"):
            _writer(tmp_path, threads=threads)
        assert list(tmp_path.iterdir()) == []  # refused before any file was made


def test_a_sky_layout_or_time_given_twice_must_agree():
    """The config's value silently won over the scenario's."""
    with pytest.raises(Exception, match=r"sky: 'overcast' disagrees with scenario.sky 'clear'; give it once"):
        GenerateConfig(sky="overcast", scenario=ScenarioConfig(sky="clear"))
    with pytest.raises(Exception, match=r"layout: 'street' disagrees with scenario.layout 'highway'"):
        DatasetConfig(layout="street", scenario=ScenarioConfig(layout="highway"))
    same = GenerateConfig(sky="clear", scenario=ScenarioConfig(sky="clear"))
    assert same.scenario_config().sky == "clear"


@pytest.mark.parametrize("field, value, message", [
    ("min_box_height", float("nan"), r"min_box_height: expected a finite number >= 0 px, got nan"),
    ("min_box_height", "8", r"min_box_height: expected a finite number >= 0 px, got '8'"),
    ("min_visible_fraction", float("inf"), r"min_visible_fraction: expected a number in 0\.\.1, got inf"),
    ("min_visible_pixels", 2.5, r"min_visible_pixels: expected an integer >= 1, got 2\.5"),
])
def test_label_filter_thresholds_are_checked(field, value, message):
    """NaN passed ``< 0`` and turned every actor into an ignore region."""
    with pytest.raises(ValueError, match=message):
        LabelFilter(**{field: value})
    assert LabelFilter(min_box_height=np.float32(4), min_visible_pixels=np.int64(3)).min_visible_pixels == 3


def test_rain_laws_refuse_negative_rates_and_take_arrays():
    """A negative rate gave NaN with a warning; ``visibility_km`` of an array raised numpy's
    "truth value of an array is ambiguous"."""
    for law in (physical.extinction_coefficient, physical.visibility_km, physical.marshall_palmer_slope):
        with pytest.raises(ValueError, match=r"rate_mm_h: expected finite rates >= 0 mm/h, got -1"):
            law(-1)
    with pytest.raises(ValueError, match=r"^rate_mm_h: expected finite rates >= 0 mm/h, got np\.float64\(-2\.0\) "
                                         r"among 30 rates$"):
        physical.extinction_coefficient(np.r_[np.zeros(20), -2.0, np.ones(9)])
    visibility = physical.visibility_km(np.array([0.0, 10.0]))
    assert visibility[0] == np.inf and visibility[1] == pytest.approx(physical.visibility_km(10.0))
    with pytest.raises(ValueError, match=r"rate_mm_h: expected a finite rate >= 0 mm/h, got -5"):
        weather_at("clear", -5, follows_rate=False)


def test_the_documented_range_count_is_the_code_s():
    """The docstring's ``floor((stop - start) / step + 1e-9) + 1`` gave 1000 here, the code 1001."""
    span = 1000 / 1.0000000005
    assert len(parse_rates("0:1000:1.0000000005")) == int(np.floor(span + 1e-9 * max(1.0, span))) + 1 == 1001


def test_previews_and_videos_check_what_they_are_given(tmp_path):
    """R = 0 divided by zero, ``columns=0`` became 4, boxes without class ids raised a TypeError,
    and a numpy fps (what a shard's attribute reads as) was refused."""
    from rainbench.store.preview import montage  # noqa: PLC0415
    from rainbench.store.video import write_videos  # noqa: PLC0415

    images, rates = np.zeros((2, 24, 32, 3), np.uint8), np.array([0.0, 50.0])
    with pytest.raises(ValueError, match=r"images: expected at least one image, got none \(R = 0\)"):
        montage(images[:0], rates[:0])
    with pytest.raises(ValueError, match=r"columns: expected a positive integer or None \(up to 4\), got 0"):
        montage(images, rates, columns=0)
    with pytest.raises(ValueError, match=r"class_ids: expected one class id per box with boxes, got none"):
        montage(images, rates, boxes=np.array([[1, 1, 5, 5]]))
    assert montage(images, rates, columns=1, tile_width=32).shape == (48, 32, 3)
    path = write_labelled_shard(tmp_path / "data", FRAMES)
    videos = write_videos(path, tmp_path / "videos", fps=np.float32(10))
    assert [video.name for video in videos] == ["rate_0.mp4"] and videos[0].stat().st_size > 0


def test_detections_must_be_finite_and_verify_names_a_missing_folder(tmp_path):
    from rainbench.eval.metrics.coco import coco_detections  # noqa: PLC0415

    with pytest.raises(ValueError, match=r"boxes/scores of image 3: expected finite values, got NaN or inf"):
        coco_detections(3, np.array([[0, 0, np.nan, 5]]), np.array([0.5]), np.array([2]))
    assert coco_detections(3, np.array([[0, 0, 4, 5]]), np.array([0.5]), np.array([2]))[0]["bbox"] == [0, 0, 4, 5]
    assert store.verify_dataset(tmp_path / "nothing") == [f"{tmp_path / 'nothing'}: no such dataset folder"]
    shard = write_labelled_shard(tmp_path / "data", FRAMES)
    assert store.verify_dataset(shard) == [f"{shard}: not a dataset folder (a file; a dataset is a folder "
                                           "with manifest.json)"]


def test_run_eval_refuses_inference_settings_it_would_ignore(tmp_path):
    """With predictions_dir, the detector settings did nothing, silently (the CLI refused their
    flags, the function did not); a batch of "32x" raised int()'s own message."""
    from rainbench.eval.pipeline import EvalError, run_eval  # noqa: PLC0415

    for settings, message in (({"batch": 16}, r"batch: has no effect with predictions_dir .* leave it at 32"),
                              ({"device": "cpu"}, r"device: has no effect with predictions_dir"),
                              ({"force": True}, r"force: has no effect with predictions_dir")):
        with pytest.raises(EvalError, match=message):
            run_eval(tmp_path / "data", tmp_path / "out", predictions_dir=tmp_path / "preds", **settings)
    with pytest.raises(EvalError, match=r"^--batch: expected an integer >= 1, got '32x'$"):
        run_eval(tmp_path / "data", tmp_path / "out", weights=["m.pt"], batch="32x")
    with pytest.raises(EvalError, match=r"^--conf: expected a value in \[0, 1\], got 'high'$"):
        run_eval(tmp_path / "data", tmp_path / "out", weights=["m.pt"], conf="high")
    assert not (tmp_path / "out").exists()


def test_the_ray_executor_without_ray_writes_nothing(tmp_path, monkeypatch):
    """The missing Ray was found after OUT was made: an empty dataset folder was left behind."""
    import importlib.util  # noqa: PLC0415

    from rainbench.gen import dataset as ds  # noqa: PLC0415

    import sys  # noqa: PLC0415

    find_spec = importlib.util.find_spec
    monkeypatch.delitem(sys.modules, "ray", raising=False)  # as in a process that never imported it
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *args: None if name == "ray" else find_spec(name, *args))
    with pytest.raises(ds.DatasetError, match=r"^executor ray: Ray is not installed; pip install 'rainbench\[ray\]'$"):
        ds.run_dataset(DatasetConfig(frames=1, width=32, height=24), tmp_path / "out", executor="ray")
    assert not (tmp_path / "out").exists()


def test_the_version_is_one_number_everywhere():
    """``rainbench.__version__`` (stored in every shard as ``generator_version``) is written by hand
    beside pyproject.toml's: the two, and the installed metadata, must not drift apart."""
    import importlib.metadata  # noqa: PLC0415
    import tomllib  # noqa: PLC0415
    from pathlib import Path  # noqa: PLC0415

    import rainbench  # noqa: PLC0415

    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    assert rainbench.__version__ == pyproject["project"]["version"] == importlib.metadata.version("rainbench")
