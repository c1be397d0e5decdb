"""Training straight from shards (issue 19, part 1): the ultralytics dataset over the one reader,
rain curricula, a tiny training run that reads rainy shards, and a recipe's rain in its tile
stages (curriculum exports and RandomRain on training tiles)."""

import collections
import dataclasses
import json
import random
import re
import shutil

import cv2
import numpy as np
import pytest
import torch
from labelled_shards import write_labelled_shard

from rainbench import cli
from rainbench.experiments import train
from rainbench.experiments.shard_training import CurriculumError, RainCurriculum, shard_dataset_class

FRAMES = [
    [(2, 0, (10, 12, 40, 50), 1.0, 0.0), (0, 1, (60, 5, 70, 30), 0.5, 0.0), (5, 2, (70, 40, 98, 79), 1.0, 0.2)],
    [(3, 0, (1, 1, 99, 79), 1.0, 0.0)],
    [],
]


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    root = tmp_path_factory.mktemp("shards")
    write_labelled_shard(root, FRAMES, width=100, height=80, rates=(0.0, 50.0, 100.0))
    return root


def _dataset(root, *, augment=False, curriculum=RainCurriculum(), keep_classes=None, imgsz=64, rain_data=None):
    from ultralytics.cfg import get_cfg

    dataset_class = shard_dataset_class()
    return dataset_class(img_path=str(root), imgsz=imgsz, augment=augment, hyp=get_cfg(), rect=False,
                         batch_size=2, stride=32, pad=0.5, task="detect",
                         data={"names": {i: str(i) for i in range(8)}, "channels": 3},
                         curriculum=curriculum, keep_classes=keep_classes, rain_data=rain_data)


def _pixel_boxes(item):
    """The item's boxes mapped back to the shard image with ultralytics' own inverse letterbox."""
    from ultralytics.utils import ops

    height, width = item["img"].shape[1:]
    cx, cy, w, h = item["bboxes"].double().T
    xyxy = torch.stack([(cx - w / 2) * width, (cy - h / 2) * height, (cx + w / 2) * width,
                        (cy + h / 2) * height], dim=1)
    return ops.scale_boxes((height, width), xyxy, item["ori_shape"], ratio_pad=item["ratio_pad"]).numpy()


def _load_epochs(dataset, drawn: list, seed: int, count: int) -> list:
    """What ``drawn`` records over ``count`` epochs of ``dataset.load_image`` with Python's
    ``random`` seeded by ``seed`` (the generator ultralytics seeds per worker)."""
    random.seed(seed)
    drawn.clear()
    for _ in range(count):
        for index in range(len(dataset)):
            dataset.load_image(index)
    return list(drawn)


@pytest.mark.parametrize("keep_classes", [None, [0, 2]])
def test_the_dataset_yields_exactly_the_shards_boxes_after_the_letterbox(shards, keep_classes):
    dataset = _dataset(shards, keep_classes=keep_classes)
    assert len(dataset) == 3
    for index, labels in enumerate(FRAMES):
        kept = [label for label in labels if keep_classes is None or label[0] in keep_classes]
        item = dataset[index]
        assert item["img"].shape == (3, 64, 64) and item["ori_shape"] == (80, 100)
        assert item["cls"].ravel().tolist() == [float(label[0]) for label in kept]
        np.testing.assert_allclose(_pixel_boxes(item), np.array([label[2] for label in kept], float).reshape(-1, 4),
                                   atol=1e-3)


def test_load_image_resizes_the_stored_frame_as_ultralytics_does(shards):
    """The long side goes to imgsz (80x100 -> 52x64), BGR uint8 of the stored frame."""
    dataset = _dataset(shards, curriculum=RainCurriculum(((None, 100.0),), (1.0,)))
    image, original, resized = dataset.load_image(0)
    assert original == (80, 100) and resized == (52, 64) and image.shape == (52, 64, 3)
    assert image.dtype == np.uint8 and image[0, 0, 0] == 90  # the grey background of the shard


