"""The generator end to end on small clips: shards, determinism, variation, classes, motion."""

import hashlib
import json
import math
import re
import threading
import time

import h5py
from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np
import pytest

from rainbench.gen import labels as lb
from rainbench.gen import sim
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene, frame_labels, generate_shard, render_clip
from rainbench.gen.render import FrameRenderer
from rainbench.store.labels import FrameLabels
from rainbench.store.shard import (ShardFormatError, ShardWriter, open_checked, open_shard, read_frame_ignore,
                                   read_frame_labels)
from rainbench.mjcf import layout as L
from rainbench.mjcf.scene import build_spec, export_scene

SMALL = dict(frames=6, width=160, height=120, store=("depth", "instance"))


def _digest(path):
    with h5py.File(path, "r") as f:
        digest = hashlib.sha256()
        for key in ("rgb", "depth", "instance", "labels/bbox", "labels/class_id",
                    "labels/visible_fraction", "labels/truncation", "camera/T_world_cam",
                    "ignore/bbox", "ignore/instance_id"):
            digest.update(f[key][()].tobytes())
        return digest.hexdigest()


@pytest.fixture(scope="module")
def small_shard(tmp_path_factory):
    out = tmp_path_factory.mktemp("shard")
    return generate_shard(GenerateConfig(seed=5, frame_offset=60, **SMALL), out)


def test_shard_layout_follows_format_v2(small_shard):
    with open_shard(small_shard) as f:
        assert f.attrs["format"] == "rainbench.shard" and f.attrs["format_version"] == 2
        assert f.attrs["sky"] in ("clear", "cloudy", "overcast")
        assert not f.attrs["weather_follows_rate"]  # jeon2022's default: the paper's method
        assert f["weather/rain_mm_h"][()].tolist() == [0.0]
        # an unwritten chunk reads as sky and no actor, not as depth 0 and actor 0
        assert (f["depth"].fillvalue, f["instance"].fillvalue) == (np.inf, -1)
        assert json.loads(f.attrs["class_names"]) == ["person", "bicycle", "car", "motorcycle",
                                                      "airplane", "bus", "train", "truck"]
        assert f.attrs["layout"] in L.LAYOUTS and f.attrs["time_of_day"] in ("day", "dusk", "night")
        assert f.attrs["scene_seed"] == 5 and f.attrs["frame_offset"] == 60
        assert json.loads(f.attrs["config"])["width"] == 160
        assert f["rgb"].shape == (1, 6, 120, 160, 3) and f["rgb"].dtype == np.uint8
        assert f["rates"][()].tolist() == [0.0]
        assert f["depth"].shape == (6, 120, 160) and f["instance"].dtype == np.int32
        assert f["camera/K"].shape == (3, 3) and f["camera/T_world_cam"].shape == (6, 4, 4)
        offsets = f["labels/offsets"][()]
        assert offsets[0] == 0 and offsets[-1] == f["labels/bbox"].shape[0] > 0
        assert f["rain/ssim"][()].min() == 1.0 and np.isinf(f["rain/psnr"][()]).all()
        assert f["labels/rain_coverage"].shape == (1, offsets[-1])


def test_every_box_is_the_tight_box_of_its_instance_pixels(small_shard):
    """Checked against the pixels themselves (np.nonzero), not against lb.tight_boxes, the
    function the generator uses: pixel-edge xyxy, x2 and y2 one past the last pixel."""
    checked = 0
    with open_shard(small_shard) as f:
        instance = f["instance"][()]
        for frame in range(instance.shape[0]):
            labels = read_frame_labels(f, frame)
            for box, instance_id in zip(labels["bbox"], labels["instance_id"]):
                rows, cols = np.nonzero(instance[frame] == instance_id)
                np.testing.assert_array_equal(box, [cols.min(), rows.min(), cols.max() + 1, rows.max() + 1])
                checked += 1
    assert checked > 0


