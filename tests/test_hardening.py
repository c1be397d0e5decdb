"""Issue 18, hardening: interrupted runs that resume, every image size, tracebacks turned into
one-line errors, label checks in every reader, leftovers and edges, a Ray cluster by address,
safe .pt loading. (The property-based fuzzer is tests/test_fuzz.py.)"""

import ctypes.util
import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from rainbench import ShardDataset, cli
from rainbench import store
from rainbench.gen import dataset as ds
from rainbench.gen.config import MAX_FRAMES, DatasetConfig, GenerateConfig
from rainbench.store import export as ex
from rainbench import gl
from rainbench.gen.generate import build_scene, generate_shard
from rainbench.gen.render import FrameRenderer, padded_size
from rainbench.store.manifest import write_manifest
from rainbench.store.shard import ShardFormatError
from rainbench.store.signals import STOP_SIGNALS, signals_held
from rainbench.mjcf.scene import build_spec
from cli_errors import cli_status, one_line_error

# torch's triton segfaults when first loaded after Mesa's llvmpipe rendered in this process
# (tests/test_eval_pipeline.py): load it at collection, before any fixture renders.
from rainbench.eval import backends  # noqa: E402
from rainbench.eval import weights as registry  # noqa: E402
from rainbench.eval.backends.ultralytics import TRUST_PICKLE_ENV, _offline_ultralytics  # noqa: E402

_offline_ultralytics()
import torch._dynamo  # noqa: E402,F401

SMALL = dict(scenes=1, frames=4, frames_per_shard=2, width=96, height=72, rates=(0.0, 50.0))
# The issue's interrupted run (three shards, two workers), with shards long enough (~1.5 s each)
# to be interrupted in the middle.
GEN = ["generate", "--frames", "48", "--frames-per-shard", "16", "--width", "160", "--height", "120",
       "--rates", "0,50,100", "--quiet"]
SLOW = ["--workers", "2", "--threads", "1", "--render-threads", "1"]


def _hashes(root):
    manifest = json.loads((Path(root) / store.MANIFEST).read_text())
    return [(entry["path"], entry["sha256"]) for entry in manifest["shards"]]


_cli = cli_status
_one_line_error = one_line_error


def _copy_tree(source, target):
    shutil.copytree(source, target)
    return Path(target)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A complete small dataset: 2 shards of 2 frames, 96 x 72, 0 and 50 mm/h."""
    root = tmp_path_factory.mktemp("small")
    ds.run_dataset(DatasetConfig(**SMALL), root, workers=1)
    return root


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """One shard of 3 frames whose frames 1 and 2 hold one label each (frame 0 none): a rendered
    shard whose labels are replaced by these known ones (the street's actors are too small to
    label at 96x72 in the first 0.3 s)."""
    root = tmp_path_factory.mktemp("labelled")
    path = generate_shard(GenerateConfig(frames=3, width=96, height=72, rates=(0.0, 50.0),
                                         layout="street", time_of_day="day"), root)
    known = {
        "offsets": np.array([0, 0, 1, 2], np.int64),
        "bbox": np.array([[44, 30, 52, 42], [10, 20, 30, 40]], np.float32),
        "bbox_amodal": np.array([[44, 30, 52, 42], [10, 20, 30, 40]], np.float32),
        "class_id": np.array([2, 0], np.int32), "instance_id": np.array([3, 5], np.int32),
        "visible_fraction": np.array([1.0, 0.5], np.float32),
        "truncation": np.array([0.0, 0.0], np.float32),
        "rain_coverage": np.zeros((2, 2), np.float32), "contrast_loss": np.zeros((2, 2), np.float32),
    }
    with h5py.File(path, "r+") as handle:
        for key, value in known.items():
            del handle[f"labels/{key}"]
            handle.create_dataset(f"labels/{key}", data=value)
    return path


def _mutated(source, target_dir, **changes):
    """A copy of shard ``source`` in ``target_dir`` with /labels datasets replaced."""
    target_dir.mkdir(parents=True, exist_ok=True)
    path = target_dir / source.name
    shutil.copy(source, path)
    with h5py.File(path, "r+") as handle:
        for key, value in changes.items():
            data = handle[f"labels/{key}"][()]
            value = value(data.copy()) if callable(value) else value
            del handle[f"labels/{key}"]
            handle.create_dataset(f"labels/{key}", data=value)
    return path


def _nan_box(bbox):
    bbox[0, 1] = np.nan
    return bbox


# -- 1. interrupted multi-worker runs -------------------------------------------------------------

def _proc_stat(pid):
    """(state, ppid, pgrp) of a process, None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()
    return fields[0], int(fields[1]), int(fields[2])


def _live_group(pgid):
    """Live (not zombie) processes of process group ``pgid``."""
    live = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            stat = _proc_stat(int(entry.name))
            if stat and stat[2] == pgid and stat[0] != "Z":
                live.append(int(entry.name))
    return live


def _start(out, *extra):
    argv = [sys.executable, "-m", "rainbench.cli", *GEN, "--out", str(out), *extra]
    # Ctrl-C with its default disposition, as in a terminal: a test run started in the background
    # of a non-interactive shell (`make test &`) inherits SIGINT ignored, and so would the child.
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for_temporary(process, out, timeout=180):
    deadline = time.time() + timeout
    while time.time() < deadline and process.poll() is None:
        if list(out.glob(".scene*.tmp-*")):
            return
        time.sleep(0.05)
    raise AssertionError(f"no temporary shard appeared (rc {process.poll()})")


def _wait_group_gone(pgid, timeout=20):
    deadline = time.time() + timeout
    while _live_group(pgid) and time.time() < deadline:
        time.sleep(0.1)
    return _live_group(pgid)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The issue's dataset rendered by one uninterrupted run (one worker)."""
    root = tmp_path_factory.mktemp("reference")
    assert cli.main(GEN + ["--out", str(root), "--workers", "1"]) == 0
    return _hashes(root)


