"""The scene's state at a time is its kinematic targets: stepping there and posing there agree
(gen/sim.py), so a piece of a clip starts at its first frame without stepping from 0 s."""

import numpy as np
import pytest

from rainbench.gl import mujoco
from rainbench.gen import sim
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene, render_clip
from rainbench.mjcf import layout as L
from rainbench.mjcf import parts

SMALL = dict(width=96, height=72, rates=(0.0,), rain_model="jeon2022")


@pytest.mark.parametrize("name", list(L.LAYOUTS))
def test_stepping_to_a_time_poses_the_scene_as_posing_it_there(name):
    """Every joint is a person's driven limb or a bicycle's cranks, and 6 s stepped at 50 Hz from
    0 s leave every body and geom exactly (bit for bit) where ``advance(t, t)`` puts them."""
    setup = build_scene(GenerateConfig(frames=60, seed=4, layout=name, **SMALL))
    model, driver = setup.model, sim.ActorDriver(setup.model, setup.layout)
    people = sum(actor.class_id == L.PERSON for actor in setup.layout.actors)
    bicycles = sum(actor.role == "bicycle" for actor in setup.layout.actors)
    assert model.njnt == people * len(parts.PERSON_JOINTS) + bicycles > 0
    stepped, posed = mujoco.MjData(model), mujoco.MjData(model)
    previous = 0.0
    for frame in range(1, 61):
        sim.advance(model, stepped, driver, previous, frame / 10)
        previous = frame / 10
    sim.advance(model, posed, driver, 6.0, 6.0)
    for field in ("qpos", "xpos", "xquat", "geom_xpos", "geom_xmat", "mocap_pos", "cam_xpos"):
        assert np.array_equal(getattr(stepped, field), getattr(posed, field)), field


def test_a_piece_steps_only_between_its_own_frames(monkeypatch):
    """A piece from clip frame 150 steps 5 times (0.1 s at the 0.02 s timestep) between each of
    its frames and not at all before its first (it stepped 750 times to get there before)."""
    steps = []
    step = mujoco.mj_step
    monkeypatch.setattr(mujoco, "mj_step", lambda model, data: steps.append(1) or step(model, data))
    config = GenerateConfig(frames=3, frame_offset=150, seed=4, layout="street", **SMALL)
    frames = [frame.rgb.copy() for _, frame, _ in render_clip(config)]
    assert len(frames) == 3 and len(steps) == 2 * 5


def test_cyclists_pedal_with_the_distance_ridden_and_motorcyclists_sit_still():
    """The cranks turn once per PEDAL_DEVELOPMENT_M ridden and the rider's legs follow them;
    a motorcyclist's legs stay on the pegs."""
    setup = build_scene(GenerateConfig(frames=200, seed=0, layout="street", **SMALL))
    model, layout = setup.model, setup.layout
    driver, data = sim.ActorDriver(model, layout), mujoco.MjData(model)
    bicycle = next(actor for actor in layout.actors if actor.role == "bicycle")
    rider = next(actor for actor in layout.actors if actor.role == "rider" and actor.unit == bicycle.unit)
    moto_rider = next(actor for actor in layout.actors if actor.role == "rider"
                      and layout.units[actor.unit].kind == "motorcycle")
    unit = layout.units[bicycle.unit]
    crank = model.joint(f"actor{bicycle.instance_id:03d}/crank").qposadr[0]

    def knees(actor):
        return [data.qpos[model.joint(f"actor{actor.instance_id:03d}/knee_{tag}").qposadr[0]] for tag in "lr"]

    seen, moto_seen = set(), set()
    for t in (2.0, 2.1, 2.2, 2.3):
        sim.advance(model, data, driver, t, t)
        distance = L.unit_distance(unit, t)
        assert 0.0 < distance < unit.max_distance
        expected = (2 * np.pi * distance / parts.PEDAL_DEVELOPMENT_M) % (2 * np.pi)
        assert data.qpos[crank] == pytest.approx(expected, abs=1e-9)
        pose = parts.riding_pose(unit.style, unit.build, expected)
        assert knees(rider) == pytest.approx([pose["knee_l"], pose["knee_r"]], abs=1e-12)
        seen.add(tuple(np.round(knees(rider), 6)))
        moto_seen.add(tuple(np.round(knees(moto_rider), 6)))
    assert len(seen) == 4 and len(moto_seen) == 1


def test_walkers_step_onto_the_curb_over_a_step_not_in_one_frame():
    """A crossing walker's body rose the curb's 0.15 m between two frames (a scene audit); it now
    rises with the ground averaged over CURB_STEP_S of its walk: at most 0.06 m a frame at 10
    frames/s, the ground's own height wherever it is level around the walker."""
    layout = L.sample_layout(21, GenerateConfig(seed=21, layout="street").scenario_config(),
                             np.random.default_rng(21))
    times = np.arange(0.0, 20.0, 0.1)
    crossed = 0
    for unit in layout.units:
        if unit.kind != "pedestrian":
            continue
        ground = L.ground_heights(layout, L.unit_position(unit, times))
        body = sim.walker_height(layout, unit, times)
        if np.abs(np.diff(ground)).max() == pytest.approx(0.15):  # this one steps onto a curb
            crossed += 1
            assert np.abs(np.diff(body)).max() <= 0.06 + 1e-9
        # level around it (the ground the same over the whole window): exactly the ground
        window = np.stack([L.ground_heights(layout, L.unit_position(unit, times + offset))
                           for offset in np.linspace(-sim.CURB_STEP_S / 2, sim.CURB_STEP_S / 2, 5)])
        level = (window == window[0]).all(axis=0)
        assert level.any() and np.array_equal(body[level], ground[level])
    assert crossed > 0