def test_every_visible_actor_is_a_label_or_an_ignore_region(small_shard):
    regions_seen = 0
    with open_shard(small_shard) as f:
        instance = f["instance"][()]
        for frame in range(instance.shape[0]):
            labels, regions = read_frame_labels(f, frame), read_frame_ignore(f, frame)
            counts, boxes = lb.tight_boxes(instance[frame], 64)
            labelled, ignored = set(labels["instance_id"].tolist()), set(regions["instance_id"].tolist())
            assert not labelled & ignored
            assert labelled | ignored == set(np.flatnonzero(counts).tolist())
            for box, instance_id in zip(regions["bbox"], regions["instance_id"]):
                seen = boxes[instance_id]  # the region encloses the actor's visible pixels
                assert box[0] <= seen[0] and box[1] <= seen[1] and box[2] >= seen[2] and box[3] >= seen[3]
            regions_seen += len(ignored)
    assert regions_seen > 0  # at 160x120 some actors are too small to label


def test_ego_moves_forward_and_camera_looks_along_x(small_shard):
    with open_shard(small_shard) as f:
        poses = f["camera/T_world_cam"][()]
    steps = np.diff(poses[:, 0, 3])
    assert (steps > 0.5).all()  # 7..10 m/s at 10 frames/s
    # optical axis along x, tilted up by the camera rig's pitch; image y is down
    layout = L.sample_layout(5, GenerateConfig(seed=5, frame_offset=60, **SMALL).scenario_config(),
                             np.random.default_rng(5))
    pitch = math.radians(layout.camera_pitch_deg)
    if layout.name != "curved":  # the other layouts drive straight along x
        np.testing.assert_allclose(poses[0, :3, 2], [math.cos(pitch), 0, math.sin(pitch)],
                                   atol=1e-9)
        np.testing.assert_allclose(poses[0, :3, 1], [math.sin(pitch), 0, -math.cos(pitch)],
                                   atol=1e-9)


def test_same_seed_same_bytes_other_seed_differs(tmp_path, small_shard):
    again = generate_shard(GenerateConfig(seed=5, frame_offset=60, **SMALL), tmp_path / "a")
    assert _digest(again) == _digest(small_shard)
    other = generate_shard(GenerateConfig(seed=6, frame_offset=60, **SMALL), tmp_path / "b")
    assert _digest(other) != _digest(small_shard)
    with h5py.File(small_shard) as f1, h5py.File(other) as f2:
        assert np.abs(f1["rgb"][0, 0].astype(int) - f2["rgb"][0, 0].astype(int)).mean() > 5


def test_default_clip_shows_all_four_classes():
    """The paper's 200-frame clip of seed 0; labels only, at 320x240 (boxes at 800x600 are
    2.5x larger, so anything labelled here is labelled there)."""
    config = GenerateConfig(width=320, height=240, layout="street", time_of_day="day")
    setup = build_scene(config)
    data = mujoco.MjData(setup.model)
    driver = sim.ActorDriver(setup.model, setup.layout)
    seen = np.zeros(4, int)
    with FrameRenderer(setup.model, 320, 240, setup.geom_instance) as renderer:
        previous = 0.0
        for frame in range(0, 200, 2):
            sim.advance(setup.model, data, driver, previous, frame / 10)
            previous = frame / 10
            renderer.update(data)
            visible, _ = renderer.render_instances()
            labels = frame_labels(renderer, data, visible, setup.class_of_instance,
                                  config.label_filter)
            seen += np.bincount(labels.class_id, minlength=8)[:4]
    assert (seen > 0).all(), f"labels per class (person, bicycle, car, motorcycle): {seen}"
    counts = [sum(a.class_id == c for a in setup.layout.actors) for c in range(4)]
    assert counts == [8 + 3, 2, 6, 1]  # 8 pedestrians + 3 riders (labelled as person, COCO)


