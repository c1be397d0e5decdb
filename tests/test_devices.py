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
    statistics, torch, ONNX and train readers now refuse the same values with one message."""
    message = rf"^--device: expected auto, cpu, cuda, cuda:N or CUDA indices \(0 or 0,1\), got {value!r}$"
    with pytest.raises(ValueError, match=message):
        parse_device(value)
    with pytest.raises(DatasetError, match=message):
        stats_device_for(value)
    with pytest.raises(BackendError, match=message):
        onnx_cuda_device(Path("m.onnx"), value)


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


def test_the_default_device_is_cuda_only_where_torch_sees_it(monkeypatch):
    """``--device cpu`` on a GPU machine runs on the CPU: the paper's default models are then the
    CPU set, and a shipped model resolves to its ONNX copy (an empty or ``auto`` device counted as
    CUDA even without CUDA before)."""
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
