"""`rainbench train` and `rainbench paper` refuse bad input before generating anything: a recipe's
architecture, init_weights and train() arguments, the device, the models and the rain models.
Each case is a one-line error naming what is at fault, exit status 2, and no file written."""

import dataclasses
import os
import re
from pathlib import Path

import pytest
import torch

from rainbench import cli
from rainbench.eval.backends import BackendError
from rainbench.eval.backends.ultralytics import _offline_ultralytics
from rainbench.eval.pipeline import EvalError
from rainbench.eval.weights import shipped_models
from rainbench.experiments import train
from rainbench.experiments.paper import PaperConfig, check_models, run_paper
from rainbench.gen.config import DatasetConfig
from rainbench.store.locks import directory_lock, locked_output_dir

# Load torch's lazy modules before anything could render in this process (see test_eval_pipeline).
_offline_ultralytics()
import torch._dynamo  # noqa: E402,F401

# Tiny data, never generated here: every case must fail before the first frame.
TINY_RECIPE = """
name: tiny-yolo
architecture: yolo11n.yaml
eval_imgsz: 96
train_data: {seed: 1000000, scenes: 1, frames: 2, fps: 0.2, width: 160, height: 120}
val_data: {seed: 2000000, scenes: 1, frames: 2, fps: 0.1, width: 160, height: 120}
train: {epochs: 2, imgsz: 96, batch: 4, seed: 0, workers: 0, cache: false}
cpu: {epochs: 1, imgsz: 64}
"""
PAPER_TINY = ["--frames", "2", "--width", "160", "--height", "120", "--rates", "0,50", "--quiet"]


def _run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _one_line_error(err: str, message: str) -> None:
    assert err == f"rainbench: error: {message}\n", err


def _nothing_written(*roots: Path) -> None:
    for root in roots:
        assert not root.exists(), sorted(root.rglob("*"))
    found = [p for p in roots[0].parent.rglob("*") if p.suffix in (".h5", ".png", ".onnx")
             or p.name in ("manifest.json", "dataset.yaml", "shards.yaml", "recipe.json")]
    assert not found, found


def _recipe(tmp_path: Path, old: str = "", new: str = "") -> Path:
    assert old in TINY_RECIPE
    path = tmp_path / "recipe.yaml"
    path.write_text(TINY_RECIPE.replace(old, new, 1) if old else TINY_RECIPE)
    return path


def _no_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)


# ---- rainbench train ----------------------------------------------------------------------------


def test_train_refuses_an_unknown_architecture_before_generating(tmp_path, capsys):
    recipe = _recipe(tmp_path, "architecture: yolo11n.yaml", "architecture: nonexistent.yaml")
    out = tmp_path / "tr"
    code, stdout, err = _run(capsys, "train", "--recipe", recipe, "--out", out, "--device", "cpu")
    assert code == 2 and stdout == ""
    _one_line_error(err, f"{recipe}: `architecture`: 'nonexistent.yaml' is not an ultralytics model yaml or a file")
    _nothing_written(out)


@pytest.mark.parametrize("architecture, message", [
    ("yolo11n.pt", "'yolo11n.pt' is not an ultralytics model yaml or a file"),
    ("https://example.com/yolo11n.yaml", "'https://example.com/yolo11n.yaml' is not an ultralytics model yaml or a file"),
    ("RECIPE", "RECIPE is not an ultralytics model yaml (it needs `backbone` and `head`)"),
])
def test_architecture_must_be_a_model_yaml_ultralytics_finds(tmp_path, architecture, message):
    recipe = _recipe(tmp_path)
    architecture = architecture.replace("RECIPE", str(recipe))
    with pytest.raises(train.TrainError) as error:
        train.check_architecture(architecture, "R")
    assert str(error.value) == "R: `architecture`: " + message.replace("RECIPE", str(recipe))
    # what ultralytics builds by name, or from its file
    assert train.check_architecture("yolo11n.yaml", "R") == "yolo11n.yaml"
    assert train.check_architecture("yolov8s.yaml", "R") == "yolov8s.yaml"


def test_train_checks_a_recipe_object_before_writing(tmp_path):
    """train() itself refuses a Recipe whose architecture cannot be built (one not from load_recipe)."""
    recipe = dataclasses.replace(train.load_recipe(_recipe(tmp_path)), architecture="nonexistent.yaml")
    out = tmp_path / "tr"
    with pytest.raises(train.TrainError, match=r"`architecture`: 'nonexistent.yaml' is not an ultralytics"):
        train.train(recipe, out, device="cpu")
    _nothing_written(out)