def _rectangles_overlap(a, b) -> bool:
    """Whether two convex polygons ((4, 2) corners each) overlap: separating axes."""
    for corners in (a, b):
        for edge in (corners[1] - corners[0], corners[3] - corners[0]):
            axis = np.array([-edge[1], edge[0]])
            pa, pb = a @ axis, b @ axis
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_actors_never_interpenetrate(seed):
    """Units never overlap during the clip (3D, from MuJoCo's geometry): each unit's geoms
    bounded in the unit's own frame (units turn only about z), compared as oriented boxes."""
    config = GenerateConfig(seed=seed, width=64, height=48)
    setup = build_scene(config)
    model, data = setup.model, mujoco.MjData(setup.model)
    driver = sim.ActorDriver(model, setup.layout)
    unit_of_geom = np.array([model.body(model.geom_bodyid[g]).rootid[0] for g in range(model.ngeom)])
    actor_geoms = np.flatnonzero(setup.geom_instance >= 0)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    previous = 0.0
    for t in np.arange(0.0, 20.0, 0.25):
        sim.advance(model, data, driver, previous, t)
        previous = t
        boxes = {}
        for g in actor_geoms:
            unit = unit_of_geom[g]
            rotation = data.geom_xmat[g].reshape(3, 3)
            corners = data.geom_xpos[g] + (model.geom_aabb[g, :3] + signs * model.geom_aabb[g, 3:]) \
                @ rotation.T
            root = data.xmat[unit].reshape(3, 3)
            local = (corners - data.xpos[unit]) @ root  # in the unit's frame
            lo, hi = local.min(axis=0), local.max(axis=0)
            if unit in boxes:
                boxes[unit] = (np.minimum(boxes[unit][0], lo), np.maximum(boxes[unit][1], hi))
            else:
                boxes[unit] = (lo, hi)
        footprints = {}
        for unit, (lo, hi) in boxes.items():
            root = data.xmat[unit].reshape(3, 3)
            square = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
            footprints[unit] = (square @ root[:2, :2].T + data.xpos[unit][:2],
                                lo[2] + data.xpos[unit][2], hi[2] + data.xpos[unit][2])
        units = sorted(boxes)
        for i, a in enumerate(units):
            for b in units[i + 1:]:
                (poly_a, z0a, z1a), (poly_b, z0b, z1b) = footprints[a], footprints[b]
                overlap = z0a < z1b and z0b < z1a and _rectangles_overlap(poly_a, poly_b)
                assert not overlap, f"seed {seed}: units {a} and {b} overlap at t={t}"


def test_people_walk_with_moving_limbs():
    setup = build_scene(GenerateConfig(seed=0, width=64, height=48))
    model, data = setup.model, mujoco.MjData(setup.model)
    driver = sim.ActorDriver(model, setup.layout)
    walker = next(a for a in setup.layout.actors if a.role == "pedestrian"
                  and setup.layout.units[a.unit].start_time == 0.0)
    hip = model.joint(f"actor{walker.instance_id:03d}/hip_l").qposadr[0]
    angles = []
    for t in (5.0, 5.3, 5.6):
        sim.advance(model, data, driver, 0.0, t)
        angles.append(data.qpos[hip])
    assert np.ptp(angles) > 0.1


def test_layouts_vary_with_seed():
    config = L.ScenarioConfig()
    a = L.sample_layout(1, config, np.random.default_rng(1))
    b = L.sample_layout(2, config, np.random.default_rng(2))
    assert a.units[0].start_xy != b.units[0].start_xy and a.sun_direction != b.sun_direction
    assert L.sample_layout(1, config, np.random.default_rng(1)) == a


def test_scene_export_loads_standalone(tmp_path):
    layout = L.sample_layout(3, L.ScenarioConfig(), np.random.default_rng(3))
    path = export_scene(build_spec(layout, 800, 600), tmp_path)
    model = mujoco.MjModel.from_xml_path(str(path))
    assert model.camera("ego").id >= 0
    assert (tmp_path / "asphalt.png").stat().st_size > 1000
    assert model.ngeom > 300


