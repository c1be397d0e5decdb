"""Small named parts of the road scene, each added to a ``mujoco.MjSpec`` body.

Actor parts (people, bicycles, motorcycles; vehicles are in :mod:`rainbench.mjcf.vehicles`)
build their geometry under a given body with every geom named ``{prefix}{part}``; the prefix
(``actor07/``) is how the generator maps a geom back to its labelled instance. Body frames: x forward, y left, z up, origin on the ground at the
centre of the footprint. Actor geoms never collide (contype 0): motion is planned collision-free
(see :mod:`rainbench.mjcf.layout`) and collision detection would only cost time.

Parts that need meshes (tyre rings, fenders, a torso, an umbrella canopy) build them in a small
child ``MjSpec`` and attach it under the body (a body does not know its spec); the attached
holder body is named ``{prefix}{group}_meshes`` and carries no joint. People's builds, gaits and
walking/standing poses are plain data in :mod:`rainbench.mjcf.people`, re-exported here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np

from .people import (  # noqa: F401  -- re-exported: the generator reaches people through parts
    ADULT_HEIGHT_RANGE, BICYCLE_STYLES, CHILD_HEIGHT_RANGE, CLOTHING_STYLES, DEFAULT_BUILD,
    DEFAULT_GAIT, MOTORCYCLE_STYLES, HAIR_STYLES, HAT_STYLES, PERSON_JOINTS, Gait, PersonBuild, Proportions, body_proportions,
    gait_cycle_length, gait_speed, hip_height, sample_gait, sample_person_build, standing_pose,
    walking_pose,
)

GEOM = mujoco.mjtGeom
HINGE = mujoco.mjtJoint.mjJNT_HINGE

GLASS = (0.10, 0.14, 0.20, 1.0)
SCREEN_GLASS = (0.17, 0.21, 0.27, 1.0)
"""A windscreen's or rear window's colour: a raked pane faces up and mirrors the bright sky, so
it shows lighter than the upright side windows (:data:`GLASS`), which mirror the darker street
and buildings. Chosen for the look: MuJoCo mirrors only planes, so no reflection is drawn, and
the colour does not follow the weather."""
TYRE = (0.06, 0.06, 0.06, 1.0)
RIM = (0.55, 0.56, 0.58, 1.0)
TRIM = (0.05, 0.05, 0.05, 1.0)
HEADLIGHT = (1.0, 0.97, 0.85, 1.0)
TAILLIGHT = (0.75, 0.03, 0.03, 1.0)
METAL = (0.35, 0.36, 0.38, 1.0)
CHROME = (0.70, 0.71, 0.73, 1.0)
SPOKE = (0.62, 0.63, 0.66, 1.0)
WICKER = (0.55, 0.40, 0.22, 1.0)
# Colours of a person's optional parts when ``colours`` does not name them.
DEFAULT_PERSON_COLOURS: dict[str, tuple[float, float, float]] = {
    "hair": (0.1, 0.08, 0.05), "shoes": (0.09, 0.08, 0.08), "hat": (0.16, 0.17, 0.22),
}

Y_AXIS_QUAT = (math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0)  # z axis -> y axis


def rgba(colour: tuple[float, float, float], alpha: float = 1.0) -> list[float]:
    return [float(colour[0]), float(colour[1]), float(colour[2]), alpha]


def _geom(body, name: str, kind, size, rgba_value, **kwargs):
    geom = body.add_geom(name=name, type=kind, size=list(size) + [0.0] * (3 - len(size)),
                         rgba=list(rgba_value), contype=0, conaffinity=0, **kwargs)
    return geom


# -- meshes -------------------------------------------------------------------------------------

def ring_mesh(rings, wrap: bool = False, caps=None) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle mesh through ``rings`` (K, N, 3): ring k is joined to ring k + 1 (and
    the last to the first when ``wrap``); ``caps`` (2, 3), when given, are the points that close
    the first and the last ring. Returns vertices (V, 3) float64 and faces (F, 3) int32 wound so
    that normals point outwards (positive volume)."""
    rings = np.asarray(rings, dtype=np.float64)
    count, around, _ = rings.shape
    j = np.arange(around)
    j_next = (j + 1) % around
    faces = []
    for k in range(count - 1 + int(wrap)):
        k_next = (k + 1) % count
        a, b = k * around + j, k * around + j_next
        c, d = k_next * around + j_next, k_next * around + j
        faces += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
    vertices = rings.reshape(-1, 3)
    if caps is not None:
        start, end = count * around, count * around + 1
        vertices = np.concatenate([vertices, np.asarray(caps, dtype=np.float64).reshape(2, 3)])
        last = (count - 1) * around
        faces += [np.stack([np.full(around, start), j_next, j], 1),
                  np.stack([np.full(around, end), last + j, last + j_next], 1)]
    faces = np.concatenate(faces).astype(np.int32)
    v0, v1, v2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    if np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() < 0:
        faces = faces[:, ::-1].copy()
    return vertices, faces