@pytest.mark.parametrize("field, make, message", [
    ("architecture", lambda d: _write(d / "random.pt", bytes(range(256)) * 8),
     r"`architecture`: \S+random\.pt does not load as an ultralytics model \(.*not a loadable checkpoint.*\)"),
    ("architecture", lambda d: "yolo11n-cls.yaml",
     r"`architecture`: yolo11n-cls\.yaml is a 'classify' model; expected a detection model"),
    ("init_weights", lambda d: _write(d / "random.pt", bytes(range(256)) * 8),
     r"`init_weights`: \S+random\.pt does not load as an ultralytics model \(.*not a loadable checkpoint.*\)"),
    ("init_weights", lambda d: _torch_save(d / "dict.pt", {"a": 1}),
     r"`init_weights`: \S+dict\.pt does not load as an ultralytics model \(.+\)"),
])
def test_train_builds_its_first_model_before_generating(tmp_path, capsys, field, make, message):
    """A file that is not a checkpoint (or a model that is not a detector) as `architecture` or
    `init_weights` passed the name checks, then failed with a traceback after the data was made."""
    value = make(tmp_path)
    old = "architecture: yolo11n.yaml"
    recipe = _recipe(tmp_path, old, f"architecture: {value}" if field == "architecture" else f"{old}\ninit_weights: {value}")
    out = tmp_path / "tr"
    code, stdout, err = _run(capsys, "train", "--recipe", recipe, "--out", out, "--device", "cpu")
    assert code == 2 and stdout == "" and err.count("\n") == 1
    assert re.fullmatch(r"rainbench: error: " + re.escape(str(recipe)) + ": " + message + "\n", err), err
    _nothing_written(out)


@pytest.mark.parametrize("name", ["/tmp/elsewhere", "sub/model", "../up", ".hidden", "", "a b", "x" * 129])
def test_a_recipe_name_is_a_plain_file_name(tmp_path, name):
    """The name becomes OUT/<name>.pt and the default OUT runs/<name>: an absolute name wrote the
    model outside OUT, one with a slash failed after training."""
    recipe = _recipe(tmp_path, "name: tiny-yolo", f"name: '{name}'")
    with pytest.raises(train.TrainError, match=r"^" + re.escape(f"{recipe}: `name` must be a file name of letters, "
                                                                 "digits, '.', '_' and '-'") + r".*got '.*'$"):
        train.load_recipe(recipe)
    assert train.load_recipe(_recipe(tmp_path, "name: tiny-yolo", "name: My_model-2.1")).name == "My_model-2.1"


def test_a_run_cut_off_after_its_last_epoch_counts_as_finished(tmp_path):
    """Cut off after ultralytics saved the last epoch but before it stripped last.pt: the rerun
    asked ultralytics to resume it, which refuses ("nothing to resume"), on every rerun."""
    last = tmp_path / "last.pt"
    for epoch, epochs, finished in ((-1, 4, True), (3, 4, True), (2, 4, False), (3, None, False)):
        torch.save({"epoch": epoch}, last)
        assert train._finished(last, epochs) is finished, (epoch, epochs)
    # a last.pt cut short (the disk filled, the machine died while saving) is named, not a
    # torch traceback's "PytorchStreamReader failed ..." without a file
    whole = last.read_bytes()
    last.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(train.TrainError, match=f"^{re.escape(str(last))}: cannot be read to resume the run "
                                               r"\(.+\); delete it to train that stage again$"):
        train._finished(last, 4)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _torch_save(path: Path, value) -> Path:
    torch.save(value, path)
    return path


@pytest.mark.parametrize("device, message", [
    ("banana", "--device: expected auto, cpu, cuda, cuda:N or CUDA indices (0 or 0,1), got 'banana'"),
    ("cuda:x", "--device: expected auto, cpu, cuda, cuda:N or CUDA indices (0 or 0,1), got 'cuda:x'"),
    ("0", "--device 0: CUDA is not available on this machine"),
    ("cuda:0", "--device cuda:0: CUDA is not available on this machine"),
])
def test_train_refuses_a_device_before_generating(tmp_path, capsys, monkeypatch, device, message):
    _no_cuda(monkeypatch)
    out = tmp_path / "tr"
    code, _, err = _run(capsys, "train", "--recipe", _recipe(tmp_path), "--out", out, "--device", device)
    assert code == 2
    _one_line_error(err, message)
    _nothing_written(out)