def test_a_curriculum_draws_its_rates_in_its_proportions_and_by_seed(shards, monkeypatch):
    curriculum = RainCurriculum.from_mapping({0: 2, "50": 1, 100.0: 1})
    assert curriculum.rates == (0.0, 50.0, 100.0) and curriculum.shares == (0.5, 0.25, 0.25)
    dataset = _dataset(shards, augment=True, curriculum=curriculum)
    drawn = []
    real_read = dataset.store.read_rgb
    monkeypatch.setattr(dataset.store, "read_rgb",
                        lambda handle, image, rate: drawn.append(rate) or real_read(handle, image, rate))

    first = _load_epochs(dataset, drawn, 0, 1000)  # 3000 loads
    counts = collections.Counter(first)
    assert set(counts) == {0.0, 50.0, 100.0}
    for rate, share in zip(curriculum.rates, curriculum.shares):
        sigma = (len(first) * share * (1 - share)) ** 0.5
        assert abs(counts[rate] - len(first) * share) < 4 * sigma, (rate, counts)
    assert _load_epochs(dataset, drawn, 0, 1000) == first and _load_epochs(dataset, drawn, 1, 1000) != first  # deterministic by seed


def test_augmented_items_keep_their_boxes_inside_the_image(shards):
    random.seed(0)
    dataset = _dataset(shards, augment=True, curriculum=RainCurriculum.from_mapping({0: 1, 100: 1}))
    for index in range(6):
        item = dataset[index % len(dataset)]
        assert item["img"].shape[0] == 3 and item["img"].dtype == torch.uint8
        boxes = item["bboxes"]
        assert ((boxes >= 0) & (boxes <= 1)).all()


@pytest.mark.parametrize("curriculum, message", [
    ({}, "expected a mapping of rate -> weight"),
    ({0: -1}, "expected weights >= 0 with a positive sum"),
    ({0: 0}, "expected weights >= 0 with a positive sum"),
    ({"x": 1}, "expected a number in mm/h"),
    ({0: 1, "0.0": 1}, "repeat a rate"),
])
def test_bad_curricula_are_one_line_errors(curriculum, message):
    with pytest.raises(CurriculumError, match=message):
        RainCurriculum.from_mapping(curriculum)


def _mark_pixels(shard, base):
    """Make every stored image of ``shard`` tell its rain model and rate row apart: add
    ``base + 20 * rate row + frame`` to it (mod 256), in place (HDF5 rewrites the chunks)."""
    import h5py

    with h5py.File(shard, "r+") as handle:
        rgb = handle["rgb"]
        for row in range(rgb.shape[0]):
            for frame in range(rgb.shape[1]):
                rgb[row, frame] = (rgb[row, frame].astype(np.int64) + base + 20 * row + frame) % 256


TWO_MODEL_RATES = {"physical": (0.0, 50.0, 100.0), "jeon2022": (50.0, 100.0)}


@pytest.fixture(scope="module")
def two_models(tmp_path_factory):
    """The same three frames stored as two rain models' data, with different pixels: rain model ->
    (dataset directory, its shard)."""
    root = tmp_path_factory.mktemp("two_models")
    data = {}
    for base, (model, rates) in zip((40, 140), TWO_MODEL_RATES.items()):
        shard = write_labelled_shard(root / model, FRAMES, width=100, height=80, rates=rates)
        _mark_pixels(shard, base)
        data[model] = (root / model, shard)
    return data


TWO_MODEL_CURRICULUM = {"physical": {0: 2, 50: 1, 100: 1}, "jeon2022": {50: 1, 100: 1}}


def _two_model_dataset(two_models, **options):
    rain_data = {model: str(folder) for model, (folder, _) in two_models.items()}
    return _dataset(two_models["physical"][0], curriculum=RainCurriculum.from_mapping(TWO_MODEL_CURRICULUM),
                    rain_data=rain_data, **options)


def test_a_two_model_curriculum_shares_its_weights_over_all_pairs():
    curriculum = RainCurriculum.from_mapping(TWO_MODEL_CURRICULUM)
    assert curriculum.entries == (("physical", 0.0), ("physical", 50.0), ("physical", 100.0),
                                  ("jeon2022", 50.0), ("jeon2022", 100.0))
    assert curriculum.shares == pytest.approx((2 / 6, 1 / 6, 1 / 6, 1 / 6, 1 / 6))
    assert curriculum.rain_models == ("physical", "jeon2022") and curriculum.rates == (0.0, 50.0, 100.0)
    assert curriculum.rates_of("jeon2022") == (50.0, 100.0) and curriculum.rates_of(None) == ()
    assert RainCurriculum.from_mapping({0: 1}).draw(random.Random(0)) == (None, 0.0)