def test_kill_9_of_a_two_worker_run_kills_its_workers_and_the_rerun_resumes(reference, tmp_path):
    out = tmp_path / "k3"
    process = _start(out, *SLOW)
    try:
        _wait_for_temporary(process, out)
        workers = [pid for pid in _live_group(process.pid) if pid != process.pid]
        assert len(workers) >= 2  # two workers (and multiprocessing's resource tracker)
        process.send_signal(signal.SIGKILL)
        process.wait()
        assert _wait_group_gone(process.pid) == []  # no orphan renders on
        listing = sorted(p.name for p in out.iterdir())
        time.sleep(2)
        assert sorted(p.name for p in out.iterdir()) == listing  # nothing appears afterwards
        # the manifest was written before the first shard and lists only complete ones
        manifest = json.loads((out / store.MANIFEST).read_text())
        assert manifest["complete"] is False and len(manifest["shards"]) < 3
    finally:
        if _live_group(process.pid):
            os.killpg(process.pid, signal.SIGKILL)
    rerun = subprocess.run([sys.executable, "-m", "rainbench.cli", *GEN, "--out", str(out),
                            "--workers", "2"], capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stderr
    assert store.verify_dataset(out) == [] and _hashes(out) == reference
    assert not list(out.glob(".*"))  # no temporary file, no lock file left


@pytest.mark.parametrize("stop", ["ctrl-c", "sigterm"])
def test_ctrl_c_stops_the_workers_tells_the_truth_and_the_rerun_resumes(reference, tmp_path,
                                                                        capsys, stop):
    """Ctrl-C (SIGINT to the whole process group), or SIGTERM to the parent alone (`kill PID`, a
    job scheduler's time limit: it killed the run silently, leaving its lock, temporary shards and
    a shard missing from the manifest)."""
    out = tmp_path / "k3"
    process = _start(out, *SLOW)
    try:
        _wait_for_temporary(process, out)
        # a second generate on the same OUT meanwhile is refused (real processes); the run is held
        # (SIGSTOP to its group) meanwhile: on a fast machine it could finish before the second
        # one, started in this process, reached its check (a CI run saw exit 0)
        os.killpg(process.pid, signal.SIGSTOP)
        try:
            code = cli.main(GEN + ["--out", str(out), "--workers", "1"])
        finally:
            os.killpg(process.pid, signal.SIGCONT)
        _one_line_error(capsys, code, re.escape(f"OUT: {out} is being written by another rainbench "
                                                f"generate (pid {process.pid}); wait for it to "
                                                "finish or choose another OUT"))
        if stop == "ctrl-c":
            os.killpg(process.pid, signal.SIGINT)  # Ctrl-C: the whole process group
        else:
            process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
        assert process.returncode == (130 if stop == "ctrl-c" else 128 + signal.SIGTERM)
        how = "interrupted" if stop == "ctrl-c" else "terminated by SIGTERM"
        if (out / store.MANIFEST).exists():
            assert err.strip().splitlines() == [
                f"rainbench: {how}; the workers are stopped, {out / 'manifest.json'} lists the "
                "complete shards and nothing partial is under a final name; run the same command "
                "again to resume"]
        else:  # stopped in its first shard: the manifest it wrote first is removed, as it came
            assert err.strip().splitlines() == [
                f"rainbench: {how} before a shard was finished; nothing of the run is kept: run the "
                "same command again to start it"]
            assert not any(out.iterdir())
        assert not (out / ".rainbench.lock").exists()
        assert _wait_group_gone(process.pid, timeout=10) == []
        finals = sorted(p.name for p in out.glob("scene*.h5"))
        time.sleep(2)
        assert sorted(p.name for p in out.glob("scene*.h5")) == finals  # no shard afterwards
        assert not list(out.glob(".*tmp*"))  # the stopped workers' temporary files are removed
        if finals:
            listed = sorted(e["path"] for e in json.loads((out / store.MANIFEST).read_text())["shards"])
            assert listed == finals
    finally:
        if _live_group(process.pid):
            os.killpg(process.pid, signal.SIGKILL)
    assert cli.main(GEN + ["--out", str(out), "--workers", "2"]) == 0
    assert _hashes(out) == reference


def test_a_worker_killed_on_its_own_is_one_line_naming_its_shard(tmp_path):
    """The kernel's out-of-memory killer takes one worker: the parent said only "A process in the
    process pool was terminated abruptly while the future was running or pending"."""
    out = tmp_path / "oom"
    process = _start(out, *SLOW)
    try:
        _wait_for_temporary(process, out)
        workers = [pid for pid in _live_group(process.pid) if pid != process.pid
                   and b"resource_tracker" not in Path(f"/proc/{pid}/cmdline").read_bytes()]
        assert workers
        os.kill(workers[0], signal.SIGKILL)
        _, err = process.communicate(timeout=120)
        assert process.returncode == 2
        assert re.fullmatch(r"rainbench: error: OUT: a worker process died while rendering (scene000000_f000(00|16|32)\.h5"
                            r"(, )?)+ \(killed: out of memory\? fewer --workers, or a smaller image, need less\); the "
                            r"finished shards are kept\n", err), err
        manifest = out / store.MANIFEST  # absent when no shard was finished (a new OUT is left as it was)
        listed = {entry["path"] for entry in json.loads(manifest.read_text())["shards"]} if manifest.exists() else set()
        assert not any(name in err for name in listed)  # only shards still being rendered are named
        assert _wait_group_gone(process.pid, timeout=10) == []
        assert not list(out.glob(".*tmp*"))
    finally:
        if _live_group(process.pid):
            os.killpg(process.pid, signal.SIGKILL)


def test_ctrl_c_while_the_command_starts_is_one_line():
    """Ctrl-C in the first second (the CLI's imports) printed a traceback through numpy."""
    hook = ("import sys, runpy\n"
            "class Interrupt:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name == 'rainbench.rain.weather':\n"
            "            raise KeyboardInterrupt\n"
            "sys.meta_path.insert(0, Interrupt())\n"
            "runpy.run_module('rainbench.cli', run_name='__main__')\n")
    result = subprocess.run([sys.executable, "-c", hook, "stats", "nowhere"], capture_output=True, text=True)
    assert (result.returncode, result.stderr) == (130, "rainbench: interrupted\n")


def test_a_second_ctrl_c_cannot_cut_the_cleanup_short():
    """While a stopped run cleans up (or an export swaps or rolls back), Ctrl-C, SIGTERM and
    SIGHUP are ignored; the handlers come back afterwards (a second Ctrl-C left a traceback and the
    cleanup half done)."""
    received = []
    original = {signum: signal.signal(signum, lambda number, frame: received.append(number))
                for signum in STOP_SIGNALS}  # known handlers (a background run may ignore SIGINT)
    try:
        mine = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
        with signals_held():
            assert all(signal.getsignal(signum) == signal.SIG_IGN for signum in STOP_SIGNALS)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        assert received == [] and {signum: signal.getsignal(signum) for signum in STOP_SIGNALS} == mine
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert received == [signal.SIGINT]
    finally:
        for signum, handler in original.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
    assert ds.PARENT_SIGNALS == STOP_SIGNALS


def test_a_signal_ignored_before_the_command_stays_ignored(monkeypatch):
    """`nohup rainbench generate ... &`: SIGHUP is ignored so the run outlives its terminal; the
    CLI's SIGTERM/SIGHUP handling must not undo that."""
    seen = {}

    def run(args):
        seen.update({signum: signal.getsignal(signum) for signum in (signal.SIGHUP, signal.SIGTERM)})
        return 0

    monkeypatch.setattr(cli, "_run", run)
    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        assert cli.main(["stats", "anything"]) == 0
        assert seen[signal.SIGHUP] is signal.SIG_IGN and seen[signal.SIGTERM] is cli._raise_terminated
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN and signal.getsignal(signal.SIGTERM) is not cli._raise_terminated
    finally:
        signal.signal(signal.SIGHUP, before if before is not None else signal.SIG_DFL)


def test_ctrl_c_as_the_last_shard_is_listed_says_the_dataset_is_complete(tmp_path, capsys, monkeypatch):
    """Ctrl-C right after the final manifest write said "run the same command again to resume"."""
    real, raised = ds.write_manifest, []

    def then_interrupted(root, config, entries, complete):
        path = real(root, config, entries, complete)
        if complete and not raised:
            raised.append(True)
            raise KeyboardInterrupt
        return path

    monkeypatch.setattr(ds, "write_manifest", then_interrupted)
    out = tmp_path / "done"
    code = cli.main(["generate", "--frames", "2", "--width", "96", "--height", "72", "--rates", "0", "--quiet",
                     "--workers", "1", "--out", str(out)])
    assert code == 130 and raised
    assert capsys.readouterr().err == (f"rainbench: interrupted; {out / store.MANIFEST} says the dataset is complete "
                                       f"(rainbench verify {out} checks it)\n")
    assert store.verify_dataset(out) == []


def test_a_termination_ray_reraises_as_a_plain_interrupt_keeps_its_signal(monkeypatch, capsys):
    """Ray's waits re-raise what a signal handler raised as a bare KeyboardInterrupt: SIGHUP was
    reported as "interrupted", exit 130."""
    def stats_like_ray(args):
        try:
            cli._raise_terminated(signal.SIGHUP, None)
        except KeyboardInterrupt:
            raise KeyboardInterrupt from None  # what ray.wait does

    monkeypatch.setattr(cli, "cmd_stats", stats_like_ray)
    assert cli.main(["stats", "anything"]) == 128 + signal.SIGHUP
    assert capsys.readouterr().err == "rainbench: terminated by SIGHUP\n"


def test_the_manifest_exists_before_the_first_shard(tmp_path):
    seen = []

    def interrupt(frames):
        seen.append(sorted(p.name for p in tmp_path.iterdir()))
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ds.run_dataset(DatasetConfig(**SMALL), tmp_path, workers=1, progress=interrupt)
    assert seen and "manifest.json" in seen[0]  # a kill -9 here leaves a manifest to resume
    assert list(tmp_path.iterdir()) == []  # a caught failure with nothing done leaves nothing


def test_a_complete_shard_missing_from_the_manifest_is_adopted(small, tmp_path, monkeypatch):
    """A run killed between a shard's rename and the manifest update: the re-run adopts it."""
    out = _copy_tree(small, tmp_path / "copy")
    manifest = json.loads((out / store.MANIFEST).read_text())
    manifest["shards"], manifest["complete"] = manifest["shards"][:1], False
    (out / store.MANIFEST).write_text(json.dumps(manifest))

    def no_render(*args, **kwargs):
        raise AssertionError("the shard should have been adopted, not rendered")

    monkeypatch.setattr(ds, "generate_shard", no_render)
    ds.run_dataset(DatasetConfig(**SMALL), out, workers=1)
    assert _hashes(out) == _hashes(small) and store.verify_dataset(out) == []


def test_a_corrupt_unlisted_shard_is_rendered_again(small, tmp_path, monkeypatch):
    out = _copy_tree(small, tmp_path / "copy")
    manifest = json.loads((out / store.MANIFEST).read_text())
    manifest["shards"], manifest["complete"] = manifest["shards"][:1], False
    (out / store.MANIFEST).write_text(json.dumps(manifest))
    corrupt = out / "scene000000_f00002.h5"
    with h5py.File(corrupt) as handle:
        info = handle["rgb"].id.get_chunk_info_by_coord((0, 0, 0, 0, 0))
    data = bytearray(corrupt.read_bytes())
    data[info.byte_offset + info.size // 2] ^= 0x55  # inside an RGB chunk: h5py still opens it
    corrupt.write_bytes(bytes(data))
    task = DatasetConfig(**SMALL).tasks()[1]
    assert not ds._adoptable(corrupt, task)
    assert ds._adoptable(small / corrupt.name, task)
    rendered = []
    real = ds.generate_shard

    def spy(task, out_dir, **kwargs):
        rendered.append(task.frame_offset)
        return real(task, out_dir, **kwargs)

    monkeypatch.setattr(ds, "generate_shard", spy)
    ds.run_dataset(DatasetConfig(**SMALL), out, workers=1)
    assert rendered == [2] and _hashes(out) == _hashes(small)


def test_the_lock_refuses_a_second_run_and_is_released(tmp_path, capsys):
    with ds._locked(tmp_path):
        assert (tmp_path / ds.LOCK).read_text() == f"{os.getpid()} generate"
        code = cli.main(["generate", "--out", str(tmp_path), "--frames", "1", "--quiet"])
        _one_line_error(capsys, code, re.escape(f"OUT: {tmp_path} is being written by another "
                                                f"rainbench generate (pid {os.getpid()})") + ".*")
    assert list(tmp_path.iterdir()) == []  # released and removed
    with ds._locked(tmp_path):  # and can be taken again
        pass


def test_workers_die_with_their_parent(tmp_path):
    """_die_with_parent in a process whose parent is then killed with SIGKILL."""
    script = (
        "import os, sys, time\n"
        "from rainbench.gen.dataset import _die_with_parent\n"
        "child = os.fork()\n"
        "if child == 0:\n"
        "    _die_with_parent(os.getppid())\n"
        "    open(sys.argv[1], 'w').write(str(os.getpid()))\n"
        "    time.sleep(60)\n"
        "    os._exit(0)\n"
        "time.sleep(60)\n")
    marker = tmp_path / "child.pid"
    process = subprocess.Popen([sys.executable, "-c", script, str(marker)], start_new_session=True)
    try:
        deadline = time.time() + 60
        while not (marker.exists() and marker.read_text()) and time.time() < deadline:
            time.sleep(0.05)
        child = int(marker.read_text())
        assert _proc_stat(child)[0] != "Z"
        process.send_signal(signal.SIGKILL)
        process.wait()
        deadline = time.time() + 5
        while _proc_stat(child) and _proc_stat(child)[0] != "Z" and time.time() < deadline:
            time.sleep(0.05)
        assert _proc_stat(child) is None or _proc_stat(child)[0] == "Z"
    finally:
        if _live_group(process.pid):
            os.killpg(process.pid, signal.SIGKILL)


# -- 2. every image size ------------------------------------------------------------------------

@pytest.mark.parametrize("width, height", [(200, 150), (250, 190), (333, 250), (801, 601)])
def test_every_accepted_size_gets_a_big_enough_framebuffer(width, height):
    config = GenerateConfig(frames=1, width=width, height=height)
    setup = build_scene(config)
    vis = setup.model.vis.global_
    assert (vis.offwidth, vis.offheight) == padded_size(width, height)[:2]
    with FrameRenderer(setup.model, width, height, setup.geom_instance) as renderer:
        assert (renderer.padded_width, renderer.padded_height) == padded_size(width, height)[:2]


def test_the_issue_size_generates(tmp_path, capsys):
    assert cli.main(["generate", "--frames", "1", "--width", "200", "--height", "150", "--quiet",
                     "--out", str(tmp_path)]) == 0
    with h5py.File(tmp_path / "scene000000_f00000.h5") as handle:
        assert handle["rgb"].shape == (1, 1, 150, 200, 3)


def test_sizes_whose_framebuffer_does_not_render_are_refused_up_front(tmp_path, capsys):
    code = _cli(["generate", "--width", "8192", "--height", "4096", "--frames", "1", "--quiet",
                 "--out", str(tmp_path / "o")])
    _one_line_error(capsys, code, re.escape("WIDTH x HEIGHT: 8192x4096 = 33554432 pixels; at most "
                                            "16777216 (4096x4096): larger framebuffers do not render"))
    assert not (tmp_path / "o").exists()


@pytest.mark.slow  # about 11 s and 3 GB each
@pytest.mark.parametrize("width, height", [(4096, 4096), (8192, 2048), (2048, 8192)])
def test_the_largest_accepted_sizes_render(tmp_path, width, height):
    assert cli.main(["generate", "--frames", "1", "--width", str(width), "--height", str(height),
                     "--quiet", "--out", str(tmp_path)]) == 0
    with h5py.File(tmp_path / "scene000000_f00000.h5") as handle:
        assert handle["rgb"].shape == (1, 1, height, width, 3)


def test_build_spec_and_the_renderer_share_one_size_rule():
    from rainbench.mjcf import layout as L

    config = GenerateConfig(frames=1)
    layout = L.sample_layout(0, config.scenario_config(), np.random.default_rng(0))
    for width, height in ((16, 16), (17, 19), (200, 150), (8192, 16), (16, 8191)):
        spec = build_spec(layout, width, height)
        assert (spec.visual.global_.offwidth, spec.visual.global_.offheight) == \
            padded_size(width, height)[:2]
        padded_w, padded_h, margin_x, margin_y = padded_size(width, height)
        assert margin_x >= width * 0.25 and margin_y >= height * 0.25
        assert (padded_w, padded_h) == (width + 2 * margin_x, height + 2 * margin_y)


# -- 3. one-line errors instead of tracebacks ---------------------------------------------------

def _manifest_cases():
    def drop(key):
        return lambda m: {k: v for k, v in m.items() if k != key}

    def entry(change):
        def apply(m):
            m["shards"][0] = change(dict(m["shards"][0]))
            return m
        return apply

    return [
        ("no shards", drop("shards"), r'"shards" must be a list of shard entries, got None'),
        ("shards null", lambda m: dict(m, shards=None),
         r'"shards" must be a list of shard entries, got None'),
        ("no sha256", entry(lambda e: {k: v for k, v in e.items() if k != "sha256"}),
         r'shards\[0\]: "sha256" is missing'),
        ("no path", entry(lambda e: {k: v for k, v in e.items() if k != "path"}),
         r'shards\[0\]: "path" is missing'),
        ("passwd", entry(lambda e: dict(e, path="../../../etc/passwd")),
         r"shards\[0\]: path '\.\./\.\./\.\./etc/passwd' leaves the dataset directory; shard paths "
         r"must be relative paths inside it"),
        ("absolute", entry(lambda e: dict(e, path="/etc/passwd")),
         r"shards\[0\]: path '/etc/passwd' leaves the dataset directory.*"),
        ("bad sha", entry(lambda e: dict(e, sha256="xyz")),
         r'shards\[0\]: "sha256" must be 64 lowercase hex digits, got \'xyz\''),
        ("bytes null", entry(lambda e: dict(e, bytes=None)),
         r'shards\[0\]: "bytes" must be an integer >= 0, got None'),
        ("config list", lambda m: dict(m, config=[]), r'"config" must be an object, got list'),
    ]


@pytest.mark.parametrize("name, change, message", _manifest_cases(), ids=[c[0] for c in _manifest_cases()])
def test_bad_manifests_are_one_line_errors_everywhere(small, tmp_path, capsys, name, change, message):
    out = _copy_tree(small, tmp_path / "copy")
    manifest = change(json.loads((out / store.MANIFEST).read_text()))
    (out / store.MANIFEST).write_text(json.dumps(manifest))
    where = re.escape(str(out / store.MANIFEST)) + ": "
    # generate names the way out: --overwrite replaces a dataset whose manifest it cannot read
    overwrite = re.escape(f"; use --overwrite to replace the dataset in {out} or choose another OUT")
    for argv, pattern in (
            (["verify", str(out)], where + message),
            (["generate", "--out", str(out), "--frames", "4", "--frames-per-shard", "2",
              "--width", "96", "--height", "72", "--rates", "0,50", "--quiet"],
             "OUT: " + where + message + overwrite),
            (["export", str(out), "--format", "coco", "--out", str(tmp_path / "export")], where + message),
            (["preview", str(out), "--out", str(tmp_path / "p.png")], where + message)):
        _one_line_error(capsys, cli.main(argv), pattern)
    assert not (tmp_path / "export").exists() and not (tmp_path / "p.png").exists()
    with pytest.raises(ds.DatasetError, match=where + message):
        ShardDataset(out)


def test_deeply_nested_manifest_names_the_file(small, tmp_path, capsys):
    out = _copy_tree(small, tmp_path / "copy")
    (out / store.MANIFEST).write_text("[" * 200_000)
    _one_line_error(capsys, cli.main(["verify", str(out)]),
                    re.escape(f"{out / store.MANIFEST}: not a readable manifest (nested too deeply)"))


def _run_cli_env(tmp_path, env_changes):
    env = dict(os.environ)
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    env.update(env_changes)
    return subprocess.run([sys.executable, "-m", "rainbench.cli", "generate", "--frames", "1",
                           "--width", "64", "--height", "48", "--quiet", "--out",
                           str(tmp_path / "gl")], capture_output=True, text=True, env=env,
                          timeout=300)


@pytest.mark.skipif(ctypes.util.find_library("OSMesa") is not None, reason="OSMesa is installed")
def test_mujoco_gl_osmesa_without_osmesa_is_one_line(tmp_path):
    result = _run_cli_env(tmp_path, {"MUJOCO_GL": "osmesa"})
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "rainbench: error: MUJOCO_GL=osmesa: the OSMesa library is not installed (package "
        "libosmesa6); " + ("set MUJOCO_GL=egl (installed here) or unset MUJOCO_GL"
                            if ctypes.util.find_library("EGL") else
                            "install libegl1 for egl; install libosmesa6 for osmesa")]
    assert not (tmp_path / "gl").exists()


def test_mujoco_gl_glfw_without_a_display_is_one_line(tmp_path):
    result = _run_cli_env(tmp_path, {"MUJOCO_GL": "glfw"})
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "rainbench: error: MUJOCO_GL=glfw: needs a display and DISPLAY is unset; rainbench renders "
        "offscreen: "), lines
    assert "EGL" not in lines[0] or ctypes.util.find_library("EGL") is None


