"""rainbench train (a tiny CPU run), the shipped weights, and rainbench paper in a reduced mode."""

import json
import math
import shutil

import numpy as np
import pytest

from rainbench import cli
from rainbench.eval import backends, train
from rainbench.eval.metrics import CLASS_NAMES

# Load torch's lazy modules before anything renders in this process (see test_eval_pipeline).
backends._offline_ultralytics()
import torch._dynamo  # noqa: E402,F401
import ultralytics  # noqa: E402,F401

TINY_RECIPE = """
name: tiny-yolo
architecture: yolo11n.yaml
train_data: {seed: 1000000, scenes: 2, frames: 4, fps: 0.2, width: 160, height: 120,
             scenario: {num_cars: 3, num_pedestrians: 3, num_bicycles: 1, num_motorcycles: 1}}
val_data: {seed: 2000000, scenes: 1, frames: 2, fps: 0.1, width: 160, height: 120}
train: {epochs: 2, imgsz: 96, batch: 4, seed: 0, deterministic: true, workers: 0, cache: false}
cpu: {epochs: 1, imgsz: 64}
"""
# A warm restart with a zero learning rate: its parameters must stay the first stage's.
RESTART = "cpu: {epochs: 1, imgsz: 64, restarts: [{optimizer: AdamW, lr0: 0.0, warmup_epochs: 0, warmup_bias_lr: 0.0}]}"


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_shipped_recipes_load_and_keep_seeds_apart():
    for name in ("rainbench-yolo11n", "rainbench-yolo11s"):
        recipe = train.load_recipe(name)
        assert recipe.name == name and recipe.architecture == name.split("-")[1] + ".yaml"
        seeds = set(range(recipe.train_data.seed, recipe.train_data.seed + recipe.train_data.scenes))
        val = set(range(recipe.val_data.seed, recipe.val_data.seed + recipe.val_data.scenes))
        assert min(seeds | val) >= train.TRAIN_SEED_START and not seeds & val
        assert recipe.train_data.rates == (0.0,) and recipe.arguments(cuda=False)["imgsz"] < \
            recipe.arguments(cuda=True)["imgsz"]


def test_bad_recipes_are_one_line_errors(tmp_path):
    def write(text):
        path = tmp_path / "r.yaml"
        path.write_text(text)
        return path

    with pytest.raises(train.TrainError, match="neither a .yaml file nor a shipped recipe"):
        train.load_recipe("no-such-recipe")
    with pytest.raises(train.TrainError, match="missing `architecture`"):
        train.load_recipe(write("name: x\ntrain_data: {}\nval_data: {}\ntrain: {}\n"))
    bad_seed = TINY_RECIPE.replace("seed: 1000000", "seed: 5")
    with pytest.raises(train.TrainError, match=r"`train_data.seed` must be >= 1000000 .* got 5"):
        train.load_recipe(write(bad_seed))
    overlap = TINY_RECIPE.replace("seed: 2000000", "seed: 1000001")
    with pytest.raises(train.TrainError, match="seeds overlap"):
        train.load_recipe(write(overlap))
    with pytest.raises(train.TrainError, match="`train.data` is set by rainbench train itself"):
        train.load_recipe(write(TINY_RECIPE.replace("train: {epochs", "train: {data: x, epochs")))
    with pytest.raises(train.TrainError, match="`val_data.colour` is not a dataset setting"):
        train.load_recipe(write(TINY_RECIPE.replace("val_data: {seed", "val_data: {colour: 1, seed")))
    with pytest.raises(train.TrainError, match="`cpu.restarts` must be a list of mappings"):
        train.load_recipe(write(TINY_RECIPE.replace("imgsz: 64}", "imgsz: 64, restarts: {epochs: 3}}")))
    with pytest.raises(train.TrainError, match=r"`train.restarts\[1\].resume` cannot be set in a restart"):
        train.load_recipe(write(TINY_RECIPE.replace("cache: false}", "cache: false, restarts: [{resume: true}]}")))


def test_restarts_override_the_first_stage_and_cpu_wins():
    recipe = train.load_recipe("rainbench-yolo11n")
    cpu_stages, gpu_stages = recipe.stages(cuda=False), recipe.stages(cuda=True)
    assert len(gpu_stages) == 1 and "restarts" not in gpu_stages[0]
    assert len(cpu_stages) == 2 and cpu_stages[1]["imgsz"] == cpu_stages[0]["imgsz"] == 416
    assert cpu_stages[1]["epochs"] == 15 and cpu_stages[0]["epochs"] == 10


def test_tiny_training_run_writes_weights_the_evaluator_loads(tmp_path, capsys):
    recipe_path = tmp_path / "tiny.yaml"
    recipe_path.write_text(TINY_RECIPE)
    out = tmp_path / "run"
    code, stdout, err = _run(capsys, "train", "--recipe", recipe_path, "--out", out, "--device", "cpu")
    assert code == 0, err
    weights = out / "tiny-yolo.pt"
    assert stdout.strip().endswith(str(weights)) and weights.is_file()
    settings = json.loads((out / "recipe.json").read_text())
    assert settings["device"] == "cpu" and settings["train_args"]["imgsz"] == 64  # the cpu overrides
    manifest = json.loads((out / "data" / "train" / "manifest.json").read_text())
    assert manifest["complete"] and [s["scene_seed"] for s in manifest["shards"]] == [1000000, 1000001]
    assert manifest["config"]["scenario"]["num_motorcycles"] == 1
    detector = backends.load_detector(weights, device="cpu")
    assert [detector.model.names[i] for i in range(4)] == list(CLASS_NAMES)
    image = np.zeros((120, 160, 3), np.uint8)
    boxes, scores, ids = detector.predict([image], imgsz=64, conf=0.0, iou=0.7, max_det=10)[0]
    assert boxes.shape[1] == 4 and set(ids.tolist()) <= {0, 1, 2, 3}
    # Running it again finds the run finished: nothing is retrained, the weights are re-copied.
    before = (out / "run" / "weights" / "last.pt").stat().st_mtime_ns
    code, _, err = _run(capsys, "train", "--recipe", recipe_path, "--out", out, "--device", "cpu")
    assert code == 0, err
    assert (out / "run" / "weights" / "last.pt").stat().st_mtime_ns == before


