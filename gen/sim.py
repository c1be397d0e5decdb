"""Stepping the scene: kinematic actor motion applied to a compiled model, advanced by ``mj_step``.

Every moving unit is a mocap body following its planned path of straights and arcs (see
:func:`rainbench.mjcf.layout.unit_pose`), turning with it; people's limbs are hinge joints driven by each walker's
gait, a standing sway for people who stand (before they start or after they arrive), the riding
pose of the rider's bicycle or motorcycle style, and the raised arm of umbrella carriers. Between frames the simulation advances with ``mj_step`` at the model
timestep, with the kinematic targets written before every step; before a frame is rendered the
exact state at the frame time is written and ``mj_forward`` recomputes every pose.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from rainbench.mjcf import layout as L
from rainbench.mjcf import parts
from rainbench.mjcf.scene import ACTOR_PREFIX, ride_style


class ActorDriver:
    """Writes the layout's motion at time ``t`` into ``data`` (mocap poses and limb angles)."""

    def __init__(self, model: mujoco.MjModel, layout: L.Layout) -> None:
        self._layout = layout
        self._ego_mocap = int(model.body("ego").mocapid[0])
        rig = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "sun_rig")
        self._rig_mocap = int(model.body_mocapid[rig]) if rig >= 0 else -1
        self._unit_mocap = np.array(
            [int(model.body(unit.name).mocapid[0]) for unit in layout.units], dtype=np.int64
        )
        # Per person actor: (unit index, qpos addresses of PERSON_JOINTS, the riding pose's
        # angles or None for a pedestrian, the standing sway's phase)
        self._people: list[tuple[int, np.ndarray, np.ndarray | None, float]] = []
        for actor in layout.actors:
            if actor.class_id != L.PERSON:
                continue
            prefix = ACTOR_PREFIX.format(actor.instance_id)
            addresses = np.array(
                [int(model.joint(prefix + joint).qposadr[0]) for joint in parts.PERSON_JOINTS]
            )
            unit = layout.units[actor.unit]
            riding = None
            if actor.role == "rider":
                pose = parts.riding_pose(ride_style(unit), unit.build)
                riding = np.array([pose[j] for j in parts.PERSON_JOINTS])
            # a fixed, well-spread phase per person: people do not sway in step
            phase = (actor.instance_id * 0.618034 % 1.0) * 2 * math.pi
            self._people.append((actor.unit, addresses, riding, phase))

    def apply(self, data: mujoco.MjData, t: float) -> None:
        """Pose every mocap body (ego, sun rig, units) and every person's joints at time ``t``."""
        layout = self._layout
        x, y, yaw = L.unit_pose(layout.ego, t)
        data.mocap_pos[self._ego_mocap] = [x, y, 0.0]
        data.mocap_quat[self._ego_mocap] = parts.unit_yaw_quat(yaw)
        if self._rig_mocap >= 0:  # the sun follows the ego's position, not its yaw
            data.mocap_pos[self._rig_mocap] = [x, y, 0.0]
        for unit, mocap_id in zip(layout.units, self._unit_mocap):
            x, y, yaw = L.unit_pose(unit, t)
            z = L.ground_height(layout, x, y) if unit.kind == "pedestrian" else 0.0
            data.mocap_pos[mocap_id] = [x, y, z]
            data.mocap_quat[mocap_id] = parts.unit_yaw_quat(yaw)
        for unit_index, addresses, riding, sway_phase in self._people:
            if riding is not None:
                data.qpos[addresses] = riding
                continue
            unit = layout.units[unit_index]
            distance = L.unit_distance(unit, t)
            if unit.speed > 0 and 0.0 < distance < unit.max_distance:
                pose = parts.walking_pose(2 * math.pi * distance / unit.stride_length, unit.gait)
            else:  # not started, arrived, or standing still
                pose = parts.standing_pose(t, sway_phase)
            if "umbrella" in unit.colours:
                pose = {**pose, **parts.UMBRELLA_ARM}
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