def test_check_environment_says_what_works_instead():
    found = {"EGL": "libEGL.so.1"}.get
    gl.check_environment({"MUJOCO_GL": "egl"}, found)  # fine
    gl.check_environment({}, found)
    with pytest.raises(gl.GLBackendError, match=r"^MUJOCO_GL=osmesa: the OSMesa library is not "
                       r"installed \(package libosmesa6\); set MUJOCO_GL=egl \(installed here\)"):
        gl.check_environment({"MUJOCO_GL": "osmesa"}, found)
    with pytest.raises(gl.GLBackendError, match=r"^MUJOCO_GL=egl: .* install libegl1 for egl; "
                       r"install libosmesa6 for osmesa$"):
        gl.check_environment({"MUJOCO_GL": "egl"}, lambda name: None)
    gl.check_environment({"MUJOCO_GL": "glfw", "DISPLAY": ":0"}, found)


def test_preview_out_directory_and_bad_suffix(labelled, tmp_path, capsys):
    folder = tmp_path / "somedir"
    folder.mkdir()
    assert cli.main(["preview", str(labelled), "--frame", "1", "--out", str(folder)]) == 0
    written = folder / f"{labelled.stem}_frame0001_rates.png"
    assert capsys.readouterr().out.strip() == str(written) and written.stat().st_size > 0
    assert [p.name for p in folder.iterdir()] == [written.name]  # no temporary left
    code = cli.main(["preview", str(labelled), "--out", str(tmp_path / "x.txt")])
    _one_line_error(capsys, code, re.escape(f"--out: expected a .png file name or a directory, got "
                                            f"{tmp_path / 'x.txt'}"))
    assert not (tmp_path / "x.txt").exists()


