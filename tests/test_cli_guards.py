"""Bad inputs found by a sweep of the command line: an incomplete dataset read as if whole,
``verify`` passing a manifest that disagrees with its config or shards, flags that were ignored
(``preview --rates``, ``--ray-address``, ``make dataset WEATHER=...``), a corrupt manifest that
``--overwrite`` could not replace, an unreachable Ray address that hung, and a closed pipe
reported as an error."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import pytest

from cli_errors import cli_status, one_line_error
from rainbench import store
from rainbench.gen import dataset as ds
from rainbench.gen.config import DatasetConfig
from rainbench.store.manifest import sha256_of
from rainbench.eval.backends.ultralytics import _offline_ultralytics

# torch (through torch._dynamo) loads triton, whose bundled LLVM segfaults when it is loaded after
# Mesa rendered in this process: `paper` loads weights files after the module's datasets rendered.
_offline_ultralytics()
import torch._dynamo  # noqa: E402,F401

REPO = Path(__file__).resolve().parents[1]
SMALL = dict(scenes=1, frames=4, frames_per_shard=2, width=96, height=72, rates=(0.0, 50.0))
GENERATE = ["generate", "--frames", "4", "--frames-per-shard", "2", "--width", "96", "--height",
            "72", "--rates", "0,50", "--quiet"]


_cli = cli_status
_one_line_error = one_line_error


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A complete dataset: 2 shards of 2 frames, 96 x 72, 0 and 50 mm/h."""
    root = tmp_path_factory.mktemp("small")
    ds.run_dataset(DatasetConfig(**SMALL), root, workers=1)
    return root


def _edited(small, target, change):
    """A copy of ``small`` whose manifest ``change(manifest)`` edited in place."""
    shutil.copytree(small, target)
    manifest = json.loads((target / store.MANIFEST).read_text())
    change(manifest)
    (target / store.MANIFEST).write_text(json.dumps(manifest))
    return target


# -- an incomplete dataset is refused unless asked for ------------------------------------------

@pytest.fixture()
def incomplete(small, tmp_path):
    """``small`` as a run cut off after its first shard leaves it."""
    def cut(manifest):
        manifest["complete"] = False
        del manifest["shards"][1]
    return _edited(small, tmp_path / "cut", cut)


@pytest.mark.parametrize("argv", [
    ["stats", "{data}"],
    ["export", "{data}", "--format", "coco", "--out", "{tmp}/export"],
    ["preview", "{data}", "--out", "{tmp}/preview.png"],
    ["eval", "--data", "{data}", "--predictions", "{tmp}/predictions", "--out", "{tmp}/eval"],
])
def test_an_incomplete_dataset_is_refused_and_nothing_is_written(incomplete, tmp_path, capsys, argv):
    argv = [arg.format(data=incomplete, tmp=tmp_path) for arg in argv]
    flag = {"stats": "DATA", "export": "DATA", "preview": "SHARD", "eval": "--data"}[argv[0]]
    _one_line_error(capsys, _cli(argv), re.escape(
        f'{flag}: {incomplete} is an incomplete dataset (its manifest lists 1 finished shards and '
        'says "complete": false): run the same rainbench generate again to finish it, or pass '
        '--allow-incomplete to read the finished shards only'))
    assert sorted(path.name for path in tmp_path.iterdir()) == ["cut"]


