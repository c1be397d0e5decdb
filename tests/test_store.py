"""The dataset layer (rainbench.store): one reader, one numbering, rates found by their decimal,
and an import that loads no renderer."""

import os
import re
import subprocess
import sys

import h5py
import numpy as np
import pytest
from labelled_shards import write_labelled_shard

from rainbench import store
from rainbench.store.labels import FrameLabels
from rainbench.store.manifest import write_manifest
from rainbench.store.rates import rate_decimal, rate_token
from rainbench.store.shard import ShardWriter, shard_name

ODD_RATES = (0.0, 0.1, 12.5, 100.0)


def _rate_shard(folder, rates=ODD_RATES, frames=2, scene_seed=0):
    """A shard whose image at rate row r, frame f is filled with 10 * r + f, and one car box per
    frame plus a person box on frame 1."""
    path = folder / shard_name(scene_seed, 0)
    folder.mkdir(parents=True, exist_ok=True)
    with ShardWriter(path, attrs={"class_names": '["person", "bicycle", "car", "motorcycle"]'},
                     rates=np.asarray(rates, np.float32), num_frames=frames, width=32, height=24,
                     K=np.eye(3), threads=1) as writer:
        for frame in range(frames):
            boxes = [[2, 2, 10, 12]] + ([[12, 4, 16, 20]] if frame == 1 else [])
            classes = [2] + ([0] if frame == 1 else [])
            count = len(boxes)
            labels = FrameLabels(bbox=np.asarray(boxes, np.float32), bbox_amodal=np.asarray(boxes, np.float32),
                                 class_id=np.asarray(classes, np.int32), instance_id=np.arange(count, dtype=np.int32),
                                 visible_fraction=np.ones(count, np.float32), truncation=np.zeros(count, np.float32))
            rgb = np.stack([np.full((24, 32, 3), 10 * row + frame, np.uint8) for row in range(len(rates))])
            writer.write_frame(frame, rgb, labels, np.eye(4))
        writer.commit()
    return path


def test_importing_the_dataset_layer_and_the_evaluator_loads_no_renderer_and_chooses_no_gl():
    code = (
        "import importlib, os, pkgutil, sys\n"
        "import rainbench, rainbench.store, rainbench.eval\n"
        "for package in (rainbench.store, rainbench.eval):\n"
        "    for module in pkgutil.walk_packages(package.__path__, package.__name__ + '.'):\n"
        "        if module.name not in ('rainbench.store.torch_dataset', 'rainbench.eval.backends.torch_batched'):\n"
        "            importlib.import_module(module.name)\n"
        "loaded = sorted({m.split('.')[0] for m in sys.modules} & {'mujoco', 'OpenGL', 'torch', 'ultralytics'})\n"
        "print(loaded, os.environ.get('MUJOCO_GL'), 'rainbench.gen' in sys.modules, 'rainbench.mjcf' in sys.modules)\n"
    )
    env = {key: value for key, value in os.environ.items() if key != "MUJOCO_GL"}
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert result.stdout.split("\n")[0] == "[] None False False"


def test_the_gl_backend_is_chosen_when_mujoco_is_first_needed():
    """The CLI, the configs and the packages choose nothing; the first module that builds scenes
    chooses the backend, then imports MuJoCo."""
    code = ("import os, sys\nimport rainbench.cli, rainbench.gen, rainbench.gen.config, rainbench.mjcf.layout\n"
            "before = (os.environ.get('MUJOCO_GL'), 'mujoco' in sys.modules)\n"
            "import rainbench.mjcf.scene\n"
            "print(*before, os.environ.get('MUJOCO_GL'), 'mujoco' in sys.modules)\n")
    env = {key: value for key, value in os.environ.items() if key != "MUJOCO_GL"}
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    before, loaded_before, chosen, loaded_after = result.stdout.split()
    assert (before, loaded_before, loaded_after) == ("None", "False", "True") and chosen in ("egl", "osmesa")


@pytest.mark.parametrize("written, row", [("0.1", 1), (0.1, 1), (np.float32(0.1), 1),
                                          (float(np.float32(0.1)), 1), ("12.50", 2), (12.5, 2),
                                          ("100", 3), (100, 3), ("0", 0), (0.0, 0)])
