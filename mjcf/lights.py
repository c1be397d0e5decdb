"""Lights after dark: headlights, tail lights and street lights of a dusk or night scene.

:func:`add_time_of_day_lights` edits an already-built road scene spec
(:func:`rainbench.mjcf.scene.build_spec`): by day it adds nothing; at dusk and night it adds the
ego car's low beams, a beam for each listed vehicle, a spot light under each street lamp head,
makes lamp geoms emissive, turns the low sun orange and near-horizontal (dusk) or off (night), and
makes the road and sidewalks fine enough grids for per-vertex lighting to draw light pools.
By day :func:`add_dark_vehicle_lamps` gives the vehicle lamp geoms dark materials, which the
weather rig lights when rain takes the daylight below 1 000 lux.

Light levels are not fixed here: ``rainbench.gen.weather.WeatherRig`` writes each weather's
levels (``rainbench.mjcf.weather.scene_lighting``) times the gains below into the model, and
chooses which of the lights are on in each frame.

The renderer's limit (mujoco 4.0.0, classic OpenGL renderer; docs/rain.md, "Time of day"): an
``mjvScene`` holds up to ``mjMAXLIGHT`` = 100 lights, the headlight first, then the model's
*active* lights in model order (world body first, then bodies in tree order); ``mjr_render``
enables ``GL_LIGHT0 + i`` for each, and the fixed-function pipeline has ``GL_MAX_LIGHTS`` = 8
(Mesa and NVIDIA), so only the first 8 light anything: not the nearest, the first. Lighting is
per vertex (Gouraud), so a light pool shows only on surfaces with vertices inside it.
"""

from __future__ import annotations

import math
import re
from typing import Sequence

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np

from rainbench.rain.weather import DUSK_SUN_ELEVATION_DEG, check_time_of_day, weather_at

from .weather import HEADLAMP_RGB, STREET_LIGHT_PEAK_LUX, STREET_LIGHT_RGB, scene_lighting

LIGHT_PREFIX = "tod/"
"""Names of every light added here start with this (``tod/lamp3``, ``tod/ego_beam_l``,
``tod/car2_beam``)."""
EGO_BEAM_NAMES = ("tod/ego_beam_l", "tod/ego_beam_r")
TIME_OF_DAY_TEXT = "rainbench/time_of_day"
"""Custom text naming the scene's time of day (absent by day), read by the weather rig."""
GL_MAX_LIGHTS = 8
"""Lights the fixed-function OpenGL pipeline enables (GL_LIGHT0..GL_LIGHT7; queried on Mesa
llvmpipe 22.3: 8, the OpenGL 1.x minimum NVIDIA and AMD also report), the headlight included."""

# -- ego low beams (ego body frame: x forward, origin at the footprint's centre, z up) ----------
BEAM_SOURCE_HEIGHT_M = 2.0
EGO_BEAM_POS = (2.0, 0.62, BEAM_SOURCE_HEIGHT_M)
"""The ego's low beams: 2 m ahead of its centre, 0.62 m to each side, and 2.0 m up -- not the
lamps' real 0.7 m (other vehicles' beams too: between their headlight geoms, 2 m up). The
renderer shades per vertex with Lambert's n.l and adds lights linearly in display values, so a
source 0.7 m up lights the road at d m with n.l = 0.7 / d (0.05 at 15 m) where the camera's
tone curve would show (0.05)^(1/2.2) = 0.26 of the on-axis level; a source
2 m up gives n.l = 0.13-0.4 over 5-15 m, close to that tone-mapped fall-off, so the road gets
the lit patch a dashcam shows. Objects in the beam are lit from slightly higher than real."""
BEAM_DOWN_DEG = 5.0
"""Low beams aim down: from 2 m their axis meets the road ~23 m ahead."""
BEAM_SPLAY_DEG = 4.0
"""Each beam turns this far outwards, widening the pair's patch (a real low beam is wide and
flat; an OpenGL spot is a round cone)."""
BEAM_CUTOFF_DEG = 40.0
BEAM_EXPONENT = 30.0
"""Spot cone of a low beam: OpenGL cones are round, so the real beam's flat cut-off is a cone
whose intensity falls as cos^30 off the axis (half at 12 degrees, nothing left at 40): the
road's lit patch and what stands in it, not the whole street."""
BEAM_ATTENUATION = (1.0, 0.03, 0.0)
"""Linear fall-off 1 / (1 + 0.03 d): with the road's n.l the lit road fades out 40-60 m
ahead."""
BEAM_REFERENCE_M = 10.0
BEAM_GAIN = 1.0 + BEAM_ATTENUATION[1] * BEAM_REFERENCE_M
"""Diffuse = peak level x this: a surface facing the lamp 10 m ahead on the axis gets the
headlamp's peak level (``scene_lighting(...).beam_diffuse``)."""
VEHICLE_BEAM_REACH_M = 12.0
"""Where another vehicle's beam pool centres, ahead of its lamps (used to pick lights)."""