def test_writer_leaves_no_file_when_aborted(tmp_path):
    path = tmp_path / "x.h5"
    with pytest.raises(RuntimeError, match="boom"):
        with ShardWriter(path, attrs={}, rates=np.zeros(1), num_frames=2, width=16, height=16,
                         K=np.eye(3)):
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with ShardWriter(path, attrs={}, rates=np.zeros(1), num_frames=2, width=16, height=16,
                     K=np.eye(3)) as writer:
        with pytest.raises(RuntimeError, match=r"frames \[0, 1\] were never written"):
            writer.commit()
    assert list(tmp_path.iterdir()) == []


def test_writer_takes_the_images_of_a_frame_as_one_array_or_one_per_rate(tmp_path):
    """A list of (H, W, 3) images, one per rate, is stored as the (R, H, W, 3) array is: the
    same file bytes."""
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (2, 3, 16, 16, 3), dtype=np.uint8)  # (frames, rates, H, W, 3)
    labels = FrameLabels(bbox=np.zeros((0, 4), np.float32), bbox_amodal=np.zeros((0, 4), np.float32),
                         class_id=np.zeros(0, np.int32), instance_id=np.zeros(0, np.int32),
                         visible_fraction=np.zeros(0, np.float32), truncation=np.zeros(0, np.float32))
    digests = []
    for name, as_list in (("array.h5", False), ("list.h5", True)):
        with ShardWriter(tmp_path / name, attrs={}, rates=np.array([0.0, 10.0, 20.0]),
                         num_frames=2, width=16, height=16, K=np.eye(3), threads=2) as writer:
            for frame in range(2):
                rgb = list(images[frame]) if as_list else images[frame]
                writer.write_frame(frame, rgb, labels, np.eye(4))
            digests.append(hashlib.sha256(writer.commit().read_bytes()).hexdigest())
    assert digests[0] == digests[1]
    with ShardWriter(tmp_path / "bad.h5", attrs={}, rates=np.array([0.0, 10.0]), num_frames=1,
                     width=16, height=16, K=np.eye(3)) as writer:
        with pytest.raises(ValueError, match="rgb_by_rate: expected 2 images of"):
            writer.write_frame(0, [images[0, 0]], labels, np.eye(4))
        with pytest.raises(ValueError, match="rgb_by_rate: expected 2 images of"):
            writer.write_frame(0, [images[0, 0], images[0, 1, :8]], labels, np.eye(4))


def test_frames_in_flight_keep_the_bytes_the_order_and_the_bound(tmp_path, monkeypatch):
    """Several frames rained at once: the shard's bytes are those of a serial run, frames are
    written in order, no more than ``frames_in_flight`` frames are rained at once, and a frame
    whose rain fails leaves no shard behind."""
    from rainbench.gen import generate as gen_module

    config = GenerateConfig(seed=5, frame_offset=60, frames=6, width=96, height=72)
    serial = hashlib.sha256(generate_shard(config, tmp_path / "serial", threads=1).read_bytes())

    rain_for_frame, written = gen_module._rain_for_frame, []
    running, most_running, frames_ahead, lock = [0], [0], [], threading.Lock()

    def counted_rain(config, frame, K, global_frame, *args):
        with lock:
            running[0] += 1
            most_running[0] = max(most_running[0], running[0])
        try:
            # even frames finish after the odd frames rendered after them (a frame renders in
            # ~0.15 s here), and unbounded rendering would run 4 frames ahead
            time.sleep(0.8 if global_frame % 2 == 0 else 0.0)
            return rain_for_frame(config, frame, K, global_frame, *args)
        finally:
            with lock:
                running[0] -= 1

    write_frame = ShardWriter.write_frame

    def ordered_write(self, index, *args, **kwargs):
        written.append(index)
        return write_frame(self, index, *args, **kwargs)

    def watched_clip(*args, **kwargs):
        for index, frame, renderer in render_clip(*args, **kwargs):
            with lock:
                frames_ahead.append(index - len(written))  # rendered and not yet written
            yield index, frame, renderer

    monkeypatch.setattr(gen_module, "_rain_for_frame", counted_rain)
    monkeypatch.setattr(gen_module, "render_clip", watched_clip)
    monkeypatch.setattr(ShardWriter, "write_frame", ordered_write)
    pipelined = generate_shard(config, tmp_path / "pipelined", threads=4, frames_in_flight=3)
    assert hashlib.sha256(pipelined.read_bytes()).hexdigest() == serial.hexdigest()
    assert written == list(range(6))
    assert 1 <= most_running[0] <= 3
    # frame i is rendered only once frame i - 4 is written: at most 3 frames held besides it
    assert max(frames_ahead) <= 3

    def failing_rain(config, frame, K, global_frame, *args):
        if global_frame == 62:
            raise RuntimeError("rain of frame 62 failed")
        return rain_for_frame(config, frame, K, global_frame, *args)

    monkeypatch.setattr(gen_module, "_rain_for_frame", failing_rain)
    with pytest.raises(RuntimeError, match="rain of frame 62 failed"):
        generate_shard(config, tmp_path / "failed", threads=4, frames_in_flight=3)
    assert list((tmp_path / "failed").iterdir()) == []