def test_check_device_normalises_what_it_accepts(monkeypatch):
    assert train.check_device(None) is None and train.check_device("") is None
    assert train.check_device("cpu") == train.check_device(" CPU ") == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert train.check_device("cuda:1") == "1" and train.check_device("cuda") == "0"
    assert train.check_device("0,1") == "0,1"
    with pytest.raises(train.TrainError, match=r"^--device 2: there is no CUDA device 2 \(2 visible\)$"):
        train.check_device("2")
    with pytest.raises(train.TrainError, match="got 'tpu'"):
        train.check_device("tpu")


@pytest.mark.parametrize("old, new, message", [
    ("epochs: 2", "epochs: -5", "`train.epochs` must be an integer >= 1, got -5"),
    ("imgsz: 96, batch", "imgsz: 16, batch", "`train.imgsz` must be an integer >= 32 (px), got 16"),
    ("batch: 4", "batch: 0", "`train.batch` must be an integer >= 1, -1 (AutoBatch) or a GPU memory fraction in "
                             "(0, 1), got 0"),
    ("workers: 0", "workers: -1", "`train.workers` must be an integer >= 0, got -1"),
    ("cache: false", "cache: false, lr0: -0.1",
     "`train.lr0`: 'lr0=-0.1' is an invalid value. Valid 'lr0' values are between 0.0 and 1.0."),
    ("cache: false", "cache: false, warmup_epochs: -1", "`train.warmup_epochs` must be a number >= 0, got -1"),
    ("cache: false", "cache: false, epoch: 3", "`train.epoch` is not an ultralytics train() argument"),
    ("cpu: {epochs: 1", "cpu: {epochs: 0", "`cpu.epochs` must be an integer >= 1, got 0"),
    ("imgsz: 64}", "imgsz: 64, restarts: [{epochs: 2}, {imgsz: 20}]}",
     "`cpu.restarts[2].imgsz` must be an integer >= 32 (px), got 20"),
    ("eval_imgsz: 96", "eval_imgsz: 96\ninit_weights: missing.pt",
     "`init_weights`: missing.pt: expected a shipped model name (" + ", ".join(shipped_models())
     + ") or an existing .pt checkpoint"),
    ("eval_imgsz: 96", "eval_imgsz: 96\nwise_alpha: 0.9",
     "`wise_alpha` needs `init_weights` (it mixes the trained weights with the checkpoint they started from)"),
    ("eval_imgsz: 96", "eval_imgsz: 96\ninit_weights: rainbench-yolo11n\nwise_alpha: 0",
     "`wise_alpha` must be a number in (0, 1], got 0"),
    ("eval_imgsz: 96", "eval_imgsz: 96\ninit_weights: rainbench-yolo11n\nwise_alpha: true",
     "`wise_alpha` must be a number in (0, 1], got True"),
])
def test_train_refuses_bad_recipe_values_before_generating(tmp_path, capsys, old, new, message):
    recipe = _recipe(tmp_path, old, new)
    out = tmp_path / "tr"
    code, _, err = _run(capsys, "train", "--recipe", recipe, "--out", out, "--device", "cpu")
    assert code == 2
    _one_line_error(err, f"{recipe}: {message}")
    _nothing_written(out)


def test_recipes_keep_what_ultralytics_accepts(tmp_path):
    """ultralytics' automatic batch (-1), a batch as a share of GPU memory (0.7) and a restart at
    a zero learning rate reach the stages' train() arguments as written."""
    for old, new, stages in (
            ("batch: 4", "batch: -1", [(-1, None)]), ("batch: 4", "batch: 0.7", [(0.7, None)]),
            ("cpu: {epochs: 1, imgsz: 64}", "cpu: {epochs: 1, imgsz: 64, restarts: [{lr0: 0.0}]}",
             [(4, None), (4, 0.0)])):
        recipe = train.load_recipe(_recipe(tmp_path, old, new))
        assert [(stage["batch"], stage.get("lr0")) for stage in recipe.stages(cuda=False)] == stages
    for name in ("rainbench-yolo11n", "rainbench-yolo11s", "rainbench-yolo11n-weak"):
        assert train.load_recipe(name).stages(cuda=False)


# ---- rainbench paper ----------------------------------------------------------------------------