def test_preview_boxes_on_a_nan_box_and_a_corrupt_chunk_name_the_file(labelled, tmp_path, capsys):
    bad = _mutated(labelled, tmp_path / "nan", bbox=_nan_box)
    code = cli.main(["preview", str(bad), "--frame", "1", "--boxes", "--out", str(tmp_path / "p.png")])
    _one_line_error(capsys, code, re.escape(f"{bad}: frame 1: label 0 has bbox [44.0, nan, ") + ".*")
    corrupt = tmp_path / "corrupt" / labelled.name
    corrupt.parent.mkdir()
    shutil.copy(labelled, corrupt)
    with h5py.File(corrupt) as handle:
        info = handle["rgb"].id.get_chunk_info_by_coord((0, 1, 0, 0, 0))  # rate row 0, frame 1
    data = bytearray(corrupt.read_bytes())
    data[info.byte_offset + 40] ^= 0xFF
    corrupt.write_bytes(bytes(data))
    code = cli.main(["preview", str(corrupt), "--frame", "1", "--out", str(tmp_path / "p.png")])
    _one_line_error(capsys, code, re.escape(f"{corrupt}: /rgb chunk of rate row 0, frame 1 is corrupt")
                    + ".*")
    assert not (tmp_path / "p.png").exists()


# -- 4. readers check labels --------------------------------------------------------------------