def test_weather_images_finished_off_the_render_thread_keep_the_bytes(tmp_path, monkeypatch):
    """``physical`` with the weather following the rate at night (wet road, puddles, the lamps'
    mirror images and glow): each re-render's array work is left to the pool's threads
    (PendingImage) while the next frames render, and the shard's bytes are the serial run's, also
    when a frame's images are finished only after later frames have changed the renderer's
    weather and the scene's state."""
    from rainbench.gen import generate as gen_module
    from rainbench.gen import render as render_module

    config = GenerateConfig(seed=5, frame_offset=60, frames=4, width=96, height=72,
                            rates=(0.0, 25.0, 100.0), rain_model="physical", sky="overcast",
                            time_of_day="night")
    assert config.follows_rate
    result, finished_in = render_module.PendingImage.result, []

    def watched_result(self):
        if self._image is None:  # work left: record the thread that does it
            finished_in.append(threading.current_thread().name)
        return result(self)

    monkeypatch.setattr(render_module.PendingImage, "result", watched_result)
    serial = hashlib.sha256(generate_shard(config, tmp_path / "serial", threads=1).read_bytes())
    assert finished_in and set(finished_in) == {threading.main_thread().name}
    finished_in.clear()
    rain_for_frame = gen_module._rain_for_frame

    def late_rain(config, frame, K, global_frame, *args):
        # frame 60's images are finished after frames 61 and 62 have rendered (0.15 s each here)
        time.sleep(0.8 if global_frame == 60 else 0.0)
        return rain_for_frame(config, frame, K, global_frame, *args)

    monkeypatch.setattr(gen_module, "_rain_for_frame", late_rain)
    # each rainy rate's camera response runs in the pool too, off the frame's own thread (which
    # gives the clean image its night noise first)
    from rainbench.rain import weather as wx

    response, responded_in = wx.camera_response, []

    def watched_response(*args):
        responded_in.append(threading.current_thread().name)
        return response(*args)

    monkeypatch.setattr(wx, "camera_response", watched_response)
    pipelined = generate_shard(config, tmp_path / "pipelined", threads=4, frames_in_flight=3)
    assert hashlib.sha256(pipelined.read_bytes()).hexdigest() == serial.hexdigest()
    assert finished_in and all(name.startswith("rainbench-rate") for name in finished_in)
    assert sorted(name.split("_")[0] for name in responded_in) == ["rainbench-frame"] * 4 + ["rainbench-rate"] * 8


def test_frames_in_flight_default_and_bad_values(tmp_path):
    from rainbench.gen.generate import default_frames_in_flight

    assert [default_frames_in_flight(n) for n in (1, 2, 11, 12, 16, 32, 64)] == [1, 2, 2, 3, 4, 8, 8]
    config = GenerateConfig(seed=5, frames=1, width=32, height=24)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="frames_in_flight: expected an integer >= 1, got"):
            generate_shard(config, tmp_path, threads=2, frames_in_flight=bad)