# -- street lights ------------------------------------------------------------------------------
LAMP_DROP_M = 0.1
"""The light hangs this far below the lamp head's centre (out of the head's box)."""
LAMP_CUTOFF_DEG = 62.0
LAMP_EXPONENT = 1.0
"""Street luminaires spread wide along the road (batwing optics reaching 60-70 degrees off the
vertical, so that lamps 30 m apart overlap) and cut off above (little light on facades): a
62-degree cone (a pool of ~15 m radius from 7.9 m up) with a gentle cos fall-off."""
LAMP_ATTENUATION = (1.0, 0.05, 0.0)
LAMP_REFERENCE_M = 7.9
LAMP_GAIN = 1.0 + LAMP_ATTENUATION[1] * LAMP_REFERENCE_M
"""Diffuse = peak level x this: the road straight under a lamp head ~7.9 m up gets the street
light's peak level (``scene_lighting(...).lamp_diffuse``)."""
POOL_RADIUS_M = 12.0
"""Radius of a street light's pool on the road (used to pick lights)."""
FOCUS_AHEAD_M = 15.0
"""The road the camera sees best is about this far ahead: the lights whose pools come nearest
to it are the ones switched on."""

# -- emissive lamp geoms ------------------------------------------------------------------------
HEADLAMP_EMISSION = 1.6
TAILLAMP_EMISSION = 1.4
STREET_LAMP_EMISSION = 1.5
"""Emission x the geom's colour is added to its lit colour: lamps saturate like a real camera's
view of a light source (red tails stay red: their green and blue are small)."""
LAMP_MATERIALS = ("tod_headlamp", "tod_taillamp", "tod_streetlamp")
"""The emissive materials of head and tail lights and street lamp heads: the scene's lights as
a camera sees them (their mirror images on a wet road streak, rainbench.rain.weather)."""
TAILLAMP_RGBA = (1.0, 0.06, 0.04, 1.0)
STREET_LAMP_RGBA = (1.0, 0.86, 0.66, 1.0)

# -- the lights' intensity towards a viewer (the glow rain lays around them) ----------------------
STREET_LAMP_NADIR_CD = STREET_LIGHT_PEAK_LUX * LAMP_REFERENCE_M**2
"""A street light's luminous intensity straight down: its peak illuminance from a head 7.9 m up,
30 lux x (7.9 m)^2 = 1 872 cd. Towards a viewer at gamma from the vertical it sends
cos(gamma)^LAMP_EXPONENT of that inside the LAMP_CUTOFF_DEG cone and nothing beyond (the render's
spot light below it): a cut-off luminaire, which a camera farther than ~12 m along the street
sees lit but receives little light from."""
HEADLAMP_ONCOMING_CD = 350.0
"""A low beam's intensity towards an oncoming driver: UN ECE R112 caps its point B50L (the
oncoming driver's eyes at 50 m) at 350 cd."""
TAILLAMP_CD = 10.0
"""A rear position lamp's intensity on its axis (UN ECE R7: 4 to 17 cd)."""
LAMP_KINDS = {"tod_headlamp": "head", "tod_taillamp": "tail", "tod_streetlamp": "street"}