LABEL_DEFECTS = [
    ("nan box", dict(bbox=_nan_box), r"frame 1: label 0 has bbox \[44\.0, nan, 52\.0, 42\.0\]; "
                                     r"expected finite 0 <= x1 < x2 <= 96, 0 <= y1 < y2 <= 72"),
    ("offsets decrease", dict(offsets=np.array([0, 1, 0, 2])),
     r"frame 1: /labels/offsets decreases \(1 -> 0\)"),
    ("offsets past the labels", dict(offsets=np.array([0, 0, 1, 3])),
     r"frame 2: /labels/offsets ends at 3 but /labels/bbox has 2 rows"),
    ("class out of range", dict(class_id=np.array([2, 9], np.int32)),
     r"frame 2: label 0 has a class_id outside 0\.\.7"),
    ("visible fraction nan", dict(visible_fraction=np.array([0.5, np.nan], np.float32)),
     r"frame 2: label 0 has visible_fraction outside \[0, 1\]"),
    ("short instance ids", dict(instance_id=np.array([1], np.int32)),
     r"/labels/instance_id has shape \(1,\), expected \(2,\)"),
]


@pytest.mark.parametrize("name, change, message", LABEL_DEFECTS, ids=[d[0] for d in LABEL_DEFECTS])
def test_every_reader_refuses_bad_labels_naming_file_and_frame(labelled, tmp_path, capsys, name,
                                                               change, message):
    bad = _mutated(labelled, tmp_path / "data", **change)
    pattern = re.escape(str(bad)) + ": " + message
    with pytest.raises(ShardFormatError, match=pattern):
        ShardDataset(bad)
    with pytest.raises(ShardFormatError, match=pattern):
        store.Dataset([bad])
    for fmt in ("yolo", "coco"):
        code = cli.main(["export", str(bad), "--format", fmt, "--out", str(tmp_path / fmt)])
        _one_line_error(capsys, code, pattern)
        assert not (tmp_path / fmt).exists()
    predictions = tmp_path / "predictions" / "model"
    predictions.mkdir(parents=True)
    for token in ("0", "50"):
        (predictions / f"rate_{token}.json").write_text("[]")
    code = cli.main(["eval", "--data", str(bad.parent), "--predictions", str(predictions.parent),
                     "--out", str(tmp_path / "eval"), "--n-boot", "5", "--quiet"])
    _one_line_error(capsys, code, pattern)


def test_verify_reports_bad_labels(small, tmp_path, capsys):
    out = _copy_tree(small, tmp_path / "copy")
    shard = out / "scene000000_f00000.h5"
    with h5py.File(shard, "r+") as handle:
        offsets = handle["labels/offsets"][()]
        assert offsets.shape == (3,)
        del handle["labels/offsets"]
        handle.create_dataset("labels/offsets", data=np.array([0, offsets[-1] + 1, offsets[-1]]))
    manifest = json.loads((out / store.MANIFEST).read_text())
    manifest["shards"][0].update(sha256=ds.sha256_of(shard), bytes=shard.stat().st_size)
    (out / store.MANIFEST).write_text(json.dumps(manifest))
    assert cli.main(["verify", str(out)]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        f"rainbench: bad: {shard}: frame 1: /labels/offsets decreases ({offsets[-1] + 1} -> "
        f"{offsets[-1]})"]


def test_good_labels_pass_the_check(labelled, small):
    for path in [labelled, *sorted(small.glob("*.h5"))]:
        with store.open_checked(path) as handle:
            assert handle["labels/offsets"][-1] == handle["labels/bbox"].shape[0]


# -- 5. leftovers and edges ---------------------------------------------------------------------