def loft_mesh(sections, around: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A closed body through horizontal superellipse sections, listed bottom to top as
    ``(z, half_x, half_y, centre_x, exponent)`` (exponent 2: ellipse, larger: boxier)."""
    t = 2 * np.pi * np.arange(around) / around
    cos, sin = np.cos(t), np.sin(t)
    rings = []
    for z, half_x, half_y, centre_x, exponent in sections:
        x = centre_x + half_x * np.sign(cos) * np.abs(cos) ** (2 / exponent)
        y = half_y * np.sign(sin) * np.abs(sin) ** (2 / exponent)
        rings.append(np.stack([x, y, np.full(around, z)], 1))
    caps = [(sections[0][3], 0.0, sections[0][0]), (sections[-1][3], 0.0, sections[-1][0])]
    return ring_mesh(rings, caps=caps)


def side_loft_mesh(sections, around: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A closed body along x through vertical superellipse sections, listed front to back (or
    back to front) as ``(x, z_bottom, z_top, half_y, exponent)``: vehicle bodywork."""
    t = 2 * np.pi * np.arange(around) / around
    cos, sin = np.cos(t), np.sin(t)
    rings = []
    for x, bottom, top, half_y, exponent in sections:
        y = half_y * np.sign(cos) * np.abs(cos) ** (2 / exponent)
        z = (top + bottom) / 2 + (top - bottom) / 2 * np.sign(sin) * np.abs(sin) ** (2 / exponent)
        rings.append(np.stack([np.full(around, x), y, z], 1))
    first, last = sections[0], sections[-1]
    caps = [(first[0], 0.0, (first[1] + first[2]) / 2), (last[0], 0.0, (last[1] + last[2]) / 2)]
    return ring_mesh(rings, caps=caps)


def tube_ring_mesh(major: float, radial: float, axial: float, arc=(0.0, 2 * math.pi),
                   segments: int = 24, sides: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A tube of elliptic section (``radial`` x ``axial`` half axes) bent around the y axis at
    radius ``major`` in the x-z plane: a tyre, a rim or, over part of a turn (``arc``: angles from
    +x towards +z, radians), a fender."""
    full = arc[1] - arc[0] >= 2 * math.pi - 1e-9
    u = np.linspace(arc[0], arc[1], segments, endpoint=not full)
    v = 2 * np.pi * np.arange(sides) / sides
    out = np.stack([np.cos(u), np.zeros_like(u), np.sin(u)], 1)  # (S, 3) radial directions
    rings = (major * out[:, None, :] + radial * np.cos(v)[None, :, None] * out[:, None, :]
             + axial * np.sin(v)[None, :, None] * np.array([0.0, 1.0, 0.0]))
    if full:
        return ring_mesh(rings, wrap=True)
    return ring_mesh(rings, caps=[major * out[0], major * out[-1]])


def canopy_mesh(radius: float, depth: float, ribs: int = 8, thickness: float = 0.012,
                per_rib: int = 4, rings: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """An open umbrella's canopy: a shallow dome ``depth`` high whose rim (radius ``radius``,
    at z = 0 under the ribs) is scalloped between ``ribs`` rib tips; a shell ``thickness``
    thick, apex on +z."""
    phi = 2 * np.pi * np.arange(ribs * per_rib) / (ribs * per_rib)
    scallop = np.sin(ribs * phi / 2) ** 2  # 0 at the rib tips, 1 midway between them
    edge = radius * (1 - 0.07 * scallop)
    lift = 0.18 * depth * scallop
    top = []
    for rho in np.arange(1, rings + 1) / rings:
        r = rho * edge
        z = depth * (1 - rho ** 2) + rho ** 2 * lift
        top.append(np.stack([r * np.cos(phi), r * np.sin(phi), z], 1))
    bottom = [ring - [0.0, 0.0, thickness] for ring in reversed(top)]
    return ring_mesh(top + bottom, caps=[(0, 0, depth), (0, 0, depth - thickness)])


def _attach_meshes(body, prefix: str, group: str, meshes: dict, geoms: list) -> None:
    """Attach mesh geoms under ``body``: ``meshes`` maps a mesh name to (vertices, faces);
    ``geoms`` lists (part name, mesh name, rgba, pos, quat). Geoms are named ``{prefix}{part}``,
    meshes ``{prefix}{mesh}_mesh``; they hang from a joint-less body ``{prefix}{group}_meshes``."""
    child = mujoco.MjSpec()
    child.default.name = f"{group}_class"  # attach prefixes it: unique per actor and group
    holder = child.worldbody.add_body(name=f"{group}_meshes")
    for name, (vertices, faces) in meshes.items():
        child.add_mesh(name=f"{name}_mesh", uservert=vertices.ravel().tolist(),
                       userface=faces.ravel().tolist())
    for part, mesh, colour, pos, quat in geoms:
        holder.add_geom(name=part, type=GEOM.mjGEOM_MESH, meshname=f"{mesh}_mesh",
                        rgba=list(colour), pos=list(pos), quat=list(quat), contype=0,
                        conaffinity=0)
    body.add_frame().attach_body(holder, prefix, "")


def _quat_z_to(direction) -> list[float]:
    """Unit quaternion (w, x, y, z) rotating +z onto ``direction`` (3,)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    axis = np.cross([0.0, 0.0, 1.0], d)
    sin = np.linalg.norm(axis)
    if sin < 1e-12:
        return [1.0, 0.0, 0.0, 0.0] if d[2] > 0 else [0.0, 1.0, 0.0, 0.0]
    angle = math.atan2(sin, d[2])
    axis = axis / sin
    return [math.cos(angle / 2), *(math.sin(angle / 2) * axis)]


def _pitch_quat(angle: float) -> list[float]:
    """Rotation by ``angle`` about +y (positive tips +z towards +x)."""
    return [math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0]


def limb_direction(angle: float) -> np.ndarray:
    """(x, z) direction of a limb segment hanging along -z at angle 0, swung by ``angle``
    about +y (positive swings it backwards, towards -x)."""
    return np.array([-math.sin(angle), -math.cos(angle)])


def limb_ik(dx: float, dz: float, upper: float, lower: float, bend: int) -> tuple[float, float]:
    """(root, middle) joint angles that put the end of a two-segment limb (``upper``, ``lower``
    metres, hanging along -z at zero angles) at (``dx``, ``dz``) from its root, in the limb's
    plane. ``bend`` +1 bends the middle joint backwards (a knee), -1 forwards (an elbow). A target
    out of reach gives the limb stretched (or folded) towards it."""
    reach = min(max(math.hypot(dx, dz), abs(upper - lower) + 1e-6), upper + lower - 1e-6)
    aim = math.atan2(-dx, -dz)
    root = math.acos(np.clip((upper ** 2 + reach ** 2 - lower ** 2) / (2 * upper * reach), -1, 1))
    middle = math.pi - math.acos(
        np.clip((upper ** 2 + lower ** 2 - reach ** 2) / (2 * upper * lower), -1, 1))
    return aim - bend * root, bend * middle


# -- people -------------------------------------------------------------------------------------

# The umbrella is held in the right hand: forearm up, hand in front of the shoulder at chin
# height. The motion code writes these angles over the gait of anyone carrying an umbrella.
UMBRELLA_ARM: dict[str, float] = {"shoulder_r": -0.45, "elbow_r": -2.5}


def _colour(colours: dict, key: str, fallback: str | None = None) -> list[float]:
    if key in colours:
        return rgba(colours[key])
    if fallback is not None:
        return rgba(colours[fallback])
    return rgba(DEFAULT_PERSON_COLOURS[key])


def add_person(
    parent, prefix: str, colours: dict, scale: float = 1.0, pos=(0.0, 0.0, 0.0),
    helmet: tuple[float, float, float] | None = None, build: PersonBuild | None = None,
    umbrella: tuple[float, float, float] | None = None, leg_splay: float = 0.0,
    head_pitch: float = 0.0,
) -> None:
    """An articulated person: pelvis, torso on a waist hinge, neck, head, two-segment arms and
    legs, shoes, hair or a hat, clothes; optionally an open umbrella held in the right hand.

    ``parent`` gets a child body ``{prefix}root`` at ``pos`` holding the person; its joints
    (``{prefix}{joint}`` for joint in :data:`PERSON_JOINTS`) are hinges about the lateral axis,
    set kinematically by the generator. ``build`` (default: the 1.75 m adult, hip joints at
    0.93 m) sets size, proportions, girth and clothes; ``scale`` multiplies every length.
    ``colours`` must name ``shirt``, ``trousers`` (the lower garment) and ``skin``; ``hair``,
    ``shoes``, ``hat`` and ``coat`` (default: the shirt colour) are optional. ``helmet`` (rgb)
    replaces hair and hat. ``umbrella`` (rgb canopy colour) adds geoms ``{prefix}umbrella_canopy``
    and ``{prefix}umbrella_shaft`` fixed to the torso where the right hand is when the arm takes
    :data:`UMBRELLA_ARM`. ``leg_splay`` (radians) yaws the thighs outwards (riders straddling a
    tank) and ``head_pitch`` (radians) tips the head back against the torso's lean (riders
    looking ahead); both 0 for walkers.
    """
    missing = [key for key in ("shirt", "trousers", "skin") if key not in colours]
    if missing:
        raise ValueError(f"colours: expected keys shirt, trousers and skin, missing "
                         f"{', '.join(missing)}")
    if not scale > 0:
        raise ValueError(f"scale: expected > 0, got {scale}")
    if umbrella is not None and len(umbrella) != 3:
        raise ValueError(f"umbrella: expected an rgb triple, got {umbrella!r}")
    b = DEFAULT_BUILD if build is None else build
    p = body_proportions(b, scale)
    k = p.height / 1.75  # size relative to the default adult
    skin, lower = _colour(colours, "skin"), _colour(colours, "trousers")
    shirt, coat = _colour(colours, "shirt"), _colour(colours, "coat", "shirt")
    shoes = _colour(colours, "shoes")
    coated = b.clothing == "long_coat"
    upper = coat if coated else shirt
    sleeve = upper if (b.long_sleeves or coated) else skin

    root = parent.add_body(name=f"{prefix}root", pos=list(pos))
    hip_z = p.hip_z
    _geom(root, f"{prefix}pelvis", GEOM.mjGEOM_ELLIPSOID,
          [0.85 * p.torso_half_depth, p.hip_half_width + 0.7 * p.thigh_radius,
           p.pelvis_drop + 0.02 * k],
          lower, pos=[0, 0, hip_z + 0.02 * k])
    if b.clothing in ("skirt", "long_coat"):
        g = b.girth
        if b.clothing == "skirt":
            hem = hip_z - 0.8 * p.thigh
            sections = [(hem, 0.21 * k * g, 0.23 * k * g ** 0.5, 0.01 * k, 2.0),
                        (hip_z - 0.12 * k, 0.15 * k * g, 0.18 * k * g ** 0.5, 0.0, 2.2),
                        (hip_z + 0.07 * k, 0.11 * k * g, 0.15 * k * g ** 0.5, 0.0, 2.2)]
            colour = lower
        else:
            hem = hip_z - p.thigh - 0.08 * k
            sections = [(hem, 0.23 * k * g, 0.22 * k * g ** 0.5, 0.02 * k, 2.2),
                        (hip_z - 0.12 * k, 0.145 * k * g, 0.19 * k * g ** 0.5, 0.0, 2.4),
                        (hip_z + 0.10 * k, 0.12 * k * g, 0.17 * k * g ** 0.5, 0.0, 2.4)]
            colour = coat
        name = "skirt" if b.clothing == "skirt" else "coat_tail"
        _attach_meshes(root, prefix, "lower", {name: loft_mesh(sections)},
                       [(name, name, colour, (0, 0, 0), (1, 0, 0, 0))])

    legs_bare = b.clothing == "skirt"
    for side, tag in ((1, "l"), (-1, "r")):
        hip = root.add_body(name=f"{prefix}thigh_{tag}", pos=[0, side * p.hip_half_width, hip_z],
                            quat=unit_yaw_quat(side * leg_splay).tolist())
        hip.add_joint(name=f"{prefix}hip_{tag}", type=HINGE, axis=[0, 1, 0])
        if b.clothing == "shorts":
            _geom(hip, f"{prefix}thigh_{tag}", GEOM.mjGEOM_CAPSULE, [1.06 * p.thigh_radius],
                  lower, fromto=[0, 0, 0, 0, 0, -0.5 * p.thigh])
            _geom(hip, f"{prefix}knee_{tag}", GEOM.mjGEOM_ELLIPSOID,
                  [0.85 * p.thigh_radius, 0.85 * p.thigh_radius, 0.3 * p.thigh], skin,
                  pos=[0, 0, -0.7 * p.thigh])
        else:  # an ellipsoid: full at the hip, tapering into the knee
            _geom(hip, f"{prefix}thigh_{tag}", GEOM.mjGEOM_ELLIPSOID,
                  [p.thigh_radius, p.thigh_radius, 0.5 * p.thigh + 0.045 * k],
                  skin if legs_bare else lower, pos=[0, 0, -0.5 * p.thigh])
        knee = hip.add_body(name=f"{prefix}shin_{tag}", pos=[0, 0, -p.thigh])
        knee.add_joint(name=f"{prefix}knee_{tag}", type=HINGE, axis=[0, 1, 0])
        bare = legs_bare or b.clothing == "shorts"
        _geom(knee, f"{prefix}shin_{tag}", GEOM.mjGEOM_CAPSULE, [p.shin_radius],
              skin if bare else lower, fromto=[0, 0, 0, 0, 0, -p.shin])
        half_foot = p.foot_length / 2
        _geom(knee, f"{prefix}foot_{tag}", GEOM.mjGEOM_ELLIPSOID,
              [half_foot, 0.048 * k, 0.045 * k], shoes,
              pos=[half_foot - 0.065 * k, 0, -p.shin - p.ankle_z + 0.045 * k])

    torso = root.add_body(name=f"{prefix}torso", pos=[0, 0, p.waist_z])
    torso.add_joint(name=f"{prefix}waist", type=HINGE, axis=[0, 1, 0])
    top = p.shoulder_z - p.waist_z  # shoulder joints above the waist hinge
    bottom = hip_z - p.waist_z - 0.03 * k
    hw, hd, girth = p.torso_half_width, p.torso_half_depth, b.girth
    shoulder_y = p.shoulder_half_width + 0.3 * p.upper_arm_radius
    torso_sections = [
        (bottom, 0.92 * hd, 0.86 * hw, 0.0, 2.3),
        (0.0, 0.90 * hd, 0.84 * hw, 0.0, 2.3),
        (0.30 * top, 0.98 * hd * girth ** 0.3, 0.90 * hw, 0.006 * k, 2.4),
        (0.62 * top, hd, hw, 0.01 * k, 2.5),
        (0.84 * top, 0.90 * hd, 0.5 * (hw + shoulder_y), 0.005 * k, 2.8),
        (top, 0.76 * hd, shoulder_y, 0.0, 3.0),
        (top + 0.035 * k, 0.64 * hd, 0.86 * shoulder_y, 0.0, 2.8),
        (top + 0.06 * k, 0.52 * hd, 0.55 * hw, 0.0, 2.4),
        (top + 0.08 * k, 0.42 * hd, 0.34 * hw, 0.0, 2.2),
    ]
    meshes = {"torso": loft_mesh(torso_sections)}
    mesh_geoms = [("torso", "torso", upper, (0, 0, 0), (1, 0, 0, 0))]
    # Neck and head hang from a joint-less body at the base of the neck, pitched back by
    # ``head_pitch`` (a leaning rider still looks ahead).
    neck_base = top + 0.03 * k
    head = torso.add_body(name=f"{prefix}head", pos=[0, 0, neck_base],
                          quat=_pitch_quat(-head_pitch))
    chin = p.chin_z - p.waist_z - neck_base
    _geom(head, f"{prefix}neck", GEOM.mjGEOM_CAPSULE, [p.neck_radius], skin,
          fromto=[0, 0, -0.01 * k, 0.008 * k, 0, chin + 0.03 * k])
    half_head = p.head_height / 2
    head_x, head_z = 0.01 * k, chin + half_head
    hl, hwh = p.head_half_length, p.head_half_width
    _geom(head, f"{prefix}head", GEOM.mjGEOM_ELLIPSOID, [hl, hwh, half_head], skin,
          pos=[head_x, 0, head_z])
    if helmet is not None:
        _geom(head, f"{prefix}helmet", GEOM.mjGEOM_ELLIPSOID,
              [hl + 0.022 * k, hwh + 0.022 * k, 0.8 * half_head], rgba(helmet),
              pos=[head_x - 0.012 * k, 0, head_z + 0.24 * half_head])
    else:
        _add_hair_and_hat(head, prefix, b, colours, k, head_x, head_z, hl, hwh, half_head)

    for side, tag in ((1, "l"), (-1, "r")):
        shoulder = torso.add_body(name=f"{prefix}upper_arm_{tag}",
                                  pos=[0, side * p.shoulder_half_width, top])
        shoulder.add_joint(name=f"{prefix}shoulder_{tag}", type=HINGE, axis=[0, 1, 0])
        _geom(shoulder, f"{prefix}upper_arm_{tag}", GEOM.mjGEOM_CAPSULE, [p.upper_arm_radius],
              upper, fromto=[0, 0, 0, 0, 0, -p.upper_arm])
        elbow = shoulder.add_body(name=f"{prefix}forearm_{tag}", pos=[0, 0, -p.upper_arm])
        elbow.add_joint(name=f"{prefix}elbow_{tag}", type=HINGE, axis=[0, 1, 0])
        _geom(elbow, f"{prefix}forearm_{tag}", GEOM.mjGEOM_CAPSULE, [p.forearm_radius], sleeve,
              fromto=[0, 0, 0, 0, 0, -(p.forearm - 1.1 * p.hand_radius)])
        _geom(elbow, f"{prefix}hand_{tag}", GEOM.mjGEOM_ELLIPSOID,
              [0.62 * p.hand_radius, 0.5 * p.hand_radius, 1.1 * p.hand_radius], skin,
              pos=[0, 0, -p.forearm])

    if umbrella is not None:
        shoulder_r = np.array([0.0, top])
        hand_xz = (shoulder_r + p.upper_arm * limb_direction(UMBRELLA_ARM["shoulder_r"])
                   + p.forearm * limb_direction(UMBRELLA_ARM["shoulder_r"]
                                                + UMBRELLA_ARM["elbow_r"]))
        hand = np.array([hand_xz[0], -p.shoulder_half_width, hand_xz[1]])
        size = min(1.0, 0.55 + 0.45 * p.height / 1.75)
        radius, depth = 0.5 * size, 0.2 * size
        apex = np.array([0.5 * hand[0] + 0.03 * k, -0.08 * k, p.height - p.waist_z + 0.38 * size])
        axis = (apex - hand) / np.linalg.norm(apex - hand)
        _geom(torso, f"{prefix}umbrella_shaft", GEOM.mjGEOM_CAPSULE, [0.011], TRIM,
              fromto=list(hand - 0.13 * axis) + list(apex + 0.06 * axis))
        meshes["umbrella_canopy"] = canopy_mesh(radius, depth)
        mesh_geoms.append(("umbrella_canopy", "umbrella_canopy", rgba(umbrella),
                           tuple(apex - depth * axis), tuple(_quat_z_to(axis))))
    _attach_meshes(torso, prefix, "upper", meshes, mesh_geoms)


def _add_hair_and_hat(head, prefix: str, b: PersonBuild, colours: dict, k: float,
                      head_x: float, head_z: float, hl: float, hw: float, hh: float) -> None:
    hair = _colour(colours, "hair")
    hat = _colour(colours, "hat")
    if b.hair != "bald":
        _geom(head, f"{prefix}hair", GEOM.mjGEOM_ELLIPSOID,
              [hl + 0.01 * k, hw + 0.009 * k, 0.78 * hh], hair,
              pos=[head_x - 0.016 * k, 0, head_z + 0.3 * hh])
    if b.hair == "long":
        _geom(head, f"{prefix}hair_long", GEOM.mjGEOM_ELLIPSOID,
              [0.45 * hl, 0.92 * hw, 0.8 * hh], hair,
              pos=[head_x - 0.62 * hl, 0, head_z - 0.5 * hh])
    elif b.hair == "bun":
        _geom(head, f"{prefix}hair_bun", GEOM.mjGEOM_SPHERE, [0.38 * hw], hair,
              pos=[head_x - 0.85 * hl, 0, head_z + 0.6 * hh])
    if b.hat == "cap":
        _geom(head, f"{prefix}hat", GEOM.mjGEOM_ELLIPSOID,
              [hl + 0.014 * k, hw + 0.014 * k, 0.62 * hh], hat,
              pos=[head_x - 0.005 * k, 0, head_z + 0.42 * hh])
        _geom(head, f"{prefix}hat_brim", GEOM.mjGEOM_ELLIPSOID, [0.075 * k, 0.75 * hw, 0.008 * k],
              hat, pos=[head_x + hl + 0.02 * k, 0, head_z + 0.42 * hh], quat=_pitch_quat(0.2))
    elif b.hat == "beanie":
        _geom(head, f"{prefix}hat", GEOM.mjGEOM_ELLIPSOID,
              [hl + 0.016 * k, hw + 0.016 * k, 0.72 * hh], hat,
              pos=[head_x - 0.008 * k, 0, head_z + 0.42 * hh])
    elif b.hat == "brimmed":
        _geom(head, f"{prefix}hat", GEOM.mjGEOM_CYLINDER, [hw + 0.02 * k, 0.32 * hh], hat,
              pos=[head_x - 0.005 * k, 0, head_z + 0.9 * hh])
        _geom(head, f"{prefix}hat_brim", GEOM.mjGEOM_CYLINDER, [hl + 0.07 * k, 0.006 * k], hat,
              pos=[head_x - 0.005 * k, 0, head_z + 0.62 * hh])



# -- bicycles and motorcycles -------------------------------------------------------------------



@dataclass(frozen=True)
class RiderFit:
    """Where a rider meets a vehicle style, in the vehicle body's frame (metres, radians).

    ``saddle_x``: x of the rider's hips (the pelvis centre); ``saddle_top``: height of the saddle
    surface the pelvis rests on (a bicycle's saddle is set for its rider's legs instead,
    :func:`saddle_height`: this is its lowest setting); ``grip``: (x, z) of the hands on the handlebar; ``foot_l`` /
    ``foot_r``: (x, z) of the ankles with the feet on the pedals, pegs or floorboard;
    ``lean``: the torso's forward lean (waist angle); ``splay``: the thighs' outward yaw.
    """

    saddle_x: float
    saddle_top: float
    grip: tuple[float, float]
    foot_l: tuple[float, float]
    foot_r: tuple[float, float]
    lean: float
    splay: float


CRANK_LENGTH = 0.17
CRANK_ANGLE = math.radians(25)  # the left pedal forward and up, the right one back and down
BOTTOM_BRACKET = (0.0, 0.27)
_PEDAL_FRONT = (BOTTOM_BRACKET[0] + CRANK_LENGTH * math.cos(CRANK_ANGLE),
                BOTTOM_BRACKET[1] + CRANK_LENGTH * math.sin(CRANK_ANGLE))
_PEDAL_BACK = (BOTTOM_BRACKET[0] - CRANK_LENGTH * math.cos(CRANK_ANGLE),
               BOTTOM_BRACKET[1] - CRANK_LENGTH * math.sin(CRANK_ANGLE))
_ANKLE_ABOVE_PEDAL = (-0.06, 0.085)  # the ball of the foot on the pedal
_ANKLE_FRONT = (_PEDAL_FRONT[0] + _ANKLE_ABOVE_PEDAL[0], _PEDAL_FRONT[1] + _ANKLE_ABOVE_PEDAL[1])
_ANKLE_BACK = (_PEDAL_BACK[0] + _ANKLE_ABOVE_PEDAL[0], _PEDAL_BACK[1] + _ANKLE_ABOVE_PEDAL[1])
PEDAL_DEVELOPMENT_M = 5.0
"""How far a bicycle goes for one turn of its cranks (a 2.1 m tyre and a gear of 2.4): at 3.5-6.5
m/s, 42-78 turns a minute."""


def crank_angle(distance: float) -> float:
    """The bicycle's crank joint angle (radians in [0, 2 pi), about the bicycle's +y axis: the
    front pedal goes down) after ``distance`` metres ridden, 0 in the modelled pose
    (:data:`CRANK_ANGLE`)."""
    return (2.0 * math.pi * distance / PEDAL_DEVELOPMENT_M) % (2.0 * math.pi)


def pedal_ankles(crank: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """(x, z) of the left and right ankles (feet on the pedals) in the bicycle's frame with the
    cranks turned by ``crank`` (radians, :func:`crank_angle`) from the modelled pose."""
    c, s = math.cos(crank), math.sin(crank)
    ankles = []
    for pedal in (_PEDAL_FRONT, _PEDAL_BACK):  # the left pedal starts in front
        dx, dz = pedal[0] - BOTTOM_BRACKET[0], pedal[1] - BOTTOM_BRACKET[1]
        ankles.append((BOTTOM_BRACKET[0] + c * dx + s * dz + _ANKLE_ABOVE_PEDAL[0],
                       BOTTOM_BRACKET[1] - s * dx + c * dz + _ANKLE_ABOVE_PEDAL[1]))
    return ankles[0], ankles[1]

RIDER_FITS: dict[str, RiderFit] = {
    "city": RiderFit(-0.20, 0.82, (0.24, 1.05), _ANKLE_FRONT, _ANKLE_BACK, 0.25, 0.06),
    "road": RiderFit(-0.24, 0.82, (0.54, 0.91), _ANKLE_FRONT, _ANKLE_BACK, 1.0, 0.06),
    "standard": RiderFit(-0.30, 0.86, (0.36, 1.05), (-0.07, 0.43), (-0.07, 0.43), 0.4, 0.35),
    "sport": RiderFit(-0.26, 0.86, (0.36, 0.95), (-0.21, 0.51), (-0.21, 0.51), 0.9, 0.38),
    "scooter": RiderFit(-0.30, 0.82, (0.27, 1.0), (0.10, 0.41), (0.04, 0.41), 0.25, 0.12),
}


def _fit(vehicle_style: str) -> RiderFit:
    if vehicle_style not in RIDER_FITS:
        raise ValueError(f"vehicle style: expected one of {', '.join(RIDER_FITS)}, "
                         f"got {vehicle_style!r}")
    return RIDER_FITS[vehicle_style]


SADDLE_LEG_REACH = 0.96
"""A bicycle's saddle is set so that, over the whole pedal stroke, the rider's hip comes at most
this share of the leg (hip to ankle) from the ankle: the knee still bent by about 30 degrees at
the bottom, as a bicycle fitter sets it."""


@lru_cache(maxsize=1024)  # a rider's is asked at every physics step (riding_pose): 90 us a time
def saddle_height(vehicle_style: str, build: PersonBuild | None = None) -> float:
    """Height (m) of the saddle (seat) surface of ``vehicle_style`` for a rider of ``build``
    (default adult): a motorcycle's is its style's (:data:`RIDER_FITS`); a bicycle's is set for
    the rider's legs (:data:`SADDLE_LEG_REACH`), no lower than its style's ``saddle_top`` (the
    seat post all the way down, where the shortest riders stretch)."""
    fit = _fit(vehicle_style)
    if vehicle_style not in BICYCLE_STYLES:
        return fit.saddle_top
    p = body_proportions(build)
    reach = SADDLE_LEG_REACH * (p.thigh + p.shin)
    hip = math.inf
    for crank in np.linspace(0.0, 2.0 * math.pi, 72, endpoint=False):
        for x, z in pedal_ankles(float(crank)):
            dx = (x - fit.saddle_x) / math.cos(fit.splay)
            hip = min(hip, z + math.sqrt(max(reach ** 2 - dx ** 2, 0.0)))
    return max(fit.saddle_top, round(hip - 0.005 - p.pelvis_drop, 4))


def rider_position(vehicle_style: str,
                   build: PersonBuild | None = None) -> tuple[float, float, float]:
    """``pos`` for :func:`add_person` that seats a rider of ``build`` on ``vehicle_style``: the
    pelvis rests on the saddle (:func:`saddle_height`, 5 mm above its surface), hips over
    ``saddle_x``."""
    fit = _fit(vehicle_style)
    p = body_proportions(build)
    return (fit.saddle_x, 0.0, saddle_height(vehicle_style, build) + 0.005 + p.pelvis_drop - p.hip_z)


def riding_pose(vehicle_style: str, build: PersonBuild | None = None,
                crank: float = 0.0) -> dict[str, float]:
    """Joint angles (radians) of a rider of ``build`` (default adult) placed at
    :func:`rider_position` on ``vehicle_style``: torso leaned by the style (more when the arms
    are short), legs reaching the pedals / pegs / floorboard and hands on the grips (two-segment
    inverse kinematics). On a bicycle the feet follow the pedals with the cranks turned by
    ``crank`` (radians, :func:`crank_angle`; a leg too short for the bottom of the stroke is
    stretched towards it); a motorcycle's rider does not depend on it."""
    fit = _fit(vehicle_style)
    p = body_proportions(build)
    x0, _, z0 = rider_position(vehicle_style, build)
    pose = {"waist": fit.lean}
    feet = pedal_ankles(crank) if vehicle_style in BICYCLE_STYLES else (fit.foot_l, fit.foot_r)
    for tag, foot in zip(("l", "r"), feet):
        dx = (foot[0] - x0) / math.cos(fit.splay)
        pose[f"hip_{tag}"], pose[f"knee_{tag}"] = limb_ik(dx, foot[1] - z0 - p.hip_z, p.thigh,
                                                          p.shin, bend=1)
    top = p.shoulder_z - p.waist_z
    # A rider with short arms leans further forwards (up to 0.4 rad more) to reach the grips.
    for lean in fit.lean + np.linspace(0.0, 0.4, 9):
        shoulder = (x0 + top * math.sin(lean), z0 + p.waist_z + top * math.cos(lean))
        if math.dist(fit.grip, shoulder) <= 0.97 * (p.upper_arm + p.forearm):
            break
    pose["waist"] = float(lean)
    for tag in ("l", "r"):
        angles = limb_ik(fit.grip[0] - shoulder[0], fit.grip[1] - shoulder[1], p.upper_arm,
                         p.forearm, bend=-1)
        # Joint angles are relative to the leaned torso.
        pose[f"shoulder_{tag}"], pose[f"elbow_{tag}"] = angles[0] - lean, angles[1]
    return {joint: pose[joint] for joint in PERSON_JOINTS}


def add_rider(body, prefix: str, colours: dict, vehicle_style: str,
              build: PersonBuild | None = None,
              helmet: tuple[float, float, float] | None = None) -> None:
    """A person seated on the ``vehicle_style`` bicycle or motorcycle built under ``body``:
    :func:`add_person` at :func:`rider_position` with the style's leg splay, the head tipped back
    by 80 % of the torso's lean so that the rider looks ahead. Pose it with
    :func:`riding_pose` (``vehicle_style``, ``build``)."""
    lean = riding_pose(vehicle_style, build)["waist"]
    add_person(body, prefix, colours, pos=rider_position(vehicle_style, build), helmet=helmet,
               build=build, leg_splay=_fit(vehicle_style).splay, head_pitch=0.8 * lean)


def _tube(body, name: str, start, end, radius: float, colour) -> None:
    _geom(body, name, GEOM.mjGEOM_CAPSULE, [radius], colour, fromto=list(start) + list(end))


def _xz(point, y: float = 0.0) -> tuple[float, float, float]:
    return (point[0], y, point[1])


def _wheels(body, prefix: str, half_base: float, radius: float, tyre_section: tuple,
            rim: tuple, spokes: tuple, hub: tuple, meshes: dict, mesh_geoms: list) -> None:
    """Two wheels at x = +-``half_base``: a ring tyre (mesh, section ``tyre_section`` =
    (radial, axial) half axes, outer radius ``radius``), a ring rim (``rim`` = (major, section,
    colour)), ``spokes`` = (count of diameters, radius, colour) and a hub (radius, half width)."""
    radial, axial = tyre_section
    meshes["tyre"] = tube_ring_mesh(radius - radial, radial, axial, segments=28, sides=8)
    rim_major, rim_section, rim_colour = rim
    meshes["rim"] = tube_ring_mesh(rim_major, rim_section, rim_section * 1.2, segments=24,
                                   sides=6)
    count, spoke_radius, spoke_colour = spokes
    for x, tag in ((half_base, "front"), (-half_base, "rear")):
        mesh_geoms.append((f"tyre_{tag}", "tyre", TYRE, (x, 0, radius), (1, 0, 0, 0)))
        mesh_geoms.append((f"rim_{tag}", "rim", rim_colour, (x, 0, radius), (1, 0, 0, 0)))
        for index in range(count):
            angle = math.pi * (index + 0.25) / count
            dx, dz = rim_major * math.cos(angle), rim_major * math.sin(angle)
            _tube(body, f"{prefix}spokes_{tag}{index}", (x - dx, 0, radius - dz),
                  (x + dx, 0, radius + dz), spoke_radius, spoke_colour)
        _geom(body, f"{prefix}hub_{tag}", GEOM.mjGEOM_CYLINDER, list(hub), METAL,
              pos=[x, 0, radius], quat=Y_AXIS_QUAT)


def _fender(meshes: dict, mesh_geoms: list, name: str, x: float, axle_z: float, major: float,
            arc_deg: tuple[float, float], section: tuple[float, float], colour) -> None:
    meshes[name] = tube_ring_mesh(major, section[0], section[1],
                                  arc=(math.radians(arc_deg[0]), math.radians(arc_deg[1])),
                                  segments=12, sides=6)
    mesh_geoms.append((name, name, colour, (x, 0, axle_z), (1, 0, 0, 0)))


def add_bicycle(body, prefix: str, frame_colour: tuple[float, float, float],
                style: str = "city", rider: PersonBuild | None = None) -> float:
    """A bicycle of ``style`` (:data:`BICYCLE_STYLES`) with see-through ring wheels and spokes.

    "city": step-through frame, fenders, front basket, rear rack, chain guard, upright swept-back
    bars, wide saddle. "road": diamond frame, drop bars, thin tyres, narrow saddle set high.
    The saddle is set for a ``rider`` of that build (default adult; :func:`saddle_height`), and
    the cranks turn on a hinge joint ``{prefix}crank``.
    Returns the height (m) of the saddle's top surface, where the rider's pelvis rests
    (:func:`add_rider` with the same build seats a rider there).
    """
    if style not in BICYCLE_STYLES:
        raise ValueError(f"bicycle style: expected one of {', '.join(BICYCLE_STYLES)}, "
                         f"got {style!r}")
    frame = rgba(frame_colour)
    fit = RIDER_FITS[style]
    road = style == "road"
    radius, half_base = (0.34, 0.50) if road else (0.345, 0.54)
    meshes: dict = {}
    mesh_geoms: list = []
    _wheels(body, prefix, half_base, radius, (0.012, 0.012) if road else (0.021, 0.023),
            (radius - 0.04, 0.014, TRIM if road else RIM), (3, 0.0035, SPOKE), (0.03, 0.05),
            meshes, mesh_geoms)
    bb = BOTTOM_BRACKET
    rear_axle, front_axle = (-half_base, radius), (half_base, radius)
    if road:
        seat_cluster, head_top, head_low = (-0.16, 0.80), (0.40, 0.84), (0.44, 0.70)
        tubes = [("top_tube", seat_cluster, head_top), ("down_tube", bb, head_low),
                 ("seat_tube", bb, seat_cluster), ("seat_stay", seat_cluster, rear_axle)]
    else:
        seat_cluster, head_top, head_low = (-0.155, 0.80), (0.39, 0.86), (0.43, 0.68)
        bend = (0.21, 0.36)
        tubes = [("down_tube", head_low, bend), ("down_tube_low", bend, bb),
                 ("seat_tube", bb, seat_cluster), ("seat_stay", (-0.13, 0.70), rear_axle)]
    tubes += [("chain_stay", bb, rear_axle), ("head_tube", head_low, head_top),
              ("fork", head_low, front_axle)]
    for name, a, b in tubes:
        _tube(body, f"{prefix}{name}", _xz(a), _xz(b), 0.018 if road else 0.022, frame)
    # Seat post along the seat tube up to the saddle.
    direction = np.subtract(seat_cluster, bb) / np.linalg.norm(np.subtract(seat_cluster, bb))
    saddle_top = saddle_height(style, rider)
    post_top = np.array(seat_cluster) + direction * (saddle_top - 0.03 - seat_cluster[1]) \
        / direction[1]
    _tube(body, f"{prefix}seat_post", _xz(seat_cluster), _xz(post_top), 0.014, METAL)
    saddle_half = (0.13, 0.06, 0.025) if road else (0.12, 0.095, 0.04)
    _geom(body, f"{prefix}saddle", GEOM.mjGEOM_ELLIPSOID, saddle_half, TRIM,
          pos=[fit.saddle_x + 0.02, 0, saddle_top - saddle_half[2]])
    # Cranks and pedals, modelled at the pose of CRANK_ANGLE, turn on the ``crank`` hinge about
    # the bottom bracket (the motion code turns them with the distance ridden: crank_angle).
    _geom(body, f"{prefix}chainring", GEOM.mjGEOM_CYLINDER, [0.1, 0.004], METAL,
          pos=[bb[0], -0.05, bb[1]], quat=Y_AXIS_QUAT)
    crankset = body.add_body(name=f"{prefix}crankset", pos=[bb[0], 0.0, bb[1]])
    crankset.add_joint(name=f"{prefix}crank", type=HINGE, axis=[0, 1, 0])
    local = [(x - bb[0], z - bb[1]) for x, z in (_PEDAL_BACK, _PEDAL_FRONT)]
    _tube(crankset, f"{prefix}crank", _xz(local[0]), _xz(local[1]), 0.012, METAL)
    for (px, pz), side, tag in ((local[1], 1, "l"), (local[0], -1, "r")):
        # round about the pedal axle (y): it looks the same at every crank angle, as a pedal that
        # stays level under the foot does, with no joint of its own
        _geom(crankset, f"{prefix}pedal_{tag}", GEOM.mjGEOM_CYLINDER, [0.02, 0.045], TRIM,
              pos=[px, side * 0.1, pz], quat=Y_AXIS_QUAT)
    if road:
        stem_end = (0.50, 0.88)
        _tube(body, f"{prefix}stem", _xz(head_top), _xz(stem_end), 0.016, METAL)
        _tube(body, f"{prefix}handlebar", (stem_end[0], -0.21, stem_end[1]),
              (stem_end[0], 0.21, stem_end[1]), 0.013, TRIM)
        for side, tag in ((1, "l"), (-1, "r")):
            y = side * 0.21
            _tube(body, f"{prefix}drop_{tag}", (stem_end[0], y, stem_end[1]),
                  (0.59, y, 0.83), 0.013, TRIM)
            _tube(body, f"{prefix}drop_end_{tag}", (0.59, y, 0.83), (0.51, y, 0.76), 0.013, TRIM)
            _geom(body, f"{prefix}hood_{tag}", GEOM.mjGEOM_ELLIPSOID, [0.035, 0.016, 0.022],
                  TRIM, pos=[0.55, y, 0.9])
    else:
        stem_end = (0.37, 1.05)
        _tube(body, f"{prefix}stem", _xz(head_top), _xz(stem_end), 0.016, METAL)
        _tube(body, f"{prefix}handlebar", (stem_end[0], -0.2, stem_end[1]),
              (stem_end[0], 0.2, stem_end[1]), 0.013, METAL)
        for side, tag in ((1, "l"), (-1, "r")):
            _tube(body, f"{prefix}grip_{tag}", (stem_end[0], side * 0.2, stem_end[1]),
                  (fit.grip[0] - 0.02, side * 0.27, fit.grip[1]), 0.017, TRIM)
        _geom(body, f"{prefix}basket", GEOM.mjGEOM_BOX, [0.12, 0.16, 0.09], WICKER,
              pos=[0.56, 0, 0.93])
        _geom(body, f"{prefix}rack", GEOM.mjGEOM_BOX, [0.19, 0.075, 0.012], METAL,
              pos=[-0.47, 0, 0.76])
        _geom(body, f"{prefix}chain_guard", GEOM.mjGEOM_BOX, [0.26, 0.006, 0.03], frame,
              pos=[-0.22, -0.07, 0.31], quat=_pitch_quat(-0.12))
        _fender(meshes, mesh_geoms, "fender_front", half_base, radius, radius + 0.03, (20, 150),
                (0.006, 0.032), frame)
        _fender(meshes, mesh_geoms, "fender_rear", -half_base, radius, radius + 0.03, (35, 165),
                (0.006, 0.032), frame)
    _attach_meshes(body, prefix, "bicycle", meshes, mesh_geoms)
    return saddle_top


def add_motorcycle(body, prefix: str, colour: tuple[float, float, float],
                   style: str = "standard") -> float:
    """A motorcycle of ``style`` (:data:`MOTORCYCLE_STYLES`) with ring tyres.

    "standard": naked bike, round headlight, tank, flat seat, wide bars, mirrors. "sport": full
    fairing with windscreen and twin lights, belly pan, low clip-on bars, raised tail. "scooter":
    small wheels, leg shield, floorboard, seat box and a rear body over the engine.
    Returns the height (m) of the seat's top surface, where the rider's pelvis rests.
    """
    if style not in MOTORCYCLE_STYLES:
        raise ValueError(f"motorcycle style: expected one of {', '.join(MOTORCYCLE_STYLES)}, "
                         f"got {style!r}")
    paint = rgba(colour)
    fit = RIDER_FITS[style]
    meshes: dict = {}
    mesh_geoms: list = []
    if style == "scooter":
        radius, half_base = 0.22, 0.62
        _wheels(body, prefix, half_base, radius, (0.055, 0.055), (0.125, 0.014, RIM),
                (0, 0.0, METAL), (0.1, 0.05), meshes, mesh_geoms)
    else:
        radius, half_base = (0.31, 0.72) if style == "standard" else (0.30, 0.70)
        _wheels(body, prefix, half_base, radius, (0.065, 0.062), (radius - 0.125, 0.014, RIM),
                (3, 0.014, METAL), (0.06, 0.06), meshes, mesh_geoms)
    seat_top = fit.saddle_top
    if style == "standard":
        _geom(body, f"{prefix}engine", GEOM.mjGEOM_BOX, [0.22, 0.15, 0.15], METAL,
              pos=[0.0, 0, 0.42])
        _geom(body, f"{prefix}cylinder_head", GEOM.mjGEOM_BOX, [0.1, 0.14, 0.08], CHROME,
              pos=[0.14, 0, 0.62], quat=_pitch_quat(0.35))
        _tube(body, f"{prefix}frame", (0.52, 0, 0.95), (-0.40, 0, 0.76), 0.03, TRIM)
        _tube(body, f"{prefix}down_frame", (0.50, 0, 0.90), (0.20, 0, 0.30), 0.028, TRIM)
        _geom(body, f"{prefix}tank", GEOM.mjGEOM_ELLIPSOID, [0.28, 0.155, 0.12], paint,
              pos=[0.16, 0, 0.84])
        _geom(body, f"{prefix}seat", GEOM.mjGEOM_BOX, [0.27, 0.14, 0.05], TRIM,
              pos=[fit.saddle_x - 0.02, 0, seat_top - 0.05])
        _geom(body, f"{prefix}side_cover", GEOM.mjGEOM_BOX, [0.14, 0.12, 0.09], TRIM,
              pos=[-0.24, 0, 0.66])
        _geom(body, f"{prefix}tail", GEOM.mjGEOM_BOX, [0.17, 0.11, 0.045], paint,
              pos=[-0.66, 0, 0.79])
        _geom(body, f"{prefix}taillight", GEOM.mjGEOM_BOX, [0.02, 0.07, 0.03], TAILLIGHT,
              pos=[-0.84, 0, 0.78])
        _tube(body, f"{prefix}swingarm", (-0.15, -0.1, 0.38), (-half_base, -0.1, radius), 0.03,
              METAL)
        _tube(body, f"{prefix}shock", (-0.42, -0.11, 0.74), (-0.60, -0.11, 0.40), 0.025, CHROME)
        for side, tag in ((1, "l"), (-1, "r")):
            _tube(body, f"{prefix}fork_{tag}", (0.54, side * 0.09, 0.98),
                  (half_base, side * 0.09, radius), 0.03, CHROME)
            _tube(body, f"{prefix}footpeg_{tag}", (-0.02, side * 0.12, 0.36),
                  (-0.02, side * 0.24, 0.36), 0.015, TRIM)
        _geom(body, f"{prefix}headlight", GEOM.mjGEOM_SPHERE, [0.09], HEADLIGHT,
              pos=[0.64, 0, 0.92])
        bar_z = fit.grip[1] + 0.01
        _tube(body, f"{prefix}handlebar", (0.47, -0.2, bar_z), (0.47, 0.2, bar_z), 0.02, TRIM)
        for side, tag in ((1, "l"), (-1, "r")):
            _tube(body, f"{prefix}grip_{tag}", (0.47, side * 0.2, bar_z),
                  (fit.grip[0], side * 0.37, fit.grip[1]), 0.02, TRIM)
            _tube(body, f"{prefix}mirror_stem_{tag}", (0.44, side * 0.26, bar_z),
                  (0.42, side * 0.33, bar_z + 0.18), 0.007, CHROME)
            _geom(body, f"{prefix}mirror_{tag}", GEOM.mjGEOM_ELLIPSOID, [0.02, 0.05, 0.035],
                  TRIM, pos=[0.42, side * 0.34, bar_z + 0.2])
        _tube(body, f"{prefix}exhaust", (0.05, -0.18, 0.28), (-0.78, -0.18, 0.45), 0.045, CHROME)
        _fender(meshes, mesh_geoms, "fender_front", half_base, radius, radius + 0.04, (35, 145),
                (0.01, 0.07), paint)
        _fender(meshes, mesh_geoms, "fender_rear", -half_base, radius, radius + 0.04, (70, 150),
                (0.01, 0.07), paint)
    elif style == "sport":
        # One shell from the nose over the tank to the raised tail.
        meshes["bodywork"] = side_loft_mesh([
            (0.82, 0.80, 0.88, 0.04, 2.2), (0.74, 0.64, 0.98, 0.15, 2.4),
            (0.58, 0.52, 1.04, 0.21, 2.6), (0.38, 0.46, 1.0, 0.22, 2.6),
            (0.16, 0.52, 0.99, 0.19, 2.6), (-0.05, 0.56, 0.95, 0.16, 2.6),
            (-0.13, 0.60, 0.84, 0.14, 2.6), (-0.42, 0.64, 0.84, 0.13, 2.6),
            (-0.62, 0.76, 0.92, 0.10, 2.4), (-0.82, 0.88, 0.94, 0.03, 2.2)])
        mesh_geoms.append(("bodywork", "bodywork", paint, (0, 0, 0), (1, 0, 0, 0)))
        _geom(body, f"{prefix}windscreen", GEOM.mjGEOM_ELLIPSOID, [0.012, 0.15, 0.12], GLASS,
              pos=[0.52, 0, 1.07], quat=_pitch_quat(-1.0))
        for side, tag in ((1, "l"), (-1, "r")):
            _geom(body, f"{prefix}headlight_{tag}", GEOM.mjGEOM_ELLIPSOID, [0.03, 0.05, 0.03],
                  HEADLIGHT, pos=[0.775, side * 0.07, 0.84])
            _tube(body, f"{prefix}fork_{tag}", (0.52, side * 0.09, 0.92),
                  (half_base, side * 0.09, radius), 0.03, CHROME)
            _tube(body, f"{prefix}clip_on_{tag}", (0.44, side * 0.1, fit.grip[1] - 0.01),
                  (fit.grip[0], side * 0.29, fit.grip[1]), 0.019, TRIM)
            _geom(body, f"{prefix}mirror_{tag}", GEOM.mjGEOM_ELLIPSOID, [0.04, 0.05, 0.03],
                  paint, pos=[0.56, side * 0.24, 0.98])
            _tube(body, f"{prefix}rearset_{tag}", (-0.16, side * 0.12, 0.44),
                  (-0.16, side * 0.22, 0.44), 0.014, METAL)
            _tube(body, f"{prefix}beam_{tag}", (0.42, side * 0.12, 0.84),
                  (-0.25, side * 0.12, 0.66), 0.04, METAL)
        _geom(body, f"{prefix}belly_pan", GEOM.mjGEOM_ELLIPSOID, [0.36, 0.16, 0.15], paint,
              pos=[0.12, 0, 0.42])
        _geom(body, f"{prefix}seat", GEOM.mjGEOM_BOX, [0.17, 0.125, 0.025], TRIM,
              pos=[fit.saddle_x, 0, seat_top - 0.025])
        _geom(body, f"{prefix}taillight", GEOM.mjGEOM_BOX, [0.02, 0.05, 0.02], TAILLIGHT,
              pos=[-0.80, 0, 0.91])
        _tube(body, f"{prefix}swingarm", (-0.1, -0.1, 0.40), (-half_base, -0.1, radius), 0.035,
              METAL)
        _tube(body, f"{prefix}exhaust", (-0.30, -0.13, 0.52), (-0.72, -0.13, 0.68), 0.05,
              CHROME)
        _fender(meshes, mesh_geoms, "fender_front", half_base, radius, radius + 0.03, (45, 135),
                (0.008, 0.06), paint)
    else:  # scooter
        _geom(body, f"{prefix}floorboard", GEOM.mjGEOM_BOX, [0.27, 0.17, 0.035], TRIM,
              pos=[0.06, 0, 0.30])
        _geom(body, f"{prefix}leg_shield", GEOM.mjGEOM_ELLIPSOID, [0.08, 0.22, 0.36], paint,
              pos=[0.41, 0, 0.66], quat=_pitch_quat(-0.22))
        _geom(body, f"{prefix}headset", GEOM.mjGEOM_BOX, [0.08, 0.12, 0.055], paint,
              pos=[0.40, 0, fit.grip[1] + 0.01])
        _geom(body, f"{prefix}headlight", GEOM.mjGEOM_ELLIPSOID, [0.03, 0.07, 0.04], HEADLIGHT,
              pos=[0.47, 0, fit.grip[1] + 0.01])
        for side, tag in ((1, "l"), (-1, "r")):
            _tube(body, f"{prefix}grip_{tag}", (0.40, side * 0.11, fit.grip[1] + 0.01),
                  (fit.grip[0], side * 0.33, fit.grip[1]), 0.018, TRIM)
            _tube(body, f"{prefix}mirror_stem_{tag}", (0.36, side * 0.2, fit.grip[1] + 0.02),
                  (0.35, side * 0.27, fit.grip[1] + 0.18), 0.007, CHROME)
            _geom(body, f"{prefix}mirror_{tag}", GEOM.mjGEOM_ELLIPSOID, [0.02, 0.045, 0.03],
                  TRIM, pos=[0.35, side * 0.28, fit.grip[1] + 0.2])
        _tube(body, f"{prefix}fork", (0.47, 0, 0.55), (half_base, 0, radius), 0.03, METAL)
        # The seat box and the rear body over the engine and the rear wheel, one shell.
        meshes["rear_body"] = side_loft_mesh([
            (-0.04, 0.33, 0.70, 0.12, 3.0), (-0.10, 0.30, 0.73, 0.16, 3.0),
            (-0.30, 0.30, 0.74, 0.20, 2.8), (-0.58, 0.36, 0.74, 0.21, 2.6),
            (-0.76, 0.47, 0.71, 0.17, 2.4), (-0.87, 0.56, 0.65, 0.07, 2.2)])
        mesh_geoms.append(("rear_body", "rear_body", paint, (0, 0, 0), (1, 0, 0, 0)))
        _geom(body, f"{prefix}seat", GEOM.mjGEOM_ELLIPSOID, [0.31, 0.15, 0.055], TRIM,
              pos=[fit.saddle_x - 0.03, 0, seat_top - 0.055])
        _geom(body, f"{prefix}taillight", GEOM.mjGEOM_BOX, [0.02, 0.07, 0.025], TAILLIGHT,
              pos=[-0.83, 0, 0.60])
        _geom(body, f"{prefix}engine", GEOM.mjGEOM_BOX, [0.2, 0.05, 0.07], METAL,
              pos=[-0.45, -0.11, 0.25])
        _tube(body, f"{prefix}exhaust", (-0.35, 0.14, 0.2), (-0.76, 0.14, 0.3), 0.035, METAL)
        _fender(meshes, mesh_geoms, "fender_front", half_base, radius, radius + 0.03, (20, 160),
                (0.012, 0.075), paint)
    _attach_meshes(body, prefix, "motorcycle", meshes, mesh_geoms)
    return seat_top


def unit_yaw_quat(heading: float) -> np.ndarray:
    """(4,) quaternion (w, x, y, z) of a turn by ``heading`` radians about +z (the general
    yaw-pitch-roll one is :func:`rainbench.mjcf.layout.yaw_quat`)."""
    return np.array([math.cos(heading / 2), 0.0, 0.0, math.sin(heading / 2)])