def test_depth_is_rendered_only_where_it_is_used():
    """jeon2022 under a fixed weather reads no depth back; the physical model, weather that
    follows the rate (spray) and stored depth do. Without it the frame is otherwise the same."""
    assert not GenerateConfig(frames=1).needs_depth
    assert not GenerateConfig(frames=1, store=("instance",)).needs_depth
    assert GenerateConfig(frames=1, store=("depth",)).needs_depth
    assert GenerateConfig(frames=1, rain_model="physical").needs_depth
    assert GenerateConfig(frames=1, rain_model="physical", weather_follows_rate=False).needs_depth
    assert GenerateConfig(frames=1, weather_follows_rate=True).needs_depth
    config = GenerateConfig(seed=5, frames=2, width=160, height=120)
    setup = build_scene(config)
    with_depth = list(frame.__dict__ for _, frame, _ in render_clip(config, setup))
    without = list(frame.__dict__ for _, frame, _ in render_clip(config, setup, depth=False))
    for full, lean in zip(with_depth, without):
        assert full["depth"].shape == (120, 160) and lean["depth"] is None
        assert np.array_equal(full["rgb"], lean["rgb"])
        assert np.array_equal(full["instance"], lean["instance"])
        assert full["labels"].bbox.tobytes() == lean["labels"].bbox.tobytes()
        assert full["labels"].visible_fraction.tobytes() == lean["labels"].visible_fraction.tobytes()


def _delete(key):
    def edit(f):
        del f[key]
    return edit


def _set_attr(key, value):
    def edit(f):
        f.attrs[key] = value
    return edit


def _scale(key, factor=None, value=None, at=(0, 0)):
    def edit(f):
        data = f[key][()]
        data[at] = value if value is not None else data[at] * factor
        del f[key]
        f.create_dataset(key, data=data)
    return edit


# Found by a format audit: each edit passed `verify` and every reader (its manifest rehashed),
# and the COCO export wrote rain_coverage 0.0 for every box of a shard without it.
BAD_SHARDS = {
    "no rain_coverage": (_delete("labels/rain_coverage"), r"incomplete shard, /labels/rain_coverage is missing"),
    "no contrast_loss": (_delete("labels/contrast_loss"), r"incomplete shard, /labels/contrast_loss is missing"),
    "no ssim": (_delete("rain/ssim"), r"incomplete shard, /rain/ssim is missing"),
    "no drop_count": (_delete("rain/drop_count"), r"incomplete shard, /rain/drop_count is missing"),
    "no poses": (_delete("camera/T_world_cam"), r"incomplete shard, /camera/T_world_cam is missing"),
    "no format_version": (lambda f: f.attrs.__delitem__("format_version"), r"no format_version attribute; this rainbench reads versions 1, 2"),
    "version as text": (_set_attr("format_version", "2"), r"unknown format_version '2' \(not an integer\)"),
    "version 1.7": (_set_attr("format_version", 1.7), r"unknown format_version 1.7 \(not an integer\)"),
    "height as text": (_set_attr("height", "120"), r"attribute height is '120'; expected a positive integer of pixels"),
    "sky purple": (_set_attr("sky", "purple"), r"attribute sky is 'purple'; expected one of clear, cloudy, overcast"),
    "layout moon": (_set_attr("layout", "moon"), r"attribute layout is 'moon'; expected one of street, intersection, curved, highway, residential"),
    "time noon": (_set_attr("time_of_day", "noon"), r"attribute time_of_day is 'noon'; expected one of day, dusk, night"),
    "rain model": (_set_attr("rain_model", "bogus"), r"attribute rain_model is 'bogus'; expected one of jeon2022, physical"),
    "fps negative": (_set_attr("fps", -3.0), r"attribute fps is -3.0; expected a positive number"),
    "config not json": (_set_attr("config", "{not json"), r"attribute config is not a JSON object"),
    "follows as text": (_set_attr("weather_follows_rate", "yes"), r"attribute weather_follows_rate is 'yes'; expected a bool"),
    "ssim nan": (_scale("rain/ssim", value=np.nan, at=(1, 1)), r"frame 1: /rain/ssim holds an SSIM outside \[-1, 1\]"),
    "psnr negative": (_scale("rain/psnr", value=-1.0, at=(1, 0)), r"frame 0: /rain/psnr holds a PSNR that is NaN or negative"),
    "drops negative": (_scale("rain/drop_count", value=-4, at=(1, 1)), r"frame 1: /rain/drop_count holds a negative drop count"),
    "pose nan": (_scale("camera/T_world_cam", value=np.nan, at=(1, 0, 3)), r"frame 1: /camera/T_world_cam holds a non-finite pose"),
    "coverage 5": (_scale("labels/rain_coverage", value=5.0, at=(1, 0)), r"frame 0: label 0 has rain_coverage outside \[0, 1\]"),
    "weather nan": (_scale("weather/gain", value=np.nan, at=(0,)), r"/weather/gain is not 2 finite numbers \(one per rate\)"),
}


