"""Weight-space interpolation of a fine-tune with its start (WiSE-FT):
rainbench.eval.weights.interpolate_checkpoints, on the shipped nano model and its rain fine-tune."""

import pytest
import torch

from rainbench.eval.backends import BackendError
from rainbench.eval.backends.ultralytics import _offline_ultralytics, preload_torch
from rainbench.eval.weights import checkpoint_file, interpolate_checkpoints

preload_torch()

BASE, TUNED = "rainbench-yolo11n", "rainbench-yolo11n-rain"


def _state(path):
    return torch.load(path, map_location="cpu", weights_only=False)["model"].float().state_dict()


def test_the_ends_are_the_two_models_and_the_middle_is_their_mean(tmp_path):
    base, tuned = _state(checkpoint_file(BASE)), _state(checkpoint_file(TUNED))
    assert any(not torch.equal(base[name], tuned[name]) for name in base)
    for alpha, expected in ((0.0, base), (1.0, tuned)):
        got = _state(interpolate_checkpoints(BASE, TUNED, alpha, tmp_path / f"{alpha}.pt"))
        assert all(torch.equal(got[name], expected[name]) for name in expected)
    middle = interpolate_checkpoints(BASE, TUNED, 0.5, tmp_path / "half.pt")
    got = _state(middle)
    for name, value in tuned.items():
        if value.is_floating_point():
            assert torch.equal(got[name], ((base[name] + value) / 2).half().float()), name
        else:
            assert torch.equal(got[name], value), name
    checkpoint = torch.load(middle, map_location="cpu", weights_only=False)
    assert checkpoint["interpolated"] == {"base": f"{BASE}.pt", "fine_tuned": f"{TUNED}.pt",
                                          "alpha": 0.5}
    assert checkpoint["model"].names == torch.load(checkpoint_file(TUNED), map_location="cpu",
                                                   weights_only=False)["model"].names
    assert _offline_ultralytics().YOLO(str(middle)).names[0] == "person"  # ultralytics loads it
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize("alpha", [-0.1, 1.5, float("nan")])
def test_alpha_outside_zero_to_one_is_refused(tmp_path, alpha):
    with pytest.raises(BackendError, match=r"^alpha: expected a number in \[0, 1\], got "):
        interpolate_checkpoints(BASE, TUNED, alpha, tmp_path / "x.pt")
    assert list(tmp_path.iterdir()) == []


def test_two_architectures_or_a_non_checkpoint_are_refused(tmp_path):
    with pytest.raises(BackendError, match=r"rainbench-yolo11s\.pt: its tensors differ from "
                                           r".*rainbench-yolo11n\.pt's \(first: .*\); expected a "
                                           r"fine-tune of the same architecture$"):
        interpolate_checkpoints(BASE, "rainbench-yolo11s", 0.5, tmp_path / "x.pt")
    junk = tmp_path / "junk.pt"
    junk.write_text("not a checkpoint")
    with pytest.raises(BackendError, match=r"junk\.pt: expected an ultralytics checkpoint with a "
                                           r"'model' \("):
        interpolate_checkpoints(BASE, junk, 0.5, tmp_path / "x.pt")
    assert not (tmp_path / "x.pt").exists()
