"""Datasets: manifest, resume after crashes, verify, worker-count independence, Ray, readers."""

import dataclasses
import io
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from labelled_shards import write_labelled_shard
from rainbench import ShardDataset, cli, store
from rainbench.gen import dataset as ds
from rainbench.gen.config import DatasetConfig
from rainbench.store.reader import ShardReader
from rainbench.store.shard import ShardFormatError, ShardWriter, read_frame_labels, read_rgb

SMALL = dict(scenes=2, frames=4, frames_per_shard=2, width=96, height=72, rates=(0.0, 50.0))


def _hashes(root):
    manifest = json.loads((Path(root) / store.MANIFEST).read_text())
    return [(entry["path"], entry["sha256"]) for entry in manifest["shards"]]


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    ds.run_dataset(DatasetConfig(**SMALL), root, workers=1)
    return root


def test_manifest_lists_every_shard_in_order(dataset_dir):
    manifest = json.loads((dataset_dir / store.MANIFEST).read_text())
    assert manifest["complete"] is True and manifest["config"]["scenes"] == 2
    assert [(e["scene_seed"], e["frame_offset"], e["frames"]) for e in manifest["shards"]] == [
        (0, 0, 2), (0, 2, 2), (1, 0, 2), (1, 2, 2)]
    for entry in manifest["shards"]:
        assert entry["bytes"] == (dataset_dir / entry["path"]).stat().st_size
        assert entry["rates"] == [0.0, 50.0] and len(entry["sha256"]) == 64
    ids = [image.image_id for image in store.Dataset(dataset_dir).images]
    assert ids == list(range(1, 9))


def test_walk_opens_each_shard_once_and_closes_it(dataset_dir):
    dataset = store.Dataset(dataset_dir)
    index = [(image.image_id, image.shard, image.frame) for image in dataset.images]
    seen, handles = [], {}
    for image, handle in dataset.walk():
        image_id, path, frame = image.image_id, image.shard, image.frame
        seen.append((image_id, path, frame))
        handles.setdefault(path, []).append(handle)
        assert Path(handle.filename) == path and handle.id.valid
    assert seen == index
    assert all(len({id(h) for h in per_shard}) == 1 for per_shard in handles.values())
    assert len(handles) == 4 and not any(h[0].id.valid for h in handles.values())


def test_split_shards_continue_one_clip(dataset_dir, tmp_path):
    """Frames 2..3 of scene 0 equal frames 2..3 of the same scene rendered as one shard."""
    whole = dict(SMALL, scenes=1, frames_per_shard=4)
    ds.run_dataset(DatasetConfig(**whole), tmp_path, workers=1)
    with h5py.File(tmp_path / "scene000000_f00000.h5") as one, \
            h5py.File(dataset_dir / "scene000000_f00002.h5") as part:
        np.testing.assert_array_equal(one["rgb"][:, 2:4], part["rgb"][()])
        np.testing.assert_array_equal(one["camera/T_world_cam"][2:4], part["camera/T_world_cam"][()])


def test_part_of_a_clip_is_that_clip_s_frames(dataset_dir, tmp_path):
    """first_frame=1, frames=2, clip_frames=4: frames 1..2 of scene 0's 4-frame clip, byte for
    byte (the layout is planned for the whole clip), in a dataset that verifies."""
    part = dict(SMALL, scenes=1, frames=2, first_frame=1, clip_frames=4)
    ds.run_dataset(DatasetConfig(**part), tmp_path, workers=1)
    assert [p.name for p in sorted(tmp_path.glob("*.h5"))] == ["scene000000_f00001.h5"]
    assert store.verify_dataset(tmp_path) == []
    with h5py.File(tmp_path / "scene000000_f00001.h5") as got, \
            h5py.File(dataset_dir / "scene000000_f00000.h5") as first, \
            h5py.File(dataset_dir / "scene000000_f00002.h5") as second:
        np.testing.assert_array_equal(got["rgb"][:, 0], first["rgb"][:, 1])
        np.testing.assert_array_equal(got["rgb"][:, 1], second["rgb"][:, 0])
        assert got.attrs["time_of_day"] == first.attrs["time_of_day"]