def lamp_intensity_cd(kinds: Sequence[str], positions: np.ndarray, forwards: np.ndarray,
                      viewer: np.ndarray) -> np.ndarray:
    """(N,) float64: each light's luminous intensity (cd) towards ``viewer``.

    Args:
        kinds: (N,) of ``"street"``, ``"head"`` or ``"tail"`` (:data:`LAMP_KINDS`).
        positions: (N, 3) world metres, each light's centre.
        forwards: (N, 3) the forward axis of each light's vehicle (street lamps: unused).
        viewer: (3,) world metres.

    A street lamp: :data:`STREET_LAMP_NADIR_CD` x cos(gamma)^:data:`LAMP_EXPONENT`, gamma the
    viewer's angle from the vertical below the lamp, 0 beyond :data:`LAMP_CUTOFF_DEG`; a head
    lamp: :data:`HEADLAMP_ONCOMING_CD` if the viewer is ahead of its vehicle, else 0; a tail lamp:
    :data:`TAILLAMP_CD` if the viewer is behind it, else 0.
    """
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    to_viewer = np.asarray(viewer, np.float64).reshape(3) - positions
    distance = np.maximum(np.linalg.norm(to_viewer, axis=1), 1e-9)
    ahead = np.einsum("ij,ij->i", np.asarray(forwards, np.float64).reshape(-1, 3), to_viewer)
    cos_gamma = -to_viewer[:, 2] / distance
    kinds = np.asarray(kinds)
    street = np.where(cos_gamma >= math.cos(math.radians(LAMP_CUTOFF_DEG)),
                      STREET_LAMP_NADIR_CD * np.maximum(cos_gamma, 0.0) ** LAMP_EXPONENT, 0.0)
    return np.select([kinds == "street", kinds == "head", kinds == "tail"],
                     [street, np.where(ahead > 0, HEADLAMP_ONCOMING_CD, 0.0),
                      np.where(ahead < 0, TAILLAMP_CD, 0.0)], 0.0)


def lamp_colour(kind: str) -> tuple[float, float, float]:
    """The colour (RGB in 0..1) of a light of ``kind`` (:data:`LAMP_KINDS`)."""
    return {"street": STREET_LIGHT_RGB, "head": HEADLAMP_RGB, "tail": tuple(TAILLAMP_RGBA[:3])}[kind]


STREET_LAMP_NAME = re.compile(r"^scenery/(?!signal)[a-z0-9_]*lamp\d*$")
"""Street lamp heads: ``scenery/pole_lamp3``, ``scenery/median_lamp0``, ``scenery/pole3_lamp``;
traffic signal lamps (``scenery/signal_lamp*``) are not street lights."""

# -- light receivers -----------------------------------------------------------------------------
RECEIVER_MATERIALS = ("asphalt", "concrete")
RECEIVER_MIN_HALF_M = 2.0
RECEIVER_MIN_WIDTH_HALF_M = 0.5
RECEIVER_MAX_TOP_M = 0.5
"""Road and sidewalk boxes (world geoms of these materials, longer than 4 m and at least 1 m wide
(not a barrier's foot, whose plane would float over the road beside it), their top face
level and at most 0.5 m up: not decks a camera can pass under) are replaced by planes at their
top faces after dark: a box face has numquads^2 (16) quads, so per-vertex lighting cannot draw a
20 m pool on a 400 m road; a plane is drawn as a grid of up to 200 x 200 quads
(mjMAXPLANEGRID), the finest MuJoCo draws a surface without a mesh (and the road must stay a
plane or box to be the renderer's mirror)."""
RECEIVER_GRID_M = 0.5
"""Requested grid cell of the receiver planes (across the road; along it the 200-cell limit
makes cells of road length / 198, ~2-3 m)."""
DEFAULT_ACTIVE_LAMPS = 3
"""Lamps switched on in the spec as built (the nearest ahead of the ego's start), so that an
exported scene.xml shows lit lamps; the renderer re-chooses them every frame."""


SPOT_RANGE_M = 200.0
"""Light ``range`` (ignored by the classic renderer, used by MuJoCo's Filament renderer)."""


def _unit(vector) -> list[float]:
    vector = np.asarray(vector, dtype=np.float64)
    return (vector / np.linalg.norm(vector)).tolist()


def _beam_dir(splay_deg: float = 0.0) -> list[float]:
    """Unit direction (body frame) of a beam aimed BEAM_DOWN_DEG down, ``splay_deg`` to the left."""
    down, yaw = math.radians(BEAM_DOWN_DEG), math.radians(splay_deg)
    return _unit([math.cos(down) * math.cos(yaw), math.cos(down) * math.sin(yaw), -math.sin(down)])


