"""bench/generate_profile.py, the stage profile the GPU check runs first (bench/gpu_check.sh):
its timers must reach every stage of a real generation, or a GPU session's one try reports
nothing for the stages whose functions were renamed or moved. Run in a subprocess: the
profile wraps module functions for the rest of its process."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "generate_profile.py"


def _profile(tmp_path, *args):
    out = tmp_path / "profile.json"
    run = subprocess.run([sys.executable, str(SCRIPT), *args, "--json", str(out)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300,
                         env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(out.read_text()), run.stdout


@pytest.mark.parametrize("rain_model, stages", [
    ("jeon2022", ("scene build", "GL renderer start", "simulate", "render: RGB",
                  "render: segmentation", "labels (total, incl. actor passes)", "rain sweep",
                  "statistics: clean references (SSIM)", "statistics: clean references (boxes)",
                  "statistics: SSIM / PSNR per rate", "statistics: box rain labels per rate",
                  "compress", "write (writer thread, incl. compress)", "commit")),
    ("physical", ("render: weather re-renders", "weather images' array work",
                  "weather rain (spray, sweeps, camera response)", "camera response",
                  "rain sweep", "compress")),
])
def test_the_profile_times_every_stage_of_a_real_generation(tmp_path, rain_model, stages):
    frames = 2 if rain_model == "jeon2022" else 1
    result, table = _profile(tmp_path, "--rain-model", rain_model, "--frames", str(frames),
                             "--threads", "2", "--device", "cpu", "--out", str(tmp_path))
    assert result["frames"] == frames and result["rates"] == 11 and result["threads"] == 2
    assert result["weather_follows_rate"] == (rain_model == "physical")
    assert result["stats_device"] == "cpu" and "statistics on cpu" in table
    assert result["out_dir"] == str(tmp_path.resolve()) and f"written in {tmp_path.resolve()}" in table
    assert sorted(path.name for path in tmp_path.iterdir()) == ["profile.json"]  # shard removed
    for stage in stages:
        row = result["stages"].get(stage)
        assert row is not None, f"{stage}: never timed (its function was renamed or moved?)"
        assert row["calls"] >= 1 and row["seconds"] > 0 and row["cpu_seconds"] >= 0
        assert stage in table
    once = ("scene build", "GL renderer start", "commit")
    assert all(result["stages"][stage]["calls"] == 1 for stage in once if stage in stages)
    if rain_model == "jeon2022":
        assert result["stages"]["compress"]["calls"] == 11 * frames  # every image of every rate
        assert result["stages"]["statistics: SSIM / PSNR per rate"]["calls"] == 10 * frames
    assert 0 < result["cpu_s"] and 0 < result["wall_s"]
    assert result["process_start_to_generate_s"] > 0
    assert "main thread waiting" in table


def test_the_profile_refuses_no_frames_and_one_worker(tmp_path):
    for flags, message in ((["--frames", "0"], "--frames: expected an integer >= 1, got 0"),
                           (["--out", str(tmp_path / "none")], f"--out: {tmp_path / 'none'} is not a directory"),
                           (["--workers", "1"], r"--workers: expected an integer >= 2 (pieces), got 1")):
        run = subprocess.run([sys.executable, str(SCRIPT), *flags], capture_output=True,
                             text=True, cwd=ROOT, timeout=120)
        assert run.returncode == 2 and message in run.stderr, run.stderr


def test_the_pieces_profile_sees_every_piece_joined(tmp_path):
    result, table = _profile(tmp_path, "--frames", "16", "--workers", "2")
    assert result["mode"] == "pieces" and result["pieces"] == 2 and result["workers"] == 2
    assert len(result["joined_at_s"]) == 2 and result["joined_at_s"] == sorted(result["joined_at_s"])
    assert 0 < result["joined_at_s"][-1] <= result["wall_s"]
    assert result["stages"]["join: copy a piece's chunks (parent)"]["calls"] == 2
    assert result["stages"]["join: commit the shard (parent)"]["calls"] == 1
    assert result["shard_bytes"] > 16 * 11 * 100_000  # 176 deflated 800x600 images
    assert "pieces joined from" in table


def test_the_profile_times_the_torch_statistics_where_they_run():
    """With a GPU statistics device the profile wraps the batched torch statistics (run here
    on the CPU: the stage is the same function)."""
    code = """
import numpy as np, sys
sys.path.insert(0, "bench")
import generate_profile as gp
from rainbench.rain.metrics_torch import TorchRateStatistics
timers = gp.StageTimers()
gp.install(timers, "cuda")
clean = np.zeros((24, 32, 3), np.uint8)
TorchRateStatistics("cpu", 24, 32).frame(clean, [clean + 9], [np.zeros((24, 32), np.float32)],
                                         np.array([[1, 1, 9, 9]], np.float32))
print(timers.calls)
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "'statistics: torch, all rates of a frame': 1" in run.stdout


def test_the_statistics_bench_compares_both_paths_on_the_same_frames(tmp_path):
    """bench/stats_device.py, the GPU check's measure of item 3, run here with the CPU's torch
    path standing in for the GPU: both paths timed and their figures compared."""
    out = tmp_path / "stats.json"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "stats_device.py"), "--frames", "1",
                          "--repeats", "1", "--device", "cpu", "--threads", "2", "--json", str(out)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(out.read_text())
    assert result["device"] == "cpu" and result["cpu_threads"] == 2 and result["rainy_rates"] == 10
    assert result["cpu_ms_per_frame"] > 0 and result["device_ms_per_frame"] > 0
    assert result["largest_difference"]["ssim"] < 1e-5 and result["largest_difference"]["psnr"] == 0
    assert "statistics of one frame" in run.stdout


def test_the_rain_memory_bench_alternates_its_pairs_and_times_warm_draws(tmp_path):
    """bench/rain_memory.py on the paper case, two pairs: the pairs alternate which mode runs
    first, each run times warm draws (at least one, the median reported) beside its first one,
    the reported ratio is the median pair's, and both modes draw the same bytes."""
    out = tmp_path / "memory.json"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "rain_memory.py"), "--cases", "paper",
                          "--repeats", "2", "--json", str(out)],
                         capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    row = json.loads(out.read_text())["paper"]
    pairs = row["pairs"]
    assert [pair["first"] for pair in pairs] == ["shipped", "baseline"]
    for pair in pairs:
        for mode in ("shipped", "baseline"):
            assert pair[mode]["draws"] >= 1 and pair[mode]["seconds"] > 0 and pair[mode]["first_draw_s"] > 0
        assert pair["time_ratio"] == pair["shipped"]["seconds"] / pair["baseline"]["seconds"]
    assert row["time_ratio"] == min(pair["time_ratio"] for pair in pairs)  # the lower middle of 2
    assert row["same_bytes"] and row["memory_ratio"] > 0
    assert "the median of 2 pair(s)" in run.stdout
