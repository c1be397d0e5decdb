"""The generator's configs (rainbench.gen.config): one definition of the fields, every field
checked when a config is built, before anything renders."""

import dataclasses
import re

import pytest

from rainbench import cli
from rainbench.experiments import train
from rainbench.gen import config as gc
from rainbench.gen.config import ClipConfig, DatasetConfig, GenerateConfig
from rainbench.mjcf.layout import ScenarioConfig
from rainbench.rain.config import RAIN_OPTIONS, RainConfig

RECIPE = """
name: bad-rain
architecture: yolo11n.yaml
train_data: {seed: 1000000, frames: 2, width: 96, height: 72, rain_options: {OPTIONS}}
val_data: {seed: 2000000, frames: 2, width: 96, height: 72}
train: {epochs: 1, imgsz: 64}
"""


@pytest.mark.parametrize("kind", [DatasetConfig, GenerateConfig])
@pytest.mark.parametrize("options, pattern", [
    ({"exposure": 0.01}, r"rain_options: unknown option 'exposure'; expected some of exposure_s, "),
    ({"model": "physical"}, r"rain_options: unknown option 'model'; "),
    ({"exposure_s": -1.0}, r"rain_options: RainConfig\.exposure_s must be a finite number > 0, "
                           r"got -1\.0"),
    ({"airlight_rgb": 7}, r"rain_options: RainConfig\.airlight_rgb must be None or three numbers"),
    ({"lens_life_min_s": 1.0, "lens_fade_s": 0.6}, r"rain_options: RainConfig\.lens_fade_s must be "
                                                   r"at most half of lens_life_min_s"),
])
def test_a_bad_rain_option_fails_when_the_config_is_built(kind, options, pattern):
    with pytest.raises(ValueError, match=pattern) as error:
        kind(rain_model="physical", rain_options=options)
    assert "\n" not in str(error.value)


def test_good_rain_options_give_the_rain_config_the_shards_are_drawn_with():
    config = DatasetConfig(rain_model="physical", rain_options={"exposure_s": 0.01,
                                                                "airlight_rgb": [200, 190, 180]})
    assert config.rain_config() == RainConfig(model="physical", exposure_s=0.01,
                                              airlight_rgb=(200.0, 190.0, 180.0))
    assert all(task.rain_config() == config.rain_config() for task in config.tasks())
    assert set(RAIN_OPTIONS) == {f.name for f in dataclasses.fields(RainConfig)} - {"model"}