def test_a_rate_is_found_by_the_decimal_the_user_wrote(tmp_path, written, row):
    dataset = store.Dataset(_rate_shard(tmp_path))
    assert dataset.rates == ODD_RATES  # the stored float32 rates as their decimals
    assert dataset.rate_row(written) == row
    image = dataset.images[1]
    with dataset.open(0) as handle:
        assert dataset.read_rgb(handle, image, written)[0, 0, 0] == 10 * row + 1


def test_rate_decimals_and_tokens():
    assert [rate_token(rate) for rate in ("0.10", 0.1, np.float32(0.1), 12.5, "100")] == \
        ["0.1", "0.1", "0.1", "12.5", "100"]
    assert str(rate_decimal(float(np.float32(0.1)))) == "0.1"  # a float read back from float32
    assert str(rate_decimal(0.123456789)) == "0.123456789"  # not a float32 value: as written
    for bad in ("x", -1, float("nan"), None, True):
        with pytest.raises(ValueError, match="rate"):
            rate_decimal(bad)


def test_selected_rates_come_in_the_order_asked_and_missing_ones_name_the_shard(tmp_path):
    path = _rate_shard(tmp_path)
    dataset = store.Dataset(path, rates=["100", 0.1, "0.10"])
    assert dataset.rates == (100.0, 0.1)  # a repeat is dropped
    frames = list(dataset.frames())
    assert [[int(rgb[0, 0, 0]) for rgb in frame.rgb] for frame in frames] == [[30, 10], [31, 11]]
    with pytest.raises(store.DatasetError, match=r"^rate 25 mm/h is not in the dataset: "
                       r"scene000000_f00000\.h5 has no rate 25 mm/h \(it has 0, 0\.1, 12\.5, 100\)$"):
        store.Dataset(path, rates=[25])
    with pytest.raises(store.DatasetError, match=r"rates: expected at least one rate"):
        store.Dataset(path, rates=[])
    with pytest.raises(store.DatasetError, match=r"rate 50 mm/h is not among the selected rates \(100, 0\.1\)"):
        dataset.rate_row(50)


def test_frames_filter_classes_and_slice_rain_statistics_to_the_selected_rates(tmp_path):
    dataset = store.Dataset(_rate_shard(tmp_path), rates=[12.5])
    cars = [frame.labels for frame in dataset.frames(classes=[2])]
    assert [labels["class_id"].tolist() for labels in cars] == [[2], [2]]
    assert cars[1]["rain_coverage"].shape == (1, 1) and cars[0]["bbox"].tolist() == [[2, 2, 10, 12]]
    everyone = [frame.labels["class_id"].tolist() for frame in dataset.frames()]
    assert everyone == [[2], [2, 0]]


def test_one_shard_order_and_numbering_for_every_reader(tmp_path):
    """Manifest order (here not name order) decides the image ids of the reader, the numpy
    reader, and both exports."""
    root = tmp_path / "data"
    first = write_labelled_shard(root, [[(2, 0, (1, 1, 9, 9), 1.0, 0.0)]] * 2, scene_seed=5)
    second = write_labelled_shard(root, [[(0, 0, (2, 2, 8, 12), 1.0, 0.0)]] * 3, scene_seed=1)
    entries = [store.manifest.shard_entry(path, root, scene_seed=seed, frame_offset=0, frames=frames,
                                          rates=[0.0])
               for path, seed, frames in ((first, 5, 2), (second, 1, 3))]
    write_manifest(root, {"note": "test"}, entries, complete=True)
    dataset = store.Dataset(root)
    assert [(image.image_id, image.shard.name, image.frame) for image in dataset.images] == [
        (1, first.name, 0), (2, first.name, 1), (3, second.name, 0), (4, second.name, 1), (5, second.name, 2)]
    reader = store.ShardReader(root)
    assert [reader.sample(i)[1]["image_id"] for i in range(len(reader))] == [1, 2, 3, 4, 5]
    assert [reader.sample(i)[1]["labels"].tolist() for i in (1, 2)] == [[2], [0]]
    from rainbench.store.export import export_coco
    coco = export_coco(root, tmp_path / "coco", images=False)[0]
    import json
    images = json.loads(coco.read_text())["images"]
    assert [(record["id"], record["shard"], record["frame"]) for record in images] == [
        (1, first.name, 0), (2, first.name, 1), (3, second.name, 0), (4, second.name, 1), (5, second.name, 2)]
    # without the manifest, sorted names decide
    (root / store.MANIFEST).unlink()
    assert [image.shard.name for image in store.Dataset(root).images][:1] == [second.name]


