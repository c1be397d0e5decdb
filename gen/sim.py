"""Stepping the scene: kinematic actor motion applied to a compiled model, advanced by ``mj_step``.

Every moving unit is a mocap body following its planned path of straights and arcs (see
:func:`rainbench.mjcf.layout.unit_pose`), turning with it; people's limbs are hinge joints driven by each walker's
gait, a standing sway for people who stand (before they start or after they arrive), the riding
pose of the rider's bicycle or motorcycle style (a cyclist's legs follow the pedals, which turn
with the distance ridden), and the raised arm of umbrella carriers. Between frames the simulation advances with ``mj_step`` at the model
timestep, with the kinematic targets written before every step; before a frame is rendered the
exact state at the frame time is written and ``mj_forward`` recomputes every pose.

Every degree of freedom is written (mocap poses, every joint's angle, zero velocities), so the
state at a time does not depend on the steps that led there: ``advance(t, t)`` poses a scene at
``t`` exactly as stepping from 0 s would, and a clip's piece starts at its first frame
(``tests/test_sim.py`` checks both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np

from rainbench.mjcf import layout as L
from rainbench.mjcf import parts
from rainbench.mjcf.scene import ACTOR_PREFIX, ride_style, sun_rig_position


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
        # Per bicycle: (unit index, qpos address of its crank, its rider's PERSON_JOINTS
        # addresses, the bicycle's style, the rider's build); the rider's legs follow the pedals
        self._cyclists: list[tuple[int, int, np.ndarray, str, object]] = []
        cranks = {actor.unit: int(model.joint(ACTOR_PREFIX.format(actor.instance_id) + "crank").qposadr[0])
                  for actor in layout.actors if actor.role == "bicycle"}
        for actor in layout.actors:
            if actor.class_id != L.PERSON:
                continue
            prefix = ACTOR_PREFIX.format(actor.instance_id)
            addresses = np.array(
                [int(model.joint(prefix + joint).qposadr[0]) for joint in parts.PERSON_JOINTS]
            )
            unit = layout.units[actor.unit]
            riding = None
            if actor.role == "rider" and actor.unit in cranks:
                self._cyclists.append((actor.unit, cranks[actor.unit], addresses, ride_style(unit),
                                       unit.build))
                continue
            if actor.role == "rider":
                pose = parts.riding_pose(ride_style(unit), unit.build)
                riding = np.array([pose[j] for j in parts.PERSON_JOINTS])
            # a fixed, well-spread phase per person: people do not sway in step
            phase = (actor.instance_id * 0.618034 % 1.0) * 2 * math.pi
            self._people.append((actor.unit, addresses, riding, phase))

    def plan(self, times) -> "_Targets":
        """The kinematic targets at ``times`` (T,) seconds, every unit's path evaluated once for
        all of them (vectorised over time: a frame's physics steps share one evaluation)."""
        layout = self._layout
        times = np.atleast_1d(np.asarray(times, dtype=np.float64))
        ego = L.unit_pose(layout.ego, times)  # (T, 3)
        units = np.stack([L.unit_pose(unit, times) for unit in layout.units]) if layout.units \
            else np.zeros((0, times.size, 3))  # (N, T, 3)
        heights = np.zeros(units.shape[:2])
        for index, unit in enumerate(layout.units):
            if unit.kind == "pedestrian":
                heights[index] = walker_height(layout, unit, times)
        return _Targets(times, ego, units, heights)

    def write(self, data: mujoco.MjData, targets: "_Targets", step: int) -> None:
        """Pose every mocap body (ego, sun rig, units) and every person's joints at
        ``targets.times[step]``."""
        layout = self._layout
        t = float(targets.times[step])
        x, y, yaw = targets.ego[step]
        data.mocap_pos[self._ego_mocap] = [x, y, 0.0]
        data.mocap_quat[self._ego_mocap] = parts.unit_yaw_quat(yaw)
        if self._rig_mocap >= 0:  # the sun's shadow box stays ahead of the ego; never turned
            data.mocap_pos[self._rig_mocap] = sun_rig_position(x, y, yaw)
        if len(self._unit_mocap):
            poses = targets.units[:, step]
            data.mocap_pos[self._unit_mocap, 0] = poses[:, 0]
            data.mocap_pos[self._unit_mocap, 1] = poses[:, 1]
            data.mocap_pos[self._unit_mocap, 2] = targets.heights[:, step]
            half = poses[:, 2] / 2
            data.mocap_quat[self._unit_mocap] = np.stack(
                [np.cos(half), np.zeros_like(half), np.zeros_like(half), np.sin(half)], axis=-1)
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
        for unit_index, crank_address, addresses, style, build in self._cyclists:
            crank = parts.crank_angle(L.unit_distance(layout.units[unit_index], t))
            data.qpos[crank_address] = crank
            pose = parts.riding_pose(style, build, crank)
            data.qpos[addresses] = [pose[j] for j in parts.PERSON_JOINTS]
        data.qvel[:] = 0.0

    def apply(self, data: mujoco.MjData, t: float) -> None:
        """Pose every mocap body (ego, sun rig, units) and every person's joints at time ``t``."""
        self.write(data, self.plan([t]), 0)


CURB_STEP_S = 0.3
"""How long a walker takes to step up or down a curb (about a step): the body rises with the
ground averaged over this much of the walker's own walk, not by the curb's 0.15 m in one frame."""


def walker_height(layout: L.Layout, unit: L.Unit, times: np.ndarray) -> np.ndarray:
    """(T,) height (m) of a pedestrian ``unit``'s body at ``times`` (T,) seconds: the ground
    under it (:func:`rainbench.mjcf.layout.ground_heights`) averaged over five points of its
    walk within :data:`CURB_STEP_S` around each time, so that it steps onto a curb over a step,
    not in one frame; where the ground is level over that stretch (and for anyone standing) the
    ground's own height. A pure function of the time, as every target is."""
    times = np.asarray(times, np.float64)
    offsets = np.linspace(-CURB_STEP_S / 2, CURB_STEP_S / 2, 5)
    # the five offsets' positions and ground in one call each (a call costs as much as its points)
    around = (times[None, :] + offsets[:, None]).ravel()
    samples = L.ground_heights(layout, L.unit_position(unit, around)).reshape(len(offsets), -1)
    level = (samples == samples[2]).all(axis=0)  # exactly the ground there, not a rounded mean
    return np.where(level, samples[2], samples.mean(axis=0))


@dataclass(frozen=True)
class _Targets:
    """Kinematic targets at ``times`` (T,): the ego's (T, 3) and every unit's (N, T, 3) pose
    (x, y, yaw), and the units' (N, T) ground heights (people on walkways, else 0)."""

    times: np.ndarray
    ego: np.ndarray
    units: np.ndarray
    heights: np.ndarray


def advance(model: mujoco.MjModel, data: mujoco.MjData, driver: ActorDriver,
            t_from: float, t_to: float) -> None:
    """Step the physics from ``t_from`` to ``t_to`` with ``mj_step``, then pose exactly at ``t_to``."""
    steps = max(0, int(round((t_to - t_from) / model.opt.timestep)))
    targets = driver.plan(np.append(t_from + np.arange(steps) * model.opt.timestep, t_to))
    for step in range(steps):
        driver.write(data, targets, step)
        mujoco.mj_step(model, data)
    driver.write(data, targets, steps)
    data.time = t_to
    mujoco.mj_forward(model, data)