def test_a_two_model_curriculum_draws_each_pair_in_its_proportions_and_by_seed(two_models, monkeypatch):
    dataset = _two_model_dataset(two_models)
    assert dataset.stores["physical"] is dataset.store and dataset.stores["jeon2022"] is not dataset.store
    drawn = []
    for model, store in dataset.stores.items():
        real_read = store.read_rgb
        monkeypatch.setattr(store, "read_rgb", lambda handle, image, rate, model=model, real_read=real_read:
                            drawn.append((model, rate)) or real_read(handle, image, rate))

    first = _load_epochs(dataset, drawn, 0, 1000)  # 3000 loads
    counts = collections.Counter(first)
    curriculum = dataset.curriculum
    assert set(counts) == set(curriculum.entries)
    for entry, share in zip(curriculum.entries, curriculum.shares):
        sigma = (len(first) * share * (1 - share)) ** 0.5
        assert abs(counts[entry] - len(first) * share) < 4 * sigma, (entry, counts)
    assert _load_epochs(dataset, drawn, 0, 1000) == first and _load_epochs(dataset, drawn, 1, 1000) != first  # deterministic by seed


@pytest.mark.parametrize("model, rate", [(model, rate) for model, rates in TWO_MODEL_RATES.items()
                                         for rate in rates])
def test_an_image_drawn_at_a_rain_model_and_rate_is_that_models_stored_frame(two_models, model, rate):
    """With imgsz 100 (the stored width) nothing is resized: the loaded BGR image is exactly the
    drawn rain model's stored RGB frame at the drawn rate; the labels are the same for all."""
    import h5py

    dataset = _two_model_dataset(two_models, imgsz=100)
    dataset.curriculum = RainCurriculum(((model, rate),), (1.0,))  # always draws this pair
    with h5py.File(two_models[model][1]) as handle:
        row = TWO_MODEL_RATES[model].index(rate)
        for index in range(len(FRAMES)):
            image, original, resized = dataset.load_image(index)
            assert original == resized == (80, 100)
            np.testing.assert_array_equal(image, handle["rgb"][row, index][:, :, ::-1])
            assert dataset.labels[index]["cls"].ravel().tolist() == [float(c) for c, *_ in FRAMES[index]]


def test_rain_models_whose_frames_differ_are_refused(two_models, tmp_path):
    rain_data = {model: str(folder) for model, (folder, _) in two_models.items()}
    curriculum = RainCurriculum.from_mapping(TWO_MODEL_CURRICULUM)
    fewer = tmp_path / "fewer"
    write_labelled_shard(fewer, FRAMES[:2], width=100, height=80, rates=(50.0, 100.0))
    with pytest.raises(CurriculumError, match=rf"rain curriculum: {re.escape(str(fewer))} holds 2 images but .*physical holds 3"):
        _dataset(two_models["physical"][0], curriculum=curriculum, rain_data={**rain_data, "jeon2022": str(fewer)})
    moved = tmp_path / "moved"
    write_labelled_shard(moved, [FRAMES[0], FRAMES[2], FRAMES[1]], width=100, height=80, rates=(50.0, 100.0))
    with pytest.raises(CurriculumError, match=rf"rain curriculum: {re.escape(str(moved))} image 2 \(scene000000_f00000\.h5#1\) is not the frame of "):
        _dataset(two_models["physical"][0], curriculum=curriculum, rain_data={**rain_data, "jeon2022": str(moved)})
    with pytest.raises(CurriculumError, match=r"no training data for rain model 'jeon2022' \(rain_data names physical\)"):
        _dataset(two_models["physical"][0], curriculum=curriculum, rain_data={"physical": rain_data["physical"]})