def test_shards_with_other_rates_need_a_selection_every_shard_holds(tmp_path):
    root = tmp_path / "data"
    write_labelled_shard(root, [[]], scene_seed=0, rates=(0.0, 50.0))
    write_labelled_shard(root, [[]], scene_seed=1, rates=(0.0, 100.0))
    with pytest.raises(store.DatasetError, match="all shards of a dataset must share the same rates"):
        store.Dataset(root)
    assert store.Dataset(root, rates=["0"]).rates == (0.0,)
    with pytest.raises(store.DatasetError, match=r"rate 50 mm/h is not in the dataset: scene000001_f00000\.h5"):
        store.Dataset(root, rates=[0, 50])


ALLOWED_IMPORTS = {
    "store": set(), "rain": {"store"}, "mjcf": {"rain", "store"}, "gen": {"mjcf", "rain", "store"},
    "eval": {"store"}, "experiments": {"gen", "mjcf", "eval", "store"},
}
"""The import graph of docs/architecture.md: package -> the rainbench packages it may import
(``rainbench.gl``, ``rainbench.devices`` and ``__version__`` from the root are open to all)."""


def test_packages_import_only_what_docs_architecture_allows():
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    folders = {"store": "store", "rain": "rain", "mjcf": "mjcf", "gen": "gen", "eval": "eval",
               "experiments": "experiments"}
    seen = {}
    for package, folder in folders.items():
        used = set()
        for path in (root / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
                for name in names:
                    parts = name.split(".")
                    if parts[0] == "rainbench" and len(parts) > 1 and parts[1] in folders:
                        used.add(parts[1])
        seen[package] = used - {package}
    assert {package: sorted(used - ALLOWED_IMPORTS[package]) for package, used in seen.items()} == \
        {package: [] for package in folders}
    documented = {}
    for line in (root / "docs" / "architecture.md").read_text().splitlines():
        package, arrow, targets = line.partition(" -> ")
        if arrow and package.strip() in folders:
            documented[package.strip()] = {t.strip() for t in targets.split(",")} - {"(nothing)"}
    assert documented == ALLOWED_IMPORTS


# -- ignore regions ------------------------------------------------------------------------------

def _ignore_shard(folder):
    """Two frames: frame 0 a car label and a tiny person ignore region, frame 1 nothing."""
    return write_labelled_shard(folder, [[(2, 0, (10, 10, 40, 30), 1.0, 0.0)], []],
                                ignore=[[(0, 5, (60, 20, 63, 27))], []])


def test_ignore_regions_round_trip_and_older_shards_have_none(tmp_path):
    path = _ignore_shard(tmp_path / "new")
    with store.open_checked(path) as handle:
        regions = store.read_frame_ignore(handle, 0)
        assert regions["bbox"].tolist() == [[60, 20, 63, 27]] and regions["bbox"].dtype == np.float32
        assert regions["class_id"].tolist() == [0] and regions["instance_id"].tolist() == [5]
        assert all(len(array) == 0 for array in store.read_frame_ignore(handle, 1).values())
        assert store.read_frame_labels(handle, 0)["instance_id"].tolist() == [0]  # labels unchanged
    frames = list(store.Dataset([path]).frames())
    assert frames[0].ignore["instance_id"].tolist() == [5] and len(frames[1].ignore["bbox"]) == 0
    only_cars = next(store.Dataset([path]).frames(classes=[2]))  # a class filter filters both
    assert only_cars.labels["instance_id"].tolist() == [0] and len(only_cars.ignore["class_id"]) == 0
    with h5py.File(path, "r+") as handle:  # as written before ignore regions
        del handle["ignore"]
    with store.open_checked(path) as handle:
        regions = store.read_frame_ignore(handle, 0)
        assert regions["bbox"].shape == (0, 4) and regions["class_id"].shape == (0,)


@pytest.mark.parametrize("key, data, message", [
    ("offsets", np.array([0, 2, 1]), r"frame 1: /ignore/offsets decreases \(2 -> 1\)"),
    ("offsets", np.array([0, 1]), r"/ignore/offsets has shape \(2,\) int64; expected \(3,\) integers"),
    ("bbox", np.array([[60, 20, 120, 27]], np.float32),
     r"frame 0: ignore region 0 has bbox \[60\.0, 20\.0, 120\.0, 27\.0\], class_id 0, instance_id 5; "
     r"expected a finite box with 0 <= x1 < x2 <= 100, 0 <= y1 < y2 <= 80"),
    ("class_id", np.array([4], np.int32), r"frame 0: ignore region 0 .* class_id 4"),
    ("instance_id", np.array([5, 6], np.int32), r"/ignore/instance_id has shape \(2,\), expected \(1,\)"),
])
def test_readers_refuse_bad_ignore_regions_naming_file_and_frame(tmp_path, key, data, message):
    path = _ignore_shard(tmp_path / "bad")
    with h5py.File(path, "r+") as handle:
        del handle[f"ignore/{key}"]
        handle.create_dataset(f"ignore/{key}", data=data)
    with pytest.raises(store.ShardFormatError, match=re.escape(str(path)) + ": " + message):
        store.Dataset([path])


def test_preview_draws_ignore_regions_in_grey_under_the_labels():
    from rainbench.store.classes import CLASS_COLOURS
    from rainbench.store.preview import IGNORE_COLOUR, montage

    image = np.zeros((1, 80, 200, 3), np.uint8)  # clear of the rate printed at the top left
    sheet = montage(image, np.array([0.0]), tile_width=200, boxes=np.array([[20, 40, 40, 60]], np.float32),
                    class_ids=np.array([2]), ignore_boxes=np.array([[120, 40, 130, 55], [20, 40, 40, 60]], np.float32))
    assert tuple(sheet[40, 125]) == tuple(sheet[54, 125]) == tuple(sheet[47, 129]) == IGNORE_COLOUR  # its edges
    assert tuple(sheet[47, 125]) == (0, 0, 0)  # outlines only
    assert tuple(sheet[59, 30]) == CLASS_COLOURS[2]  # a label is drawn over a region on the same box
    with pytest.raises(ValueError, match=r"ignore_boxes: expected finite x1, y1, x2, y2, got \[nan"):
        montage(image, np.array([0.0]), ignore_boxes=np.array([[np.nan, 0, 5, 5]], np.float32))
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match=r"tile_width: expected a positive integer of pixels, got "):
            montage(image, np.array([0.0]), tile_width=bad)
    wide = np.zeros((1, 16, 8192, 3), np.uint8)  # a tile one pixel high, not none
    assert montage(wide, np.array([0.0]), tile_width=32).shape == (1, 32, 3)
    tall = np.zeros((4, 8192, 16, 3), np.uint8)  # 8192 px tiles would be 4 GB of sheet
    with pytest.raises(ValueError, match=r"tile_width: 8192 px tiles of 16x8192 images make a 32768x4194304 "
                                         r"sheet, over 134217728 pixels; choose narrower tiles"):
        montage(tall, np.zeros(4), tile_width=8192)