def test_allow_incomplete_reads_the_finished_shards_with_a_warning(incomplete, capsys):
    assert _cli(["stats", incomplete, "--json", "--allow-incomplete"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["frames"] == 2  # the one finished shard of 2 frames
    assert captured.err == (f"rainbench: warning: {incomplete} is incomplete: reading its 1 "
                            "finished shards only\n")


# -- verify checks the manifest against its config and its shards -------------------------------

def _verify_problems(root, capsys):
    code = _cli(["verify", root])
    lines = capsys.readouterr().err.strip().splitlines()
    return code, [line for line in lines if line.startswith("rainbench: bad: ")]


def test_rates_that_float32_does_not_hold_exactly_verify(tmp_path, capsys):
    """A shard stores its rates as float32 and the manifest as given: 12.3 and 0.1 (no float32
    holds them exactly) are the same rates in both."""
    root = tmp_path / "decimals"
    assert _cli([*GENERATE, "--frames", "1", "--rates", "0,0.1,12.3", "--out", str(root)]) == 0
    capsys.readouterr()
    assert _verify_problems(root, capsys) == (0, [])


def test_verify_finds_config_numbers_no_dataset_has(small, tmp_path, capsys):
    """A hand-edited config (its shards unchanged) is named, each number on its own line."""
    def edit(manifest):
        manifest["config"].update(fps=float("nan"), frames_per_shard=1e30, rates=[50.0, 0.0])

    root = _edited(small, tmp_path / "numbers", edit)
    code, problems = _verify_problems(root, capsys)
    manifest = root / store.MANIFEST
    assert code == 1 and problems[:3] == [
        f"rainbench: bad: {manifest}: config.frames_per_shard must be an integer >= 1, got 1e+30",
        f"rainbench: bad: {manifest}: config.fps must be a finite number > 0, got nan",
        f"rainbench: bad: {manifest}: config.rates: expected ascending distinct values in [0, 1000] "
        "mm/h, got (50.0, 0.0)"]


def test_verify_finds_a_complete_manifest_without_its_shards(small, tmp_path, capsys):
    root = _edited(small, tmp_path / "empty", lambda manifest: manifest.update(shards=[]))
    code, problems = _verify_problems(root, capsys)
    assert code == 1 and problems == [
        f"rainbench: bad: {root / store.MANIFEST}: says complete but lists 0 of the config's 2 "
        "shards (first missing: scene 0, frame offset 0)"]


def test_verify_finds_rates_that_disagree(small, tmp_path, capsys):
    root = _edited(small, tmp_path / "rates",
                   lambda manifest: manifest["shards"][0].update(rates=[0.0, 25.0]))
    code, problems = _verify_problems(root, capsys)
    assert code == 1 and problems == [
        f"rainbench: bad: {root / store.MANIFEST}: shards[0] (scene000000_f00000.h5): rates "
        "'0,25' disagree with the config's '0,50'",
        f"rainbench: bad: {root / 'scene000000_f00000.h5'}: its rates '0,50' disagree with the "
        "manifest's '0,25'"]


def test_verify_finds_a_shard_of_another_config(small, tmp_path, capsys):
    root = _edited(small, tmp_path / "other",
                   lambda manifest: manifest["shards"][1].update(scene_seed=7))
    code, problems = _verify_problems(root, capsys)
    assert code == 1 and problems == [
        f"rainbench: bad: {root / store.MANIFEST}: shards[1] (scene000000_f00002.h5): the shard of scene 7 from "
        "frame 2 is named scene000007_f00002.h5, not scene000000_f00002.h5",
        f"rainbench: bad: {root / store.MANIFEST}: shards[1] (scene000000_f00002.h5): scene 7, "
        "frames 2..3 is not a shard of the manifest's config",
        f"rainbench: bad: {root / store.MANIFEST}: says complete but lists 1 of the config's 2 "
        "shards (first missing: scene 0, frame offset 2)",
        f"rainbench: bad: {root / 'scene000000_f00002.h5'}: holds scene 0 from frame 2, its manifest says scene 7 "
        "from frame 2"]


def test_verify_finds_a_shard_whose_stored_rates_differ(small, tmp_path, capsys):
    root = tmp_path / "stored"
    shutil.copytree(small, root)
    shard = root / "scene000000_f00002.h5"
    with h5py.File(shard, "r+") as handle:
        handle["rates"][1] = 60.0
    manifest = json.loads((root / store.MANIFEST).read_text())
    manifest["shards"][1].update(sha256=sha256_of(shard), bytes=shard.stat().st_size)
    (root / store.MANIFEST).write_text(json.dumps(manifest))
    code, problems = _verify_problems(root, capsys)
    assert code == 1 and problems == [
        f"rainbench: bad: {shard}: its rates '0,60' disagree with the manifest's '0,50'"]
    assert _verify_problems(small, capsys) == (0, [])


# -- flags that were ignored --------------------------------------------------------------------

@pytest.mark.parametrize("flags, flag", [(["--rates", "a,b"], "--rates"), (["--rates", "50"], "--rates"),
                                         (["--overwrite"], "--overwrite")])
def test_preview_montage_refuses_video_only_flags(small, tmp_path, capsys, flags, flag):
    code = _cli(["preview", small, "--out", tmp_path / "montage.png", *flags])
    _one_line_error(capsys, code, re.escape(
        f"{flag}: only used with --video (a montage shows every rate of one frame)"))
    assert not (tmp_path / "montage.png").exists()


def test_ray_address_needs_the_ray_executor(tmp_path, capsys):
    code = _cli([*GENERATE, "--out", tmp_path / "out", "--ray-address", "127.0.0.1:1"])
    _one_line_error(capsys, code, re.escape("--ray-address: only used with --executor ray"))
    assert not (tmp_path / "out").exists()


def test_workers_is_refused_with_the_ray_executor(tmp_path, capsys):
    """``--executor ray --workers 8`` ran on Ray's own count, the flag silently ignored."""
    code = _cli([*GENERATE, "--out", tmp_path / "out", "--executor", "ray", "--workers", "8"])
    _one_line_error(capsys, code, re.escape("--workers: has no effect with --executor ray") + ".*leave it out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("address", ["", ":6379", "http://head:6379", "head", "head:0", "head:99999", "ray://",
                                     "a b:1"])
def test_a_ray_address_ray_cannot_take_is_refused_before_anything_is_written(tmp_path, capsys, address):
    """An empty address, ``:6379`` or ``http://...`` went to Ray (a traceback, or a hang)."""
    out = tmp_path / "out"
    code = _cli([*GENERATE, "--out", out, "--executor", "ray", "--ray-address", address])
    _one_line_error(capsys, code, re.escape("--ray-address: expected auto, local, HOST:PORT or "
                                            f"ray://HOST[:PORT], got {address!r}"))
    assert not out.exists()
    for good in (None, "auto", "local", "10.0.0.1:6379", "ray://head", "ray://head:10001", "[::1]:6379"):
        assert ds.check_ray_address(good) == good


def test_an_unreachable_ray_address_fails_at_once():
    """Ray itself retried ``--ray-address foo:1`` for minutes; nothing listens on port 1."""
    with pytest.raises(ds.DatasetError, match=r"^--ray-address 127\.0\.0\.1:1: nothing answers "
                                              r"at 127\.0\.0\.1:1 \(.+\)$"):
        ds._check_reachable("127.0.0.1:1")
    with pytest.raises(ds.DatasetError, match=r"^--ray-address ray://127\.0\.0\.1:1: nothing"):
        ds._check_reachable("ray://127.0.0.1:1")
    for left_to_ray in (None, "auto", "local", "headnode"):
        ds._check_reachable(left_to_ray)


def test_make_dataset_refuses_a_bad_weather_and_passes_the_clip_options(tmp_path):
    bad = subprocess.run(["make", "-n", "-C", REPO, "dataset", "WEATHER=maybe"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode != 0
    assert "WEATHER: expected on or off (or unset: the rain model decides), got 'maybe'" in bad.stderr
    [good] = _make_argv(tmp_path, "dataset", "WEATHER=off", "OUT=a b")
    assert good[:3] == ["generate", "--out", "a b"] and "--no-weather-follows-rate" in good
    assert "--device" not in good  # unset: the CLI's own default (auto)
    [part] = _make_argv(tmp_path, "dataset", "FRAMES=10", "CLIP_FRAMES=200", "FIRST_FRAME=70")
    assert all(part[part.index(flag) + 1] == value
               for flag, value in (("--frames", "10"), ("--clip-frames", "200"), ("--first-frame", "70")))
    [device] = _make_argv(tmp_path, "dataset", "DEVICE=cpu")
    assert device[device.index("--device") + 1] == "cpu"


def _make_argv(tmp_path, *arguments):
    """The argv each `rainbench` command of ``make <arguments>`` receives (the targets run
    against a stand-in `rainbench` that records its argv, with the venv step skipped)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    log = tmp_path / "argv.jsonl"
    log.unlink(missing_ok=True)
    fake = bin_dir / "rainbench"
    fake.write_text(f"#!{sys.executable}\nimport json, sys\n"
                    f"open({str(log)!r}, 'a').write(json.dumps(sys.argv[1:]) + '\\n')\n")
    fake.chmod(0o755)
    made = subprocess.run(["make", "-s", "-C", REPO, f"BIN={bin_dir}", f"STAMP={fake}", *arguments],
                          capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    return [json.loads(line) for line in log.read_text().splitlines()]


def test_make_targets_pass_each_value_as_one_argument(tmp_path):
    """Paths with spaces and apostrophes reach rainbench whole (an apostrophe in OUT broke the
    targets' quoting), each of WEIGHTS, MODELS, COMPARE and RAIN_OPTIONS as one argument."""
    odd = "it's a dir"
    [generate] = _make_argv(tmp_path, "dataset", f"OUT={odd}", "RATES=0,50", "RAIN_OPTIONS=lens_drops=false x=it's")
    assert generate[:3] == ["generate", "--out", odd] and generate[generate.index("--rates") + 1] == "0,50"
    assert [generate[i + 1] for i, a in enumerate(generate) if a == "--rain-option"] == ["lens_drops=false", "x=it's"]
    [evaluate] = _make_argv(tmp_path, "eval", f"OUT={odd}", "RESULTS=r's", "WEIGHTS=a'b.pt c.pt", "COMPARE=a=b")
    assert evaluate == ["eval", "--data", odd, "--out", "r's", "--weights", "a'b.pt", "--weights", "c.pt",
                        "--compare", "a=b"]
    [paper] = _make_argv(tmp_path, "paper", f"OUT={odd}", "PAPER_OUT=p'q", "MODELS=m'1 m2")
    assert paper[:5] == ["paper", "--out", "p'q", "--data", f"{odd}/paper"]
    assert [paper[i + 1] for i, a in enumerate(paper) if a == "--model"] == ["m'1", "m2"]
    assert _make_argv(tmp_path, "verify", f"OUT={odd}") == [["verify", odd]]
    assert _make_argv(tmp_path, "verify", f"OUT={odd}", "IMAGES=1") == [["verify", odd, "--images"]]
    assert _make_argv(tmp_path, "train", "RECIPE=my recipe.yaml", f"TRAIN_OUT={odd}") == [
        ["train", "--recipe", "my recipe.yaml", "--out", odd]]


def test_make_scene_takes_the_clip_settings_and_a_folder_per_scene(tmp_path):
    """make scene passed no FRAMES, WIDTH or HEIGHT (a scene is laid out for its clip's length),
    and wrote every scene of a seed, and the paper's clip, into one OUT/scene_<seed>."""
    [paper_clip] = _make_argv(tmp_path, "scene", "FRAMES=50", "WIDTH=320", "HEIGHT=240")
    assert paper_clip == ["scene", "--frames", "50", "--width", "320", "--height", "240", "--out", "data/scene_paper"]
    [seeded] = _make_argv(tmp_path, "scene", "SEED=0")
    assert seeded[:3] == ["scene", "--seed", "0"] and seeded[-2:] == ["--out", "data/scene_0"]
    [night] = _make_argv(tmp_path, "scene", "SEED=3", "LAYOUT=highway", "TIME=night", "OVERWRITE=1")
    assert night[-3:] == ["--out", "data/scene_3_highway_night", "--overwrite"]
    [chosen] = _make_argv(tmp_path, "scene", "SEED=3", "SCENE_OUT=my scene")
    assert chosen[-2:] == ["--out", "my scene"]


def test_verify_images_finds_a_damaged_chunk_whose_manifest_was_rewritten(small, tmp_path, capsys):
    """Bytes flipped inside an image chunk, the manifest rehashed to match: verify said ok and
    every reader then failed on that image (a format audit). ``--images`` decodes them."""
    data = tmp_path / "data"
    shutil.copytree(small, data)
    shard = data / "scene000000_f00002.h5"
    with h5py.File(shard, "r") as handle:
        info = handle["rgb"].id.get_chunk_info_by_coord((1, 1, 0, 0, 0))
    raw = bytearray(shard.read_bytes())
    middle = info.byte_offset + info.size // 2
    raw[middle:middle + 16] = bytes(255 - b for b in raw[middle:middle + 16])
    shard.write_bytes(bytes(raw))
    manifest = json.loads((data / store.MANIFEST).read_text())
    for entry in manifest["shards"]:
        if entry["path"] == shard.name:
            entry["sha256"] = sha256_of(shard)
    (data / store.MANIFEST).write_text(json.dumps(manifest))
    assert _cli(["verify", data]) == 0 and capsys.readouterr().out.strip() == f"{data}: ok"
    assert _cli(["verify", data, "--images"]) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(
        f"rainbench: bad: {shard}: /rgb chunk of rate row 1, frame 1 is corrupt ("), err
    assert _cli(["verify", small, "--images"]) == 0


# -- a corrupt manifest and --overwrite ---------------------------------------------------------

def test_a_corrupt_manifest_names_overwrite_which_replaces_it(small, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(small, out)
    (out / store.MANIFEST).write_text('{"complete": tru')
    code = _cli([*GENERATE, "--out", out])
    _one_line_error(capsys, code, re.escape(f"OUT: {out / store.MANIFEST}: not a readable manifest (")
                    + r".+" + re.escape(f"); use --overwrite to replace the dataset in {out} or "
                                        "choose another OUT"))
    assert _cli([*GENERATE, "--out", out, "--overwrite"]) == 0
    capsys.readouterr()
    assert _cli(["verify", out]) == 0
    assert store.read_manifest(out)["complete"]


# -- a closed pipe ------------------------------------------------------------------------------

def test_a_reader_that_goes_away_ends_the_command_quietly(small):
    """``rainbench stats DATA | head -1``: the reader has gone before the output is written."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        result = subprocess.run([sys.executable, "-m", "rainbench.cli", "stats", str(small)],
                                stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert (result.returncode, result.stderr) == (141, "")


# -- weights named badly ------------------------------------------------------------------------

def test_an_empty_weights_name_is_named_as_such(small, tmp_path, capsys):
    code = _cli(["eval", "--data", small, "--weights", "", "--out", tmp_path / "eval"])
    _one_line_error(capsys, code, r"--weights: expected a shipped model name \(rainbench-yolo11n, .*\) "
                                  r"or a weights file, got an empty name")
    assert not (tmp_path / "eval").exists()


def test_a_long_checkpoint_error_is_cut_at_a_word(small, tmp_path, capsys):
    from rainbench.eval.weights import WEIGHTS_DIR

    # a zip archive cut short: a checkpoint's first bytes, so ultralytics' own long advice
    (tmp_path / "cut.pt").write_bytes((WEIGHTS_DIR / "rainbench-yolo11n.pt").read_bytes()[:300])
    code = _cli(["eval", "--data", small, "--weights", tmp_path / "cut.pt", "--out", tmp_path / "eval"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    reason = re.fullmatch(r"rainbench: error: --weights: .*cut\.pt is not a loadable ultralytics "
                          r"checkpoint \((.+)\)", err[0]).group(1)
    # whole words: a reason cut short ends with " ..." after a complete word of ultralytics' text
    assert len(reason) <= 204 and (not reason.endswith("...") or reason.endswith(" ..."))
    assert not (tmp_path / "eval").exists()


# -- image files on a full disk -----------------------------------------------------------------

def test_write_image_writes_what_imwrite_writes(tmp_path):
    import cv2
    import numpy as np

    from rainbench.store.images import write_image

    rgb = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    for suffix, params in ((".png", []), (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 95])):
        write_image(tmp_path / f"ours{suffix}", rgb, params)
        cv2.imwrite(str(tmp_path / f"opencv{suffix}"), rgb[:, :, ::-1].copy(), params)
        assert (tmp_path / f"ours{suffix}").read_bytes() == (tmp_path / f"opencv{suffix}").read_bytes()
    with pytest.raises(OSError, match=r"^.*image\.xyz: could not encode the image"):
        write_image(tmp_path / "image.xyz", rgb)


def test_export_on_a_full_disk_is_one_line_naming_the_image(small, tmp_path, capsys, monkeypatch):
    """libpng printed its own `libpng error: Write Error` line before rainbench's."""
    write_bytes = Path.write_bytes

    def full_disk(self, data):
        if self.suffix == ".png":
            raise OSError(28, "No space left on device")
        return write_bytes(self, data)

    monkeypatch.setattr(Path, "write_bytes", full_disk)
    code = _cli(["export", small, "--format", "yolo", "--out", tmp_path / "export"])
    _one_line_error(capsys, code, r"\S+\.png: No space left on device")
    assert not (tmp_path / "export").exists()


# -- output directories are checked by making them ----------------------------------------------

def test_an_out_that_cannot_be_made_is_refused_before_any_work(small, capsys, tmp_path):
    """/proc refuses new directories even to root, whose permission bits say writable (root gets
    ENOENT, other users EACCES): the check makes the directory, so eval fails in one line before
    any inference."""
    code = _cli(["eval", "--data", small, "--weights", "rainbench-yolo11n", "--out", "/proc/x/y"])
    _one_line_error(capsys, code, r"--out: /proc/x/y is not a writable directory "
                                  r"\((No such file or directory|Permission denied)\)")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code = _cli(["eval", "--data", small, "--weights", "rainbench-yolo11n", "--out", blocker / "y"])
    _one_line_error(capsys, code, r"--out: .*/file/y is not a writable directory "
                                  r"\(.*/file is not a directory\)")


def test_the_out_check_leaves_nothing_behind(tmp_path):
    from rainbench.cli import _writable_dir

    deep = tmp_path / "a" / "b" / "c"
    assert _writable_dir(deep, "--out") == deep
    assert list(tmp_path.iterdir()) == []


def test_scene_refuses_to_replace_a_scene_unless_asked(tmp_path, capsys):
    out = tmp_path / "scene"
    assert _cli(["scene", "--seed", "3", "--width", "96", "--height", "72", "--out", out]) == 0
    first = (out / "scene.xml").read_bytes()
    capsys.readouterr()
    code = _cli(["scene", "--seed", "4", "--width", "96", "--height", "72", "--out", out])
    _one_line_error(capsys, code, r"--out: .*/scene/scene.xml exists; use --overwrite to replace "
                                  r"it \(and its textures\)")
    assert (out / "scene.xml").read_bytes() == first
    assert _cli(["scene", "--seed", "4", "--width", "96", "--height", "72", "--out", out,
                 "--overwrite"]) == 0
    assert (out / "scene.xml").read_bytes() != first


def test_clip_frames_and_first_frame_flags(tmp_path, capsys):
    """--first-frame and --clip-frames reach the dataset (the shard starts at the first frame and
    records the clip it was planned for); a clip shorter than the frames asked is refused before
    anything is written."""
    out = tmp_path / "part"
    assert _cli(GENERATE + ["--first-frame", "3", "--clip-frames", "200", "--out", out]) == 0
    assert sorted(path.name for path in out.glob("*.h5")) == ["scene000000_f00003.h5",
                                                            "scene000000_f00005.h5"]
    with h5py.File(out / "scene000000_f00003.h5") as handle:
        assert json.loads(handle.attrs["config"])["clip_frames"] == 200
    _one_line_error(capsys, _cli(GENERATE + ["--clip-frames", "3", "--out", tmp_path / "short"]),
                    re.escape("clip-frames: expected an integer >= first-frame + frames = 4, got 3"))
    _one_line_error(capsys, _cli(GENERATE + ["--first-frame", "-2", "--out", tmp_path / "neg"]),
                    re.escape("argument --first-frame: FIRST_FRAME: expected >= 0, got -2"))
    assert not (tmp_path / "short").exists() and not (tmp_path / "neg").exists()


# -- --rain-option -----------------------------------------------------------------------------

@pytest.mark.parametrize("option, message", [
    ("lens_drops", r"argument --rain-option: expected NAME=VALUE, got 'lens_drops'"),
    ("lens_drop=1", r"argument --rain-option: unknown option 'lens_drop'; expected one of exposure_s, .*"),
    ("model=physical", r"argument --rain-option: unknown option 'model'; expected one of .*"),
    ("exposure_s=fast", r"argument --rain-option: exposure_s: expected a number, got 'fast'"),
    ("max_streak_candidates=1.5", r"argument --rain-option: max_streak_candidates: expected an integer, got '1\.5'"),
    ("lens_drops=maybe", r"argument --rain-option: lens_drops: expected true or false, got 'maybe'"),
    ("airlight_rgb=1,2", r"argument --rain-option: airlight_rgb: expected R,G,B or none, got '1,2'"),
    ("exposure_s=-1", r"rain_options: RainConfig\.exposure_s must be a finite number > 0, got -1\.0"),
])
def test_a_bad_rain_option_is_one_line_and_nothing_is_written(tmp_path, capsys, option, message):
    code = _cli([*GENERATE, "--out", tmp_path / "out", "--rain-option", option])
    _one_line_error(capsys, code, message)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_rain_options_reach_the_rain_and_the_manifest(tmp_path):
    out = tmp_path / "out"
    argv = [*GENERATE, "--out", out, "--rain-model", "physical", "--rates", "0,50", "--quiet",
            "--rain-option", "lens_drops=false", "--rain-option", "airlight_rgb=120,125,130",
            "--rain-option", "exposure_s = 0.002"]
    assert _cli(argv) == 0
    config = json.loads((out / "manifest.json").read_text())["config"]
    assert config["rain_options"] == {"lens_drops": False, "airlight_rgb": [120.0, 125.0, 130.0],
                                      "exposure_s": 0.002}
    rain_config = DatasetConfig(rain_model="physical", rain_options=config["rain_options"]).rain_config()
    assert rain_config.lens_drops is False and rain_config.exposure_s == 0.002
    twice = _cli([*GENERATE, "--out", tmp_path / "b", "--rain-option", "lens_drops=false",
                  "--rain-option", "lens_drops=true"])
    assert twice == 2
    made = subprocess.run(["make", "-n", "-C", REPO, "dataset", "RAIN_OPTIONS=lens_drops=false exposure_s=0.002"],
                          capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    assert "--rain-option 'lens_drops=false' --rain-option 'exposure_s=0.002'" in made.stdout


def test_an_error_raised_in_a_dataloader_worker_is_reported_without_its_traceback(monkeypatch, capsys):
    """torch re-raises a worker's error with the worker's traceback folded into its message (a
    corrupt shard read while training): the command line prints the worker's own message, one
    line, exit 2."""
    import torch

    from rainbench import cli
    from rainbench.store.shard import ShardFormatError

    message = "/data/s.h5: /rgb chunk of rate row 1, frame 1 is corrupt (Decompression failed)"

    class Corrupt(torch.utils.data.Dataset):
        def __len__(self):
            return 1

        def __getitem__(self, index):
            raise ShardFormatError(message)

    def train_on_corrupt(args):
        for _ in torch.utils.data.DataLoader(Corrupt(), num_workers=1):
            pass
        return 0

    with pytest.raises(ShardFormatError) as caught:
        train_on_corrupt(None)
    assert str(caught.value).startswith("Caught ShardFormatError in DataLoader worker process 0.")
    assert cli.worker_error_message(caught.value) == message
    assert cli.worker_error_message(ValueError("plain\nmessage")) == "plain\nmessage"
    monkeypatch.setattr(cli, "cmd_train", train_on_corrupt)
    assert cli.main(["train"]) == 2
    assert capsys.readouterr().err == f"rainbench: error: {message}\n"


# -- checked before any work, and named (a second sweep of the command line) --------------------

TINY = ["--frames", "1", "--width", "16", "--height", "16", "--rates", "0", "--quiet"]
NOT_A_CHECKPOINT = ("is not a loadable ultralytics checkpoint: expected a PyTorch checkpoint file (a zip "
                    "archive written by torch.save, as ultralytics saves), got ")


@pytest.mark.parametrize("flag, name, content, message", [
    ("--weights", "text.pt", "hello, not a checkpoint\n", re.escape(NOT_A_CHECKPOINT + "a text file")),
    ("--model", "text.pt", "hello, not a checkpoint\n", re.escape(NOT_A_CHECKPOINT + "a text file")),
    ("--model", "empty.onnx", "", r"is not a loadable ONNX model \(.+\)"),
    ("--weights", "folder.onnx", None, re.escape("is a directory, not a weights file (expected an ultralytics "
                                                 ".pt, an .onnx export or a Darknet .cfg/.weights file, or a "
                                                 "shipped model name)")),
], ids=["weights-text", "model-text", "model-empty-onnx", "weights-directory"])
def test_paper_loads_every_weights_file_before_generating_and_names_its_flag(tmp_path, capsys, flag, name,
                                                                             content, message):
    """``paper`` rendered every dataset before a weights file failed to load, and blamed
    ``--weights`` for a file given by ``--model``."""
    weights = tmp_path / name
    if content is None:
        weights.mkdir()
    else:
        weights.write_text(content)
    code = _cli(["paper", *TINY, "--data", tmp_path / "data", "--out", tmp_path / "out", flag, weights])
    _one_line_error(capsys, code, re.escape(f"{flag}: {weights} ") + message)
    assert not (tmp_path / "data").exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("trust", [[], ["--trust-pickle"]])
@pytest.mark.parametrize("content, found", [(b"hello world\n", "a text file"), (b"", "an empty file"),
                                            (b"\x89PNG\r\n\x1a\n" + bytes(16), "a PNG image"),
                                            (bytes(range(7, 40)), "a file whose first bytes are 07 08 09 0a 0b 0c 0d 0e")],
                         ids=["text", "empty", "png", "binary"])
def test_a_file_that_is_no_checkpoint_says_what_was_expected_and_what_came(small, tmp_path, capsys, trust,
                                                                          content, found):
    weights = tmp_path / "model.pt"
    weights.write_bytes(content)
    code = _cli(["eval", "--data", small, "--weights", weights, "--out", tmp_path / "eval", *trust])
    _one_line_error(capsys, code, re.escape(f"--weights: {weights} {NOT_A_CHECKPOINT}{found}"))
    assert not (tmp_path / "eval").exists()


def test_weights_and_a_recipe_that_are_directories_are_named_as_such(small, tmp_path, capsys):
    folder = tmp_path / "model.pt"
    folder.mkdir()
    code = _cli(["eval", "--data", small, "--weights", folder, "--out", tmp_path / "eval"])
    _one_line_error(capsys, code, re.escape(
        f"--weights: {folder} is a directory, not a weights file (expected an ultralytics .pt, an .onnx "
        "export or a Darknet .cfg/.weights file, or a shipped model name)"))
    recipe = tmp_path / "x.yaml"
    recipe.mkdir()
    code = _cli(["train", "--recipe", recipe, "--out", tmp_path / "run"])
    _one_line_error(capsys, code, re.escape(
        f"--recipe: {recipe} is a directory, not a file (expected a recipe .yaml file or a shipped recipe name)"))
    assert not (tmp_path / "eval").exists() and not (tmp_path / "run").exists()


def _cli_with_gl(argv, value):
    env = {key: item for key, item in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["MUJOCO_GL"] = value
    return subprocess.run([sys.executable, "-m", "rainbench.cli", *map(str, argv)], capture_output=True,
                          text=True, env=env, timeout=300)


def _gl_instead():
    import ctypes.util

    return ("set MUJOCO_GL=egl (installed here) or unset MUJOCO_GL" if ctypes.util.find_library("EGL")
            else "install libegl1 for egl; install libosmesa6 for osmesa")


def test_scene_with_a_gl_backend_that_cannot_work_is_one_line(tmp_path):
    """``scene`` imported mujoco with MUJOCO_GL=osmesa and no OSMesa: a traceback ending in
    ``cannot import name 'mujoco' from 'rainbench.gl'``, exit 1."""
    import ctypes.util

    if ctypes.util.find_library("OSMesa") is not None:
        pytest.skip("OSMesa is installed")
    result = _cli_with_gl(["scene", "--width", "16", "--height", "16", "--out", tmp_path / "scene"], "osmesa")
    assert (result.returncode, result.stderr.splitlines()) == (2, [
        "rainbench: error: MUJOCO_GL=osmesa: the OSMesa library is not installed (package libosmesa6); "
        + _gl_instead()])
    assert not (tmp_path / "scene").exists()


@pytest.mark.parametrize("command", [["scene"], ["generate", *TINY]])
def test_an_unknown_mujoco_gl_lists_the_values_that_work(tmp_path, command):
    result = _cli_with_gl([*command, "--out", tmp_path / "out"], "bogus")
    assert (result.returncode, result.stderr.splitlines()) == (2, [
        "rainbench: error: MUJOCO_GL: expected one of egl, osmesa, glfw (glfw needs a display), got 'bogus'; "
        + _gl_instead()])
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("extra, message", [
    ({"PYOPENGL_PLATFORM": "osmesa"}, "PYOPENGL_PLATFORM=osmesa conflicts with MUJOCO_GL=egl: MuJoCo's egl "
     "rendering needs PyOpenGL on the same platform; unset PYOPENGL_PLATFORM or set it to egl"),
    ({"__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent/vendor.json"},
     "MUJOCO_GL=egl: the EGL library is installed but no OpenGL context could be made ("),
], ids=["pyopengl", "broken-egl"])
def test_an_installed_backend_that_fails_is_not_called_missing(tmp_path, extra, message):
    """Both said 'tried egl (install libegl1); install one of these packages' on a machine with
    EGL installed (a GL audit)."""
    import ctypes.util

    if ctypes.util.find_library("EGL") is None:
        pytest.fail("these machines have EGL (Mesa's software renderer): the test needs it")
    env = {key: item for key, item in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    result = subprocess.run([sys.executable, "-m", "rainbench.cli", "generate", *TINY, "--out", tmp_path / "out"],
                            capture_output=True, text=True, timeout=300,
                            env={**env, "MUJOCO_GL": "egl", **extra})
    lines = result.stderr.splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("rainbench: error: " + message), lines
    assert "install libegl1" not in lines[0]
    assert not (tmp_path / "out" / "manifest.json").exists()


def test_the_python_api_names_a_conflicting_pyopengl_platform_at_the_first_renderer():
    """With PYOPENGL_PLATFORM=glx the first renderer failed blaming a missing libegl1. Building a
    scene needs no context and still works; the renderer names the variable."""
    env = {key: item for key, item in os.environ.items() if key not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY")}
    code = ("from rainbench.gl import mujoco\n"
            "import numpy as np\n"
            "from rainbench.gen.render import FrameRenderer\n"
            "spec = mujoco.MjSpec()\n"
            "spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[5, 5, 0.1])\n"
            "spec.worldbody.add_body(name='ego', mocap=True).add_camera(name='ego')\n"
            "model = spec.compile()\n"
            "print('built', flush=True)\n"
            "FrameRenderer(model, 32, 24, np.full(model.ngeom, -1, np.int32))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                            env={**env, "PYOPENGL_PLATFORM": "glx"})
    assert result.returncode == 1 and result.stdout.strip() == "built", result.stderr
    assert result.stderr.splitlines()[-1] == (
        "rainbench.gl.GLBackendError: PYOPENGL_PLATFORM=glx conflicts with MUJOCO_GL=egl: MuJoCo's egl "
        "rendering needs PyOpenGL on the same platform; unset PYOPENGL_PLATFORM or set it to egl")


def test_preview_makes_a_missing_out_folder(small, tmp_path, capsys):
    out = tmp_path / "new" / "deeper" / "montage.png"
    assert _cli(["preview", small, "--out", out]) == 0
    assert capsys.readouterr().out.strip() == str(out) and out.read_bytes()[:4] == b"\x89PNG"
    assert [path.name for path in out.parent.iterdir()] == ["montage.png"]  # no temporary left


@pytest.mark.parametrize("spelled", ["newdir/", "newdir"])
def test_preview_makes_a_missing_out_directory(small, tmp_path, capsys, spelled):
    """`--out DIR/` (or a name without a suffix) for a DIR that does not exist yet was refused,
    though --help says "PNG path or directory, made if missing"."""
    code = _cli(["preview", small, "--out", f"{tmp_path}/deep/{spelled}"])
    written = tmp_path / "deep" / "newdir" / "scene000000_f00000_frame0000_rates.png"
    assert code == 0 and capsys.readouterr().out.strip() == str(written)
    assert written.read_bytes()[:4] == b"\x89PNG" and [p.name for p in written.parent.iterdir()] == [written.name]


def test_preview_video_of_one_shard_writes_beside_it(small, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(small, data)
    assert _cli(["preview", data / "scene000000_f00002.h5", "--video"]) == 0
    assert capsys.readouterr().out.split() == [str(data / "videos" / "rate_0.mp4"),
                                               str(data / "videos" / "rate_50.mp4")]


@pytest.mark.parametrize("frame", ["5", "0"])
def test_preview_video_refuses_frame(small, tmp_path, capsys, frame):
    code = _cli(["preview", small, "--video", "--frame", frame, "--out", tmp_path / "videos"])
    _one_line_error(capsys, code, re.escape(
        "--frame: only used without --video (a video shows every frame; --frame picks the montage's frame)"))
    assert not (tmp_path / "videos").exists()


@pytest.mark.parametrize("tile_width", [None, "96", "1000"])
def test_preview_tile_width_sets_the_sheet(small, tmp_path, capsys, tile_width):
    """Tiles were 400 px whatever the images: a 1920x1080 dataset could not be previewed at its
    own resolution. Two rates of 96x72 images side by side, each tile ``--tile-width`` wide."""
    out = tmp_path / "montage.png"
    code = _cli(["preview", small, "--out", out, *(["--tile-width", tile_width] if tile_width else [])])
    assert code == 0, capsys.readouterr().err
    width = int(tile_width or 400)
    assert cv2.imread(str(out)).shape == (round(72 * width / 96), 2 * width, 3)


@pytest.mark.parametrize("tile_width", ["31", "8193", "-400", "0"])
def test_preview_refuses_a_tile_width_out_of_range(small, tmp_path, capsys, tile_width):
    out = tmp_path / "montage.png"
    _one_line_error(capsys, _cli(["preview", small, "--out", out, "--tile-width", tile_width]),
                    re.escape(f"--tile-width: expected 32..8192 pixels, got {tile_width}"))
    assert not out.exists()


def test_preview_video_refuses_tile_width(small, tmp_path, capsys):
    _one_line_error(capsys, _cli(["preview", small, "--video", "--tile-width", "200", "--out", tmp_path / "v"]),
                    re.escape("--tile-width: only used without --video (a video keeps the images' size; "
                              "--tile-width sizes the montage's tiles)"))
    assert not (tmp_path / "v").exists()


@pytest.mark.parametrize("target, found", [
    ("nope", "no such directory; expected the directory that rainbench generate wrote, with its manifest.json"),
    ("shard", "a file; expected the directory that rainbench generate wrote, with its manifest.json"),
    ("folder", "no manifest.json")], ids=["missing", "shard", "folder"])
def test_verify_refuses_what_is_not_a_dataset_directory(small, tmp_path, capsys, target, found):
    """``verify /nope`` said ``rainbench: bad: /nope/manifest.json: missing``, exit 1, as if a
    dataset had failed verification."""
    path = {"nope": tmp_path / "nope", "shard": small / "scene000000_f00000.h5", "folder": tmp_path}[target]
    _one_line_error(capsys, _cli(["verify", path]),
                    re.escape(f"DATA: {path} is not a dataset directory ({found})"))


EVAL_INFERENCE_ONLY = [["--conf", "0.9"], ["--iou", "0.5"], ["--imgsz", "640"], ["--batch", "32"],
                       ["--max-det", "300"], ["--class-map", "car=2"], ["--device", "cpu"],
                       ["--pt-backend", "batched"], ["--workers", "0"], ["--force"], ["--trust-pickle"]]


@pytest.mark.parametrize("flags", EVAL_INFERENCE_ONLY, ids=[flags[0] for flags in EVAL_INFERENCE_ONLY])
def test_eval_refuses_inference_flags_with_predictions(small, tmp_path, capsys, flags):
    """They were accepted and ignored: detections are read from the files, nothing is inferred.
    A flag given at its default value is refused too (it was given)."""
    code = _cli(["eval", "--data", small, "--predictions", tmp_path / "preds", "--out", tmp_path / "eval",
                 *flags])
    _one_line_error(capsys, code, re.escape(
        f"{flags[0]}: has no effect with --predictions (detections are read from its files, not inferred); "
        "leave it out, or evaluate with --weights"))
    assert not (tmp_path / "eval").exists()