@pytest.mark.parametrize("curriculum, message", [
    ({"physical": {0: 1}, 50: 1}, r"entry 50: 1 mixes the two forms"),
    ({0: 1, "physical": {0: 1}}, r"entry 'physical': \{0: 1\} mixes the two forms"),
    ({"rainy": {0: 1}}, r"unknown rain model 'rainy'; expected one of jeon2022, physical"),
    ({"physical": {}}, r"physical: expected a mapping of rate -> weight, got \{\}"),
    ({"physical": {0: 1}, "jeon2022": {50: 0}}, r"jeon2022: expected weights >= 0 with a positive sum, got \[0\]"),
    ({"physical": {0: 1, 50: -1}}, r"physical: expected weights >= 0 with a positive sum, got \[1, -1\]"),
    ({"jeon2022": {50: "1"}}, r"jeon2022: expected weights >= 0 with a positive sum, got \['1'\]"),
    ({"jeon2022": {"wet": 1}}, r"jeon2022: .*expected a number in mm/h"),
    ({"jeon2022": {50: 1, "50.0": 1}}, r"jeon2022: rates \[50.0, 50.0\] repeat a rate"),
])
def test_bad_rain_model_curricula_are_one_line_errors(curriculum, message):
    with pytest.raises(CurriculumError, match="rain curriculum: " + message) as error:
        RainCurriculum.from_mapping(curriculum)
    assert "\n" not in str(error.value)


RAINY_RECIPE = """
name: tiny-rain
architecture: yolo11n.yaml
eval_imgsz: 64
rain_curriculum: {0: 1, 50: 1}
train_data: {seed: 1000000, scenes: 1, frames: 3, fps: 0.2, width: 160, height: 120, rain_model: physical,
             scenario: {num_cars: 3, num_pedestrians: 3, num_bicycles: 1, num_motorcycles: 1}}
val_data: {seed: 2000000, scenes: 1, frames: 2, fps: 0.1, width: 160, height: 120}
train: {epochs: 1, imgsz: 64, batch: 2, seed: 0, deterministic: true, workers: 0}
"""