@pytest.mark.parametrize("flags, message", [
    (["--model", "foo"], "--model: 'foo' is neither a shipped model (" + ", ".join(shipped_models())
     + ") nor an existing weights file"),
    (["--model", "rainbench-yolo11n", "--weights", "w/x.pt"],
     "--weights: w/x.pt does not exist (weights are loaded from local files only)"),
    (["--weights", "foo"], "--weights: 'foo' is neither a shipped model (" + ", ".join(shipped_models())
     + ") nor an existing weights file"),
    (["--model", "rainbench-yolo11n", "--model", "rainbench-yolo11n"],
     "--model: rainbench-yolo11n is a second model named 'rainbench-yolo11n' (after --model rainbench-yolo11n); "
     "model names (file stems) must be unique"),
    (["--model", "rainbench-yolo11n", "--weights", "w/rainbench-yolo11n.pt"],
     "--weights: w/rainbench-yolo11n.pt is a second model named 'rainbench-yolo11n' (after --model "
     "rainbench-yolo11n); model names (file stems) must be unique"),
    (["--model", "rainbench-yolo11n", "--device", "banana"],
     "--device: expected auto, cpu, cuda, cuda:N or CUDA indices (0 or 0,1), got 'banana'"),
    (["--model", "rainbench-yolo11n", "--device", "0"], "--device 0: CUDA is not available on this machine"),
    (["--model", "rainbench-yolo11n", "--rain-models", "jeon2022,jeon2022"], "--rain-models: jeon2022 is named twice"),
    (["--model", "rainbench-yolo11n", "--rain-models", "jeon2022,rainy"],
     "--rain-models: expected some of jeon2022, physical, got ['jeon2022', 'rainy']"),
])
def test_paper_refuses_models_devices_and_rain_models_before_generating(tmp_path, capsys, monkeypatch, flags,
                                                                        message):
    _no_cuda(monkeypatch)
    monkeypatch.chdir(tmp_path)
    if "w/rainbench-yolo11n.pt" in flags:
        (tmp_path / "w").mkdir()
        (tmp_path / "w" / "rainbench-yolo11n.pt").write_bytes(b"not read")
    code, stdout, err = _run(capsys, "paper", *PAPER_TINY, *flags, "--out", "pp", "--data", "pd")
    assert code == 2 and stdout == ""
    _one_line_error(err, message)
    _nothing_written(tmp_path / "pp", tmp_path / "pd")


def test_run_paper_checks_models_and_device_before_generating(tmp_path, monkeypatch):
    dataset = DatasetConfig(frames=2, width=160, height=120, rates=(0.0, 50.0))
    out, data = tmp_path / "pp", tmp_path / "pd"
    with pytest.raises(EvalError, match=r"^--weights: .*missing\.pt does not exist"):
        run_paper(PaperConfig(dataset=dataset, rain_models=("jeon2022",), weights=(str(tmp_path / "missing.pt"),)),
                  out, data, progress=False)
    with pytest.raises(train.TrainError, match="got 'banana'"):
        run_paper(PaperConfig(dataset=dataset, rain_models=("jeon2022",), device="banana"), out, data, progress=False)
    _nothing_written(out, data)
    # an ONNX model on a GPU without onnxruntime's CUDA provider: refused before generating, not
    # after (as if this machine had the GPU: check_device passes it)
    out, data = tmp_path / "runs" / "pp", tmp_path / "runs" / "pd"  # beside the model, not above it
    onnx_model = tmp_path / "m.onnx"
    onnx_model.write_bytes(b"not read by the check")
    with monkeypatch.context() as patch:
        patch.setattr(train, "check_device", lambda device: device)
        with pytest.raises(BackendError, match=r"^--device cuda:0: .*m\.onnx is an ONNX model and this "
                                               r"onnxruntime has no CUDA provider"):
            run_paper(PaperConfig(dataset=dataset, rain_models=("jeon2022",), weights=(str(onnx_model),),
                                  device="cuda:0"), out, data, progress=False)
    _nothing_written(out, data)
    with pytest.raises(EvalError, match="^--rain-models: physical is named twice$"):
        PaperConfig(dataset=dataset, rain_models=("physical", "jeon2022", "physical"))
    check_models([("--model", name) for name in shipped_models()])  # every shipped name is known
    # the ONNX refusal is check_models' own, so the CLI's check (with --model too) makes it
    with pytest.raises(BackendError, match=r"^--device 0: .*m\.onnx is an ONNX model"):
        check_models([("--model", "rainbench-yolo11n"), ("--weights", str(onnx_model))], "0")
    check_models([("--weights", str(onnx_model))], "cpu")


# ---- one run at a time per --out --------------------------------------------------------------


