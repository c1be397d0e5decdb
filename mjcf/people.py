"""People as plain data: body builds, body proportions, gaits and the joint poses of walking and
standing still.

Nothing here touches MuJoCo: :mod:`rainbench.mjcf.parts` turns a :class:`PersonBuild` into geoms
and re-exports every name of this module, and :mod:`rainbench.mjcf.layout` may sample builds and
gaits without importing the part builders. Joint angles are radians about the person's lateral
(y) axis, keyed by the names of :data:`PERSON_JOINTS`: positive hip/shoulder swings the limb
backwards, positive knee bends the shin backwards, negative elbow bends the forearm forwards,
positive waist leans the torso forwards.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Joints of the articulated person, in qpos order (see the module docstring for the signs).
PERSON_JOINTS: tuple[str, ...] = (
    "waist", "hip_l", "knee_l", "hip_r", "knee_r", "shoulder_l", "elbow_l",
    "shoulder_r", "elbow_r",
)
BICYCLE_STYLES: tuple[str, ...] = ("city", "road")
MOTORCYCLE_STYLES: tuple[str, ...] = ("standard", "sport", "scooter")
CLOTHING_STYLES: tuple[str, ...] = ("trousers", "shorts", "skirt", "long_coat")
HAIR_STYLES: tuple[str, ...] = ("short", "long", "bun", "bald")
HAT_STYLES: tuple[str, ...] = ("none", "cap", "beanie", "brimmed")
CHILD_HEIGHT_RANGE = (1.0, 1.4)  # metres, what sample_person_build draws for children
ADULT_HEIGHT_RANGE = (1.5, 1.95)  # metres, adults: normal(1.72, 0.09) clipped to this range
CHILD_MAX_HEIGHT = 1.45  # builds shorter than this are children (bigger heads, shorter legs)
NOMINAL_CYCLE_HZ = 0.9  # full gait cycles (two steps) per second at cadence_factor 1


def _check_choice(name: str, value: str, options: tuple[str, ...]) -> None:
    if value not in options:
        raise ValueError(f"{name}: expected one of {', '.join(options)}, got {value!r}")


@dataclass(frozen=True)
class PersonBuild:
    """How one person looks: size, girth, clothes, hair and hat.

    ``height_m`` is the standing height to the top of the head (children 1.0-1.4 m, adults
    1.5-1.95 m; any value in 0.9..2.1 is accepted); ``girth`` widens torso, hips and limbs
    (0.85 slim .. 1.3 heavy). ``clothing`` is one of :data:`CLOTHING_STYLES`: the lower garment
    (trousers, shorts, skirt) takes the ``trousers`` colour, a long coat the ``coat`` colour.
    The default is the adult every caller got before builds existed (hip joints at 0.93 m).
    """

    height_m: float = 1.75
    girth: float = 1.0
    clothing: str = "trousers"
    long_sleeves: bool = False
    hair: str = "short"
    hat: str = "none"

    def __post_init__(self) -> None:
        if not 0.9 <= self.height_m <= 2.1:
            raise ValueError(f"height_m: expected 0.9..2.1 metres, got {self.height_m}")
        if not 0.7 <= self.girth <= 1.5:
            raise ValueError(f"girth: expected 0.7..1.5, got {self.girth}")
        _check_choice("clothing", self.clothing, CLOTHING_STYLES)
        _check_choice("hair", self.hair, HAIR_STYLES)
        _check_choice("hat", self.hat, HAT_STYLES)

    @property
    def is_child(self) -> bool:
        return self.height_m < CHILD_MAX_HEIGHT


DEFAULT_BUILD = PersonBuild()


def sample_person_build(rng: np.random.Generator, child_probability: float = 0.15) -> PersonBuild:
    """A random person: a child (height uniform 1.0-1.4 m) with ``child_probability``, else an
    adult (normal 1.72 +- 0.09 m clipped to 1.5-1.95 m); girth, clothes, hair and hat.

    Always draws the same number of values from ``rng``, whatever the outcome.
    """
    if not 0.0 <= child_probability <= 1.0:
        raise ValueError(f"child_probability: expected 0..1, got {child_probability}")
    draws = rng.random(8)
    normal = rng.standard_normal()
    child = bool(draws[0] < child_probability)
    if child:
        height = CHILD_HEIGHT_RANGE[0] + draws[1] * (CHILD_HEIGHT_RANGE[1] - CHILD_HEIGHT_RANGE[0])
        girth = 0.85 + 0.25 * draws[2]
    else:
        height = float(np.clip(1.72 + 0.09 * normal, *ADULT_HEIGHT_RANGE))
        girth = 0.85 + 0.45 * draws[2] ** 1.5  # most people slim to average, some heavy
    clothing = CLOTHING_STYLES[int(np.searchsorted([0.45, 0.62, 0.77], draws[3], side="right"))]
    long_sleeves = clothing == "long_coat" or bool(draws[4] < 0.5)
    hair = HAIR_STYLES[int(np.searchsorted([0.45, 0.75, 0.88], draws[5], side="right"))]
    hat = HAT_STYLES[int(np.searchsorted([0.65, 0.8, 0.92], draws[6], side="right"))]
    return PersonBuild(round(float(height), 3), round(float(girth), 3), clothing, long_sleeves,
                       hair, hat)


@dataclass(frozen=True)
class Proportions:
    """Absolute body measures (metres) of a build standing on z = 0: heights of joints and the
    lengths and radii of the limbs. ``head_height`` is chin to crown."""

    height: float
    hip_z: float  # hip joint centres
    waist_z: float  # the waist hinge (torso body origin)
    shoulder_z: float  # shoulder joint centres
    chin_z: float
    head_height: float
    head_half_length: float  # front-back
    head_half_width: float
    shoulder_half_width: float  # y of the shoulder joints
    hip_half_width: float  # y of the hip joints
    upper_arm: float
    forearm: float  # elbow to the centre of the hand
    hand_radius: float
    thigh: float
    shin: float  # knee to ankle
    ankle_z: float
    foot_length: float
    torso_half_width: float  # at the chest
    torso_half_depth: float
    thigh_radius: float
    shin_radius: float
    upper_arm_radius: float
    forearm_radius: float
    neck_radius: float
    pelvis_drop: float  # the pelvis geom's bottom lies this far below hip_z

    @property
    def neck_length(self) -> float:
        return self.chin_z - self.shoulder_z


def _interp(height: float, points: tuple[tuple[float, float], ...]) -> float:
    xs, ys = zip(*points)
    return float(np.interp(height, xs, ys))


def body_proportions(build: PersonBuild | None = None, scale: float = 1.0) -> Proportions:
    """The proportions of ``build`` (default :data:`DEFAULT_BUILD`) scaled by ``scale``.

    Fractions of the height change with age: a 1.0 m child's head is ~19 % of its height
    (an adult's ~13 %) and its legs ~46 % (an adult's 53 %). Widths grow with ``girth``.
    """
    b = DEFAULT_BUILD if build is None else build
    height = b.height_m * scale
    h = b.height_m
    size = scale * h / 1.75  # lengths relative to the default adult
    head_h = h * _interp(h, ((1.0, 0.19), (1.4, 0.155), (1.6, 0.136), (1.95, 0.128))) * scale
    hip_z = h * _interp(h, ((1.0, 0.46), (1.4, 0.51), (1.6, 0.5314))) * scale
    neck = h * _interp(h, ((1.0, 0.03), (1.6, 0.045))) * scale
    chin_z = height - head_h
    shoulder_z = chin_z - neck - 0.025 * size  # the joints sit below the shoulder tops
    ankle_z = 0.08 * size
    leg = hip_z - ankle_z
    # Children are a little narrower at the shoulders relative to their height.
    width = size * _interp(h, ((1.0, 0.93), (1.5, 1.0))) * b.girth ** 0.5
    girth = b.girth
    return Proportions(
        height=height, hip_z=hip_z, waist_z=hip_z + 0.08 * size, shoulder_z=shoulder_z,
        chin_z=chin_z, head_height=head_h,
        head_half_length=0.43 * head_h * _interp(h, ((1.0, 0.92), (1.6, 1.0))),
        head_half_width=0.345 * head_h * _interp(h, ((1.0, 0.95), (1.6, 1.0))),
        shoulder_half_width=0.19 * width, hip_half_width=0.09 * width,
        upper_arm=0.186 * h * scale * _interp(h, ((1.0, 0.93), (1.6, 1.0))),
        forearm=0.19 * h * scale * _interp(h, ((1.0, 0.93), (1.6, 1.0))),
        hand_radius=0.045 * size, thigh=0.51 * leg, shin=0.49 * leg, ankle_z=ankle_z,
        foot_length=0.152 * h * scale,
        torso_half_width=0.165 * width, torso_half_depth=0.105 * size * girth,
        thigh_radius=0.068 * size * girth ** 0.8, shin_radius=0.05 * size * girth ** 0.6,
        upper_arm_radius=0.044 * size * girth ** 0.7, forearm_radius=0.036 * size * girth ** 0.5,
        neck_radius=0.05 * size * girth ** 0.5, pelvis_drop=0.08 * size,
    )


def hip_height(build: PersonBuild | None = None, scale: float = 1.0) -> float:
    """Height (m) of the hip joints of ``build`` standing on the ground."""
    return body_proportions(build, scale).hip_z


@dataclass(frozen=True)
class Gait:
    """A walking style. Angles in radians (see the module docstring for the signs).

    ``stride_amplitude``: hip swing either side of vertical; ``knee_lift``: extra knee bend in
    mid-swing; ``knee_stance``: knee bend throughout; ``arm_swing``: shoulder swing amplitude;
    ``elbow_bend``: mean elbow angle (<= 0); ``elbow_swing``: extra forward bend of the elbow while
    the arm swings forwards; ``torso_lean``: waist angle; ``cadence_factor``: gait cycles per
    second relative to :data:`NOMINAL_CYCLE_HZ` (see :func:`gait_speed`).
    The defaults are the single gait every person walked with before gaits existed.
    """

    stride_amplitude: float = 0.45
    knee_lift: float = 0.55
    knee_stance: float = 0.15
    arm_swing: float = 0.4
    elbow_bend: float = -0.35
    elbow_swing: float = 0.0
    torso_lean: float = 0.05
    cadence_factor: float = 1.0

    def __post_init__(self) -> None:
        if not 0.0 < self.stride_amplitude <= 0.8:
            raise ValueError(f"stride_amplitude: expected 0..0.8 rad, got {self.stride_amplitude}")
        if not 0.0 < self.cadence_factor <= 3.0:
            raise ValueError(f"cadence_factor: expected 0..3, got {self.cadence_factor}")


DEFAULT_GAIT = Gait()


def sample_gait(rng: np.random.Generator, build: PersonBuild | None = None) -> Gait:
    """A random walking style for ``build``: children take quicker steps and swing their arms
    more. Always draws 8 values from ``rng``."""
    u = rng.random(8)
    child = build is not None and build.is_child
    return Gait(
        stride_amplitude=round(0.33 + 0.15 * u[0], 4),
        knee_lift=round(0.42 + 0.3 * u[1], 4),
        knee_stance=round(0.08 + 0.12 * u[2], 4),
        arm_swing=round((0.3 if child else 0.15) + 0.3 * u[3], 4),
        elbow_bend=round(-0.2 - 0.4 * u[4], 4),
        elbow_swing=round(0.25 * u[5], 4),
        torso_lean=round(0.1 * u[6], 4),
        cadence_factor=round((1.1 if child else 0.88) + 0.25 * u[7], 4),
    )


def gait_cycle_length(build: PersonBuild | None = None, gait: Gait | None = None,
                      scale: float = 1.0) -> float:
    """Metres walked per full gait cycle (two steps) so that feet do not slide: a foot swings
    ``hip_z * sin(stride_amplitude)`` either side of the hip, so ``4 hip_z sin(amplitude)``.
    This is the value of ``Unit.stride_length``."""
    g = DEFAULT_GAIT if gait is None else gait
    return 4.0 * hip_height(build, scale) * math.sin(g.stride_amplitude)


def gait_speed(build: PersonBuild | None = None, gait: Gait | None = None,
               scale: float = 1.0) -> float:
    """Natural walking speed (m/s): cycle length times ``NOMINAL_CYCLE_HZ * cadence_factor``."""
    g = DEFAULT_GAIT if gait is None else gait
    return gait_cycle_length(build, g, scale) * NOMINAL_CYCLE_HZ * g.cadence_factor


def walking_pose(phase: float, gait: Gait | None = None) -> dict[str, float]:
    """Joint angles (radians) of walking at ``phase`` (radians, one cycle = 2 pi).

    The left leg swings forwards through phase 0 with its knee most bent; the right leg half a
    cycle later. ``gait=None`` is :data:`DEFAULT_GAIT`.
    """
    g = DEFAULT_GAIT if gait is None else gait
    swing = math.sin(phase)
    return {
        "waist": g.torso_lean,
        "hip_l": -g.stride_amplitude * swing,
        "knee_l": g.knee_stance + g.knee_lift * max(0.0, math.sin(phase + math.pi / 2)) ** 2,
        "hip_r": g.stride_amplitude * swing,
        "knee_r": g.knee_stance + g.knee_lift * max(0.0, math.sin(phase - math.pi / 2)) ** 2,
        "shoulder_l": g.arm_swing * swing,
        "elbow_l": g.elbow_bend - g.elbow_swing * max(0.0, -swing),
        "shoulder_r": -g.arm_swing * swing,
        "elbow_r": g.elbow_bend - g.elbow_swing * max(0.0, swing),
    }


STANDING_PERIOD_S = 5.0  # one slow weight shift from leg to leg and back


def standing_pose(t: float, rng_phase: float) -> dict[str, float]:
    """Joint angles (radians) of someone standing still at time ``t`` (s): a slow weight shift
    (the unloaded knee relaxes), a little sway of the torso and the hanging arms. Every angle
    stays within 0.2 rad. ``rng_phase`` (radians, drawn once per person) desynchronises people.
    """
    w = 2 * math.pi * t / STANDING_PERIOD_S + rng_phase
    shift = math.sin(w)
    sway = math.sin(0.61 * w + 1.3)
    return {
        "waist": 0.03 + 0.02 * sway,
        "hip_l": -0.02 + 0.03 * shift,
        "knee_l": 0.04 + 0.08 * max(0.0, shift),
        "hip_r": -0.02 - 0.03 * shift,
        "knee_r": 0.04 + 0.08 * max(0.0, -shift),
        "shoulder_l": 0.02 + 0.03 * sway,
        "elbow_l": -0.12 - 0.03 * shift,
        "shoulder_r": 0.02 - 0.03 * sway,
        "elbow_r": -0.12 + 0.03 * shift,
    }
