"""One reading of ``--device`` for every command and backend (rainbench.devices)."""

from pathlib import Path

import pytest

from rainbench.devices import parse_device
from rainbench.eval.backends import BackendError
from rainbench.eval.backends.onnx import onnx_cuda_device
from rainbench.gen.config import stats_device_for
from rainbench.store.manifest import DatasetError


@pytest.mark.parametrize("value, parsed", [
    (None, None), ("", None), (" auto ", None), ("AUTO", None),
    ("cpu", ("cpu", ())), (" CPU ", ("cpu", ())),
    ("cuda", ("cuda", ())), ("CUDA:1", ("cuda", (1,))), ("0", ("cuda", (0,))),
    ("0,1", ("cuda", (0, 1))), (" 2 , 3 ", ("cuda", (2, 3))), ("cuda:0,1", ("cuda", (0, 1))),
])
def test_device_values_read_one_way(value, parsed):
    assert parse_device(value) == parsed


@pytest.mark.parametrize("value", ["gpu", "tpu", "mps", "cuda:", "cuda:x", "cuda0", "0,,1", "-1",
                                   "1.5", "cpu:0", "\u0661"])
def test_every_reader_refuses_what_the_parser_refuses(value):
    """The ONNX backend took ``gpu`` (and any other word) as CUDA 0 while torch refused it; the
    statistics, torch, ONNX, ultralytics and train readers now refuse the same values with one
    message."""
    from rainbench.eval.backends.torch_batched import torch_device
    from rainbench.devices import ultralytics_device
    from rainbench.experiments.train import TrainError, check_device

    message = rf"^--device: expected auto, cpu, cuda, cuda:N or CUDA indices \(0 or 0,1\), got {value!r}$"
    with pytest.raises(ValueError, match=message):
        parse_device(value)
    with pytest.raises(DatasetError, match=message):
        stats_device_for(value)
    for reader in (lambda v: onnx_cuda_device(Path("m.onnx"), v), torch_device,
                   lambda v: ultralytics_device(v, BackendError)):
        with pytest.raises(BackendError, match=message):
            reader(value)
    with pytest.raises(TrainError, match=message):
        check_device(value)


def test_ultralytics_gets_a_device_it_takes():
    """ultralytics' own device parser refuses ``auto`` (ValueError: Invalid CUDA 'device=auto'),
    which the other readers take as the default: it gets None (its default) instead, and CUDA
    devices as its comma-joined indices."""
    from rainbench.devices import ultralytics_device

    assert [ultralytics_device(value) for value in (None, "", "auto", "CPU", "cuda", "cuda:1", "0,1")] \
        == [None, None, None, "cpu", "0", "1", "0,1"]


def test_the_readers_agree_on_the_device_they_name():
    for value, stats, onnx in [("0", "cuda:0", 0), ("1,0", "cuda:1", 1), ("cuda", "cuda", 0),
                               ("cuda:2", "cuda:2", 2), ("cpu", "cpu", None)]:
        assert stats_device_for(value) == stats

        class WithCuda:  # an onnxruntime with the CUDA provider
            @staticmethod
            def get_available_providers():
                return ["CUDAExecutionProvider", "CPUExecutionProvider"]

        assert onnx_cuda_device(Path("m.onnx"), value, WithCuda) == onnx
    assert onnx_cuda_device(Path("m.onnx"), "auto") is None  # the CPU wheel's default


def test_paper_picks_its_default_models_by_the_evaluation_device(monkeypatch, tmp_path, capsys):
    """``rainbench paper --device cpu`` on a GPU machine chose the GPU's model set (the small
    models, slow on a CPU) because it asked only whether torch saw a GPU."""
    import torch

    from rainbench import cli
    from rainbench.experiments import paper

    chosen = []

    def stop(specs, device=None):
        chosen.append([spec for _, spec in specs])
        raise cli.CliError("stop here")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(paper, "check_models", stop)
    for device, models in (("cpu", paper.default_models(cuda=False)),
                           ("auto", paper.default_models(cuda=True))):
        assert cli.main(["paper", "--out", str(tmp_path / device), "--device", device]) == 2
        assert "stop here" in capsys.readouterr().err
        assert chosen[-1] == list(models)
    assert paper.default_models(cuda=False) != paper.default_models(cuda=True)


def test_the_default_device_is_cuda_only_where_torch_sees_it(monkeypatch):
    """``--device cpu`` on a GPU machine runs on the CPU, and a shipped model resolves to its ONNX
    copy; the default (None, empty or ``auto``) is CUDA exactly where torch sees it (before,
    ``auto`` counted as CUDA even without CUDA, and an empty device as the CPU even with it)."""
    import torch

    from rainbench.devices import runs_on_cuda
    from rainbench.eval.weights import resolve_weights

    for available in (True, False):
        monkeypatch.setattr(torch.cuda, "is_available", lambda: available)
        assert runs_on_cuda(None) is runs_on_cuda("") is runs_on_cuda("auto") is available
        assert runs_on_cuda("cpu") is False and runs_on_cuda("cuda:1") is True
    assert resolve_weights("rainbench-yolo11n", "auto")[0].suffix == ".onnx"  # no CUDA here
    assert resolve_weights("rainbench-yolo11n", "0")[0].suffix == ".pt"
    with pytest.raises(BackendError, match="got 'gpu'"):
        resolve_weights("rainbench-yolo11n", "gpu")