@pytest.mark.parametrize("command", ["train", "paper"])
def test_a_second_run_into_a_locked_out_is_refused_before_generating(tmp_path, capsys, monkeypatch, command):
    """Two runs into one --out removed and overwrote each other's files; the second is refused,
    naming the holder, and the holder's directory is left as it was."""
    _no_cuda(monkeypatch)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "busy"
    out.mkdir()
    argv = (["train", "--recipe", _recipe(tmp_path), "--device", "cpu"] if command == "train"
            else ["paper", *PAPER_TINY, "--model", "rainbench-yolo11n", "--data", "pd"])
    with directory_lock(out, command, option="--out", error=ValueError) as lock:
        code, stdout, err = _run(capsys, *argv, "--out", out)
        assert lock.read_text() == f"{os.getpid()} {command}"
    assert code == 2 and stdout == ""
    _one_line_error(err, f"--out: {out} is being written by another rainbench {command} (pid {os.getpid()}); "
                         "wait for it to finish or choose another --out")
    assert list(out.iterdir()) == []  # the holder's lock is gone with it; nothing else was written
    _nothing_written(tmp_path / "pd")


def test_a_refused_run_leaves_no_empty_out_behind(tmp_path):
    """A run that fails under the lock removes the folders it made for --out (when empty)."""
    out = tmp_path / "new" / "out"
    with pytest.raises(RuntimeError, match="boom"):
        with locked_output_dir(out, "eval", option="--out", error=ValueError) as root:
            assert root == out and (out / ".rainbench.lock").is_file()
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match=f"^--out: {re.escape(str(tmp_path / 'file'))} exists and is not a directory$"):
        with locked_output_dir(tmp_path / "file", "eval", option="--out", error=ValueError):
            pass


def test_one_lock_per_folder_whatever_the_command(tmp_path, capsys):
    """An eval and a paper into one --out both write report.md: a run of one command refuses a
    folder another command holds, naming the holder."""
    out = tmp_path / "shared"
    out.mkdir()
    with directory_lock(out, "paper", option="--out", error=ValueError):
        with pytest.raises(ValueError, match=re.escape(f"--out: {out} is being written by another rainbench paper "
                                                       f"(pid {os.getpid()}); wait for it to finish or choose another --out")):
            with locked_output_dir(out, "eval", option="--out", error=ValueError):
                pass
    with locked_output_dir(out, "eval", option="--out", error=ValueError):  # released
        pass


def test_paper_names_a_remedy_it_has_for_a_data_folder_holding_something_else(tmp_path, capsys, monkeypatch):
    """A --data folder holding other files made paper advise --overwrite, an option it lacks."""
    _no_cuda(monkeypatch)
    monkeypatch.chdir(tmp_path)
    taken = tmp_path / "pd" / "jeon2022"
    taken.mkdir(parents=True)
    (taken / "notes.txt").write_text("mine")
    code, stdout, err = _run(capsys, "paper", *PAPER_TINY, "--model", "rainbench-yolo11n", "--out", "pp", "--data", "pd")
    assert code == 2 and stdout == ""
    _one_line_error(err, "OUT: pd/jeon2022 is not empty and has no manifest; delete pd/jeon2022 to generate it "
                         "again, or choose another --data")
    assert sorted(p.name for p in taken.iterdir()) == ["notes.txt"]


def test_paper_shows_the_frames_it_generates(tmp_path, capsys, monkeypatch):
    """make paper's generation phases ran for minutes without a line; they show a frame bar."""
    from rainbench.experiments import paper

    class Stop(Exception):
        pass

    def generate(config, out, *, progress=None, **kwargs):
        for _ in range(config.frames):
            progress(1)
        raise Stop

    monkeypatch.setattr(paper, "run_dataset", generate)
    dataset = DatasetConfig(frames=3, width=160, height=120, rates=(0.0, 50.0))
    with pytest.raises(Stop):
        run_paper(PaperConfig(dataset=dataset, rain_models=("jeon2022",), weights=("rainbench-yolo11n",),
                              device="cpu"), tmp_path / "pp", tmp_path / "pd", progress=True)
    err = capsys.readouterr().err
    assert "generate jeon2022" in err and "3/3" in err
    with pytest.raises(Stop):  # and nothing with progress off
        run_paper(PaperConfig(dataset=dataset, rain_models=("jeon2022",), weights=("rainbench-yolo11n",),
                              device="cpu"), tmp_path / "pp2", tmp_path / "pd2", progress=False)
    assert capsys.readouterr().err == ""