def test_a_failed_export_leaves_nothing_and_an_old_export_intact(small, tmp_path, capsys,
                                                                monkeypatch):
    out = tmp_path / "export"
    real = ex._write_image
    calls = []

    def fail_third(path, rgb):
        calls.append(path)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        real(path, rgb)

    monkeypatch.setattr(ex, "_write_image", fail_third)
    code = cli.main(["export", str(small), "--format", "yolo", "--out", str(out)])
    _one_line_error(capsys, code, r"\[Errno 28\] No space left on device")
    assert not out.exists()
    monkeypatch.setattr(ex, "_write_image", real)
    assert cli.main(["export", str(small), "--format", "yolo", "--out", str(out)]) == 0
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert len([p for p in before if p.suffix == ".png"]) == 8  # 4 frames x 2 rates
    calls.clear()
    monkeypatch.setattr(ex, "_write_image", fail_third)
    code = cli.main(["export", str(small), "--format", "yolo", "--out", str(out), "--overwrite"])
    assert code == 2
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before  # the failed --overwrite touched nothing
    capsys.readouterr()


def test_export_cleans_a_killed_exports_staging_folder(small, tmp_path):
    out = tmp_path / "export"
    stale = out / ".export-tmp-999999999" / "rate_0" / "images"
    stale.mkdir(parents=True)
    paths = ex.export_coco(small, out, images=False)
    assert sorted(p.name for p in out.iterdir()) == ["rate_0.json", "rate_50.json"]
    assert paths == [out / "rate_0.json", out / "rate_50.json"]


def test_verify_warns_about_shards_outside_the_manifest(small, tmp_path, capsys):
    out = _copy_tree(small, tmp_path / "copy")
    shutil.copy(out / "scene000000_f00000.h5", out / "extra.h5")
    (out / "old").mkdir()
    shutil.copy(out / "scene000000_f00000.h5", out / "old" / "scene000000_f00000.h5")
    assert cli.main(["verify", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.out.strip() == f"{out}: ok"
    assert captured.err.strip().splitlines() == [
        f"rainbench: warning: {out / name}: not listed in the manifest, so not part of the "
        "dataset (ignored)" for name in ("extra.h5", "old/scene000000_f00000.h5")]
    assert store.unlisted_shards(small) == []


def _rewrite_manifest(root, edit) -> None:
    path = root / store.MANIFEST
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest))


def test_readers_check_each_shard_against_its_manifest_entry(small, tmp_path):
    """Shards swapped, or rewritten since the manifest was written: exports, stats and the
    readers served the wrong frames (or changed labels) under the listed names; only verify
    (which hashes) noticed."""
    out = _copy_tree(small, tmp_path / "swapped")
    first, second = out / "scene000000_f00000.h5", out / "scene000000_f00002.h5"
    first.rename(out / "x.h5")
    second.rename(first)
    (out / "x.h5").rename(second)
    with pytest.raises(store.DatasetError, match=r"^" + re.escape(str(first)) + r": (\d+ bytes, its manifest says \d+ "
                       r"\(changed since it was written: rainbench verify checks the dataset\)|holds scene 0 from "
                       r"frame 2, its manifest says scene 0 from frame 0)$"):
        store.Dataset(out)
    out = _copy_tree(small, tmp_path / "offsets")
    _rewrite_manifest(out, lambda m: m["shards"][1].update(frame_offset=5))
    with pytest.raises(store.DatasetError, match=r"^" + re.escape(f"{out / 'scene000000_f00002.h5'}: holds scene 0 "
                                                                   "from frame 2, its manifest says scene 0 from frame 5") + "$"):
        store.Dataset(out)
    out = _copy_tree(small, tmp_path / "frames")
    _rewrite_manifest(out, lambda m: m["shards"][0].update(frames=3))
    with pytest.raises(store.DatasetError, match=r"^" + re.escape(f"{out / 'scene000000_f00000.h5'}: 2 frames, its "
                                                                   "manifest says 3") + "$"):
        store.Dataset(out)
    assert len(store.Dataset(small)) == 4  # the untouched dataset reads


def test_a_malformed_shard_attribute_is_one_line_and_shards_may_sit_in_a_subfolder(small, tmp_path, capsys):
    out = _copy_tree(small, tmp_path / "attr")
    shard = out / "scene000000_f00002.h5"
    with h5py.File(shard, "r+") as handle:
        handle.attrs["scene_seed"] = np.array([0, 0])
    _rewrite_manifest(out, lambda m: m["shards"][1].update(sha256=ds.sha256_of(shard), bytes=shard.stat().st_size))
    for argv in (["stats", str(out)], ["verify", str(out)]):
        code = cli.main(argv)
        err = capsys.readouterr().err
        assert code in (1, 2) and f"{shard}: its scene_seed attribute is not an integer" in err and "Traceback" not in err
    # a layout other tools may write: shards in a subfolder, listed by their relative paths
    out = _copy_tree(small, tmp_path / "sub")
    (out / "shards").mkdir()
    for shard in sorted(out.glob("scene*.h5")):
        shard.rename(out / "shards" / shard.name)
    _rewrite_manifest(out, lambda m: [entry.update(path="shards/" + entry["path"]) for entry in m["shards"]])
    assert cli.main(["verify", str(out)]) == 0 and cli.main(["stats", str(out)]) == 0
    capsys.readouterr()