@pytest.fixture(scope="module")
def rainy_shard(tmp_path_factory):
    """Two frames at 0 and 50 mm/h with labels in frame 0."""
    out = tmp_path_factory.mktemp("rainy")
    return generate_shard(GenerateConfig(seed=5, frame_offset=60, frames=2, width=160, height=120,
                                         rates=(0.0, 50.0)), out)


@pytest.mark.parametrize("case", BAD_SHARDS)
def test_a_shard_missing_or_out_of_range_data_is_refused_naming_the_file(tmp_path, rainy_shard, case):
    edit, message = BAD_SHARDS[case]
    bad = tmp_path / "bad.h5"
    bad.write_bytes(rainy_shard.read_bytes())
    open_checked(bad).close()  # the unedited copy reads
    with h5py.File(bad, "a") as f:
        edit(f)
    with pytest.raises(ShardFormatError, match=rf"^{re.escape(str(bad))}: {message}"):
        open_checked(bad).close()


def test_the_format_vocabularies_are_the_generator_s():
    from rainbench.mjcf.layout import LAYOUTS
    from rainbench.rain.config import RAIN_MODELS
    from rainbench.rain.weather import SKIES, TIMES_OF_DAY
    from rainbench.store import shard

    assert (shard.RAIN_MODEL_VALUES, shard.SKY_VALUES, shard.TIME_OF_DAY_VALUES, shard.LAYOUT_VALUES) == (
        tuple(RAIN_MODELS), tuple(SKIES), tuple(TIMES_OF_DAY), tuple(LAYOUTS))


def test_open_shard_rejects_bad_files(tmp_path, small_shard):
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(ShardFormatError, match="junk.h5: not a readable HDF5 shard"):
        open_shard(junk)
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(small_shard.read_bytes()[:5000])
    with pytest.raises(ShardFormatError, match="truncated.h5"):
        open_shard(truncated)
    future = tmp_path / "future.h5"
    future.write_bytes(small_shard.read_bytes())
    with h5py.File(future, "a") as f:
        f.attrs["format_version"] = 3
    with pytest.raises(ShardFormatError, match="unknown format_version 3"):
        open_shard(future)


def test_the_gl_backend_attribute_is_the_backend_mujoco_reads(monkeypatch):
    """``MUJOCO_GL=EGL`` (MuJoCo ignores case and spaces) was recorded as 'EGL', so shards of the
    same backend looked like two backends to a per-backend comparison."""
    from rainbench.gen.generate import shard_attrs

    config = GenerateConfig(frames=2, width=32, height=24)
    monkeypatch.setenv("MUJOCO_GL", " EGL ")
    layout = L.sample_layout(config.seed, config.scenario_config(), np.random.default_rng(config.seed))
    assert shard_attrs(config, layout)["gl_backend"] == "egl"