def test_a_bad_rain_option_in_a_recipe_fails_before_anything_is_written(tmp_path, capsys):
    recipe = tmp_path / "bad.yaml"
    recipe.write_text(RECIPE.replace("{OPTIONS}", "{streak_length: 3}"))
    with pytest.raises(train.TrainError, match=r"`train_data`: rain_options: unknown option "
                                               r"'streak_length'"):
        train.load_recipe(recipe)
    out = tmp_path / "run"
    assert cli.main(["train", "--recipe", str(recipe), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'streak_length'" in err[0] and not out.exists()
    recipe.write_text(RECIPE.replace("{OPTIONS}", "{lens_opacity: 2}"))
    with pytest.raises(train.TrainError, match=r"`train_data`: rain_options: "
                                               r"RainConfig\.lens_opacity must be a number in \[0, 1\]"):
        train.load_recipe(recipe)


def test_the_seed_limit_is_one_constant(tmp_path, capsys):
    assert cli.MAX_SEED is gc.MAX_SEED == 2**31 - 1
    bound = str(gc.MAX_SEED)
    with pytest.raises(SystemExit):
        cli.main(["generate", "--seed", str(2**31), "--out", str(tmp_path / "o")])
    assert f"SEED: expected 0..{bound}, got {2**31}" in capsys.readouterr().err
    for kind in (DatasetConfig, GenerateConfig):
        for name in ("seed", "rain_seed"):
            with pytest.raises(ValueError, match=rf"^{name}: expected an integer in 0\.\.{bound}, "):
                kind(**{name: 2**31})
    with pytest.raises(ValueError, match=rf"^SEED: seed \+ scenes - 1 must be <= {bound}, "):
        DatasetConfig(seed=gc.MAX_SEED, scenes=2)
    assert DatasetConfig(seed=gc.MAX_SEED - 1, scenes=2).tasks()[-1].seed == gc.MAX_SEED


def test_shards_share_the_dataset_fields_and_keep_their_keys():
    config = DatasetConfig(seed=4, scenes=2, frames=5, frames_per_shard=2, rates=[0, 25.0],
                           rain_model="physical", rain_options={"exposure_s": 0.01},
                           store=["depth"], sky="clear", layout="highway", time_of_day="dusk")
    tasks = config.tasks()
    assert len(tasks) == config.shard_count == 6
    assert [(t.seed, t.frame_offset, t.frames, t.clip_frames) for t in tasks] == [
        (seed, offset, frames, 5) for seed in (4, 5) for offset, frames in ((0, 2), (2, 2), (4, 1))]
    shared = [f.name for f in dataclasses.fields(ClipConfig) if f.name not in ("seed", "frames")]
    assert all(getattr(task, name) == getattr(config, name) for task in tasks for name in shared)
    # the manifest's and the shard's config objects: their keys are part of the format
    common = {"seed", "frames", "fps", "width", "height", "hfov_deg", "rates", "rain_model",
              "rain_seed", "rain_options", "store", "label_filter", "scenario", "sky", "layout",
              "time_of_day", "weather_follows_rate"}
    assert set(config.to_dict()) == common | {"scenes", "frames_per_shard"}
    assert set(tasks[0].to_dict()) == common | {"frame_offset", "clip_frames"}
    assert config.to_dict()["rates"] == [0.0, 25.0] and config.to_dict()["store"] == ["depth"]


def test_a_dataset_can_hold_part_of_a_longer_clip():
    """first_frame and clip_frames: the shards cover frames first_frame.. of the scene's clip of
    clip_frames frames, which the layout is planned for; the manifest's config names them only
    where they are not their defaults (so older manifests still match)."""
    config = DatasetConfig(seed=4, frames=5, first_frame=3, clip_frames=20, frames_per_shard=2)
    assert [(t.seed, t.frame_offset, t.frames, t.clip_frames) for t in config.tasks()] == [
        (4, 3, 2, 20), (4, 5, 2, 20), (4, 7, 1, 20)]
    assert config.duration_s == 2.0 and config.tasks()[0].duration_s == 2.0
    assert config.to_dict()["first_frame"] == 3 and config.to_dict()["clip_frames"] == 20
    from_the_start = DatasetConfig(frames=5, clip_frames=20)
    assert "first_frame" not in from_the_start.to_dict()
    assert [t.frame_offset for t in from_the_start.tasks()] == [0]
    assert DatasetConfig(first_frame=3).tasks()[0].clip_frames == 203  # default: to the last frame


@pytest.mark.parametrize("fields, pattern", [
    (dict(rain_model="snow"), r"^RAIN_MODEL: expected one of jeon2022, physical, got 'snow'$"),
    (dict(rates=(50.0, 0.0)), r"^rates: expected ascending distinct values in \[0, 1000\] mm/h"),
    (dict(rates=(0.0, 2000.0)), r"^rates: expected ascending distinct values in \[0, 1000\] mm/h"),
    (dict(fps=float("nan")), r"^fps: expected 0 < fps <= 1000, got nan$"),
    (dict(hfov_deg="wide"), r"^hfov_deg: expected 10\.\.170 degrees, got 'wide'$"),
    (dict(width=8192, height=4096), r"^WIDTH x HEIGHT: 8192x4096 = 33554432 pixels; at most"),
    (dict(store="depth"), r"^store: expected a sequence of names \(depth,instance\), got 'depth'$"),
    (dict(store=("depth", "colour")), r"^store: expected a subset of depth,instance, got colour$"),
    (dict(label_filter={"min_box_height": 4}), r"^label_filter: expected a LabelFilter, got dict$"),
    (dict(scenario={"num_cars": 1}), r"^scenario: expected a ScenarioConfig or None, got dict$"),
    (dict(rain_options=[("exposure_s", 0.01)]), r"^rain_options: expected a mapping of rain "
                                                r"options, got list$"),
    (dict(weather_follows_rate="yes"), r"^weather_follows_rate: expected True, False or None"),
    (dict(weather_follows_rate=1), r"^weather_follows_rate: expected True, False or None, got 1$"),
])
def test_every_field_is_checked_with_one_line_naming_it(fields, pattern):
    for kind in (DatasetConfig, GenerateConfig):
        with pytest.raises(ValueError, match=pattern):
            kind(**fields)


def test_dataset_only_and_shard_only_fields():
    with pytest.raises(ValueError, match=r"^SCENES: expected an integer in 1\.\.100000, got 0$"):
        DatasetConfig(scenes=0)
    with pytest.raises(ValueError, match=r"^frames-per-shard: expected an integer >= 1, got 0$"):
        DatasetConfig(frames_per_shard=0)
    with pytest.raises(ValueError, match=re.escape("scenario.duration_s: expected clip frames / fps = 20 s")):
        DatasetConfig(scenario=ScenarioConfig(duration_s=5.0))
    with pytest.raises(ValueError, match=r"^first-frame: expected an integer in 0\.\.10000000, got -1$"):
        DatasetConfig(first_frame=-1)
    with pytest.raises(ValueError, match=r"^clip-frames: expected an integer >= first-frame \+ frames "
                                         r"= 8, got 7$"):
        DatasetConfig(frames=5, first_frame=3, clip_frames=7)
    with pytest.raises(ValueError, match=r"^frame_offset: expected an integer in 0\.\.10000000, "):
        GenerateConfig(frame_offset=-1)
    with pytest.raises(ValueError, match=r"^clip_frames: expected >= frame_offset \+ frames = 210, "
                                         r"got 200$"):
        GenerateConfig(frame_offset=10, clip_frames=200)
    with pytest.raises(TypeError):
        DatasetConfig(0, 1)  # keyword-only: the field order is no interface


def test_a_clip_is_at_most_an_hour_whatever_gives_its_length():
    """A scene is laid out for its whole clip (its build time growing with the square of its
    length): a clip longer than MAX_CLIP_SECONDS is refused before anything is laid out, naming
    the flags that gave its length."""
    assert gc.MAX_CLIP_SECONDS == 3600.0
    assert DatasetConfig(frames=36000).duration_s == 3600.0  # the longest at 10 frames/s
    assert GenerateConfig(frames=360, fps=0.1).duration_s == 3600.0
    for kind in (DatasetConfig, GenerateConfig):
        with pytest.raises(ValueError, match=r"^FRAMES / FPS: a clip of 36001 frames at 10 frames/s is 3600\.1 s; "
                                             r"expected at most 3600 s \(36000 frames at 10 frames/s\): "):
            kind(frames=36001)
        with pytest.raises(ValueError, match=r"^FRAMES / FPS: a clip of 2 frames at 1e-05 frames/s is 200000 s; "
                                             r"expected at most 3600 s \(not one frame at 1e-05 frames/s: "
                                             r"raise the frame rate\)"):
            kind(frames=2, fps=1e-5)
        with pytest.raises(ValueError, match=r"^CLIP_FRAMES / FPS: a clip of 100000 frames at 10 frames/s"):
            kind(frames=1, clip_frames=100_000)
    with pytest.raises(ValueError, match=r"^\(FIRST_FRAME \+ FRAMES\) / FPS: a clip of 9999999 frames "):
        DatasetConfig(frames=1, first_frame=9_999_998)
    with pytest.raises(ValueError, match=r"^\(FIRST_FRAME \+ FRAMES\) / FPS: a clip of 36010 frames "):
        GenerateConfig(frames=10, frame_offset=36000)


def test_the_paper_experiment_builds_on_the_dataset_config():
    from rainbench.experiments.paper import PAPER_RATES, PaperConfig

    assert PaperConfig().dataset == DatasetConfig(**gc.PAPER_CLIP, rates=PAPER_RATES)
    assert PAPER_RATES == tuple(float(r) for r in range(0, 101, 10))
    with pytest.raises(ValueError, match=r"^RATES: the paper's comparison needs rate 0"):
        PaperConfig(dataset=DatasetConfig(rates=(50.0,)))
    parser = cli.build_parser()
    args = parser.parse_args(["paper", "--frames", "4", "--fps", "2", "--rates", "0,50"])
    dataset = DatasetConfig(**cli._scene_fields(args), scenes=args.scenes, rates=(0.0, 50.0))
    assert (dataset.frames, dataset.fps, dataset.hfov_deg) == (4, 2.0, DatasetConfig.hfov_deg)
    assert {name: getattr(dataset, name) for name in gc.PAPER_CLIP} == gc.PAPER_CLIP
