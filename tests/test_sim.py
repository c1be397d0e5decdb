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
    """Every joint is a person's driven limb, and 6 s stepped at 50 Hz from 0 s leave every
    body and geom exactly (bit for bit) where ``advance(t, t)`` puts them."""
    setup = build_scene(GenerateConfig(frames=60, seed=4, layout=name, **SMALL))
    model, driver = setup.model, sim.ActorDriver(setup.model, setup.layout)
    people = sum(actor.class_id == L.PERSON for actor in setup.layout.actors)
    assert model.njnt == people * len(parts.PERSON_JOINTS) > 0
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