def test_worker_and_thread_counts_give_the_same_bytes(dataset_dir, tmp_path):
    # dataset_dir: 1 worker with the default threads (one per core, frames pipelined)
    ds.run_dataset(DatasetConfig(**SMALL), tmp_path / "two", workers=2, threads=1)
    assert _hashes(tmp_path / "two") == _hashes(dataset_dir)
    ds.run_dataset(DatasetConfig(**SMALL), tmp_path / "serial", workers=1, threads=1)
    assert _hashes(tmp_path / "serial") == _hashes(dataset_dir)
    with pytest.raises(ds.DatasetError, match="THREADS: expected an integer >= 1, got 0"):
        ds.run_dataset(DatasetConfig(**SMALL), tmp_path / "bad", threads=0)


PIECES = dict(scenes=1, frames=16, fps=2.0, width=96, height=72, rates=(0.0, 50.0), rain_model="physical",
              store=("depth", "instance"))  # one 16-frame shard: two pieces of 8 frames


@pytest.fixture(scope="module")
def one_worker_shard(tmp_path_factory):
    root = tmp_path_factory.mktemp("pieces")
    ds.run_dataset(DatasetConfig(**PIECES), root, workers=1)
    return root


def test_one_shard_rendered_in_pieces_by_several_workers_is_the_same_file(one_worker_shard, tmp_path):
    """More workers than shards: the one shard is rendered in two pieces by two workers and
    joined; the file (`physical` rain with re-rendered weather, stored depth and instance maps)
    is byte for byte the one worker's, and no piece is left behind."""
    ds.run_dataset(DatasetConfig(**PIECES), tmp_path, workers=3)
    assert _hashes(tmp_path) == _hashes(one_worker_shard)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["manifest.json", "scene000000_f00000.h5"]


def test_piece_configs_split_a_shard_into_runs_of_its_clip():
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import MIN_PIECE_FRAMES, piece_configs

    assert MIN_PIECE_FRAMES == 8
    shard = GenerateConfig(frames=25, frame_offset=100)  # the clip ends with the shard: 125 frames
    runs = [(c.frame_offset, c.frames, c.clip_frames) for c in piece_configs(shard, 3)]
    assert runs == [(100, 9, 125), (109, 8, 125), (117, 8, 125)]
    assert [c.frames for c in piece_configs(shard, 8)] == [9, 8, 8]  # at least 8 frames a piece
    assert [c.frames for c in piece_configs(GenerateConfig(frames=7), 4)] == [7]
    assert piece_configs(shard, 1) == [shard]  # unchanged: its shard is the same file
    with pytest.raises(ValueError, match="pieces: expected an integer >= 1, got 0"):
        piece_configs(shard, 0)


def test_assembler_refuses_pieces_out_of_order_and_an_unfinished_shard(tmp_path):
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import ShardAssembler, generate_shard, piece_configs

    shard = GenerateConfig(frames=16, fps=2.0, width=96, height=72)
    first, second = (generate_shard(piece, tmp_path / "pieces", threads=1) for piece in piece_configs(shard, 2))
    with ShardAssembler(shard, tmp_path / "out") as assembler:
        with pytest.raises(ValueError, match=r"scene000000_f00008\.h5: expected a piece of "
                                             r"scene000000_f00000\.h5 from clip frame 0 .* got 8 frames from 8"):
            assembler.add(second)
        other_rain = generate_shard(dataclasses.replace(piece_configs(shard, 2)[0], rain_seed=1), tmp_path / "other")
        with pytest.raises(ValueError, match=r"expected a piece of scene000000_f00000\.h5 from clip frame 0"):
            assembler.add(other_rain)  # the right frames of another config
        assembler.add(first)
        with pytest.raises(RuntimeError, match="shard scene000000_f00000.h5: 8 of 16 frames were added"):
            assembler.commit()
    assert list((tmp_path / "out").iterdir()) == []  # leaving without commit removes the temporary file


