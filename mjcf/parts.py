"""Small named parts of the road scene, each added to a ``mujoco.MjSpec`` body.

Actor parts (cars, people, bicycles, motorcycles) build their geometry under a given body with
every geom named ``{prefix}{part}``; the prefix (``actor07/``) is how the generator maps a geom
back to its labelled instance. Body frames: x forward, y left, z up, origin on the ground at the
centre of the footprint. Actor geoms never collide (contype 0): motion is planned collision-free
(see :mod:`rainbench.mjcf.layout`) and collision detection would only cost time.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from . import layout as L

GEOM = mujoco.mjtGeom
HINGE = mujoco.mjtJoint.mjJNT_HINGE

GLASS = (0.10, 0.14, 0.20, 1.0)
TYRE = (0.06, 0.06, 0.06, 1.0)
RIM = (0.55, 0.56, 0.58, 1.0)
TRIM = (0.05, 0.05, 0.05, 1.0)
HEADLIGHT = (1.0, 0.97, 0.85, 1.0)
TAILLIGHT = (0.75, 0.03, 0.03, 1.0)
METAL = (0.35, 0.36, 0.38, 1.0)

# Joints of the articulated person, in qpos order; angles in radians about the body's y axis
# (lateral). Positive hip/shoulder swings the limb backwards, positive knee bends it.
PERSON_JOINTS: tuple[str, ...] = (
    "waist", "hip_l", "knee_l", "hip_r", "knee_r", "shoulder_l", "elbow_l",
    "shoulder_r", "elbow_r",
)

Y_AXIS_QUAT = (math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0)  # z axis -> y axis


def rgba(colour: tuple[float, float, float], alpha: float = 1.0) -> list[float]:
    return [float(colour[0]), float(colour[1]), float(colour[2]), alpha]


def _geom(body, name: str, kind, size, rgba_value, **kwargs):
    geom = body.add_geom(name=name, type=kind, size=list(size) + [0.0] * (3 - len(size)),
                         rgba=list(rgba_value), contype=0, conaffinity=0, **kwargs)
    return geom


def add_car(body, prefix: str, style: str, paint: tuple[float, float, float]) -> None:
    """A car of ``style`` (sedan, hatchback, suv): body, cabin with windows, wheels, lights."""
    if style not in L.CAR_DIMENSIONS:
        raise ValueError(f"car style: expected one of {L.CAR_STYLES}, got {style!r}")
    length, width, height = L.CAR_DIMENSIONS[style]
    paint_rgba = rgba(paint)
    wheel_radius = {"sedan": 0.33, "hatchback": 0.31, "suv": 0.38}[style]
    clearance = wheel_radius * 0.55
    belt = clearance + 0.52 * (height - clearance) if style != "suv" else clearance + 0.55
    # Lower body.
    _geom(body, f"{prefix}body", GEOM.mjGEOM_BOX,
          [length / 2, width / 2, (belt - clearance) / 2], paint_rgba,
          pos=[0, 0, (belt + clearance) / 2])
    # Cabin: glass box with a painted roof and pillars.
    if style == "sedan":
        cabin_len, cabin_x = 0.48 * length, -0.06 * length
    elif style == "hatchback":
        cabin_len, cabin_x = 0.62 * length, -0.17 * length
    else:
        cabin_len, cabin_x = 0.72 * length, -0.13 * length
    cabin_h = height - belt - 0.06
    _geom(body, f"{prefix}cabin", GEOM.mjGEOM_BOX,
          [cabin_len / 2, width * 0.44, cabin_h / 2], GLASS, pos=[cabin_x, 0, belt + cabin_h / 2])
    _geom(body, f"{prefix}roof", GEOM.mjGEOM_BOX,
          [cabin_len / 2 + 0.02, width * 0.45, 0.04], paint_rgba,
          pos=[cabin_x, 0, height - 0.04])
    for side in (-1, 1):
        _geom(body, f"{prefix}pillar_b{'lr'[side > 0]}", GEOM.mjGEOM_BOX,
              [0.06, 0.02, cabin_h / 2], paint_rgba,
              pos=[cabin_x, side * width * 0.445, belt + cabin_h / 2])
    # Slanted windscreen joining bonnet and roof (and a rear window on sedans).
    rake = math.radians(58 if style != "suv" else 35)
    screen_len = cabin_h / math.cos(rake)
    front = cabin_x + cabin_len / 2
    quat = [math.cos(-rake / 2), 0.0, math.sin(-rake / 2), 0.0]
    _geom(body, f"{prefix}windscreen", GEOM.mjGEOM_BOX, [0.03, width * 0.43, screen_len / 2],
          GLASS, pos=[front + math.sin(rake) * screen_len / 2, 0, belt + cabin_h / 2], quat=quat)
    if style == "sedan":
        rear = cabin_x - cabin_len / 2
        quat_rear = [math.cos(rake / 2), 0.0, math.sin(rake / 2), 0.0]
        _geom(body, f"{prefix}rear_window", GEOM.mjGEOM_BOX, [0.03, width * 0.43, screen_len / 2],
              GLASS, pos=[rear - math.sin(rake) * screen_len / 2, 0, belt + cabin_h / 2],
              quat=quat_rear)
    # Wheels with rims, arches darkened by the tyres themselves.
    axle_x = length / 2 - max(0.75, 0.18 * length)
    for fx in (-1, 1):
        for side in (-1, 1):
            tag = f"{'rf'[fx > 0]}{'rl'[side > 0]}"
            centre = [fx * axle_x, side * (width / 2 - 0.12), wheel_radius]
            _geom(body, f"{prefix}tyre_{tag}", GEOM.mjGEOM_CYLINDER, [wheel_radius, 0.11], TYRE,
                  pos=centre, quat=Y_AXIS_QUAT)
            _geom(body, f"{prefix}rim_{tag}", GEOM.mjGEOM_CYLINDER, [wheel_radius * 0.55, 0.115],
                  RIM, pos=centre, quat=Y_AXIS_QUAT)
    # Lights and bumpers.
    light_z = belt - 0.12
    for side in (-1, 1):
        _geom(body, f"{prefix}headlight_{'rl'[side > 0]}", GEOM.mjGEOM_BOX, [0.02, 0.16, 0.05],
              HEADLIGHT, pos=[length / 2 + 0.005, side * (width / 2 - 0.25), light_z])
        _geom(body, f"{prefix}taillight_{'rl'[side > 0]}", GEOM.mjGEOM_BOX, [0.02, 0.14, 0.05],
              TAILLIGHT, pos=[-length / 2 - 0.005, side * (width / 2 - 0.22), light_z])
        _geom(body, f"{prefix}mirror_{'rl'[side > 0]}", GEOM.mjGEOM_BOX, [0.06, 0.08, 0.05],
              paint_rgba, pos=[front - 0.05, side * (width / 2 + 0.07), belt + 0.08])
    for end in (-1, 1):
        _geom(body, f"{prefix}bumper_{'rf'[end > 0]}", GEOM.mjGEOM_BOX, [0.06, width / 2, 0.08],
              TRIM, pos=[end * (length / 2 + 0.03), 0, clearance + 0.12])


def add_person(
    parent, prefix: str, colours: dict, scale: float = 1.0, pos=(0.0, 0.0, 0.0),
    helmet: tuple[float, float, float] | None = None,
) -> None:
    """An articulated person: pelvis, torso on a waist hinge, head, two-segment arms and legs.

    ``parent`` gets a child body holding the person; its joints (``{prefix}{joint}`` for joint in
    :data:`PERSON_JOINTS`) are hinges about the lateral axis, set kinematically by the generator.
    Standing height is about ``1.75 * scale`` m.
    """
    s = scale
    shirt, trousers, skin = rgba(colours["shirt"]), rgba(colours["trousers"]), rgba(colours["skin"])
    root = parent.add_body(name=f"{prefix}root", pos=list(pos))
    hip_z = 0.93 * s
    _geom(root, f"{prefix}pelvis", GEOM.mjGEOM_BOX, [0.10 * s, 0.16 * s, 0.09 * s], trousers,
          pos=[0, 0, hip_z + 0.03 * s])
    torso = root.add_body(name=f"{prefix}torso", pos=[0, 0, hip_z + 0.08 * s])
    torso.add_joint(name=f"{prefix}waist", type=HINGE, axis=[0, 1, 0])
    _geom(torso, f"{prefix}chest", GEOM.mjGEOM_CAPSULE, [0.15 * s], shirt,
          fromto=[0, 0, 0.12 * s, 0, 0, 0.40 * s])
    _geom(torso, f"{prefix}shoulders", GEOM.mjGEOM_CAPSULE, [0.07 * s], shirt,
          fromto=[0, -0.17 * s, 0.45 * s, 0, 0.17 * s, 0.45 * s])
    _geom(torso, f"{prefix}neck", GEOM.mjGEOM_CAPSULE, [0.045 * s], skin,
          fromto=[0, 0, 0.48 * s, 0, 0, 0.56 * s])
    _geom(torso, f"{prefix}head", GEOM.mjGEOM_ELLIPSOID, [0.095 * s, 0.085 * s, 0.115 * s], skin,
          pos=[0.01 * s, 0, 0.66 * s])
    if helmet is not None:
        _geom(torso, f"{prefix}helmet", GEOM.mjGEOM_ELLIPSOID,
              [0.13 * s, 0.115 * s, 0.12 * s], rgba(helmet), pos=[0.0, 0, 0.70 * s])
    else:
        _geom(torso, f"{prefix}hair", GEOM.mjGEOM_ELLIPSOID, [0.10 * s, 0.09 * s, 0.07 * s],
              rgba(colours.get("hair", (0.1, 0.08, 0.05))), pos=[-0.01 * s, 0, 0.72 * s])
    for side, tag in ((1, "l"), (-1, "r")):
        shoulder = torso.add_body(name=f"{prefix}upper_arm_{tag}",
                                  pos=[0, side * 0.21 * s, 0.44 * s])
        shoulder.add_joint(name=f"{prefix}shoulder_{tag}", type=HINGE, axis=[0, 1, 0])
        _geom(shoulder, f"{prefix}upper_arm_{tag}", GEOM.mjGEOM_CAPSULE, [0.045 * s], shirt,
              fromto=[0, 0, 0, 0, 0, -0.28 * s])
        elbow = shoulder.add_body(name=f"{prefix}forearm_{tag}", pos=[0, 0, -0.29 * s])
        elbow.add_joint(name=f"{prefix}elbow_{tag}", type=HINGE, axis=[0, 1, 0])
        _geom(elbow, f"{prefix}forearm_{tag}", GEOM.mjGEOM_CAPSULE, [0.038 * s], skin,
              fromto=[0, 0, 0, 0, 0, -0.24 * s])
        _geom(elbow, f"{prefix}hand_{tag}", GEOM.mjGEOM_SPHERE, [0.045 * s], skin,
              pos=[0, 0, -0.28 * s])
        hip = root.add_body(name=f"{prefix}thigh_{tag}", pos=[0, side * 0.09 * s, hip_z])
        hip.add_joint(name=f"{prefix}hip_{tag}", type=HINGE, axis=[0, 1, 0])
        _geom(hip, f"{prefix}thigh_{tag}", GEOM.mjGEOM_CAPSULE, [0.07 * s], trousers,
              fromto=[0, 0, 0, 0, 0, -0.42 * s])
        knee = hip.add_body(name=f"{prefix}shin_{tag}", pos=[0, 0, -0.44 * s])
        knee.add_joint(name=f"{prefix}knee_{tag}", type=HINGE, axis=[0, 1, 0])
        _geom(knee, f"{prefix}shin_{tag}", GEOM.mjGEOM_CAPSULE, [0.055 * s], trousers,
              fromto=[0, 0, 0, 0, 0, -0.40 * s])
        _geom(knee, f"{prefix}foot_{tag}", GEOM.mjGEOM_BOX, [0.11 * s, 0.05 * s, 0.035 * s],
              TRIM, pos=[0.05 * s, 0, -0.46 * s])


def walking_pose(phase: float) -> dict[str, float]:
    """Joint angles (radians) of a walking gait at ``phase`` (radians, one cycle = 2 pi)."""
    swing = math.sin(phase)
    return {
        "waist": 0.05,
        "hip_l": -0.45 * swing,
        "knee_l": 0.15 + 0.55 * max(0.0, math.sin(phase + math.pi / 2)) ** 2,
        "hip_r": 0.45 * swing,
        "knee_r": 0.15 + 0.55 * max(0.0, math.sin(phase - math.pi / 2)) ** 2,
        "shoulder_l": 0.4 * swing,
        "elbow_l": -0.35,
        "shoulder_r": -0.4 * swing,
        "elbow_r": -0.35,
    }


RIDING_POSE: dict[str, float] = {
    "waist": 0.45, "hip_l": -1.35, "knee_l": 1.45, "hip_r": -1.1, "knee_r": 1.2,
    "shoulder_l": -0.95, "elbow_l": -0.35, "shoulder_r": -0.95, "elbow_r": -0.35,
}


def _tube(body, name: str, start, end, radius: float, colour) -> None:
    _geom(body, name, GEOM.mjGEOM_CAPSULE, [radius], colour, fromto=list(start) + list(end))


def add_bicycle(body, prefix: str, frame_colour: tuple[float, float, float]) -> float:
    """A bicycle: two spoked-looking wheels, diamond frame, fork, saddle, handlebar.

    Returns the saddle height (m), where the rider's pelvis sits.
    """
    frame = rgba(frame_colour)
    radius, half_base = 0.34, 0.52
    for x, tag in ((half_base, "front"), (-half_base, "rear")):
        _geom(body, f"{prefix}tyre_{tag}", GEOM.mjGEOM_CYLINDER, [radius, 0.018], TYRE,
              pos=[x, 0, radius], quat=Y_AXIS_QUAT)
        _geom(body, f"{prefix}spokes_{tag}", GEOM.mjGEOM_CYLINDER, [radius - 0.035, 0.02],
              (0.62, 0.63, 0.66, 1.0), pos=[x, 0, radius], quat=Y_AXIS_QUAT)
        _geom(body, f"{prefix}hub_{tag}", GEOM.mjGEOM_CYLINDER, [0.04, 0.05], METAL,
              pos=[x, 0, radius], quat=Y_AXIS_QUAT)
    bottom = (0.0, 0.0, 0.30)
    seat = (-0.14, 0.0, 0.86)
    head = (0.40, 0.0, 0.84)
    head_low = (0.43, 0.0, 0.70)
    rear_axle = (-half_base, 0.0, radius)
    front_axle = (half_base, 0.0, radius)
    for name, a, b in (("seat_tube", bottom, seat), ("top_tube", seat, head),
                       ("down_tube", bottom, head_low), ("chain_stay", bottom, rear_axle),
                       ("seat_stay", seat, rear_axle), ("head_tube", head_low, head),
                       ("fork", head_low, front_axle)):
        _tube(body, f"{prefix}{name}", a, b, 0.022, frame)
    _tube(body, f"{prefix}stem", head, (0.38, 0.0, 1.0), 0.02, METAL)
    _tube(body, f"{prefix}handlebar", (0.38, -0.25, 1.0), (0.38, 0.25, 1.0), 0.018, METAL)
    _geom(body, f"{prefix}saddle", GEOM.mjGEOM_BOX, [0.12, 0.06, 0.025], TRIM,
          pos=[seat[0] - 0.02, 0, seat[2] + 0.03])
    _geom(body, f"{prefix}crank", GEOM.mjGEOM_CYLINDER, [0.09, 0.03], METAL,
          pos=list(bottom), quat=Y_AXIS_QUAT)
    return seat[2] + 0.05


def add_motorcycle(body, prefix: str, colour: tuple[float, float, float]) -> float:
    """A motorcycle: thick wheels, engine block, tank, seat, fork, handlebar, headlight.

    Returns the seat height (m).
    """
    paint = rgba(colour)
    radius, half_base = 0.31, 0.72
    for x, tag in ((half_base, "front"), (-half_base, "rear")):
        _geom(body, f"{prefix}tyre_{tag}", GEOM.mjGEOM_CYLINDER, [radius, 0.07], TYRE,
              pos=[x, 0, radius], quat=Y_AXIS_QUAT)
        _geom(body, f"{prefix}rim_{tag}", GEOM.mjGEOM_CYLINDER, [0.18, 0.075], RIM,
              pos=[x, 0, radius], quat=Y_AXIS_QUAT)
    _geom(body, f"{prefix}engine", GEOM.mjGEOM_BOX, [0.28, 0.17, 0.17], METAL, pos=[0.0, 0, 0.42])
    _geom(body, f"{prefix}tank", GEOM.mjGEOM_ELLIPSOID, [0.30, 0.17, 0.13], paint,
          pos=[0.18, 0, 0.78])
    _geom(body, f"{prefix}seat", GEOM.mjGEOM_BOX, [0.32, 0.15, 0.05], TRIM, pos=[-0.32, 0, 0.80])
    _geom(body, f"{prefix}tail", GEOM.mjGEOM_BOX, [0.22, 0.12, 0.07], paint, pos=[-0.62, 0, 0.72])
    _geom(body, f"{prefix}fender", GEOM.mjGEOM_BOX, [0.20, 0.08, 0.02], paint,
          pos=[half_base, 0, 2 * radius + 0.04])
    _tube(body, f"{prefix}fork", (half_base, 0, radius), (0.50, 0, 0.98), 0.035, METAL)
    _tube(body, f"{prefix}handlebar", (0.48, -0.36, 1.02), (0.48, 0.36, 1.02), 0.022, TRIM)
    _geom(body, f"{prefix}headlight", GEOM.mjGEOM_SPHERE, [0.09], HEADLIGHT, pos=[0.60, 0, 0.92])
    _tube(body, f"{prefix}exhaust", (-0.1, -0.2, 0.30), (-0.75, -0.2, 0.42), 0.045, METAL)
    _geom(body, f"{prefix}taillight", GEOM.mjGEOM_BOX, [0.02, 0.07, 0.03], TAILLIGHT,
          pos=[-0.85, 0, 0.74])
    return 0.86


def unit_yaw_quat(heading: float) -> np.ndarray:
    return np.array([math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2)])
