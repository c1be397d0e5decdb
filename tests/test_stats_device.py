"""The per-rate statistics on a torch device (issue 17, item 3): the batched torch path, run here
on the CPU as the GPU path's twin, against the NumPy/OpenCV path; the ``stats_device`` config
field, ``--device`` and what the shard records."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from cli_errors import cli_status, one_line_error
from rainbench.gen import config as gc
from rainbench.gen import generate
from rainbench.gen.config import DatasetConfig, GenerateConfig, stats_device_for
from rainbench.rain import metrics
from rainbench.rain.metrics_torch import TorchRateStatistics
from rainbench.store.manifest import DatasetError

HEIGHT, WIDTH = 60, 80


def _frame(seed: int = 0):
    """A clean image with structure and a flat patch, four rainy versions of falling contrast
    (and one identical to the clean image), their opacity maps, and boxes of every kind: inside,
    flat, partly outside, empty, wholly outside, the whole image."""
    rng = np.random.default_rng(seed)
    rows, columns = np.mgrid[0:HEIGHT, 0:WIDTH]
    clean = np.stack([(columns * 3) % 256, (rows * 4) % 256, ((columns + rows) * 2) % 256],
                     axis=-1).astype(np.uint8)
    clean[10:20, 10:30] = 77
    rainy = [np.clip(clean * (1 - 0.15 * k) + 128 * 0.15 * k
                     + rng.integers(-k, k + 1, clean.shape), 0, 255).astype(np.uint8)
             for k in range(1, 5)] + [clean.copy()]
    coverage = [rng.random((HEIGHT, WIDTH), dtype=np.float32) for _ in rainy]
    boxes = np.array([[5, 5, 40, 30], [10, 10, 30, 20], [70, 50, 100, 80], [3, 3, 3, 9],
                      [-5, -5, 0.4, 0.4], [0.2, 0.7, 79.9, 59.6]], np.float32)
    return clean, rainy, coverage, boxes


def test_torch_statistics_equal_the_numpy_path():
    clean, rainy, coverage, boxes = _frame()
    ssim, psnr, rain_coverage, contrast = TorchRateStatistics("cpu", HEIGHT, WIDTH).frame(
        clean, rainy, coverage, boxes)
    assert ssim.dtype == psnr.dtype == rain_coverage.dtype == contrast.dtype == np.float32
    assert rain_coverage.shape == contrast.shape == (5, 6)
    ssim_reference, box_reference = metrics.SsimReference(clean), metrics.BoxRainReference(clean, boxes)
    for row, image in enumerate(rainy):
        expected_ssim, expected_psnr = ssim_reference.quality(image)
        expected_coverage, expected_contrast = box_reference.labels(image, coverage[row])
        assert abs(ssim[row] - expected_ssim) < 1e-5
        assert psnr[row] == np.float32(expected_psnr)  # the same integer sum: exactly
        np.testing.assert_allclose(rain_coverage[row], expected_coverage, rtol=0, atol=1e-6)
        np.testing.assert_allclose(contrast[row], expected_contrast, rtol=0, atol=1e-5)
    # and against the independent reference, scikit-image's SSIM on BT.601 luma
    from skimage.metrics import structural_similarity

    for row, image in enumerate(rainy[:4]):
        reference = structural_similarity(metrics.luma(clean), metrics.luma(image),
                                          gaussian_weights=True, sigma=1.5,
                                          use_sample_covariance=False, data_range=255)
        assert abs(ssim[row] - reference) < 1e-5
    # the frame exercises every case: contrast lost, a flat box (none), empty boxes (zeros)
    assert contrast[3, 0] > 0.5 and contrast[:, 1].max() == 0.0
    assert (rain_coverage[:, 3:5] == 0).all() and rain_coverage[:, 5].min() > 0.4
    assert ssim[4] == 1.0 and np.isinf(psnr[4]) and ssim[3] < ssim[0] < 1.0


def test_torch_statistics_of_no_rainy_image_and_of_no_box():
    clean, rainy, coverage, _ = _frame()
    statistics = TorchRateStatistics("cpu", HEIGHT, WIDTH)
    ssim, psnr, rain_coverage, contrast = statistics.frame(clean, [], [], np.zeros((0, 4)))
    assert ssim.shape == psnr.shape == (0,) and rain_coverage.shape == contrast.shape == (0, 0)
    ssim, _, rain_coverage, _ = statistics.frame(clean, rainy[:2], coverage[:2], np.zeros((0, 4)))
    assert ssim.shape == (2,) and rain_coverage.shape == (2, 0)


def test_torch_statistics_refuse_bad_inputs_naming_them():
    clean, rainy, coverage, boxes = _frame()
    statistics = TorchRateStatistics("cpu", HEIGHT, WIDTH)
    with pytest.raises(ValueError, match=r"expected \(60, 80, 3\) uint8 images, got ndarray \(60, 80\) uint8"):
        statistics.frame(clean, [rainy[0][..., 0]], coverage[:1], boxes)
    with pytest.raises(ValueError, match=r"one coverage map per rainy image \(2\), got 1"):
        statistics.frame(clean, rainy[:2], coverage[:1], boxes)
    with pytest.raises(ValueError, match=r"coverage must be an \(60, 80\) array, got \(80, 60\)"):
        statistics.frame(clean, rainy[:1], [coverage[0].T], boxes)
    with pytest.raises(ValueError, match=r"at least 11x11 pixels .* got 80x10"):
        TorchRateStatistics("cpu", 10, WIDTH)


def test_torch_statistics_refuse_tf32_matrix_products():
    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("high")
    try:
        with pytest.raises(ValueError, match=r"float32_matmul_precision\('high'\), expected 'highest'"):
            TorchRateStatistics("cpu", HEIGHT, WIDTH)
    finally:
        torch.set_float32_matmul_precision(before)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error of a machine without CUDA")
def test_a_cuda_stats_device_without_cuda_fails_and_leaves_no_shard(tmp_path):
    for threads in (1, 2):  # the error of the device's start, taken in this thread or a pool's
        with pytest.raises(ValueError, match=r"stats_device cuda: CUDA is not available on this machine"):
            generate.generate_shard(GenerateConfig(frames=2, width=64, height=48, rates=(0.0, 50.0),
                                                   stats_device="cuda"), tmp_path, threads=threads)
        assert not any(tmp_path.iterdir())


def test_a_cuda_index_beyond_the_machines_devices_is_named(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match=r"stats_device cuda:1: this machine has 1 CUDA device\(s\)"):
        TorchRateStatistics("cuda:1", HEIGHT, WIDTH)
    code = cli_status(["generate", "--out", tmp_path / "data", "--quiet", "--device", "cuda:2"])
    one_line_error(capsys, code, r"--device cuda:2: this machine has 1 CUDA device\(s\)")
    assert not (tmp_path / "data").exists()


def test_stats_device_field_values_and_what_the_config_records():
    assert DatasetConfig().stats_device == "cpu"
    # "cpu" is left out of the manifest's and the shard's config: old datasets keep matching
    assert "stats_device" not in DatasetConfig().to_dict()
    assert "stats_device" not in GenerateConfig().to_dict()
    config = DatasetConfig(stats_device="cuda:1")
    assert config.to_dict()["stats_device"] == "cuda:1"
    assert all(task.stats_device == "cuda:1" and task.to_dict()["stats_device"] == "cuda:1"
               for task in config.tasks())
    for bad in ("gpu", "cuda:", "CUDA", 0, None):
        with pytest.raises(DatasetError, match=r"stats_device: expected cpu, cuda or cuda:N, got"):
            DatasetConfig(stats_device=bad)


def test_device_flag_values(monkeypatch):
    assert stats_device_for("cpu") == "cpu" and stats_device_for(" CPU ") == "cpu"
    assert stats_device_for("0") == "cuda:0" and stats_device_for("1,2") == "cuda:1"
    assert stats_device_for("cuda") == "cuda" and stats_device_for("cuda:3") == "cuda:3"
    with pytest.raises(DatasetError, match=r"--device: expected auto, cpu, cuda, cuda:N or CUDA indices \(0 or 0,1\), got 'mps'"):
        stats_device_for("mps")

    class NoGpuPath(type(Path())):
        def exists(self):
            return False if str(self) == "/dev/nvidiactl" else super().exists()

    monkeypatch.setattr(gc, "Path", NoGpuPath)
    assert stats_device_for(None) == "cpu" and stats_device_for("auto") == "cpu"
    monkeypatch.setattr(gc, "Path", lambda text: Path("/"))  # "/" exists: torch is asked
    for seen, expected in ((True, "cuda"), (False, "cpu")):
        monkeypatch.setattr(torch.cuda, "is_available", lambda seen=seen: seen)
        assert stats_device_for("auto") == stats_device_for(None) == expected


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error of a machine without CUDA")
def test_generate_device_cuda_without_cuda_is_one_line_error(tmp_path, capsys):
    code = cli_status(["generate", "--out", tmp_path / "data", "--frames", "1", "--width", "64",
                       "--height", "48", "--quiet", "--device", "cuda"])
    one_line_error(capsys, code, r"--device cuda: CUDA is not available on this machine "
                                 r"\(torch.cuda.is_available\(\) is False\); use --device cpu")
    assert not (tmp_path / "data").exists() or not any((tmp_path / "data").iterdir())
    code = cli_status(["generate", "--out", tmp_path / "data", "--quiet", "--device", "tpu"])
    one_line_error(capsys, code, r"--device: expected auto, cpu, cuda, cuda:N or CUDA indices \(0 or 0,1\), got 'tpu'")


@pytest.mark.parametrize("rain_model", ["jeon2022", "physical"])
def test_a_shard_with_torch_statistics_holds_the_same_images_and_close_figures(
        tmp_path, monkeypatch, rain_model):
    """The generator with its statistics on a torch device (the CPU standing in for a GPU):
    the images and labels are the CPU path's bytes, the figures agree to float32 rounding, the
    shard records the device, and two runs (1 and 3 threads; jeon2022, to keep the suite short)
    give the same bytes."""
    base = dict(seed=5, frame_offset=60, frames=2, width=96, height=72, rates=(0.0, 20.0, 60.0, 100.0),
                rain_model=rain_model)
    cpu_shard = generate.generate_shard(GenerateConfig(**base), tmp_path / "cpu", threads=2)
    calls = []

    class CountedStatistics(TorchRateStatistics):
        def frame(self, *args):
            calls.append(len(args[1]))
            return super().frame(*args)

    monkeypatch.setattr(generate, "rate_statistics",
                        lambda config: CountedStatistics("cpu", config.height, config.width))
    device_config = GenerateConfig(**base, stats_device="cuda:0")
    runs = ((0, 1), (1, 3)) if rain_model == "jeon2022" else ((0, 2),)
    torch_shards = [generate.generate_shard(device_config, tmp_path / f"torch{k}", threads=threads)
                    for k, threads in runs]
    assert calls == [3] * 2 * len(runs)  # every frame's three rainy rates in one batch, each run
    assert all(shard.read_bytes() == torch_shards[0].read_bytes() for shard in torch_shards)
    with h5py.File(cpu_shard, "r") as cpu, h5py.File(torch_shards[0], "r") as device:
        assert json.loads(device.attrs["config"])["stats_device"] == "cuda:0"
        assert "stats_device" not in json.loads(cpu.attrs["config"])
        for key in ("rgb", "labels/bbox", "rain/drop_count"):
            np.testing.assert_array_equal(device[key][()], cpu[key][()])
        assert (cpu["rain/ssim"][1:] < 1).all()  # it rained, so there is something to compare
        np.testing.assert_allclose(device["rain/ssim"][()], cpu["rain/ssim"][()], rtol=0, atol=1e-5)
        np.testing.assert_array_equal(device["rain/psnr"][()], cpu["rain/psnr"][()])
        for key in ("labels/rain_coverage", "labels/contrast_loss"):
            assert device[key].shape == cpu[key].shape and cpu[key][()].max() > 0
            np.testing.assert_allclose(device[key][()], cpu[key][()], rtol=0, atol=1e-5)


def test_ray_tasks_on_a_cluster_without_gpus_are_refused_before_they_start(tmp_path, monkeypatch):
    """A GPU statistics device (``--device auto`` on a machine with a GPU) and a Ray cluster
    whose nodes have none: every task would fail on its first rainy frame, so the run is refused
    first, naming --device."""
    import sys
    import types

    from rainbench.gen import dataset as ds

    started = []
    fake_ray = types.SimpleNamespace(is_initialized=lambda: True,
                                     cluster_resources=lambda: {"CPU": 8.0},
                                     remote=lambda function: started.append(function))
    monkeypatch.setitem(sys.modules, "ray", fake_ray)
    config = DatasetConfig(frames=1, width=64, height=48, rates=(0.0, 50.0), stats_device="cuda")
    with pytest.raises(DatasetError, match=r"--device cuda: the Ray cluster has no GPU for the "
                                           r"statistics; use --device cpu"):
        ds.run_dataset(config, tmp_path / "data", executor="ray")
    assert started == [] and not list((tmp_path / "data").glob("*.h5"))