def test_a_failure_while_joining_pieces_leaves_no_shard_and_no_pieces(tmp_path, monkeypatch):
    from rainbench.gen.generate import ShardAssembler

    def disk_full(self, piece):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ShardAssembler, "add", disk_full)
    with pytest.raises(OSError, match="No space left on device"):
        ds.run_dataset(DatasetConfig(**dict(PIECES, rain_model="jeon2022", store=())), tmp_path, workers=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # a fresh run that finished nothing
    monkeypatch.undo()

    def interrupt(frames):  # Ctrl-C once the workers have rendered a frame
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ds.run_dataset(DatasetConfig(**dict(PIECES, rain_model="jeon2022", store=())), tmp_path, workers=2,
                       progress=interrupt)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # workers stopped, pieces removed
    (tmp_path / ".pieces.tmp-99999").mkdir()  # a folder of pieces left by kill -9
    (tmp_path / ".pieces.tmp-99999" / "scene000000_f00008.h5").write_bytes(b"piece")
    ds._remove_temporaries(tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow  # Ray's local start, 18-23 s; make test runs the Ray executor against a cluster
def test_ray_executor_on_a_local_cluster(dataset_dir, tmp_path):  # by address (test_hardening.py)
    import ray  # the ray extra, installed by the Makefile
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        ds.run_dataset(DatasetConfig(**SMALL), tmp_path, executor="ray")
    finally:
        ray.shutdown()
    assert _hashes(tmp_path) == _hashes(dataset_dir)


def test_resume_after_an_interrupted_run(dataset_dir, tmp_path):
    frames_done = []

    def crash(n):
        frames_done.append(n)
        if sum(frames_done) == 3:  # in the middle of the second shard
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ds.run_dataset(DatasetConfig(**SMALL), tmp_path, workers=1, progress=crash)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["manifest.json", "scene000000_f00000.h5"]  # nothing partial, no temp file
    assert json.loads((tmp_path / store.MANIFEST).read_text())["complete"] is False
    (tmp_path / ".scene000000_f00002.h5.tmp-99999").write_bytes(b"left by kill -9")
    # the resumed run's bar starts at the kept shard's frames: its rate counts rendered frames
    # only (they arrived as progress at once and read as thousands of frames a second)
    rendered = []
    with tqdm(total=8, file=io.StringIO()) as bar:
        ds.run_dataset(DatasetConfig(**SMALL), tmp_path, workers=1,
                       progress=lambda n: (rendered.append(n), bar.update(n)), kept=ds.start_bar_at(bar))
        assert (bar.initial, bar.n, sum(rendered)) == (2, 8, 6)
    assert _hashes(tmp_path) == _hashes(dataset_dir)
    assert not list(tmp_path.glob(".*tmp*"))
    done = []  # without ``kept`` the kept frames go to progress, in one call before any rendering
    ds.run_dataset(DatasetConfig(**SMALL), tmp_path, workers=1, progress=done.append)
    assert done == [8]


def test_kill_9_mid_run_then_resume(tmp_path):
    out = tmp_path / "killed"
    argv = [sys.executable, "-m", "rainbench.cli", "generate", "--out", str(out), "--scenes", "3",
            "--frames", "6", "--frames-per-shard", "2", "--width", "96", "--height", "72",
            "--workers", "1", "--quiet"]
    process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not (out / store.MANIFEST).exists() and time.time() < deadline and process.poll() is None:
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    listed = {e["path"] for e in json.loads((out / store.MANIFEST).read_text())["shards"]}
    for shard in out.glob("scene*.h5"):  # every shard under a final name is complete
        with h5py.File(shard) as handle:
            assert handle["labels/offsets"].shape == (3,)
    assert subprocess.run(argv, capture_output=True).returncode == 0
    assert store.verify_dataset(out) == []
    assert len(json.loads((out / store.MANIFEST).read_text())["shards"]) == 9 >= len(listed)


def test_other_config_is_refused_unless_overwrite(dataset_dir, tmp_path, capsys):
    ds.run_dataset(DatasetConfig(**SMALL), tmp_path, workers=1)
    other = dict(SMALL, rates=(0.0,))
    with pytest.raises(ds.DatasetError, match="holds a dataset of another config"):
        ds.run_dataset(DatasetConfig(**other), tmp_path, workers=1)
    ds.run_dataset(DatasetConfig(**other), tmp_path, workers=1, overwrite=True)
    assert store.verify_dataset(tmp_path) == []
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    (stranger / "notes.txt").write_text("mine")
    code = cli.main(["generate", "--out", str(stranger), "--frames", "2", "--width", "96",
                     "--height", "72", "--quiet"])
    assert code == 2 and "is not empty and has no manifest" in capsys.readouterr().err
    assert sorted(p.name for p in stranger.iterdir()) == ["notes.txt"]


def test_write_error_is_a_clear_error_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    def disk_full(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ShardWriter, "write_frame", disk_full)
    code = cli.main(["generate", "--out", str(tmp_path), "--frames", "2", "--width", "96",
                     "--height", "72", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "No space left on device" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_verify_names_flipped_and_truncated_files(dataset_dir, tmp_path, capsys):
    copy = tmp_path / "copy"
    copy.mkdir()
    for path in dataset_dir.iterdir():
        (copy / path.name).write_bytes(path.read_bytes())
    assert cli.main(["verify", str(copy)]) == 0
    flipped = copy / "scene000000_f00002.h5"
    data = bytearray(flipped.read_bytes())
    data[len(data) // 2] ^= 0xFF
    flipped.write_bytes(bytes(data))
    truncated = copy / "scene000001_f00000.h5"
    truncated.write_bytes(truncated.read_bytes()[:4000])
    capsys.readouterr()
    assert cli.main(["verify", str(copy)]) == 1
    err = capsys.readouterr().err
    assert "scene000000_f00002.h5: sha256 differs" in err
    assert "scene000001_f00000.h5: 4000 bytes" in err
    assert "scene000000_f00000.h5" not in err


def test_shard_dataset_through_a_two_worker_dataloader(dataset_dir):
    dataset = ShardDataset(dataset_dir)
    assert len(dataset) == 8 * 2 and dataset.rates == (0.0, 50.0)
    loader = DataLoader(dataset, batch_size=3, num_workers=2, collate_fn=ShardDataset.collate_fn)
    seen = []
    with h5py.File(dataset_dir / "scene000001_f00002.h5") as check:
        expected_boxes = read_frame_labels(check, 1)["bbox"]
        expected_rgb = check["rgb"][1, 1]
    for images, targets in loader:
        for image, target in zip(images, targets):
            assert image.dtype == torch.uint8 and image.shape == (3, 72, 96)
            assert target["boxes"].dtype == torch.float32 and target["labels"].dtype == torch.int64
            seen.append((target["image_id"], float(target["rate"])))
            if target["shard"] == "scene000001_f00002.h5" and target["frame"] == 1 \
                    and float(target["rate"]) == 50.0:
                np.testing.assert_array_equal(target["boxes"].numpy(), expected_boxes)
                np.testing.assert_array_equal(image.permute(1, 2, 0).numpy(), expected_rgb)
    assert sorted(seen) == sorted((i, r) for i in range(1, 9) for r in (0.0, 50.0))


@pytest.mark.parametrize("workers", [0, 2])
def test_collate_fn_views_equal_every_sample(dataset_dir, workers):
    """The batch packing (one block per key, views per sample) changes no value."""
    reader = ShardReader(dataset_dir)
    expected = {}
    for index in range(len(reader)):
        image, target = reader.sample(index)
        expected[(target["image_id"], float(target["rate"]))] = (image, target)
    loader = DataLoader(ShardDataset(dataset_dir), batch_size=5, num_workers=workers,
                        collate_fn=ShardDataset.collate_fn)
    count = 0
    for images, targets in loader:
        for image, target in zip(images, targets):
            want_image, want = expected[(target["image_id"], float(target["rate"]))]
            np.testing.assert_array_equal(image.permute(1, 2, 0).numpy(), want_image)
            assert target["rate"].shape == () and target["shard"] == want["shard"]
            for key in ("boxes", "labels", "instance_id", "visible_fraction", "truncation"):
                assert target[key].dtype == torch.from_numpy(want[key]).dtype
                np.testing.assert_array_equal(target[key].numpy(), want[key])
            count += 1
    assert count == len(reader)


def test_reader_filters_and_rate_selection(dataset_dir):
    everything = ShardReader(dataset_dir, rates=[50])
    cars_only = ShardReader(dataset_dir, rates=[50], classes=[2], min_visible_fraction=0.5)
    assert len(everything) == 8
    for index in range(8):
        _, all_target = everything.sample(index)
        _, target = cars_only.sample(index)
        assert float(target["rate"]) == 50.0
        keep = (all_target["labels"] == 2) & (all_target["visible_fraction"] >= 0.5)
        np.testing.assert_array_equal(target["boxes"], all_target["boxes"][keep])
    with pytest.raises(ds.DatasetError, match="has no rate 30 mm/h"):
        ShardReader(dataset_dir, rates=[30])


def test_reader_names_corrupt_and_future_shards(dataset_dir, tmp_path):
    bad = tmp_path / "scene000000_f00000.h5"
    bad.write_bytes((dataset_dir / "scene000000_f00000.h5").read_bytes()[:3000])
    with pytest.raises(ValueError, match="scene000000_f00000.h5: not a readable HDF5 shard"):
        ShardDataset(bad)
    future = tmp_path / "scene000000_f00002.h5"
    future.write_bytes((dataset_dir / "scene000000_f00002.h5").read_bytes())
    with h5py.File(future, "a") as handle:
        handle.attrs["format_version"] = 9
    with pytest.raises(ValueError, match="scene000000_f00002.h5: unknown format_version 9"):
        ShardDataset([future])


def test_read_rgb_equals_h5py_and_names_a_corrupt_chunk(dataset_dir, tmp_path):
    shard = dataset_dir / "scene000000_f00000.h5"
    with h5py.File(shard, "r") as handle:
        for rate_row, frame in ((0, 0), (1, 1)):
            image = read_rgb(handle, rate_row, frame)
            assert image.shape == handle["rgb"].shape[2:] and image.dtype == np.uint8
            np.testing.assert_array_equal(image, handle["rgb"][rate_row, frame])
        info = handle["rgb"].id.get_chunk_info_by_coord((1, 1, 0, 0, 0))
        with pytest.raises(IndexError, match=r"/rgb\[2, 0\] is outside its 2 rates x 2 frames"):
            read_rgb(handle, 2, 0)
    copy = tmp_path / shard.name
    data = bytearray(shard.read_bytes())
    for offset in range(info.byte_offset + 100, info.byte_offset + 120):
        data[offset] ^= 0xFF
    copy.write_bytes(bytes(data))
    reader = ShardReader(copy, rates=None)
    reader.sample(0)  # other chunks still read
    with pytest.raises(ShardFormatError, match=r"scene000000_f00000.h5: /rgb chunk of rate row 1, "
                                               r"frame 1 is corrupt"):
        reader.sample(len(reader.rates) + 1)  # frame 1, rate row 1


def _pairs(batch):
    return tuple(zip(*batch))


@pytest.mark.parametrize("workers", [0, 2])
def test_items_hold_tensors_in_dataloader_workers_too(dataset_dir, workers):
    """A worker's item held numpy targets (the main process's held tensors): code that worked
    with num_workers=0 failed on target["boxes"].to(device) with workers, or with any collate."""
    loader = DataLoader(ShardDataset(dataset_dir), batch_size=3, num_workers=workers, collate_fn=_pairs)
    images, targets = next(iter(loader))
    for target in targets:
        for key in ("boxes", "labels", "instance_id", "visible_fraction", "truncation", "rate"):
            assert isinstance(target[key], torch.Tensor), (key, type(target[key]))
        assert target["boxes"].shape[1:] == (4,) and target["rate"].shape == ()
        assert isinstance(target["image_id"], int) and isinstance(target["shard"], str)
        # one storage per target: from a worker it crosses as one shared-memory segment and one
        # open file, not six (with a plain collate, held batches ran out of file handles)
        keys = ("boxes", "labels", "instance_id", "visible_fraction", "truncation", "rate")
        assert len({target[key].untyped_storage().data_ptr() for key in keys}) == 1
    assert all(isinstance(image, torch.Tensor) and image.shape == (3, 72, 96) for image in images)
    reader = ShardReader(dataset_dir)
    for target in targets:  # and the values are the reader's
        index = next(i for i in range(len(reader)) if reader.sample(i)[1]["image_id"] == target["image_id"]
                     and reader.sample(i)[1]["rate"] == float(target["rate"]))
        want = reader.sample(index)[1]
        for key in ("boxes", "labels", "instance_id", "visible_fraction", "truncation"):
            assert target[key].dtype == torch.from_numpy(want[key]).dtype
            np.testing.assert_array_equal(target[key].numpy(), want[key])


def test_at_most_max_open_shards_stay_open(dataset_dir, monkeypatch):
    """Every shard read stayed open in every process: a shuffled epoch over a few thousand shards
    ran out of file handles (and the error called a healthy shard unreadable)."""
    monkeypatch.setattr(store.dataset, "MAX_OPEN_SHARDS", 2)
    reader = ShardReader(dataset_dir)
    fresh = ShardReader(dataset_dir)
    order = list(range(len(reader)))[::-1] + list(range(len(reader)))
    for index in order:
        image, target = reader.sample(index)
        assert len(reader.dataset._handles) <= 2
        assert all(handle.id.valid for handle in reader.dataset._handles.values())
        want_image, want = fresh.sample(index)
        np.testing.assert_array_equal(image, want_image)
        np.testing.assert_array_equal(target["boxes"], want["boxes"])
    reader.close()


def test_a_file_that_cannot_be_opened_for_lack_of_handles_is_not_called_corrupt(dataset_dir, monkeypatch):
    import errno

    shard = dataset_dir / "scene000000_f00000.h5"

    def refuse(*args, **kwargs):
        raise OSError(errno.EMFILE, "Unable to synchronously open file (errno = 24, error message = "
                                    "'Too many open files')")

    monkeypatch.setattr(h5py, "File", refuse)
    for open_it in (store.open_shard, store.Dataset, ShardDataset):  # and every reader built on them
        with pytest.raises(OSError, match=f"^{shard}: Too many open files$") as info:
            open_it(shard)
        assert not isinstance(info.value, ShardFormatError) and info.value.errno == errno.EMFILE


@pytest.mark.parametrize("options, message", [
    ({"classes": [4]}, r"^classes: unknown class 4; expected names or ids of person \(0\)"),
    ({"classes": [2.7]}, r"^classes: unknown class 2.7;"),
    ({"classes": []}, r"^classes: expected at least one class, got \[\]"),
    ({"classes": 2}, r"^classes: expected a list of class names or ids, got 2$"),
    ({"classes": "car"}, r"^classes: expected a list of class names or ids, got 'car'$"),
    ({"min_visible_fraction": 25}, r"^min_visible_fraction: expected a fraction in \[0, 1\], got 25$"),
    ({"min_visible_fraction": float("nan")}, r"^min_visible_fraction: expected a fraction in \[0, 1\], got nan$"),
])
def test_reader_filters_are_checked(dataset_dir, options, message):
    """A class id the shards never hold, a float id or a percentage dropped every label silently."""
    with pytest.raises(store.DatasetError, match=message):
        ShardDataset(dataset_dir, **options)


def test_reader_filters_take_class_names(dataset_dir):
    by_name = ShardReader(dataset_dir, rates=[50], classes=["car", "person"])
    by_id = ShardReader(dataset_dir, rates=[50], classes=[2, 0])
    assert by_name.classes.tolist() == [0, 2]
    for index in range(len(by_id)):
        np.testing.assert_array_equal(by_name.sample(index)[1]["labels"], by_id.sample(index)[1]["labels"])


def test_reader_refuses_an_unfinished_dataset_unless_allowed(dataset_dir, tmp_path):
    """A dataset still being generated (or cut off) was read as if whole, without a word."""
    partial = tmp_path / "partial"
    partial.mkdir()
    manifest = json.loads((dataset_dir / store.MANIFEST).read_text())
    first = manifest["shards"][0]
    (partial / first["path"]).write_bytes((dataset_dir / first["path"]).read_bytes())
    manifest.update(complete=False, shards=[first])
    (partial / store.MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(store.DatasetError, match=f"^{partial} is an incomplete dataset \\(its manifest lists 1 "
                                                 "finished shards .*allow_incomplete=True"):
        ShardDataset(partial)
    with pytest.warns(UserWarning, match="is incomplete: reading its 1 finished shards only"):
        dataset = ShardDataset(partial, allow_incomplete=True)
    assert len(dataset) == first["frames"] * 2


def test_reader_indexes_like_a_sequence(dataset_dir):
    reader = ShardReader(dataset_dir)
    last = reader.sample(len(reader) - 1)
    for index in (-1, np.int64(len(reader) - 1), torch.tensor(len(reader) - 1)):
        image, target = reader.sample(index)
        np.testing.assert_array_equal(image, last[0])
        assert (target["image_id"], target["rate"]) == (last[1]["image_id"], last[1]["rate"])
    with pytest.raises(IndexError, match=f"sample index {-len(reader) - 1} out of range 0..{len(reader) - 1}"):
        reader.sample(-len(reader) - 1)
    with pytest.raises(TypeError, match=r"^sample index: expected an integer, got 2.0$"):
        reader.sample(2.0)


def test_other_tools_folders_in_out_neither_block_generate_nor_warn_in_verify(dataset_dir, tmp_path, capsys):
    """`make scene` (data/scene_paper) or `make paper` (data/paper/<rain model>) left folders in
    the default OUT: `make dataset` then refused it as 'not empty', and `make verify` warned about
    every shard of the paper's datasets."""
    out = tmp_path / "data"
    (out / "scene_paper").mkdir(parents=True)
    (out / "scene_paper" / "scene.xml").write_text("<mujoco/>")
    other = out / "paper" / "jeon2022"
    shutil.copytree(dataset_dir, other)
    ds.run_dataset(DatasetConfig(**SMALL), out, workers=1)
    assert store.verify_dataset(out) == [] and store.unlisted_shards(out) == []
    assert cli.main(["verify", str(out)]) == 0
    assert "warning" not in capsys.readouterr().err
    stray = out / "old" / "scene000009_f00000.h5"  # a shard in a folder that is no dataset: still named
    stray.parent.mkdir()
    stray.write_bytes(b"x")
    assert store.unlisted_shards(out) == [stray]


LABELLED = [[(2, 0, (10, 12, 40, 50), 1.0, 0.0), (0, 1, (60, 5, 70, 30), 0.3, 0.1)],
            [(2, 0, (12, 12, 42, 50), 0.4, 0.0), (3, 2, (70, 40, 98, 79), 0.9, 0.2)]]


def test_reader_serves_the_written_labels_and_filters_them(tmp_path):
    """The rendered fixtures above hold no label at 96x72 (every actor is an ignore region
    there), so the readers' boxes and filters are checked here on known labels: xyxy as written,
    the class and visibility filters removing what they should."""
    write_labelled_shard(tmp_path, LABELLED, rates=(0.0, 50.0))
    reader = ShardReader(tmp_path, rates=[50])
    cars = ShardReader(tmp_path, rates=[50], classes=[2], min_visible_fraction=0.5)
    for frame, labels in enumerate(LABELLED):
        _, target = reader.sample(frame)
        np.testing.assert_array_equal(target["boxes"], [box for _, _, box, _, _ in labels])
        assert target["labels"].tolist() == [c for c, *_ in labels]
        np.testing.assert_allclose(target["visible_fraction"], [v for *_, v, _ in labels])
        kept = [box for c, _, box, v, _ in labels if c == 2 and v >= 0.5]
        np.testing.assert_array_equal(cars.sample(frame)[1]["boxes"].reshape(-1, 4), np.reshape(kept, (-1, 4)))
    assert [len(cars.sample(f)[1]["boxes"]) for f in (0, 1)] == [1, 0]
    _, target = ShardDataset(tmp_path, rates=[50])[1]
    assert torch.equal(target["boxes"], torch.tensor([[12, 12, 42, 50], [70, 40, 98, 79]], dtype=torch.float32))
