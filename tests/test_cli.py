"""The rainbench command: tiny end-to-end runs and every bad input's one-line error."""

import ctypes.util

import h5py
import numpy as np
import pytest

from rainbench import cli

TINY = ["--frames", "2", "--width", "96", "--height", "72", "--quiet"]


def _run(capsys, *argv):
    try:
        code = cli.main(list(argv))
    except SystemExit as exit_:  # argparse-level errors exit from the parser
        code = exit_.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_generate_writes_rates_and_clean_rate_zero(tmp_path, capsys):
    code, out, _ = _run(capsys, "generate", "--out", str(tmp_path / "a"), *TINY,
                        "--rates", "0,50,100", "--store", "depth")
    assert code == 0
    code, _, _ = _run(capsys, "generate", "--out", str(tmp_path / "b"), *TINY, "--rates", "0,100")
    assert code == 0
    with h5py.File(tmp_path / "a" / "scene000000_f00000.h5") as a, \
            h5py.File(tmp_path / "b" / "scene000000_f00000.h5") as b:
        assert a["rates"][()].tolist() == [0, 50, 100]
        assert "depth" in a and "depth" not in b
        # The requested rate set changes nothing at a given rate; rate 0 is the clean render.
        np.testing.assert_array_equal(a["rgb"][0], b["rgb"][0])
        np.testing.assert_array_equal(a["rgb"][2], b["rgb"][1])
        assert (a["rain/drop_count"][1] > 0).all() and (a["rain/drop_count"][0] == 0).all()
        assert (a["rain/drop_count"][2] > a["rain/drop_count"][1]).all()
        assert a["rain/ssim"][0].tolist() == [1.0, 1.0] and (a["rain/ssim"][2] < 1).all()


@pytest.mark.parametrize("argv, message", [
    (["--rates", "abc"], "RATES"),
    (["--rates", "100:0:10"], "RATES"),
    (["--rates", "-5"], "RATES"),
    (["--rates", "0:100:0"], "RATES"),
    (["--rates", "2000"], "RATES"),
    (["--frames", "0"], "FRAMES: expected >= 1"),
    (["--width", "abc"], "WIDTH: expected an integer"),
    (["--seed", "-1"], "SEED: expected 0..2147483647"),
    (["--store", "depth,colour"], "STORE: expected a comma list"),
    (["--rain-model", "snow"], "RAIN_MODEL: expected one of jeon2022, physical"),
])
def test_bad_inputs_are_one_line_errors_and_write_nothing(tmp_path, capsys, argv, message):
    out_dir = tmp_path / "out"
    code, _, err = _run(capsys, "generate", "--out", str(out_dir), *TINY, *argv)
    assert code == 2
    _check_one_line(err, message)
    assert not out_dir.exists()


def test_out_not_writable(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, _, err = _run(capsys, "generate", "--out", str(blocker / "sub"), *TINY)
    assert code == 2
    _check_one_line(err, "OUT: .* is not a writable directory")


def test_missing_gl_backend_is_a_clear_error(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    code, _, err = _run(capsys, "generate", "--out", str(tmp_path / "o"), *TINY)
    assert code == 2
    _check_one_line(err, r"no OpenGL backend .*libegl1.*libosmesa6")
    assert not (tmp_path / "o").exists()


def test_scene_and_preview(tmp_path, capsys):
    code, out, _ = _run(capsys, "scene", "--seed", "4", "--out", str(tmp_path / "scene"))
    assert code == 0 and (tmp_path / "scene" / "scene.xml").exists()
    assert _run(capsys, "generate", "--out", str(tmp_path / "d"), *TINY, "--rates", "0:100:50")[0] == 0
    png = tmp_path / "m.png"
    code, _, _ = _run(capsys, "preview", str(tmp_path / "d"), "--frame", "1", "--boxes",
                      "--out", str(png))
    assert code == 0 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, _, err = _run(capsys, "preview", str(tmp_path / "d"), "--frame", "9")
    assert code == 2
    _check_one_line(err, r"--frame: expected 0..1")


def _check_one_line(err, pattern):
    import re

    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("rainbench: error: ")
    assert re.search(pattern, lines[0]), lines[0]


def test_export_and_video_commands(tmp_path, capsys):
    assert _run(capsys, "generate", "--out", str(tmp_path / "d"), *TINY, "--rates", "0,50")[0] == 0
    code, out, _ = _run(capsys, "export", str(tmp_path / "d"), "--format", "yolo",
                        "--out", str(tmp_path / "yolo"), "--rates", "50")
    assert code == 0 and (tmp_path / "yolo" / "rate_50" / "data.yaml").exists()
    assert not (tmp_path / "yolo" / "rate_0").exists()
    code, out, _ = _run(capsys, "export", str(tmp_path / "d"), "--format", "coco",
                        "--out", str(tmp_path / "coco"))
    assert code == 0 and (tmp_path / "coco" / "rate_0.json").exists()
    code, _, err = _run(capsys, "export", str(tmp_path / "d"), "--format", "coco",
                        "--out", str(tmp_path / "coco2"), "--rates", "30")
    assert code == 2
    _check_one_line(err, "30")
    code, out, _ = _run(capsys, "preview", str(tmp_path / "d"), "--video", "--out",
                        str(tmp_path / "v"), "--boxes")
    assert code == 0 and sorted(p.name for p in (tmp_path / "v").iterdir()) == [
        "rate_0.mp4", "rate_50.mp4"]