def test_warm_restart_starts_from_the_first_stage_weights(tmp_path, capsys):
    import torch

    recipe_path = tmp_path / "tiny.yaml"
    recipe_path.write_text(TINY_RECIPE.replace("cpu: {epochs: 1, imgsz: 64}", RESTART))
    out = tmp_path / "run"
    code, stdout, err = _run(capsys, "train", "--recipe", recipe_path, "--out", out, "--device", "cpu")
    assert code == 0, err
    first, restart = out / "run" / "weights" / "best.pt", out / "restart1" / "weights" / "best.pt"
    assert (out / "tiny-yolo.pt").read_bytes() == restart.read_bytes()
    assert json.loads((out / "recipe.json").read_text())["restarts"][0]["lr0"] == 0.0

    def parameters(path):
        return dict(torch.load(path, map_location="cpu", weights_only=False)["model"].named_parameters())

    # With lr 0 the restart moves nothing, so it ends where it began. A cold start would end at
    # the random initialisation, which the first stage's AdamW steps moved in every tensor.
    # (ultralytics' set-up changes the class-logit convs of the head by about 1e-3: tolerated.)
    before, after = parameters(first), parameters(restart)
    assert before.keys() == after.keys()
    unchanged = [name for name in before if torch.equal(before[name], after[name])]
    assert len(unchanged) >= 0.95 * len(before), len(unchanged)
    assert max((before[n].float() - after[n].float()).abs().max().item() for n in before) < 0.01
    # A second run skips both finished stages.
    stamps = [p.stat().st_mtime_ns for p in (first, restart)]
    code, _, err = _run(capsys, "train", "--recipe", recipe_path, "--out", out, "--device", "cpu")
    assert code == 0, err
    assert [p.stat().st_mtime_ns for p in (first, restart)] == stamps


def test_shipped_weights_load_by_name_and_find_cars(tmp_path):
    """A guard against shipping broken or older weights: an unseen clean scene, car AP@0.5 >= 0.75
    and person AP@0.5 >= 0.45."""
    from rainbench.eval import pipeline
    from rainbench.gen.generate import GenerateConfig, generate_shard

    assert "rainbench-yolo11n" in backends.shipped_models()
    detector = backends.load_detector("rainbench-yolo11n", device="cpu")
    assert detector.name == "rainbench-yolo11n"
    data = tmp_path / "data"
    # Seed 7: an evaluation seed (< 1000000), never used in training or validation. Every fifth
    # frame of a 20 s clip at 10 fps.
    generate_shard(GenerateConfig(seed=7, frames=20, fps=1.0, width=800, height=600, rates=(0.0,)), data)
    result = pipeline.run_eval(data, tmp_path / "out", weights=["rainbench-yolo11n"], n_boot=1,
                               device="cpu", progress=False)
    by_class = {r["class"]: r for r in result.records}
    # Shipped model: car 0.852, person 0.528 here (the stage-1 model it replaced: 0.813, 0.347).
    # Bicycles (9 boxes) and motorcycles (3) are too few here to guard.
    car, person = by_class["car"], by_class["person"]
    assert car["n_gt"] >= 20 and car["ap50"] >= 0.75, car
    assert person["n_gt"] >= 20 and person["ap50"] >= 0.45, person


def test_paper_reduced_end_to_end(tmp_path, capsys):
    code, stdout, err = _run(capsys, "paper", "--frames", 4, "--width", 192, "--height", 144, "--rates", "0,50,100",
                             "--data", tmp_path / "data", "--out", tmp_path / "out", "--n-boot", 5,
                             "--imgsz", 192, "--quiet")
    assert code == 0, err
    report = (tmp_path / "out" / "report.md").read_text()
    for heading in ("Table I.", "Table III. AP@0.5, Normal vs 100mm/h: jeon2022",
                    "Table IV. F1, Normal vs 100mm/h: physical", "falls to half its clean value",
                    "jeon2022 vs physical", "AP@0.5 by visible fraction", "AP@0.5 by box size"):
        assert heading in report, heading
    assert "| YOLOv7x (paper) | Normal | 0.669 |" in report  # the paper's Table III row
    for rain in ("jeon2022", "physical"):
        records = json.loads((tmp_path / "out" / rain / "metrics.json").read_text())
        assert {r["model"] for r in records} == {"rainbench-yolo11n"}
        assert sorted({r["rate"] for r in records}) == [0, 50, 100]
        assert (tmp_path / "out" / rain / "ap50_vs_rate.png").stat().st_size > 1000
    # Table I counts equal the shard's labels.
    from rainbench.eval.paper import table_one

    counts = table_one(tmp_path / "data" / "jeon2022")
    records = json.loads((tmp_path / "out" / "jeon2022" / "metrics.json").read_text())
    for class_name, (objects, instances) in counts.items():
        n_gt = next(r["n_gt"] for r in records if r["class"] == class_name and r["rate"] == 0)
        assert instances == n_gt and (objects > 0) == (instances > 0)
    code, _, err = _run(capsys, "paper", "--rates", "50,100", "--data", tmp_path / "d2", "--out", tmp_path / "o2")
    assert code == 2 and "needs rate 0" in err and len(err.strip().splitlines()) == 1