def _add_spot(body, name: str, pos, direction, *, cutoff: float, exponent: float,
              attenuation, diffuse, active: bool) -> None:
    body.add_light(name=name, type=mujoco.mjtLightType.mjLIGHT_SPOT, pos=list(pos),
                   dir=list(direction), cutoff=cutoff, exponent=exponent,
                   attenuation=list(attenuation), diffuse=list(diffuse), specular=[0.1, 0.1, 0.1],
                   ambient=[0.0, 0.0, 0.0], castshadow=False, active=active, range=SPOT_RANGE_M)


def lamp_heads(spec: mujoco.MjSpec, scenery_geoms: Sequence | None = None
               ) -> list[tuple[float, float, float]]:
    """World positions (x, y, z) of the street lamp heads of a road scene: the world-body geoms
    matching :data:`STREET_LAMP_NAME`, in spec order. ``scenery_geoms``: the world geoms to
    look among, in spec order (default: every one, read from the spec; MuJoCo's list of a
    30 000-geom world body takes seconds to read, so ``build_spec`` passes what it added)."""
    geoms = spec.worldbody.geoms if scenery_geoms is None else scenery_geoms
    return [tuple(float(v) for v in geom.pos) for geom in geoms
            if STREET_LAMP_NAME.match(geom.name)]


def _emissive(spec: mujoco.MjSpec, material: str, emission: float) -> None:
    spec.add_material(name=material, emission=emission, specular=0.3, shininess=0.5,
                      rgba=[0.5, 0.5, 0.5, 1.0])  # the geom's own rgba wins over this default


DARK_LAMP_SPECULAR = DARK_LAMP_SHININESS = 0.5
"""MuJoCo's look of a geom without a material (mjvGeom: specular 0.5, shininess 0.5): the dark
lamp materials of a daytime scene render as if the lamps had none."""


def _vehicle_lamp_geoms(spec: mujoco.MjSpec, parked_bodies: Sequence[str]) -> tuple[list, list]:
    """(head lamp geoms, tail lamp geoms) of ``spec``'s vehicles (``actor*/headlight*``,
    ``actor*/taillight*``), leaving out those of ``parked_bodies`` (vehicles standing all clip:
    their lamps are off)."""
    unlit = set()
    for body_name in parked_bodies:
        body = spec.body(body_name)
        if body is None:
            raise ValueError(f"parked_bodies: expected bodies of the spec, got {body_name!r}")
        unlit.update(g.name for g in body.find_all(mujoco.mjtObj.mjOBJ_GEOM))
    heads, tails = [], []
    # actors are bodies of their own: their geoms are read body by body, not from the spec's
    # list of every geom (seconds for a long clip's scenery)
    geoms = [g for body in spec.worldbody.bodies for g in body.find_all(mujoco.mjtObj.mjOBJ_GEOM)]
    for geom in geoms:
        if geom.name in unlit or not geom.name.startswith("actor"):
            continue
        if "/headlight" in geom.name:
            heads.append(geom)
        elif "/taillight" in geom.name:
            tails.append(geom)
    return heads, tails


def add_dark_vehicle_lamps(spec: mujoco.MjSpec, parked_bodies: Sequence[str] = ()) -> None:
    """Give a daytime road scene's vehicle lamp geoms (``actor*/headlight*``,
    ``actor*/taillight*``) the materials ``tod_headlamp`` and ``tod_taillamp`` (in place), dark:
    emission 0 and the look of no material, so the scene renders byte for byte as without them.
    The weather rig (``rainbench.gen.weather.WeatherRig``) lights them where the daylight falls
    below :data:`~rainbench.mjcf.weather.VEHICLE_LAMPS_BELOW_LUX` (rain above 10 mm/h). The lamps
    of ``parked_bodies`` (vehicles that stand all clip) get none: they stay off."""
    headlamp, taillamp, _ = LAMP_MATERIALS
    for material in (headlamp, taillamp):
        spec.add_material(name=material, emission=0.0, specular=DARK_LAMP_SPECULAR,
                          shininess=DARK_LAMP_SHININESS, rgba=[0.5, 0.5, 0.5, 1.0])
    heads, tails = _vehicle_lamp_geoms(spec, parked_bodies)
    for geoms, material in ((heads, headlamp), (tails, taillamp)):
        for geom in geoms:
            geom.material = material