def test_verify_checks_the_order_names_and_contents_of_manifest_entries(small, tmp_path, capsys):
    """Entries reordered (every image id moves) or with swapped offsets: verify said ok."""
    out = _copy_tree(small, tmp_path / "order")
    _rewrite_manifest(out, lambda m: m["shards"].reverse())
    assert cli.main(["verify", str(out)]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        f"rainbench: bad: {out / store.MANIFEST}: shards[1] (scene000000_f00000.h5): scene 0 from frame 0 is listed "
        "after scene 0 from frame 2 (shards are listed in dataset order: an image's index depends on it)"]
    out = _copy_tree(small, tmp_path / "offsets")

    def swap_offsets(manifest):
        first, second = manifest["shards"]
        first["frame_offset"], second["frame_offset"] = second["frame_offset"], first["frame_offset"]

    _rewrite_manifest(out, swap_offsets)
    assert cli.main(["verify", str(out)]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert f"rainbench: bad: {out / store.MANIFEST}: shards[0] (scene000000_f00000.h5): the shard of scene 0 from " \
           "frame 2 is named scene000000_f00002.h5, not scene000000_f00000.h5" in lines
    assert f"rainbench: bad: {out / 'scene000000_f00000.h5'}: holds scene 0 from frame 0, its manifest says scene 0 " \
           "from frame 2" in lines


def test_a_manifest_that_says_complete_but_lacks_shards_is_refused(small, tmp_path, capsys):
    """Edited to list fewer shards and still say complete: stats and export covered part of it."""
    out = _copy_tree(small, tmp_path / "partial")
    _rewrite_manifest(out, lambda m: m["shards"].pop())
    for argv in (["stats", str(out)], ["export", str(out), "--format", "coco", "--out", str(tmp_path / "e")]):
        code = cli.main(argv)
        _one_line_error(capsys, code, re.escape(f"DATA: {out / store.MANIFEST}: says complete but lists 1 of the "
                                                f"config's 2 shards (first missing: scene 0, frame offset 2) "
                                                f"(rainbench verify {out} lists every problem)"))
    assert not (tmp_path / "e").exists()


def test_a_manifest_that_cannot_be_written_is_named_and_leaves_no_temporary(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(store.DatasetError, match=r"^" + re.escape(f"{tmp_path / store.MANIFEST}: cannot write it "
                                                                   "(No space left on device)") + "$"):
        write_manifest(tmp_path, DatasetConfig(**SMALL).to_dict(), [], complete=False)
    assert list(tmp_path.iterdir()) == []


def test_verify_ignores_what_hidden_folders_hold(small, tmp_path, capsys):
    """A killed run's `.pieces.tmp-PID` folder holds piece shards: verify called them strays."""
    out = _copy_tree(small, tmp_path / "copy")
    (out / ".pieces.tmp-123").mkdir()
    shutil.copy(out / "scene000000_f00000.h5", out / ".pieces.tmp-123" / "scene000000_f00000.h5")
    assert store.unlisted_shards(out) == []
    assert cli.main(["verify", str(out)]) == 0 and capsys.readouterr().err == ""


def test_an_interrupted_overwrite_puts_the_previous_export_back(small, tmp_path, monkeypatch):
    """Targets were replaced one by one: an interrupt (or an error) half way left the new images
    beside the old JSON files."""
    out = tmp_path / "export"
    ex.export_coco(small, out, rates=[0.0])
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    real, calls = os.replace, []

    def interrupted(source, target):
        calls.append(target)
        if len(calls) == 3:  # rate_0/images set aside and replaced; now rate_0.json is set aside
            raise KeyboardInterrupt
        if len(calls) == 4:  # the rollback's first rename: a second Ctrl-C must not cut it short
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        real(source, target)

    monkeypatch.setattr(ex.os, "replace", interrupted)
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        with pytest.raises(KeyboardInterrupt):
            ex.export_coco(small, out, rates=[0.0], overwrite=True, image_format="jpg")
    finally:
        signal.signal(signal.SIGINT, handler if handler is not None else signal.SIG_DFL)
    monkeypatch.setattr(ex.os, "replace", real)
    assert len(calls) == 5  # 3 renames (the third interrupted), then 2 back
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in out.iterdir()) == ["rate_0", "rate_0.json"]  # no staging folder left


def test_an_overwrite_that_would_stop_half_way_is_refused_up_front(small, tmp_path, capsys):
    out = tmp_path / "export"
    ex.export_coco(small, out)
    shutil.rmtree(out / "rate_50")
    (out / "rate_50").write_text("junk")
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    code = cli.main(["export", str(small), "--format", "coco", "--out", str(out), "--overwrite"])
    _one_line_error(capsys, code, re.escape(f"OUT: {out / 'rate_50'} is a file where the export puts a folder; remove "
                                            "it or choose another directory"))
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_a_failed_export_into_new_folders_removes_them_all(small, tmp_path, monkeypatch, capsys):
    def full(path, rgb):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ex, "_write_image", full)
    code = cli.main(["export", str(small), "--format", "yolo", "--out", str(tmp_path / "n1" / "n2" / "n3")])
    _one_line_error(capsys, code, r"\[Errno 28\] No space left on device")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("value", ["100001", "99999999999999999999", "0", "-3", "1e3"])
def test_frames_is_bounded_up_front(tmp_path, capsys, value):
    code = _cli(["generate", "--frames", value, "--out", str(tmp_path / "o"), "--quiet"])
    expected = {"1e3": "an integer, got '1e3'", "0": ">= 1, got 0", "-3": ">= 1, got -3"}.get(
        value, f"<= 100000, got {value}")
    line = _one_line_error(capsys, code, r"argument --frames: FRAMES: expected " + re.escape(expected))
    assert "frame_offset" not in line and not (tmp_path / "o").exists()
    assert cli.MAX_FRAMES == MAX_FRAMES
    with pytest.raises(ds.DatasetError, match=r"^FRAMES: expected an integer in 1\.\.100000, got 100001$"):
        DatasetConfig(frames=100_001)


def test_too_many_shards_are_refused_up_front():
    with pytest.raises(ds.DatasetError, match=r"SCENES x ceil\(FRAMES / FRAMES_PER_SHARD\) = "
                                              r"10000000 shards; at most 100000"):
        DatasetConfig(scenes=100, frames=100_000, fps=1000.0, frames_per_shard=1)  # a 100 s clip


def test_deeply_nested_predictions_name_the_file(tmp_path):
    from rainbench.eval import pipeline

    path = tmp_path / "rate_0.json"
    path.write_text("[" * 200_000)
    with pytest.raises(pipeline.EvalError, match=re.escape(f"predictions: {path} is not a COCO results "
                                                           "list (JSON nested too deeply to read)")):
        pipeline.load_predictions_file(path, {1})
    path.write_text(json.dumps([{"image_id": 1, "category_id": 0, "bbox": "1234", "score": 1}]))
    with pytest.raises(pipeline.EvalError, match=re.escape(f"{path}: record 0: bbox '1234' is not")):
        pipeline.load_predictions_file(path, {1})
    path.write_text('[{"image_id": 1, "category_id": 0, "bbox": [0, 0, 1, 1], "score": 1' + "0" * 400 + "}]")
    with pytest.raises(pipeline.EvalError, match=re.escape(f"{path}: record 0: expected image_id")):
        pipeline.load_predictions_file(path, {1})


# -- 6. a Ray cluster by address ----------------------------------------------------------------