def test_a_recipe_with_a_rain_curriculum_generates_its_rates_and_trains_from_the_shards(tmp_path, capsys):
    recipe_path = tmp_path / "rain.yaml"
    recipe_path.write_text(RAINY_RECIPE)
    recipe = train.load_recipe(recipe_path)
    assert recipe.reader == "shards" and recipe.train_data.rates == (0.0, 50.0)
    assert recipe.val_data.rates == (0.0,)
    out = tmp_path / "run"
    code = cli.main(["train", "--recipe", str(recipe_path), "--out", str(out), "--device", "cpu"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert (out / "tiny-rain.pt").is_file() and not (out / "yolo").exists()  # no export step
    manifest = json.loads((out / "data" / "train" / "manifest.json").read_text())
    assert manifest["config"]["rates"] == [0.0, 50.0] and manifest["config"]["rain_model"] == "physical"
    import yaml
    args = yaml.safe_load((out / "run" / "args.yaml").read_text())
    assert args["data"] == str(out / "shards.yaml") and args["cache"] is False


@pytest.mark.parametrize("change, message", [
    ("rain_curriculum: {0: 1, 50: 1}", None),
    ("rain_curriculum: {0: 1, 50: 1}\nreader: export", r"`rain_curriculum` needs `reader: shards`"),
    ("reader: disk", r"`reader` must be one of shards, export, got 'disk'"),
    ("rain_curriculum: {0: 0}", r"`rain_curriculum`: expected weights >= 0 with a positive sum"),
])
def test_recipe_reader_and_curriculum_are_checked_when_loaded(tmp_path, change, message):
    path = tmp_path / "recipe.yaml"
    path.write_text(RAINY_RECIPE.replace("rain_curriculum: {0: 1, 50: 1}", change))
    if message is None:
        assert train.load_recipe(path).curriculum.rates == (0.0, 50.0)
        return
    with pytest.raises(train.TrainError, match=message):
        train.load_recipe(path)


def test_a_recipe_curriculum_over_rain_models_generates_one_dataset_per_model(tmp_path):
    """``train`` holds train_data's own rain model, ``train-<model>`` the others: train_data with
    that rain model and its curriculum rates, the same seeds and fields otherwise (unset
    weather_follows_rate: each rain model's own default)."""
    recipe_text = RAINY_RECIPE.replace("rain_curriculum: {0: 1, 50: 1}",
                                       "rain_curriculum: {jeon2022: {50: 1}, physical: {0: 2, 50: 1}}")
    path = tmp_path / "recipe.yaml"
    path.write_text(recipe_text)
    recipe = train.load_recipe(path)
    datasets = recipe.train_datasets()
    assert recipe.train_data.rates == (0.0, 50.0) and recipe.curriculum.shares == (0.25, 0.5, 0.25)
    assert list(datasets) == ["physical", "jeon2022"]  # train first: its labels are trained on
    assert [folder for folder, _ in datasets.values()] == ["train", "train-jeon2022"]
    physical, jeon = datasets["physical"][1], datasets["jeon2022"][1]
    assert physical == recipe.train_data and physical.rain_model == "physical"
    assert jeon.rain_model == "jeon2022" and jeon.rates == (50.0,) and jeon.weather_follows_rate is None
    assert dataclasses.replace(jeon, rain_model="physical", rates=(0.0, 50.0)) == physical
    path.write_text(recipe_text.replace(", physical: {0: 2, 50: 1}}", "}"))  # own model not named
    assert [folder for folder, _ in train.load_recipe(path).train_datasets().values()] == ["train-jeon2022"]
    path.write_text(RAINY_RECIPE)  # the flat form: train_data's own rain model, in train
    assert {model: folder for model, (folder, _) in train.load_recipe(path).train_datasets().items()} == {
        None: "train"}


@pytest.mark.parametrize("curriculum, message", [
    ("{physical: {0: 1}, 50: 1}", r"`rain_curriculum`: entry 50: 1 mixes the two forms"),
    ("{rainy: {0: 1}}", r"`rain_curriculum`: unknown rain model 'rainy'; expected one of jeon2022, physical$"),
    ("{}", r"`rain_curriculum`: expected a mapping of rate -> weight or of rain model -> \{rate: weight\}, got \{\}"),
    ("{physical: {}}", r"`rain_curriculum`: physical: expected a mapping of rate -> weight, got \{\}"),
    ("{physical: {0: 1}, jeon2022: {50: -1}}",
     r"`rain_curriculum`: jeon2022: expected weights >= 0 with a positive sum, got \[-1\]"),
    ("{physical: {0: 1}, jeon2022: {50: 1}}\nreader: export", r"`rain_curriculum` needs `reader: shards`"),
    ("{physical: {0: 1}, jeon2022: {50: 1}}\nrandom_rain: {p: 0.5}", r"`random_rain` needs `reader: shards` and no"),
])
def test_recipe_rain_model_curricula_are_checked_when_loaded(tmp_path, curriculum, message):
    path = tmp_path / "recipe.yaml"
    path.write_text(RAINY_RECIPE.replace("rain_curriculum: {0: 1, 50: 1}", f"rain_curriculum: {curriculum}"))
    with pytest.raises(train.TrainError, match=message) as error:
        train.load_recipe(path)
    assert str(error.value).startswith(str(path)) and "\n" not in str(error.value)


def test_a_recipe_curriculum_over_rain_models_trains_on_each_models_data(tmp_path, capsys, monkeypatch):
    from rainbench.experiments import shard_training

    opened = []
    real_open = shard_training.open_rain_data

    def recording_open(img_path, curriculum, rain_data=None):
        store, stores = real_open(img_path, curriculum, rain_data)
        opened.append({model: dataset.root for model, dataset in stores.items()})
        return store, stores

    monkeypatch.setattr(shard_training, "open_rain_data", recording_open)
    recipe_path = tmp_path / "models.yaml"
    recipe_path.write_text(RAINY_RECIPE.replace("rain_curriculum: {0: 1, 50: 1}",
                                                "rain_curriculum: {physical: {0: 1, 50: 1}, jeon2022: {50: 1}}"))
    out = tmp_path / "run"
    code = cli.main(["train", "--recipe", str(recipe_path), "--out", str(out), "--device", "cpu"])
    assert code == 0, capsys.readouterr().err
    configs = {folder: json.loads((out / "data" / folder / "manifest.json").read_text())["config"]
               for folder in ("train", "train-jeon2022")}
    assert configs["train"]["rain_model"] == "physical" and configs["train"]["rates"] == [0.0, 50.0]
    assert configs["train-jeon2022"]["rain_model"] == "jeon2022" and configs["train-jeon2022"]["rates"] == [50.0]
    assert {**configs["train-jeon2022"], "rain_model": "physical", "rates": [0.0, 50.0]} == configs["train"]
    data = (out / "data").resolve()
    assert {"physical": data / "train", "jeon2022": data / "train-jeon2022"} in opened  # the training set
    assert {None: data / "val"} in opened  # validation: clean frames of its own data


def test_ultralytics_fraction_keeps_the_first_frames(shards):
    from ultralytics.cfg import get_cfg

    dataset_class = shard_dataset_class()
    common = dict(img_path=str(shards), imgsz=64, augment=False, hyp=get_cfg(), rect=False, batch_size=2,
                  stride=32, pad=0.5, task="detect", data={"names": {i: str(i) for i in range(8)}, "channels": 3})
    assert [image.frame for image in dataset_class(**common, fraction=0.67).images] == [0, 1]
    assert [image.frame for image in dataset_class(**common, fraction=1).images] == [0, 1, 2]


def test_random_rain_rains_on_the_clean_frames_by_seed(shards):
    from rainbench.experiments.shard_training import RandomRainAugment

    stored = _dataset(shards).load_image(0)[0]
    always = _dataset(shards, augment=True)
    always.random_rain, always._random_rain = (RandomRainAugment(p=1.0),
                                               RandomRainAugment(p=1.0).transform())
    random.seed(5)
    first = always.load_image(0)[0].copy()
    always.ims[0] = None  # out of the buffer: read again
    random.seed(5)
    again = always.load_image(0)[0]
    np.testing.assert_array_equal(first, again)  # deterministic by seed
    assert first.shape == stored.shape and (first != stored).mean() > 0.01  # streaks and dimming
    never = _dataset(shards, augment=True)
    never.random_rain, never._random_rain = RandomRainAugment(p=0.0), RandomRainAugment(p=0.0).transform()
    np.testing.assert_array_equal(never.load_image(0)[0], stored)


@pytest.mark.parametrize("text, message", [
    ("random_rain: {p: 0.5, rain_type: heavy}", None),
    ("random_rain: {p: 2}", r"`random_rain`: p must be a probability in \[0, 1\], got 2"),
    ("random_rain: {p: 0.5, colour: red}", r"`random_rain`: unknown option 'colour'; expected p or some of "),
    ("random_rain: {p: 0.5}\nrain_curriculum: {0: 1, 50: 1}", r"`random_rain` needs `reader: shards` and no"),
])
def test_recipe_random_rain_is_checked_when_loaded(tmp_path, text, message):
    path = tmp_path / "recipe.yaml"
    path.write_text(RAINY_RECIPE.replace("rain_curriculum: {0: 1, 50: 1}", text))
    if message is None:
        assert train.load_recipe(path).random_rain.options == (("rain_type", "heavy"),)
        return
    with pytest.raises(train.TrainError, match=message):
        train.load_recipe(path)


def test_a_recipe_with_random_rain_trains_on_the_clean_shards(tmp_path, capsys):
    recipe_path = tmp_path / "random_rain.yaml"
    recipe_path.write_text(RAINY_RECIPE.replace("rain_curriculum: {0: 1, 50: 1}", "random_rain: {p: 1.0}")
                           .replace("name: tiny-rain", "name: tiny-random-rain"))
    assert train.load_recipe(recipe_path).train_data.rates == (0.0,)
    out = tmp_path / "run"
    code = cli.main(["train", "--recipe", str(recipe_path), "--out", str(out), "--device", "cpu"])
    assert code == 0, capsys.readouterr().err
    assert (out / "tiny-random-rain.pt").is_file() and not (out / "yolo").exists()


@pytest.mark.parametrize("value, message", [
    ("rainbench-yolo11n", None),
    ("no-such-model", r"`init_weights`: no-such-model: expected a shipped model name \(.*rainbench-yolo11n.*\) or an existing \.pt"),
])
def test_recipe_init_weights_name_a_checkpoint(tmp_path, value, message):
    path = tmp_path / "recipe.yaml"
    path.write_text(RAINY_RECIPE + f"init_weights: {value}\n")
    if message is None:
        assert train.load_recipe(path).init_weights.name == "rainbench-yolo11n.pt"
        return
    with pytest.raises(train.TrainError, match=message):
        train.load_recipe(path)


def test_a_fine_tune_starts_from_its_init_weights(tmp_path, capsys):
    """With lr 0 a fine-tune of the shipped nano model ends where it began, but for the class-logit
    convs of the detection head (``model.23.cv3.*.2``), which ultralytics' set-up for a new
    dataset moves (as in the warm-restart test, here by up to 0.2). A cold start would differ in
    every tensor."""
    from rainbench.eval.weights import checkpoint_file

    recipe_path = tmp_path / "fine.yaml"
    recipe_path.write_text(RAINY_RECIPE.replace("name: tiny-rain", "name: tiny-fine") + "init_weights: rainbench-yolo11n\n"
                           + "classes: [person, bicycle, car, motorcycle, bus, truck]\n"  # the shipped model's
                           + "cpu: {optimizer: AdamW, lr0: 0.0, warmup_epochs: 0, warmup_bias_lr: 0.0}\n")
    out = tmp_path / "run"
    code = cli.main(["train", "--recipe", str(recipe_path), "--out", str(out), "--device", "cpu"])
    assert code == 0, capsys.readouterr().err

    def parameters(path):
        return dict(torch.load(path, map_location="cpu", weights_only=False)["model"].named_parameters())

    before, after = parameters(checkpoint_file("rainbench-yolo11n")), parameters(out / "tiny-fine.pt")
    assert before.keys() == after.keys()
    unchanged = [name for name in before if torch.equal(before[name], after[name])]
    assert len(unchanged) >= 0.95 * len(before), len(unchanged)
    moved = {n for n in before if (before[n].float() - after[n].float()).abs().max().item() >= 0.01}
    assert moved <= {f"model.23.cv3.{level}.2.{kind}" for level in range(3) for kind in ("weight", "bias")}, moved


def _fake_export(out, folder, rates, frames=12, size=(120, 160)):
    """``OUT/yolo/<folder>`` as prepare_data exports it: one ``rate_<token>`` YOLO folder per rate of
    ``rates`` (rate -> base), image ``i`` the constant ``base + i``, each with the same labels (a
    person box per frame), and the export's stamp."""
    height, width = size
    for rate, base in rates.items():
        root = out / "yolo" / folder / f"rate_{rate}"
        (root / "images").mkdir(parents=True)
        (root / "labels").mkdir()
        for index in range(frames):
            cv2.imwrite(str(root / "images" / f"{index:06d}.png"), np.full((height, width, 3), base + index, np.uint8))
            (root / "labels" / f"{index:06d}.txt").write_text(
                f"0 {(20 + 10 * index) / width:.6f} {60 / height:.6f} {16 / width:.6f} {30 / height:.6f}\n")
    (out / "yolo" / folder / ".exported").write_text(f"stamp of {folder}")


def _recipe(tmp_path, name, rain):
    path = tmp_path / f"{name}.yaml"
    path.write_text(RAINY_RECIPE.replace("rain_curriculum: {0: 1, 50: 1}", rain))
    return train.load_recipe(path)


def _files(folder):
    return {path.relative_to(folder): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()
            and path.name != ".exported"}


def test_tile_stages_cut_the_recipes_rain_into_training_tiles_only(tmp_path):
    """A curriculum recipe's training tiles come from its (rain model, rate) exports in its
    proportions; a RandomRain recipe's get RandomRain on about p of them; validation tiles and
    every tile's place and labels are the clean recipe's; the rain names the tile set."""
    from rainbench.experiments.tiles import TileConfig

    out = tmp_path / "run"
    bases = {("physical", 0.0): 10, ("physical", 50.0): 90, ("jeon2022", 50.0): 170}
    _fake_export(out, "train", {0: 10, 50: 90})
    _fake_export(out, "train-jeon2022", {50: 170})
    _fake_export(out, "val", {0: 240}, frames=2)
    config = TileConfig(size=32, per_image=16, background=0.3)
    clean = _recipe(tmp_path, "clean", "")
    curriculum = _recipe(tmp_path, "curriculum", "rain_curriculum: {physical: {0: 2, 50: 1}, jeon2022: {50: 1}}")
    clean_yaml = train.prepare_tiles(clean, out, config)
    assert clean_yaml == out / "tiles_s32_x1_n16_b0.3_a0.1_r0.yaml" and train.tile_rain(clean) is None
    rain_yaml = train.prepare_tiles(curriculum, out, config)
    root, clean_root = rain_yaml.with_suffix(""), clean_yaml.with_suffix("")
    assert root.name == config.token(train.tile_rain(curriculum)) and root.name.startswith(clean_root.name + "_rain")
    stamp = json.loads((root / "train" / ".exported").read_text())
    assert stamp["rain"]["rain_curriculum"][2] == {"rain_model": "jeon2022", "rate": 50.0, "weight": 1.0}
    assert stamp["sources"] == {"train": "stamp of train", "train-jeon2022": "stamp of train-jeon2022"}
    drawn = collections.Counter()
    for path in sorted((root / "train" / "images").iterdir()):
        value = int(cv2.imread(str(path))[0, 0, 0]) - int(path.stem[:6])
        drawn[next(entry for entry, base in bases.items() if base == value)] += 1
    assert sum(drawn.values()) == 12 * 16
    for entry, share in zip(curriculum.curriculum.entries, curriculum.curriculum.shares):
        sigma = (192 * share * (1 - share)) ** 0.5
        assert abs(drawn[entry] - 192 * share) < 4 * sigma, drawn
    clean_files, rain_files = _files(clean_root), _files(root)
    assert {name: data for name, data in rain_files.items() if name.parts[1] == "labels"} == \
        {name: data for name, data in clean_files.items() if name.parts[1] == "labels"}
    assert {name: data for name, data in rain_files.items() if name.parts[0] == "val"} == \
        {name: data for name, data in clean_files.items() if name.parts[0] == "val"}
    # RandomRain on the clean frames: about p of the training tiles change, no validation tile.
    random_rain = _recipe(tmp_path, "random", "random_rain: {p: 0.5}")
    random_root = train.prepare_tiles(random_rain, out, config).with_suffix("")
    assert random_root.name not in (root.name, clean_root.name)
    random_files = _files(random_root)
    assert {name: data for name, data in random_files.items() if name.parts[0] == "val"} == \
        {name: data for name, data in clean_files.items() if name.parts[0] == "val"}
    changed = sum(random_files[name] != data for name, data in clean_files.items()
                  if name.parts[:2] == ("train", "images"))
    assert abs(changed - 96) < 4 * 48 ** 0.5, changed
    # The same recipe keeps its tiles; other weights are another tile set.
    before = (root / "train" / "images" / "000000_t00.png").stat().st_mtime_ns
    assert train.prepare_tiles(curriculum, out, config) == rain_yaml
    assert (root / "train" / "images" / "000000_t00.png").stat().st_mtime_ns == before
    reweighted = _recipe(tmp_path, "reweighted", "rain_curriculum: {physical: {0: 1, 50: 1}, jeon2022: {50: 1}}")
    assert train.prepare_tiles(reweighted, out, config) not in (rain_yaml, clean_yaml)


def test_a_curriculum_without_clean_frames_exports_each_rain_model_and_rate_for_its_tiles(tmp_path):
    """prepare_data exports every (rain model, rate) of the curriculum (no rate 0 needed), redoes
    an export whose rate folder is missing, and the tile stage cuts from them."""
    from rainbench.experiments.tiles import TileConfig

    recipe = _recipe(tmp_path, "no-clean", "rain_curriculum: {physical: {50: 1}, jeon2022: {50: 1}}")
    out = tmp_path / "run"
    dataset_yaml = train.prepare_data(recipe, out)
    yolo = out / "yolo"
    assert sorted(str(path.relative_to(yolo)) for path in yolo.glob("*/rate_*")) == [
        "train-jeon2022/rate_50", "train/rate_50", "val/rate_0"]
    assert "train: train/rate_50/images" in dataset_yaml.read_text()
    shutil.rmtree(yolo / "train" / "rate_50")
    train.prepare_data(recipe, out)
    assert len(list((yolo / "train" / "rate_50" / "images").glob("*.png"))) == 3
    tile_yaml = train.prepare_tiles(recipe, out, TileConfig(size=64, per_image=2))
    root = tile_yaml.with_suffix("")
    assert len(list((root / "train" / "images").glob("*.png"))) == 3 * 2
    assert len(list((root / "val" / "images").glob("*.png"))) == 2 * 6  # 160x120 in 3x2 tiles of 64