def _plane_receivers(scenery_geoms: Sequence) -> None:
    """Replace the road and sidewalk boxes (:data:`RECEIVER_MATERIALS`) among ``scenery_geoms``
    by planes at their tops."""
    for geom in scenery_geoms:
        if geom.type != mujoco.mjtGeom.mjGEOM_BOX or geom.material not in RECEIVER_MATERIALS:
            continue
        half_x, half_y, half_z = (float(v) for v in geom.size)
        quat = np.asarray(geom.quat, dtype=np.float64)
        level = abs(quat[1]) < 1e-9 and abs(quat[2]) < 1e-9  # turned about z only
        top = float(geom.pos[2]) + half_z
        if not level or max(half_x, half_y) < RECEIVER_MIN_HALF_M or top > RECEIVER_MAX_TOP_M \
                or min(half_x, half_y) < RECEIVER_MIN_WIDTH_HALF_M:
            continue
        geom.type = mujoco.mjtGeom.mjGEOM_PLANE
        geom.pos = [float(geom.pos[0]), float(geom.pos[1]), top]
        geom.size = [half_x, half_y, RECEIVER_GRID_M / 2]


def add_time_of_day_lights(spec: mujoco.MjSpec, time_of_day: str, *, ego_body: str = "ego",
                           vehicle_bodies: Sequence[str] = (),
                           street_lamps: Sequence[tuple[float, float, float]] = (),
                           sky: str = "cloudy", parked_bodies: Sequence[str] = (),
                           scenery_geoms: Sequence | None = None) -> None:
    """Add the lights of ``time_of_day`` to ``spec`` (a built road scene), in place.

    Args:
        spec: a road scene with lights ``sun`` and ``skylight``; lamp geoms are found by name:
            ``actor*/headlight*``, ``actor*/taillight*`` (vehicles) and
            :data:`STREET_LAMP_NAME` (street lamp heads).
        time_of_day: ``day`` (nothing is added: the spec is unchanged), ``dusk`` or ``night``.
        ego_body: the body carrying the camera; gets two low beams ``tod/ego_beam_l|r``.
        vehicle_bodies: bodies of other vehicles (cars, motorcycles) to get a real beam
            ``tod/<body>_beam`` between their headlight geoms; the renderer lights at most a few
            at once (see the module docstring).
        street_lamps: (N,) world positions (x, y, z) of lamp heads (:func:`lamp_heads`); each
            gets a spot light ``tod/lamp{i}`` pointing down.
        sky: the scene's base weather, for the light levels written into the spec (what an
            exported scene.xml shows; the renderer rewrites them for every weather).
        parked_bodies: vehicles that stand all clip (parked, broken down): their lamps stay off
            (no beam, no emissive material).
        scenery_geoms: the world geoms among which the street lamp heads and the road and
            sidewalk boxes are found (default: every world geom, read from the spec; see
            :func:`lamp_heads`).
    """
    time_of_day = check_time_of_day(time_of_day)
    if time_of_day == "day":
        return
    ego = spec.body(ego_body)
    if ego is None:
        raise ValueError(f"ego_body: expected a body of the spec, got {ego_body!r}")
    lighting = scene_lighting(weather_at(sky, 0.0, time_of_day=time_of_day))
    spec.add_text(name=TIME_OF_DAY_TEXT, data=time_of_day)

    sun = spec.light("sun")
    if sun is not None:
        sun.active = lighting.sun_active
        sun.diffuse = list(lighting.sun_diffuse)
        sun.castshadow = lighting.sun_castshadow
        if time_of_day == "dusk":  # the same azimuth, the sun a few degrees above the horizon
            azimuth = math.atan2(-float(sun.dir[1]), -float(sun.dir[0]))
            elevation = math.radians(DUSK_SUN_ELEVATION_DEG)
            direction = np.array([-math.cos(elevation) * math.cos(azimuth),
                                  -math.cos(elevation) * math.sin(azimuth),
                                  -math.sin(elevation)])
            # keep the point the light looks at (its position + 60 m along its direction)
            target = (np.asarray(sun.pos, dtype=np.float64)
                      + 60.0 * np.asarray(sun.dir, dtype=np.float64))
            sun.dir = direction.tolist()
            sun.pos = (target - 60.0 * direction).tolist()
    skylight = spec.light("skylight")
    if skylight is not None:
        skylight.active = lighting.skylight_active
        skylight.diffuse = [lighting.skylight_diffuse] * 3
    spec.visual.headlight.ambient = list(lighting.headlight_ambient)
    spec.visual.headlight.diffuse = [lighting.headlight_diffuse] * 3

    beam = [c * BEAM_GAIN for c in lighting.beam_diffuse]
    for name, side in zip(EGO_BEAM_NAMES, (1.0, -1.0)):
        x, y, z = EGO_BEAM_POS
        _add_spot(ego, name, (x, side * y, z), _beam_dir(side * BEAM_SPLAY_DEG),
                  cutoff=BEAM_CUTOFF_DEG, exponent=BEAM_EXPONENT, attenuation=BEAM_ATTENUATION,
                  diffuse=beam, active=True)

    for body_name in vehicle_bodies:
        body = spec.body(body_name)
        if body is None:
            raise ValueError(f"vehicle_bodies: expected bodies of the spec, got {body_name!r}")
        heads = [g for g in body.find_all(mujoco.mjtObj.mjOBJ_GEOM) if "/headlight" in g.name]
        if not heads:
            continue
        holder = heads[0].parent  # the body whose frame the lamp geoms are placed in
        centre = np.mean([np.asarray(g.pos, dtype=np.float64) for g in heads
                          if g.parent.name == holder.name], axis=0) + [0.05, 0.0, 0.0]
        centre[2] = max(float(centre[2]), BEAM_SOURCE_HEIGHT_M)
        _add_spot(holder, f"{LIGHT_PREFIX}{body_name}_beam", centre, _beam_dir(),
                  cutoff=BEAM_CUTOFF_DEG, exponent=BEAM_EXPONENT, attenuation=BEAM_ATTENUATION,
                  diffuse=beam, active=False)

    lamp = [c * LAMP_GAIN for c in lighting.lamp_diffuse]
    ego_xy = np.asarray(ego.pos[:2], dtype=np.float64)
    ego_quat = np.asarray(ego.quat, dtype=np.float64)
    heading = 2.0 * math.atan2(ego_quat[3], ego_quat[0])  # the ego turns about z only
    forward = np.array([math.cos(heading), math.sin(heading)])

    def nearest_ahead(index: int) -> tuple[bool, float]:
        offset = np.asarray(street_lamps[index][:2], dtype=np.float64) - ego_xy
        return bool(offset @ forward < -POOL_RADIUS_M), float(np.hypot(*offset))

    default_on = set(sorted(range(len(street_lamps)), key=nearest_ahead)[:DEFAULT_ACTIVE_LAMPS])
    for index, (x, y, z) in enumerate(street_lamps):
        _add_spot(spec.worldbody, f"{LIGHT_PREFIX}lamp{index}", (x, y, z - LAMP_DROP_M),
                  (0.0, 0.0, -1.0), cutoff=LAMP_CUTOFF_DEG, exponent=LAMP_EXPONENT,
                  attenuation=LAMP_ATTENUATION, diffuse=lamp, active=index in default_on)

    headlamp, taillamp, street_lamp = LAMP_MATERIALS
    _emissive(spec, headlamp, HEADLAMP_EMISSION)
    _emissive(spec, taillamp, TAILLAMP_EMISSION)
    _emissive(spec, street_lamp, STREET_LAMP_EMISSION)
    heads, tails = _vehicle_lamp_geoms(spec, parked_bodies)
    for geom in heads:
        geom.material = headlamp
    for geom in tails:
        geom.material = taillamp
        geom.rgba = list(TAILLAMP_RGBA)
    scenery = spec.worldbody.geoms if scenery_geoms is None else scenery_geoms
    for geom in scenery:
        if STREET_LAMP_NAME.match(geom.name):
            geom.material = street_lamp
            geom.rgba = list(STREET_LAMP_RGBA)
    _plane_receivers(scenery)