def _free_port():
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def ray_head(tmp_path_factory):
    """A head started by ``ray start --block`` with token authentication (what Ray 2.60 turns on
    once a token exists), on a free port, its token in HOME/.ray/auth_token; yields
    (port, env). Stopped in teardown by terminating that ``ray start`` (which stops what it
    started), never by ``ray stop`` (that would stop other people's Ray instances too)."""
    pytest.importorskip("ray")
    home = tmp_path_factory.mktemp("home")
    (home / ".ray").mkdir()
    (home / ".ray" / "auth_token").write_text(secrets.token_hex(32))
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env.update(HOME=str(home), RAY_AUTH_MODE="token", RAY_USAGE_STATS_ENABLED="0")
    port = _free_port()
    temp_dir = Path(f"/tmp/rb-ray-{os.getpid()}-{port}")  # short: Ray's sockets live there
    log = home / "ray-start.log"
    with open(log, "w") as output:
        head = subprocess.Popen([str(Path(sys.executable).with_name("ray")), "start", "--head",
                                 f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
                                 "--disable-usage-stats", f"--temp-dir={temp_dir}", "--block"],
                                env=env, stdout=output, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:
        deadline = time.time() + 90
        while "Ray runtime started" not in log.read_text():
            assert head.poll() is None and time.time() < deadline, log.read_text()[-2000:]
            time.sleep(0.5)
        yield port, env
    finally:
        head.terminate()
        try:
            head.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
        if _live_group(head.pid):
            os.killpg(head.pid, signal.SIGKILL)
        shutil.rmtree(temp_dir, ignore_errors=True)


def _ray_argv(out, port):
    return [sys.executable, "-m", "rainbench.cli", "generate", "--out", str(out), "--frames", "4",
            "--frames-per-shard", "2", "--width", "96", "--height", "72", "--rates", "0,50",
            "--quiet", "--executor", "ray", "--ray-address", f"127.0.0.1:{port}"]


def test_ray_cluster_by_address_with_token_authentication(ray_head, tmp_path):
    """The issue: after ``ray start --head``, ``--ray-address 127.0.0.1:PORT`` with RAY_AUTH_MODE
    unset and the token in ~/.ray/auth_token (Ray 2.60 sent no token and failed); the shards
    are byte-identical to the local executor's."""
    port, env = ray_head
    driver_env = {k: v for k, v in env.items() if k != "RAY_AUTH_MODE"}
    result = subprocess.run(_ray_argv(tmp_path / "ray", port), env=driver_env, capture_output=True,
                            text=True, timeout=240)
    assert result.returncode == 0, result.stderr[-2000:]
    local = _ray_argv(tmp_path / "local", port)[3:-4]
    assert cli.main(local) == 0
    assert _hashes(tmp_path / "ray") == _hashes(tmp_path / "local")


@pytest.mark.slow  # Ray retries a refused token for about 20 s before it gives up
def test_ray_cluster_with_a_wrong_token_is_one_line(ray_head, tmp_path):
    port, env = ray_head
    wrong = dict(env, RAY_AUTH_TOKEN="0" * 64)  # RAY_AUTH_MODE=token, the wrong token
    result = subprocess.run(_ray_argv(tmp_path / "wrong", port), env=wrong, capture_output=True,
                            text=True, timeout=240)
    errors = [line for line in result.stderr.splitlines() if line.startswith("rainbench")]
    assert result.returncode == 2 and len(errors) == 1, result.stderr[-2000:]
    assert errors[0].startswith(f"rainbench: error: --ray-address 127.0.0.1:{port}: cannot "
                                "connect to the Ray cluster (")
    assert errors[0].endswith("; " + ds.RAY_AUTH_HINT)
    assert not (tmp_path / "wrong" / "manifest.json").exists()


# -- 7. .pt loading -----------------------------------------------------------------------------

class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.mkdir, (str(self.marker),))


def test_pt_files_load_safely_and_an_unsafe_one_needs_trust(tmp_path, monkeypatch, capsys):
    import torch

    monkeypatch.setenv("YOLO_CONFIG_DIR", str(tmp_path / "ultralytics"))
    monkeypatch.delenv(TRUST_PICKLE_ENV, raising=False)
    marker = tmp_path / "ran"
    evil = tmp_path / "evil.pt"
    torch.save({"model": _Evil(marker)}, evil)
    with pytest.raises(backends.BackendError, match=re.escape(
            f"--weights: {evil} cannot be loaded safely: it pickles posix.mkdir, which is outside "
            "ultralytics' allow-list of model classes, and loading it with Python's full unpickler "
            "runs code from the file; if you trust this file, pass --trust-pickle (or set "
            "RAINBENCH_TRUST_PICKLE=1)")):
        backends.load_detector(evil, device="cpu")
    assert not marker.exists()  # nothing from the file ran
    from ultralytics.nn import tasks

    seen = []
    real = tasks.torch_safe_load

    def spy(weight, safe_only=None):
        seen.append(safe_only)
        return real(weight, safe_only=safe_only)

    monkeypatch.setattr(tasks, "torch_safe_load", spy)
    detector = backends.load_detector(registry.WEIGHTS_DIR / "rainbench-yolo11n.pt", device="cpu")
    assert seen == [True] and detector.name == "rainbench-yolo11n"
    assert tasks.torch_safe_load is spy  # restored
    boxes, scores, ids = detector.predict([np.zeros((72, 96, 3), np.uint8)], imgsz=96, conf=0.5,
                                          iou=0.7, max_det=10)[0]
    assert boxes.shape[1] == 4
    capsys.readouterr()
    with pytest.raises(backends.BackendError, match="is not a loadable ultralytics checkpoint"):
        backends.load_detector(evil, device="cpu", trust_pickle=True)
    assert marker.exists()  # the trusted, unsafe path is the full unpickler
    assert (f"rainbench: warning: loading {evil} with Python's full unpickler (it pickles posix.mkdir; "
            "trusted by --trust-pickle): this runs code from the file") in capsys.readouterr().err.splitlines()
    marker.rmdir()
    monkeypatch.setenv("RAINBENCH_TRUST_PICKLE", "1")  # trusted by the environment: the warning says so
    with pytest.raises(backends.BackendError, match="is not a loadable ultralytics checkpoint"):
        backends.load_detector(evil, device="cpu")
    assert marker.exists()
    assert (f"rainbench: warning: loading {evil} with Python's full unpickler (it pickles posix.mkdir; "
            "trusted by RAINBENCH_TRUST_PICKLE=1): this runs code from the file") in capsys.readouterr().err.splitlines()


def test_render_threads_reach_the_one_worker_run_and_ray_tasks(tmp_path, monkeypatch):
    """--render-threads set LP_NUM_THREADS in pool workers only: a --workers 1 run (rendering in
    the command's own process) and Ray tasks ignored it."""
    monkeypatch.delenv("LP_NUM_THREADS", raising=False)
    seen = []
    real = ds.generate_shard

    def spy(task, out_dir, **kwargs):
        seen.append(os.environ.get("LP_NUM_THREADS"))
        return real(task, out_dir, **kwargs)

    monkeypatch.setattr(ds, "generate_shard", spy)
    ds.run_dataset(DatasetConfig(**{**SMALL, "scenes": 1}), tmp_path / "one", workers=1, render_threads=1)
    assert seen and set(seen) == {"1"} and "LP_NUM_THREADS" not in os.environ  # restored
    assert ds.ray_task_options(0, 3) == {"num_cpus": 1, "num_gpus": 0,
                                         "runtime_env": {"env_vars": {"LP_NUM_THREADS": "3"}}}
    assert ds.ray_task_options(4, None) == {"num_cpus": 1, "num_gpus": 0.25}


def test_scene_export_needs_no_display_with_mujoco_gl_glfw(tmp_path):
    """``rainbench scene`` renders nothing, yet refused MUJOCO_GL=glfw without a display ('needs a
    display'); MuJoCo imports with it, and the file is written."""
    env = {key: item for key, item in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    result = subprocess.run([sys.executable, "-m", "rainbench.cli", "scene", "--out", str(tmp_path / "scene"),
                             "--frames", "2", "--width", "16", "--height", "16"],
                            capture_output=True, text=True, timeout=300, env={**env, "MUJOCO_GL": "glfw"})
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "scene" / "scene.xml").is_file()