HDF5_FULL_DISK = ("Disable slist on flush dest failure failed (file write failed: time = Wed Nov 25 "
                  "23:34:39 2026\n, filename = '/d/.scene000000_f00000.h5.tmp-16123', file "
                  "descriptor = 4, errno = 28, error message = 'No space left on device', buf = "
                  "0x5605d4ee9b08, total write size = 1498, bytes this sub-write = 1498, offset = 8192)")


def test_a_full_disk_while_committing_is_one_line_naming_the_shard(tmp_path, monkeypatch):
    """HDF5 reports a failed write as a 300-character RuntimeError naming the temporary file
    (seen on a full tmpfs); the writer names the shard and the reason, and leaves nothing."""
    def full(self):
        raise RuntimeError(HDF5_FULL_DISK)

    monkeypatch.setattr(h5py.File, "flush", full)
    with pytest.raises(OSError, match=r"^.*/scene000000_f00000\.h5: No space left on device$") as info:
        _rate_shard(tmp_path / "d")
    assert info.value.errno == 28
    assert list((tmp_path / "d").iterdir()) == []


def test_other_runtime_errors_pass_the_shard_writer_unchanged(tmp_path, monkeypatch):
    def broken(self):
        raise RuntimeError("something else")

    monkeypatch.setattr(h5py.File, "flush", broken)
    with pytest.raises(RuntimeError, match="^something else$"):
        _rate_shard(tmp_path / "d")
    assert list((tmp_path / "d").iterdir()) == []


