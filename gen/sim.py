"""Stepping the scene: kinematic actor motion applied to a compiled model, advanced by ``mj_step``.

Every moving unit is a mocap body following its planned straight-line path (see
:func:`rainbench.mjcf.layout.unit_position`); people's limbs are hinge joints driven by a walking
gait (or the riding pose). Between frames the simulation advances with ``mj_step`` at the model
timestep, with the kinematic targets written before every step; before a frame is rendered the
exact state at the frame time is written and ``mj_forward`` recomputes every pose.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from rainbench.mjcf import layout as L
from rainbench.mjcf import parts
from rainbench.mjcf.scene import ACTOR_PREFIX


class ActorDriver:
    """Writes the layout's motion at time ``t`` into ``data`` (mocap poses and limb angles)."""

    def __init__(self, model: mujoco.MjModel, layout: L.Layout) -> None:
        self._layout = layout
        self._ego_mocap = int(model.body("ego").mocapid[0])
        self._unit_mocap = np.array(
            [int(model.body(unit.name).mocapid[0]) for unit in layout.units], dtype=np.int64
        )
        # Per person actor: (unit index, qpos addresses of PERSON_JOINTS, riding?)
        self._people: list[tuple[int, np.ndarray, bool]] = []
        for actor in layout.actors:
            if actor.class_id != L.PERSON:
                continue
            prefix = ACTOR_PREFIX.format(actor.instance_id)
            addresses = np.array(
                [int(model.joint(prefix + joint).qposadr[0]) for joint in parts.PERSON_JOINTS]
            )
            self._people.append((actor.unit, addresses, actor.role == "rider"))
        self._riding = np.array([parts.RIDING_POSE[j] for j in parts.PERSON_JOINTS])

    def apply(self, data: mujoco.MjData, t: float) -> None:
        layout = self._layout
        ego_xy = L.unit_position(layout.ego, t)
        data.mocap_pos[self._ego_mocap] = [ego_xy[0], ego_xy[1], 0.0]
        data.mocap_quat[self._ego_mocap] = [1.0, 0.0, 0.0, 0.0]
        for unit, mocap_id in zip(layout.units, self._unit_mocap):
            xy = L.unit_position(unit, t)
            z = L.ground_height(float(xy[1])) if unit.kind == "pedestrian" else 0.0
            data.mocap_pos[mocap_id] = [xy[0], xy[1], z]
            data.mocap_quat[mocap_id] = parts.unit_yaw_quat(unit.heading)
        for unit_index, addresses, riding in self._people:
            if riding:
                data.qpos[addresses] = self._riding
                continue
            unit = layout.units[unit_index]
            phase = 2 * math.pi * L.unit_distance(unit, t) / unit.stride_length
            pose = parts.walking_pose(phase)
            data.qpos[addresses] = [pose[j] for j in parts.PERSON_JOINTS]
        data.qvel[:] = 0.0


def advance(model: mujoco.MjModel, data: mujoco.MjData, driver: ActorDriver,
            t_from: float, t_to: float) -> None:
    """Step the physics from ``t_from`` to ``t_to`` with ``mj_step``, then pose exactly at ``t_to``."""
    steps = max(0, int(round((t_to - t_from) / model.opt.timestep)))
    for step in range(steps):
        driver.apply(data, t_from + step * model.opt.timestep)
        mujoco.mj_step(model, data)
    driver.apply(data, t_to)
    data.time = t_to
    mujoco.mj_forward(model, data)