def _writeback_threads():
    import threading

    return [t for t in threading.enumerate() if t.name == "rainbench-shard-writeback"]


@pytest.mark.parametrize("commit", [True, False])
def test_the_shard_is_handed_to_the_disk_while_written_and_the_thread_ends_with_it(
        tmp_path, monkeypatch, commit):
    """While frames are written a thread fdatasyncs the temporary file (so commit's fsync waits
    for little); committing or abandoning the shard stops it and closes its descriptor."""
    import threading

    from rainbench.store import shard as shard_module

    synced = []
    synced_once = threading.Event()
    real_fdatasync = os.fdatasync

    def fdatasync(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        synced_once.set()
        real_fdatasync(fd)

    monkeypatch.setattr(shard_module, "WRITEBACK_INTERVAL_S", 0.01)
    monkeypatch.setattr(shard_module.os, "fdatasync", fdatasync)
    path = tmp_path / shard_name(0, 0)
    labels = FrameLabels(bbox=np.zeros((0, 4), np.float32), bbox_amodal=np.zeros((0, 4), np.float32),
                         class_id=np.zeros(0, np.int32), instance_id=np.zeros(0, np.int32),
                         visible_fraction=np.zeros(0, np.float32), truncation=np.zeros(0, np.float32))
    with ShardWriter(path, attrs={"class_names": '["person", "bicycle", "car", "motorcycle"]'},
                     rates=np.zeros(1, np.float32), num_frames=1, width=32, height=24,
                     K=np.eye(3), threads=1) as writer:
        assert len(_writeback_threads()) == 1
        fd = writer._writeback._fd
        shard_file = os.fstat(fd)
        writer.write_frame(0, np.zeros((1, 24, 32, 3), np.uint8), labels, np.eye(4))
        assert synced_once.wait(5.0)
        if commit:
            writer.commit()
    assert _writeback_threads() == []
    try:  # its descriptor is closed, or reused for another file
        still_open = os.path.samestat(os.fstat(fd), shard_file)
    except OSError:
        still_open = False
    assert not still_open
    assert synced and all(name.startswith(str(tmp_path / ".")) and ".tmp-" in name for name in synced)
    assert path.is_file() == commit and len(list(tmp_path.iterdir())) == int(commit)


def test_rgb_chunks_are_zlib_streams_that_stdlib_zlib_and_plain_h5py_read(tmp_path):
    """The writer deflates each image itself (ISA-L's igzip): the stored chunk must be exactly
    what HDF5's gzip filter would store, so any HDF5 reader decodes it."""
    import zlib

    from rainbench.store.shard import read_rgb

    rng = np.random.default_rng(3)
    rates = (0.0, 50.0)
    gradient = np.arange(24 * 32 * 3, dtype=np.uint32).reshape(24, 32, 3) % 256
    images = np.stack([gradient.astype(np.uint8),
                       rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)])
    path = tmp_path / shard_name(0, 0)
    labels = FrameLabels(bbox=np.zeros((0, 4), np.float32), bbox_amodal=np.zeros((0, 4), np.float32),
                         class_id=np.zeros(0, np.int32), instance_id=np.zeros(0, np.int32),
                         visible_fraction=np.zeros(0, np.float32), truncation=np.zeros(0, np.float32))
    with ShardWriter(path, attrs={"class_names": '["person", "bicycle", "car", "motorcycle"]'},
                     rates=np.asarray(rates, np.float32), num_frames=1, width=32, height=24,
                     K=np.eye(3), threads=2) as writer:
        writer.write_frame(0, images, labels, np.eye(4))
        writer.commit()
    with h5py.File(path, "r") as handle:
        rgb = handle["rgb"]
        assert rgb.compression == "gzip" and rgb.chunks == (1, 1, 24, 32, 3)
        for row in range(len(rates)):
            filter_mask, chunk = rgb.id.read_direct_chunk((row, 0, 0, 0, 0))
            assert filter_mask == 0
            assert zlib.decompress(chunk) == images[row].tobytes()
            np.testing.assert_array_equal(rgb[row, 0], images[row])  # HDF5's own gzip filter
            np.testing.assert_array_equal(read_rgb(handle, row, 0), images[row])
        # the gradient repeats itself: deflated, not stored
        assert rgb.id.get_chunk_info_by_coord((0, 0, 0, 0, 0)).size < images[0].nbytes // 4
