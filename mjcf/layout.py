"""Scene layouts: what a seed decides, as plain data, and how every unit moves in time.

A layout is sampled once from an explicit ``rng`` (:func:`sample_layout`) and is then a pure
description: which road scene (:data:`LAYOUTS`: street, intersection, curved, highway,
residential), its roads and static scenery (:class:`Prop`), the surfaces people stand on, the
ego vehicle and the moving units (vehicles, pedestrians, bicycles and motorcycles with their
riders). :func:`unit_pose` gives a unit's pose (x, y, yaw) at time ``t`` along its path of
straights and arcs as a pure function, so the generator and the tests share one definition of
the motion.

World frame: the ego starts at the origin driving towards +x, y to the left, z up; metres,
seconds. Traffic keeps to the right.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from rainbench.rain.weather import SKIES

from . import people

# COCO-80 indices, so any COCO-pretrained YOLO matches them directly (one definition: mjcf/classes.py).
from rainbench.store.classes import BICYCLE, CAR, CLASS_NAMES, MOTORCYCLE, PERSON  # noqa: E402,F401

LANE_WIDTH = 3.5
NUM_LANES = 4
SHOULDER_WIDTH = 1.5  # bicycle lane / shoulder between the outer lane and the curb
ROAD_HALF_WIDTH = NUM_LANES * LANE_WIDTH / 2 + SHOULDER_WIDTH  # 8.5 m: the curb face
CURB_HEIGHT = 0.15
SIDEWALK_WIDTH = 4.0
SIDEWALK_OUTER = ROAD_HALF_WIDTH + SIDEWALK_WIDTH  # 12.5 m
POLE_Y = ROAD_HALF_WIDTH + 0.3
TREE_Y = SIDEWALK_OUTER - 0.5
PEDESTRIAN_Y_RANGE = (ROAD_HALF_WIDTH + 0.9, SIDEWALK_OUTER - 1.1)
# Lane centre lines: two lanes towards +x (y < 0), two towards -x (y > 0).
LANE_CENTRES: tuple[float, ...] = (-5.25, -1.75, 1.75, 5.25)
BIKE_LANE_Y = ROAD_HALF_WIDTH - SHOULDER_WIDTH / 2  # 7.75

# (length, width, height) of each car style's body, metres.
CAR_DIMENSIONS: dict[str, tuple[float, float, float]] = {
    "sedan": (4.7, 1.85, 1.45),
    "hatchback": (4.0, 1.78, 1.5),
    "suv": (4.8, 1.95, 1.8),
}
# Footprints (length along heading, width) used for planning; they include the swing of limbs.
FOOTPRINTS: dict[str, tuple[float, float]] = {
    "pedestrian": (0.9, 0.7),
    "bicycle": (1.9, 0.8),
    "motorcycle": (2.3, 1.0),
}
EGO_DIMENSIONS = (4.6, 1.9)
SKY_PROBABILITIES = (0.40, 0.35, 0.25)  # clear, cloudy, overcast when the seed decides

CAR_PAINTS: tuple[tuple[float, float, float], ...] = (
    (0.75, 0.08, 0.08), (0.05, 0.15, 0.55), (0.85, 0.85, 0.85), (0.08, 0.08, 0.09),
    (0.45, 0.47, 0.50), (0.10, 0.40, 0.20), (0.90, 0.60, 0.05), (0.55, 0.10, 0.35),
    (0.95, 0.95, 0.92), (0.20, 0.55, 0.75),
)
CLOTHING: tuple[tuple[float, float, float], ...] = (
    (0.70, 0.10, 0.10), (0.10, 0.20, 0.60), (0.15, 0.15, 0.15), (0.85, 0.80, 0.70),
    (0.20, 0.50, 0.25), (0.90, 0.55, 0.10), (0.50, 0.30, 0.60), (0.40, 0.40, 0.45),
    (0.95, 0.95, 0.95), (0.30, 0.20, 0.10),
)
SKIN: tuple[tuple[float, float, float], ...] = (
    (0.96, 0.80, 0.69), (0.87, 0.67, 0.53), (0.67, 0.46, 0.33), (0.45, 0.30, 0.20),
)
FACADES: tuple[tuple[float, float, float], ...] = (
    (0.72, 0.62, 0.50), (0.60, 0.58, 0.55), (0.78, 0.75, 0.68), (0.55, 0.38, 0.30),
    (0.80, 0.78, 0.80), (0.62, 0.66, 0.70), (0.70, 0.55, 0.45),
)


from rainbench.store.classes import BUS, TRUCK  # noqa: E402  -- COCO ids of the heavy vehicles

# Vehicle styles every layout draws from, with their planning dimensions (length, width, height)
# in metres; mjcf/scene.py `_add_vehicle` builds them.
VEHICLE_STYLES: tuple[str, ...] = ("sedan", "hatchback", "suv", "van", "pickup", "bus", "truck")
VEHICLE_DIMENSIONS: dict[str, tuple[float, float, float]] = {
    **CAR_DIMENSIONS,
    "van": (5.0, 2.0, 2.1),
    "pickup": (5.3, 1.95, 1.85),
    "bus": (11.0, 2.55, 3.2),
    "truck": (8.0, 2.5, 3.4),
}
VEHICLE_CLASS: dict[str, int] = {style: CAR for style in VEHICLE_STYLES} | {"bus": BUS,
                                                                          "truck": TRUCK}
VEHICLE_SIZE_JITTER = 0.05  # each body dimension is drawn within +-5 % of the style's above
# An umbrella per pedestrian with this probability under each base sky: the same at every rain
# rate of the nested sweep (the geometry may not change with the rate).
UMBRELLA_PROBABILITY: dict[str, float] = {"clear": 0.05, "cloudy": 0.25, "overcast": 0.45}
UMBRELLA_COLOURS: tuple[tuple[float, float, float], ...] = (
    (0.05, 0.05, 0.06), (0.10, 0.15, 0.45), (0.70, 0.08, 0.10), (0.95, 0.80, 0.10),
    (0.15, 0.40, 0.20), (0.85, 0.85, 0.88), (0.45, 0.10, 0.45),
)
TIMES_OF_DAY: tuple[str, ...] = ("day", "dusk", "night")
TIME_OF_DAY_PROBABILITIES = (0.70, 0.15, 0.15)
CAMERA_HEIGHT_RANGE = (1.35, 1.95)  # m: sedan roof to SUV roof
CAMERA_PITCH_RANGE_DEG = (-4.0, 2.0)  # positive looks up
PLANNING_RATE_HZ = 25.0  # footprints are checked at this many times per second
COLLISION_MARGIN_M = 0.4  # footprints are grown by this much (in total) when planning
PUDDLE_AREA_M2 = 9.0 * 2 * ROAD_HALF_WIDTH  # one puddle per this much road surface (the street's)
ARC_STEP_RAD = math.radians(3.0)  # curved strips are drawn as boxes spanning at most this angle
ARC_OVERLAP_LIFT_M = 0.001
"""How much higher every other box of a curved strip stands: lengthened so that the outer edge
has no gaps, an arc's boxes overlap on its inner side, and two coplanar tops z-fought there (pale
slivers of the other box's texture, patches missing their shadow, flickering from frame to
frame). 1 mm keeps the lane markings (2 mm up) above the asphalt."""

# One line per layout: the registry `rainbench scene --list` prints.
LAYOUTS: dict[str, str] = {
    "street": "straight 4-lane urban street: bicycle lanes, zebra crossing, sidewalks, buildings",
    "intersection": "four-way junction with crossing and turning traffic and people on the "
                    "crosswalks; the ego drives straight through",
    "curved": "S-curved suburban road, 2 lanes each way; the ego follows its lane around the bends",
    "highway": "3-4 lanes each way, jersey-barrier median, hard shoulders, guard rails, an "
               "overpass; trucks and buses, a broken-down car on the shoulder",
    "residential": "narrow two-lane street lined with parked cars, driveways, hedges and houses; "
                   "people step out between parked cars",
}
# Probability of each layout when the seed decides (same order as LAYOUTS).
LAYOUT_PROBABILITIES: dict[str, float] = {
    "street": 0.30, "intersection": 0.20, "curved": 0.15, "highway": 0.15, "residential": 0.20,
}
# Weights of the vehicle styles (VEHICLE_STYLES order) in each layout's traffic.
STYLE_WEIGHTS: dict[str, tuple[float, ...]] = {
    "street": (1, 1, 1, 0, 0, 0, 0),  # today's street: the three legacy styles
    "intersection": (0.28, 0.2, 0.2, 0.12, 0.06, 0.08, 0.06),
    "curved": (0.3, 0.2, 0.25, 0.1, 0.1, 0.0, 0.05),
    "highway": (0.25, 0.08, 0.2, 0.1, 0.07, 0.12, 0.18),
    "residential": (0.3, 0.25, 0.25, 0.1, 0.1, 0.0, 0.0),
}
HEDGE = (0.13, 0.30, 0.12, 1.0)
TRUNK = (0.35, 0.25, 0.16, 1.0)
FOLIAGE_TINTS = ((0.25, 0.50, 0.20), (0.21, 0.43, 0.17), (0.31, 0.53, 0.20), (0.18, 0.38, 0.20),
                 (0.36, 0.50, 0.21))
"""Crown colours (RGB) that tint the ``foliage`` texture (mean level ~0.75): mid, dark, yellow,
blue-green and olive greens."""
COLUMNAR_TREE_SHARE = 0.25
"""Share of trees with a narrow, tall crown (poplar, hornbeam columns); the rest are round."""
TREE_STREAM = 0x7EE
"""Each tree draws its shape from its own generator, ``default_rng([seed, TREE_STREAM, n])`` for
the layout's n-th tree, so that trees leave the layout's random stream (actors, weather) as it
was."""
POLE_METAL = (0.35, 0.36, 0.38, 1.0)
WHITE_PAINT = (0.92, 0.92, 0.90, 1.0)
YELLOW_PAINT = (0.95, 0.75, 0.10, 1.0)
ZEBRA_PAINT = (0.93, 0.93, 0.91, 1.0)
CURB = (0.62, 0.62, 0.60, 1.0)
SIGN_PLATES: tuple[tuple[float, float, float, float], ...] = (
    (0.05, 0.25, 0.65, 1.0), (0.80, 0.08, 0.08, 1.0), (0.95, 0.95, 0.95, 1.0),
    (0.95, 0.75, 0.05, 1.0), (0.05, 0.45, 0.20, 1.0),
)
ROOFS: tuple[tuple[float, float, float, float], ...] = (
    (0.45, 0.18, 0.12, 1.0), (0.25, 0.25, 0.28, 1.0), (0.38, 0.30, 0.25, 1.0),
)


@dataclass(frozen=True)
class ScenarioConfig:
    """What a user may ask of a scenario; every ``None`` is decided by the seed.

    Defaults are the paper's actor mix: 20 s at 10 frames/s, 6 cars, 8 people, 2 bicycles and
    1 motorcycle placed along the ego vehicle's route (seed paper, Table I). Each layout reads
    the counts in its own way (docs/scenes.md): e.g. the highway has no bicycles and keeps its
    people off the lanes, the residential street adds parked cars.
    """

    duration_s: float = 20.0
    num_cars: int = 6
    num_pedestrians: int = 8
    num_bicycles: int = 2
    num_motorcycles: int = 1
    ego_speed: float | None = None  # m/s; seed: the layout's range (street 7..10)
    camera_height: float | None = None  # m above the road; seed: uniform 1.35..1.95
    sun_azimuth_deg: float | None = None  # seed: uniform 0..360
    sun_elevation_deg: float | None = None  # seed: uniform 25..70
    sky: str | None = None  # base weather; seed: clear 40 %, cloudy 35 %, overcast 25 %
    layout: str | None = None  # one of LAYOUTS; seed: LAYOUT_PROBABILITIES
    time_of_day: str | None = None  # day, dusk, night; seed: 70 / 15 / 15 %
    camera_pitch_deg: float | None = None  # positive looks up; seed: uniform -4..+2

    def __post_init__(self) -> None:
        if not self.duration_s > 0:
            raise ValueError(f"duration_s: expected > 0 seconds, got {self.duration_s}")
        for name in ("num_cars", "num_pedestrians", "num_bicycles", "num_motorcycles"):
            value = getattr(self, name)
            if not (isinstance(value, int) and 0 <= value <= 64):
                raise ValueError(f"{name}: expected an integer in 0..64, got {value!r}")
        if self.ego_speed is not None and not 0 <= self.ego_speed <= 40:
            raise ValueError(f"ego_speed: expected 0..40 m/s, got {self.ego_speed}")
        if self.camera_height is not None and not 0.5 <= self.camera_height <= 4.0:
            raise ValueError(f"camera_height: expected 0.5..4.0 m, got {self.camera_height}")
        if self.sun_elevation_deg is not None and not 5 <= self.sun_elevation_deg <= 90:
            raise ValueError(f"sun_elevation_deg: expected 5..90, got {self.sun_elevation_deg}")
        if self.sky is not None and self.sky not in SKIES:
            raise ValueError(f"sky: expected one of {', '.join(SKIES)}, got {self.sky!r}")
        if self.layout is not None:
            check_layout(self.layout)
        if self.time_of_day is not None and self.time_of_day not in TIMES_OF_DAY:
            raise ValueError(f"time_of_day: expected one of {', '.join(TIMES_OF_DAY)}, "
                             f"got {self.time_of_day!r}")
        if self.camera_pitch_deg is not None and not -30 <= self.camera_pitch_deg <= 30:
            raise ValueError(f"camera_pitch_deg: expected -30..30 degrees, "
                             f"got {self.camera_pitch_deg}")


def check_layout(name) -> str:
    """``name`` if it is a layout of :data:`LAYOUTS`, else a one-line ValueError naming them."""
    if name not in LAYOUTS:
        raise ValueError(f"layout: expected one of {', '.join(LAYOUTS)}, got {name!r}")
    return name


@dataclass(frozen=True)
class Unit:
    """One moving unit: a rigid root (a mocap body) travelling along a path.

    The path starts at ``start_xy`` with yaw ``heading`` and follows ``pieces``, each
    ``(length m, curvature 1/m)`` (0: straight, > 0: turning left); beyond the last piece (and
    before the start) it continues straight. The unit is ``clip(speed * (t - start_time), 0,
    max_distance)`` metres along it at time t (:func:`unit_pose`); ``pieces == ()`` is a straight
    line. ``kind`` is "car" (any vehicle style), "pedestrian", "bicycle" or "motorcycle";
    ``style`` the vehicle style. ``footprint`` is (length along the heading, width) in metres,
    used for collision planning; units on different ``level``s (0: the ground, 1: an overpass
    deck) never meet.
    """

    name: str
    kind: str
    start_xy: tuple[float, float]
    heading: float  # radians about +z at the start; 0 = towards +x
    speed: float
    footprint: tuple[float, float]
    start_time: float = 0.0
    max_distance: float = math.inf
    style: str = ""
    colours: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    stride_length: float = 1.4  # pedestrians: metres per full gait cycle
    pieces: tuple[tuple[float, float], ...] = ()
    level: int = 0
    size: tuple[float, float, float] = ()  # vehicles: body length, width, height in metres
    build: people.PersonBuild | None = None  # pedestrians, and the rider of a bicycle/motorcycle
    gait: people.Gait | None = None  # pedestrians who walk (speed > 0)


@dataclass(frozen=True)
class Actor:
    """A labelled instance: one unit may carry two (a bicycle and its rider)."""

    instance_id: int
    class_id: int
    unit: int  # index into Layout.units
    role: str  # "car" (any vehicle), "pedestrian", "bicycle", "motorcycle", "rider"


@dataclass(frozen=True)
class Prop:
    """One static scenery geom, named ``scenery/{name}`` in the scene.

    ``shape``: box, cylinder, ellipsoid or sphere with MuJoCo ``size``; ``pos`` its centre;
    ``quat`` (w, x, y, z) its orientation; ``material`` a scene material name (asphalt,
    concrete, grass, facade0..6, foliage) or ""; ``rgba`` the geom's colour, over the
    material's when both are given (the texture modulates it: one leaf texture, every crown its
    own green), None for the material's own colour (mid grey without a material).
    """

    name: str
    shape: str
    size: tuple[float, float, float]
    pos: tuple[float, float, float]
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    material: str = ""
    rgba: tuple[float, float, float, float] | None = None


@dataclass(frozen=True)
class Slab:
    """An oriented rectangle of walkable or drivable surface: centre (x, y), half length along
    ``yaw``, half width across it, and the height ``top`` of its surface (m)."""

    centre: tuple[float, float]
    half_length: float
    half_width: float
    yaw: float
    top: float


@dataclass(frozen=True)
class Road:
    """A road along a centreline path: ``start`` (x, y, heading) at arc length 0, then
    ``pieces`` (length, curvature) and straight beyond both ends. Cross-section from the
    centre outwards: ``median`` (half width of the central reserve), ``lanes_each_way`` lanes of
    ``lane_width``, ``shoulder`` (bicycle lane, parking strip or hard shoulder), then a
    ``sidewalk`` of that width behind a curb (0: none). ``s_range`` is the drawn stretch."""

    start: tuple[float, float, float]
    pieces: tuple[tuple[float, float], ...]
    lanes_each_way: int
    lane_width: float
    shoulder: float
    median: float
    sidewalk: float
    s_range: tuple[float, float]

    @property
    def half_width(self) -> float:
        """Centre to curb (or to the asphalt's edge), metres."""
        return self.median + self.lanes_each_way * self.lane_width + self.shoulder

    def lane_offset(self, lane: int) -> float:
        """Distance from the centreline to the centre of lane ``lane`` (0 = next to the centre)."""
        return self.median + (lane + 0.5) * self.lane_width


@dataclass(frozen=True)
class Layout:
    seed: int
    config: ScenarioConfig
    ego: Unit
    camera_height: float
    sun_direction: tuple[float, float, float]  # unit vector the light travels along
    units: tuple[Unit, ...]
    actors: tuple[Actor, ...]
    name: str = "street"  # which of LAYOUTS
    camera_pitch_deg: float = 0.0  # positive looks up
    roads: tuple[Road, ...] = ()
    props: tuple[Prop, ...] = ()  # static scenery (buildings, markings, trees, signs, ...)
    walkways: tuple[Slab, ...] = ()  # raised surfaces people stand on (sidewalks, decks)
    road_surfaces: tuple[Slab, ...] = ()  # asphalt at z = 0, where puddles form
    extent: tuple[float, float, float, float] = (-100.0, -100.0, 100.0, 100.0)  # x0, y0, x1, y1
    sky: str = "cloudy"  # base weather, one of rainbench.rain.weather.SKIES
    time_of_day: str = "day"  # one of TIMES_OF_DAY (recorded; the lights follow it elsewhere)
    # Puddles on the road at full size: (x, y, half length, half width, yaw radians) each.
    puddles: tuple[tuple[float, float, float, float, float], ...] = ()


# -- paths ---------------------------------------------------------------------------------------

@lru_cache(maxsize=4096)
def _piece_table(start: tuple[float, float, float], pieces: tuple[tuple[float, float], ...]):
    """(cumulative start arc lengths (P+1,), curvatures (P+1,), start poses (P+1, 3)) of a path;
    entry P is the straight continuation after the last piece."""
    poses = [start]
    bounds = [0.0]
    for length, curvature in pieces:
        x, y, h = poses[-1]
        poses.append(tuple(_advance(x, y, h, curvature, length)))
        bounds.append(bounds[-1] + length)
    curvatures = [k for _, k in pieces] + [0.0]
    return np.array(bounds), np.array(curvatures), np.array(poses)


def _advance(x, y, h, curvature, ds):
    """Pose after ``ds`` metres of constant ``curvature`` from (x, y, h); arrays broadcast."""
    curvature = np.asarray(curvature, dtype=np.float64)
    ds = np.asarray(ds, dtype=np.float64)
    straight = np.abs(curvature) < 1e-12
    safe = np.where(straight, 1.0, curvature)
    h1 = h + curvature * ds
    x1 = np.where(straight, x + ds * np.cos(h), x + (np.sin(h1) - np.sin(h)) / safe)
    y1 = np.where(straight, y + ds * np.sin(h), y - (np.cos(h1) - np.cos(h)) / safe)
    return x1, y1, h1


def path_pose(start: tuple[float, float, float], pieces: tuple[tuple[float, float], ...],
              s: np.ndarray | float) -> np.ndarray:
    """Pose (x, y, yaw) at arc lengths ``s`` along a path: shape ``s.shape + (3,)``.

    The path starts at ``start`` (x, y, yaw), follows ``pieces`` ((length, curvature) each) and
    continues straight beyond its end; negative ``s`` runs straight backwards from the start.
    """
    s = np.asarray(s, dtype=np.float64)
    bounds, curvatures, poses = _piece_table(tuple(float(v) for v in start),
                                             tuple((float(a), float(b)) for a, b in pieces))
    index = np.clip(np.searchsorted(bounds, s, side="right") - 1, 0, len(bounds) - 1)
    ds = s - bounds[index]
    k = np.where(s < 0, 0.0, curvatures[index])
    base = poses[index]
    x, y, h = _advance(base[..., 0], base[..., 1], base[..., 2], k, ds)
    return np.stack([x, y, h], axis=-1)


def offset_pieces(pieces, lateral: float) -> tuple[tuple[float, float], ...]:
    """The pieces of the path ``lateral`` metres to the left of a path with ``pieces``."""
    out = []
    for length, curvature in pieces:
        factor = 1.0 - curvature * lateral
        if factor <= 0:
            raise ValueError(f"offset_pieces: lateral offset {lateral} m lies beyond the centre "
                             f"of a curve of radius {1 / curvature:.1f} m")
        out.append((length * factor, curvature / factor))
    return tuple(out)


def _pieces_after(pieces, s0: float) -> tuple[tuple[float, float], ...]:
    """Pieces of the path from arc length ``s0`` on (the straight lead-in first if s0 < 0)."""
    out = [(-s0, 0.0)] if s0 < 0 else []
    position = 0.0
    for length, curvature in pieces:
        if position + length > s0:
            out.append((position + length - max(s0, position), curvature))
        position += length
    return tuple(out)


def _pieces_before_reversed(pieces, s0: float) -> tuple[tuple[float, float], ...]:
    """Pieces driven backwards from arc length ``s0`` towards the start (curvature negated)."""
    out = []
    position = 0.0
    for length, curvature in pieces:
        if position >= s0:
            break
        out.append((min(length, s0 - position), -curvature))
        position += length
    if s0 > position:  # from beyond the last piece: the straight continuation first
        out.append((s0 - position, 0.0))
    return tuple(reversed(out))


def road_pose(road: Road, s, lateral=0.0) -> np.ndarray:
    """(..., 3) pose at centreline arc length ``s``, ``lateral`` metres left of the centreline,
    with the centreline's heading."""
    pose = path_pose(road.start, road.pieces, s)
    lateral = np.asarray(lateral, dtype=np.float64)
    x = pose[..., 0] - lateral * np.sin(pose[..., 2])
    y = pose[..., 1] + lateral * np.cos(pose[..., 2])
    return np.stack([x, y, pose[..., 2] + 0 * lateral], axis=-1)


def lane_path(road: Road, s0: float, lateral: float, direction: int):
    """(start (x, y), heading, pieces) of a unit at centreline arc length ``s0``, ``lateral``
    metres left of the centreline, driving with (``direction`` +1) or against (-1) the road."""
    x, y, h = road_pose(road, s0, lateral)
    if direction > 0:
        pieces = offset_pieces(_pieces_after(road.pieces, s0), lateral)
    else:
        pieces = offset_pieces(_pieces_before_reversed(road.pieces, s0), -lateral)
        h = _wrap(h + math.pi)
    if all(curvature == 0 for _, curvature in pieces):
        pieces = ()  # a straight line (the continuation beyond the pieces is straight too)
    return (float(x), float(y)), float(h), pieces


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


# -- motion ----------------------------------------------------------------------------------------

def unit_distance(unit: Unit, t) -> float | np.ndarray:
    """Metres travelled along its path by ``unit`` at time(s) ``t`` (drives the walking gait)."""
    distance = np.clip(unit.speed * (np.asarray(t, dtype=np.float64) - unit.start_time),
                       0.0, unit.max_distance)
    return float(distance) if distance.ndim == 0 else distance


def unit_pose(unit: Unit, t: np.ndarray | float) -> np.ndarray:
    """World pose (x, y, yaw) of ``unit`` at times ``t``: shape ``t.shape + (3,)``."""
    return path_pose((unit.start_xy[0], unit.start_xy[1], unit.heading), unit.pieces,
                     unit_distance(unit, t))


def unit_position(unit: Unit, t: np.ndarray | float) -> np.ndarray:
    """World (x, y) of ``unit`` at times ``t``: shape ``t.shape + (2,)``."""
    return unit_pose(unit, t)[..., :2]


def ground_height(layout: Layout, x: float, y: float) -> float:
    """Height (m) of the surface people stand on at (x, y): the highest of the layout's
    walkways (sidewalks, the overpass deck) containing the point, else the road's 0."""
    return float(ground_heights(layout, np.array([[x, y]], dtype=np.float64))[0])


def ground_heights(layout: Layout, xy: np.ndarray) -> np.ndarray:
    """(N,) float64: :func:`ground_height` of each point of ``xy`` (N, 2), all at once."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if not layout.walkways:
        return np.zeros(len(xy))
    table = _walkway_table(layout.walkways)
    dx, dy = xy[:, 0, None] - table[None, :, 0], xy[:, 1, None] - table[None, :, 1]
    along = dx * table[:, 4] + dy * table[:, 5]
    across = -dx * table[:, 5] + dy * table[:, 4]
    inside = (np.abs(along) <= table[:, 2]) & (np.abs(across) <= table[:, 3])
    tops = np.where(inside, table[:, 6], -np.inf).max(axis=1)
    return np.where(inside.any(axis=1), tops, 0.0)


@lru_cache(maxsize=32)
def _walkway_table(walkways: tuple[Slab, ...]) -> np.ndarray:
    """(N, 7): centre x, y, half length, half width, cos yaw, sin yaw, top."""
    return np.array([(w.centre[0], w.centre[1], w.half_length, w.half_width, math.cos(w.yaw),
                      math.sin(w.yaw), w.top) for w in walkways], dtype=np.float64)


def footprint_corners(unit: Unit, times: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(T, 4, 2) corners of ``unit``'s footprint rectangle, grown by ``margin`` on every side,
    at ``times`` (T,)."""
    pose = unit_pose(unit, np.asarray(times, dtype=np.float64))
    half_length = unit.footprint[0] / 2 + margin
    half_width = unit.footprint[1] / 2 + margin
    forward = np.stack([np.cos(pose[:, 2]), np.sin(pose[:, 2])], axis=-1)
    left = np.stack([-forward[:, 1], forward[:, 0]], axis=-1)
    signs = np.array([(1, 1), (1, -1), (-1, -1), (-1, 1)], dtype=np.float64)
    return (pose[:, None, :2] + signs[None, :, :1] * half_length * forward[:, None]
            + signs[None, :, 1:] * half_width * left[:, None])


def units_collide(a: Unit, b: Unit, times: np.ndarray, margin: float = COLLISION_MARGIN_M) -> bool:
    """True when the footprints of ``a`` and ``b`` (each grown by ``margin / 2``) overlap at any
    of ``times``: oriented rectangles tested by separating axes, any headings."""
    if a.level != b.level:
        return False
    times = np.asarray(times, dtype=np.float64)
    centre_a, centre_b = unit_position(a, times), unit_position(b, times)
    near = np.linalg.norm(centre_a - centre_b, axis=-1) < _reach(a, b, margin)
    return _footprints_overlap(a, b, times, near, margin)


def _reach(a: Unit, b: Unit, margin: float) -> float:
    """Centre distance (m) beyond which the grown footprints of ``a`` and ``b`` cannot touch."""
    return (math.hypot(*a.footprint) + math.hypot(*b.footprint)) / 2 + margin


def _footprints_overlap(a: Unit, b: Unit, times: np.ndarray, near: np.ndarray,
                        margin: float) -> bool:
    """:func:`units_collide` at the ``times`` (T,) where ``near`` (T,) bool holds."""
    if not near.any():
        return False
    corners_a = footprint_corners(a, times[near], margin / 2)
    corners_b = footprint_corners(b, times[near], margin / 2)
    separated = np.zeros(int(near.sum()), dtype=bool)
    for corners in (corners_a, corners_b):
        for edge in (corners[:, 1] - corners[:, 0], corners[:, 3] - corners[:, 0]):
            axis = edge / np.linalg.norm(edge, axis=-1, keepdims=True)
            proj_a = np.einsum("tcj,tj->tc", corners_a, axis)
            proj_b = np.einsum("tcj,tj->tc", corners_b, axis)
            separated |= (proj_a.max(axis=1) < proj_b.min(axis=1)) | \
                         (proj_b.max(axis=1) < proj_a.min(axis=1))
    return bool(np.any(~separated))


def planning_times(duration_s: float) -> np.ndarray:
    """The times (s) at which collision planning checks footprints: PLANNING_RATE_HZ."""
    return np.linspace(0.0, duration_s, int(math.ceil(duration_s * PLANNING_RATE_HZ)) + 1)


# -- sampling helpers ----------------------------------------------------------------------------

def _pick(rng: np.random.Generator, options: tuple):
    return options[int(rng.integers(len(options)))]


def _draw(rng: np.random.Generator, names, probabilities) -> str:
    """One of ``names`` with ``probabilities`` (one uniform draw)."""
    cumulative = np.cumsum(np.asarray(probabilities, dtype=np.float64))
    index = int(np.searchsorted(cumulative / cumulative[-1], rng.random(), side="right"))
    return tuple(names)[min(index, len(names) - 1)]


def vehicle_size(style: str, rng: np.random.Generator) -> tuple[float, float, float]:
    """(length, width, height) metres of one vehicle of ``style``: each of the style's
    :data:`VEHICLE_DIMENSIONS` times a factor drawn in 1 +- :data:`VEHICLE_SIZE_JITTER`."""
    if style not in VEHICLE_DIMENSIONS:
        raise ValueError(f"vehicle style: expected one of {', '.join(VEHICLE_STYLES)}, "
                         f"got {style!r}")
    factors = rng.uniform(1.0 - VEHICLE_SIZE_JITTER, 1.0 + VEHICLE_SIZE_JITTER, 3)
    return tuple(round(float(d * f), 3) for d, f in zip(VEHICLE_DIMENSIONS[style], factors))


def yaw_quat(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of yaw about z, then pitch about the new y, then roll about x."""
    def q(axis, angle):
        return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * np.asarray(axis)])

    def mul(p, r):
        w1, x1, y1, z1 = p
        w2, x2, y2, z2 = r
        return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                         w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])

    quat = mul(mul(q((0, 0, 1), yaw), q((0, 1, 0), pitch)), q((1, 0, 0), roll))
    return tuple(float(v) for v in quat)


def _person_colours(rng: np.random.Generator) -> dict:
    return {"shirt": _pick(rng, CLOTHING), "trousers": _pick(rng, CLOTHING),
            "skin": _pick(rng, SKIN), "hair": _pick(rng, CLOTHING[2::7] + CLOTHING[9:])}


def _rider_colours(rng: np.random.Generator) -> dict:
    return {"frame": _pick(rng, CAR_PAINTS), "shirt": _pick(rng, CLOTHING),
            "trousers": _pick(rng, CLOTHING), "skin": _pick(rng, SKIN),
            "helmet": _pick(rng, CAR_PAINTS)}


class _Builder:
    """Collects one layout's units, actors and scenery while a sampler draws them."""

    def __init__(self, seed: int, config: ScenarioConfig, rng: np.random.Generator, name: str,
                 ego: Unit) -> None:
        self.seed, self.config, self.rng, self.name = seed, config, rng, name
        self.duration = config.duration_s
        self.times = planning_times(self.duration)
        self.ego = ego
        self.placed: list[Unit] = [ego]
        self._centres: list[np.ndarray] = [unit_position(ego, self.times)]  # of self.placed
        self.units: list[Unit] = []
        self.actors: list[Actor] = []
        self.props: list[Prop] = []
        self.walkways: list[Slab] = []
        self.road_surfaces: list[Slab] = []
        self.roads: list[Road] = []
        self._counts: dict[str, int] = {}
        self._walkers_indexed = 0  # self.placed[:this] are in the walker chunks
        self._walker_chunks: list[np.ndarray] = []
        self._walker_chunk_boxes: list[np.ndarray] = []  # (x_min, y_min, x_max, y_max) of each chunk
        self._walker_box_array = np.zeros((0, 4))
        self._poles: dict[tuple[int, int], list[tuple[float, float]]] = {}  # by 1 m cell
        self.building_footprints: list[tuple] = []  # ((x, y), (half_x, half_y), yaw) of each building
        self.building_tops: list[float] = []  # the height of each building's highest point (m)
        self._building_grid: dict[tuple[int, int], list[int]] = {}
        self._trees: list[tuple[int, list[int]]] = []  # the trunk's and the crown parts' prop indices

    def label(self, base: str) -> str:
        """A fresh prop name ``base{n}``."""
        count = self._counts.get(base, 0)
        self._counts[base] = count + 1
        return f"{base}{count}"

    def prop(self, base: str, shape: str, size, pos, quat=(1.0, 0.0, 0.0, 0.0), material="",
             rgba=None, exact: bool = False) -> None:
        name = base if exact else self.label(base)
        size = tuple(float(v) for v in (list(size) + [0.0] * (3 - len(size))))
        self.props.append(Prop(name, shape, size, tuple(float(v) for v in pos),
                               tuple(float(v) for v in quat), material,
                               None if rgba is None else tuple(float(v) for v in rgba)))

    def try_place(self, make, roles: tuple[tuple[int, str], ...], tries: int = 200) -> Unit | None:
        """Draw units from ``make()`` until one collides with nothing placed and label its
        actors; None when ``tries`` draws all collide."""
        for _ in range(tries):
            unit = make()
            if not self._collides(unit):
                self.placed.append(unit)
                self._centres.append(unit_position(unit, self.times))
                self.units.append(unit)
                for class_id, role in roles:
                    self.actors.append(Actor(len(self.actors), class_id, len(self.units) - 1, role))
                return unit
        return None

    def _collides(self, unit: Unit) -> bool:
        """``any(units_collide(unit, other, self.times) for other in self.placed)``, with the
        placed units' positions computed once and the distance test done for all at once."""
        centres = unit_position(unit, self.times)
        placed_centres = np.stack(self._centres)  # (P, T, 2)
        reach = np.array([_reach(unit, other, COLLISION_MARGIN_M) for other in self.placed])
        near = np.linalg.norm(centres[None] - placed_centres, axis=-1) < reach[:, None]
        return any(other.level == unit.level and near[index].any()
                   and _footprints_overlap(unit, other, self.times, near[index],
                                           COLLISION_MARGIN_M)
                   for index, other in enumerate(self.placed))

    def _index_walkers(self) -> None:
        """Cut the paths of the ground-level pedestrians placed since the last call into chunks
        of :data:`WALKER_CHUNK_POINTS` planning-time positions, each with its bounding box, so
        that a query looks only at the chunks near it (an hour-long clip has thousands of
        points per walker)."""
        if self._walkers_indexed == len(self.placed):
            return
        for unit, centres in zip(self.placed[self._walkers_indexed:], self._centres[self._walkers_indexed:]):
            if unit.kind != "pedestrian" or unit.level != 0:  # the overpass's walkers are above
                continue
            for begin in range(0, max(len(centres) - 1, 1), WALKER_CHUNK_POINTS):
                piece = centres[begin:begin + WALKER_CHUNK_POINTS + 1]
                self._walker_chunks.append(piece)
                self._walker_chunk_boxes.append(np.concatenate([piece.min(axis=0), piece.max(axis=0)]))
        self._walkers_indexed = len(self.placed)
        self._walker_box_array = np.array(self._walker_chunk_boxes).reshape(-1, 4)

    def walker_distance(self, x: float, y: float, cap: float) -> float:
        """How near the ground-level pedestrians placed so far come to the point (x, y) over the
        clip (their centres' paths: polylines through the planning-time positions), at most
        ``cap``."""
        self._index_walkers()
        point = np.array([x, y])
        boxes = self._walker_box_array
        near = np.flatnonzero((boxes[:, 0] - cap <= x) & (boxes[:, 1] - cap <= y)
                              & (boxes[:, 2] + cap >= x) & (boxes[:, 3] + cap >= y))
        nearest = cap
        for index in near:
            piece = self._walker_chunks[index]
            if len(piece) == 1:
                nearest = min(nearest, float(np.linalg.norm(piece[0] - point)))
                continue
            start, step = piece[:-1], np.diff(piece, axis=0)
            length = np.einsum("ij,ij->i", step, step)
            along = np.clip(np.einsum("ij,ij->i", point - start, step) / np.maximum(length, 1e-12), 0.0, 1.0)
            nearest = min(nearest, float(np.min(np.linalg.norm(start + along[:, None] * step - point, axis=1))))
        return nearest

    def place_pole(self, x: float, y: float, direction: float) -> tuple[float, float]:
        """Where a lamp or sign pole meant for (x, y) stands: there, or the nearest of the points
        +- 0.5, +- 1.0, ... m (up to 4 m) along ``direction`` (radians: the road's heading there)
        that no ground-level pedestrian's path comes within :data:`POLE_WALKER_CLEARANCE_M` of
        and no pole placed before stands within :data:`POLE_SPACING_M` of. Where no point is
        clear of the walkers (one walks the whole stretch), the one they pass farthest from. No
        draws: the scenery after it is unchanged. The pole is recorded for the next."""
        along = (math.cos(direction), math.sin(direction))
        return self.place_pole_among(x, y, [(shift * along[0], shift * along[1])
                                            for shift in POLE_SHIFTS_M])

    def place_pole_among(self, x: float, y: float,
                         offsets: Sequence[tuple[float, float]]) -> tuple[float, float]:
        """:meth:`place_pole` over the given candidate ``offsets`` from (x, y) (metres, nearest
        first, the first normally (0, 0)): the first clear of the walkers and of the poles placed
        before, else the one the walkers pass farthest from. No draws; the pole is recorded."""
        best, best_distance = (x, y), -1.0
        for dx, dy in offsets:
            cx, cy = x + dx, y + dy
            if self._pole_near(cx, cy):
                continue
            distance = self.walker_distance(cx, cy, POLE_WALKER_CLEARANCE_M)
            if distance >= POLE_WALKER_CLEARANCE_M:
                best = (cx, cy)
                break
            if distance > best_distance:
                best, best_distance = (cx, cy), distance
        cell = (math.floor(best[0]), math.floor(best[1]))
        self._poles.setdefault(cell, []).append(best)
        return float(best[0]), float(best[1])

    def _pole_near(self, x: float, y: float) -> bool:
        cx, cy = math.floor(x), math.floor(y)  # 1 m cells: a neighbour within 0.5 m is in the 3x3
        return any(math.hypot(x - px, y - py) < POLE_SPACING_M
                   for i in (cx - 1, cx, cx + 1) for j in (cy - 1, cy, cy + 1)
                   for px, py in self._poles.get((i, j), ()))

    def building_fits(self, footprint, top: float = math.inf) -> bool:
        """Whether a building footprint ``((x, y), (half_x, half_y), yaw)`` overlaps none placed
        before; if it fits, it is recorded with ``top``, the height of its highest point (m).
        Buildings are looked up in a grid of :data:`BUILDING_CELL_M` cells by their bounding
        boxes (a long clip has thousands)."""
        if any(self._rectangles_near(footprint, _rectangles_overlap)):
            return False
        self.building_footprints.append(footprint)
        self.building_tops.append(float(top))
        for cell in _cells_of(footprint):
            self._building_grid.setdefault(cell, []).append(len(self.building_footprints) - 1)
        return True

    def _rectangles_near(self, footprint, test):
        """The indices of the buildings whose grid cells ``footprint``'s bounding box meets and
        for which ``test(footprint, building footprint)`` holds, each once."""
        seen: set[int] = set()
        for cell in _cells_of(footprint):
            for index in self._building_grid.get(cell, ()):
                if index not in seen:
                    seen.add(index)
                    if test(footprint, self.building_footprints[index]):
                        yield index

    def add_tree(self, first_crown_prop: int) -> None:
        """Record a tree whose trunk (a cylinder) is ``self.props[first_crown_prop - 1]`` and whose
        crown, its main ellipsoid first, is ``self.props[first_crown_prop:]`` (for
        :meth:`_fit_tree_crowns`)."""
        self._trees.append((first_crown_prop - 1, list(range(first_crown_prop, len(self.props)))))

    def _fit_tree_crowns(self) -> None:
        """Keep every tree's crown out of the buildings (they are placed in any order: the
        junction's cross streets plant their trees first). A crown that would reach within
        :data:`TREE_FACADE_CLEARANCE_M` of a wall below the building's top leans away from it
        (towards the street's light), by at most :data:`TREE_CROWN_MAX_LEAN_M` and never so far
        that the trunk's top leaves the crown, and where that is not enough is narrowed about
        its trunk (its parts' horizontal sizes and offsets scaled alike, down to
        :data:`TREE_CROWN_MIN_WIDTH`), as street trees are pruned along facades
        (:func:`_crown_fit`). No draws: the rest of the layout is unchanged."""
        for trunk_index, indices in self._trees:
            trunk_prop = self.props[trunk_index]
            trunk = (trunk_prop.pos[0], trunk_prop.pos[1])
            parts = [self.props[index] for index in indices]
            reach = max(math.hypot(part.pos[0] - trunk[0], part.pos[1] - trunk[1]) + part.size[0]
                        for part in parts) + TREE_FACADE_CLEARANCE_M + TREE_CROWN_MAX_LEAN_M
            area = ((trunk[0], trunk[1]), (reach, reach), 0.0)
            near = list(self._rectangles_near(area, lambda a, b: _rectangles_overlap(a, b, 0.0)))
            if not near:
                continue
            walls = [(self.building_footprints[index], self.building_tops[index]) for index in near]
            scale, shift = _crown_fit(trunk, parts, walls, _trunk_top(trunk_prop))
            if scale == 1.0 and shift == (0.0, 0.0):
                continue
            for index, part in zip(indices, parts):
                self.props[index] = _fitted_crown_part(part, trunk, scale, shift)

    def place(self, make, what: str, roles: tuple[tuple[int, str], ...]) -> Unit:
        """:meth:`try_place` with 200 tries, or a one-line RuntimeError."""
        unit = self.try_place(make, roles)
        if unit is not None:
            return unit
        raise RuntimeError(
            f"layout {self.name}: could not place {what} without collisions for seed {self.seed} "
            "after 200 tries; lower the actor counts (num_cars, num_pedestrians, ...)")

    def vehicle(self, name: str, make_path, speed_range, style: str | None = None,
                speed: float | None = None, what: str = "",
                size: tuple[float, float, float] | None = None,
                required: bool = True) -> Unit | None:
        """Place a vehicle of the layout's style mix; ``make_path(speed, length)`` gives (start,
        heading, pieces, start_time, max_distance) for a drawn speed and body length. ``size``
        (length, width, height): the body's size, drawn by :func:`vehicle_size` when None.
        ``required`` False: None (nothing placed) when 60 draws all collide."""
        def make() -> Unit:
            chosen = style or _draw(self.rng, VEHICLE_STYLES, STYLE_WEIGHTS[self.name])
            body = size or vehicle_size(chosen, self.rng)
            length, width, _ = body
            v = speed if speed is not None else float(self.rng.uniform(*speed_range))
            if chosen in ("bus", "truck") and speed is None:
                v *= 0.85
            start, heading, pieces, start_time, max_distance = make_path(v, length)
            return Unit(name, "car", start, heading, v, (length, width), start_time=start_time,
                        max_distance=max_distance, style=chosen, pieces=pieces,
                        colours={"paint": _pick(self.rng, CAR_PAINTS)}, size=body)
        placed = (self.place(make, what or name, ()) if required
                  else self.try_place(make, (), tries=60))
        if placed is not None:
            self.actors.append(Actor(len(self.actors), VEHICLE_CLASS[placed.style],
                                     len(self.units) - 1, "car"))
        return placed

    def meet_s(self, road: Road, speed: float, direction: int, ahead_range) -> float:
        """Centreline arc length at t = 0 of a unit that is ``ahead`` metres in front of the
        ego (measured along ``road``) at a random time of the clip."""
        meet_time = self.rng.uniform(0.1 * self.duration, 0.9 * self.duration)
        ahead = self.rng.uniform(*ahead_range)
        return unit_distance(self.ego, meet_time) + ahead - direction * speed * meet_time

    def build(self, camera_height, camera_pitch_deg, sun_direction) -> Layout:
        self._fit_tree_crowns()
        xs = [centres[:, 0] for centres in self._centres]
        ys = [centres[:, 1] for centres in self._centres]
        for prop in self.props:
            xs.append(np.array([prop.pos[0]]))
            ys.append(np.array([prop.pos[1]]))
        extent = (float(min(x.min() for x in xs)) - 60.0, float(min(y.min() for y in ys)) - 60.0,
                  float(max(x.max() for x in xs)) + 60.0, float(max(y.max() for y in ys)) + 60.0)
        return Layout(
            seed=self.seed, config=self.config, ego=self.ego, camera_height=float(camera_height),
            sun_direction=sun_direction, units=tuple(self.units), actors=tuple(self.actors),
            name=self.name, camera_pitch_deg=float(camera_pitch_deg), roads=tuple(self.roads),
            props=tuple(self.props), walkways=tuple(self.walkways),
            road_surfaces=tuple(self.road_surfaces), extent=extent)


# -- roads as scenery ----------------------------------------------------------------------------

def _intervals(road: Road, s_lo: float, s_hi: float, gaps=()):
    """Sub-intervals (a, b, curvature) of [s_lo, s_hi] of constant curvature, minus ``gaps``."""
    bounds, curvatures, _ = _piece_table(road.start, road.pieces)
    cuts = sorted({s_lo, s_hi, *[b for b in bounds if s_lo < b < s_hi]})
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        index = int(np.clip(np.searchsorted(bounds, (a + b) / 2, side="right") - 1, 0,
                            len(bounds) - 1))
        k = 0.0 if (a + b) / 2 < 0 else float(curvatures[index])
        pieces = [(a, b)]
        for gap_lo, gap_hi in gaps:
            pieces = [part for lo, hi in pieces for part in
                      ((lo, min(hi, gap_lo)), (max(lo, gap_hi), hi)) if part[1] - part[0] > 1e-6]
        out.extend((lo, hi, k) for lo, hi in pieces)
    return out


def _strip(builder: _Builder, road: Road, base: str, lateral: float, half_width: float,
           top: float, thickness: float, s_range=None, gaps=(), material: str = "",
           rgba=None, walkway: bool = False, road_surface: bool = False) -> None:
    """Boxes covering the band ``lateral +- half_width`` along ``road`` with their top at
    ``top``: one box per straight stretch, short boxes (at most ARC_STEP_RAD each) on arcs,
    lengthened so that the outer edge has no gaps; where boxes overlap, every other one stands
    ``ARC_OVERLAP_LIFT_M`` higher. The slabs recorded (walkways, road surfaces) are at ``top``."""
    s_lo, s_hi = s_range or road.s_range
    joined, end, curved = 0, None, False  # boxes so far of the run of overlapping boxes
    for a, b, k in _intervals(road, s_lo, s_hi, gaps):
        steps = 1 if k == 0 else max(1, math.ceil((b - a) * abs(k) / ARC_STEP_RAD))
        edges = np.linspace(a, b, steps + 1)
        if end is None or abs(a - end) > 1e-9 or (k == 0 and not curved):
            joined = 0  # after a gap, or two straights end to end: no overlap
        for lo, hi in zip(edges[:-1], edges[1:]):
            mid = (lo + hi) / 2
            x, y, h = road_pose(road, mid, lateral)
            stretch = max(abs(1 - k * (lateral - half_width)), abs(1 - k * (lateral + half_width)))
            half_length = (hi - lo) * stretch / 2 + (0.03 if k != 0 else 0.0)
            # an arc's boxes overlap each other on its inner side, and the straights beside it:
            # every other box of a run stands a little higher, so that two tops do not fight for
            # the same pixels (or the same shadow texels); a road without arcs is unchanged
            lifted = top + (ARC_OVERLAP_LIFT_M if joined % 2 else 0.0)
            joined += 1
            builder.prop(base, "box", (half_length, half_width, thickness / 2),
                         (x, y, lifted - thickness / 2), yaw_quat(h), material, rgba)
            slab = Slab((float(x), float(y)), float(half_length), float(half_width), float(h),
                        float(top))  # where people stand and puddles lie: the strip's own top
            if walkway:
                builder.walkways.append(slab)
            if road_surface:
                builder.road_surfaces.append(slab)
        end, curved = b, k != 0


def _dashes(builder: _Builder, road: Road, base: str, lateral: float, period: float, length: float,
            half_width: float = 0.075, rgba=WHITE_PAINT, gaps=(), s_range=None) -> None:
    s_lo, s_hi = s_range or road.s_range
    for s in np.arange(math.floor(s_lo / period) * period, s_hi, period):
        if any(lo - length <= s <= hi + length for lo, hi in gaps):
            continue
        x, y, h = road_pose(road, s, lateral)
        builder.prop(base, "box", (length / 2, half_width, STATIC_Z), (x, y, 0.0), yaw_quat(h),
                     rgba=rgba)


STATIC_Z = 0.002  # markings float this high above the asphalt (no z-fighting)


def _road_surface(builder: _Builder, road: Road, name: str, gaps=(), sidewalk_gaps=(),
                  centre: str = "double_yellow", edge_lines: bool = True,
                  dashes: bool = True, dash_range=None) -> None:
    """Asphalt, lane markings, curbs and sidewalks of ``road`` as props, and its slabs;
    dashed lines only over ``dash_range`` (default: the whole road)."""
    half = road.half_width
    _strip(builder, road, f"{name}_asphalt", 0.0, half, 0.0, 0.1, gaps=gaps, material="asphalt",
           road_surface=True)
    if road.sidewalk > 0:
        for side in (-1, 1):
            tag = "lr"[side > 0]
            _strip(builder, road, f"{name}_sidewalk_{tag}", side * (half + road.sidewalk / 2),
                   road.sidewalk / 2, CURB_HEIGHT, CURB_HEIGHT, gaps=sidewalk_gaps,
                   material="concrete", walkway=True)
            _strip(builder, road, f"{name}_curb_{tag}", side * (half + 0.1), 0.1,
                   CURB_HEIGHT + 0.005, CURB_HEIGHT, gaps=sidewalk_gaps, rgba=CURB)
    if edge_lines:
        for side in (-1, 1):
            edge = road.median + road.lanes_each_way * road.lane_width
            _strip(builder, road, f"{name}_edge_line_{'lr'[side > 0]}", side * edge, 0.075,
                   STATIC_Z, 0.002, gaps=gaps, rgba=WHITE_PAINT)
    if centre == "double_yellow":
        for offset in (-0.12, 0.12):
            _strip(builder, road, f"{name}_centre_line_{'lr'[offset > 0]}", offset, 0.06, STATIC_Z,
                   0.002, gaps=gaps, rgba=YELLOW_PAINT)
    elif centre == "dashed":
        _dashes(builder, road, f"{name}_centre_dash", 0.0, 6.0, 3.0, 0.06, YELLOW_PAINT, gaps,
                dash_range)
    if dashes:
        for side in (-1, 1):
            for lane in range(1, road.lanes_each_way):
                _dashes(builder, road, f"{name}_dash_{'lr'[side > 0]}{lane}",
                        side * (road.median + lane * road.lane_width), 9.0, 3.0, gaps=gaps,
                        s_range=dash_range)


def _tree(builder: _Builder, x: float, y: float, scale: float = 1.0) -> None:
    """A tree at (x, y): a trunk and a crown of the textured ``foliage`` material, round (a main
    ellipsoid and 2-3 lobes) or columnar (:data:`COLUMNAR_TREE_SHARE`), its size, shape and green
    drawn from the tree's own generator (:data:`TREE_STREAM`)."""
    rng = np.random.default_rng([builder.seed, TREE_STREAM, builder._counts.get("tree", 0)])
    tint = np.array(FOLIAGE_TINTS[int(rng.integers(len(FOLIAGE_TINTS)))])
    first_crown_prop = len(builder.props) + 1  # after the trunk

    def crown(name: str, shape: str, size, pos) -> None:
        shade = tuple(float(c) for c in np.clip(tint * rng.uniform(0.9, 1.1), 0.0, 1.0))
        builder.prop(name, shape, tuple(v * scale for v in size),
                     (x + pos[0] * scale, y + pos[1] * scale, pos[2] * scale),
                     material="foliage", rgba=shade + (1.0,))

    if rng.random() < COLUMNAR_TREE_SHARE:
        trunk = rng.uniform(1.0, 1.3)
        radius, half_height = rng.uniform(1.0, 1.3), rng.uniform(3.0, 3.8)
        builder.prop("tree", "cylinder", (0.13 * scale, trunk * scale), (x, y, trunk * scale),
                     rgba=TRUNK)
        top = 2 * trunk + 0.85 * half_height
        crown("tree_crown", "ellipsoid", (radius, radius, half_height), (0.0, 0.0, top))
        crown("tree_lobe", "sphere", (0.75 * radius,),
              (rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), top + 0.6 * half_height))
        builder.add_tree(first_crown_prop)
        return
    trunk = rng.uniform(1.45, 1.9)
    radius, half_height = rng.uniform(1.6, 2.1), rng.uniform(1.9, 2.4)
    builder.prop("tree", "cylinder", (rng.uniform(0.13, 0.18) * scale, trunk * scale),
                 (x, y, trunk * scale), rgba=TRUNK)
    centre = 2 * trunk + 0.75 * half_height
    crown("tree_crown", "ellipsoid", (radius, radius * rng.uniform(0.85, 1.0), half_height),
          (0.0, 0.0, centre))
    for angle in rng.uniform(0.0, 2 * math.pi) + np.arange(int(rng.integers(2, 4))) * 2.1:
        reach = rng.uniform(0.45, 0.75) * radius  # lobes bulge the crown's sides, not its top
        crown("tree_lobe", "sphere", (rng.uniform(0.55, 0.75) * radius,),
              (reach * math.cos(angle), reach * math.sin(angle),
               centre + rng.uniform(-0.35, 0.3) * half_height))
    builder.add_tree(first_crown_prop)


POLE_SHIFTS_M = (0.0, *(sign * 0.5 * k for k in range(1, 9) for sign in (1.0, -1.0)))
"""Where along the road a lamp or sign pole may move from its spot, nearest first (up to 4 m)."""
POLE_SPACING_M = 0.5
"""The least distance between two poles' axes (lamps, signs, traffic lights: each moved clear of
the walkers)."""
WALKER_CHUNK_POINTS = 32
"""Planning-time positions per chunk of a walker's path in :meth:`_Builder.walker_distance`."""
BUILDING_CELL_M = 20.0
"""Cell of the grid :meth:`_Builder.building_fits` looks buildings up in."""
SIDEWALK_WALKER_KERB_M = 1.1
"""The least distance from the kerb of a sidewalk walker's path on the curved and residential
roads, whose sidewalks (2.5 and 2 m) have the lamp and sign poles 0.3-0.35 m from the kerb: at
0.6 m people walked along the poles' line, 0.25-0.3 m beside it, and where they covered all of
a pole's 4 m of play (:meth:`_Builder.place_pole`) an arm brushed it (2-3 % of those roads'
poles). From 1.1 m a walker's centre passes a pole's axis at 0.75 m or more."""
POLE_WALKER_CLEARANCE_M = 0.9
"""How near a pedestrian's centre may pass a lamp or sign pole: half a shoulder width (0.25 m), an
open umbrella's reach beyond it (0.5 m) and the pole or sign plate (0.15 m)."""
BUSH_WALKER_CLEARANCE_M = 0.35
"""How near a pedestrian's centre may pass a bush's edge (about a walking person's half width)."""


def _lamp(builder: _Builder, x: float, y: float, towards: float, z0: float = 0.0) -> None:
    """A street light at (x, y), moved along the road clear of the pedestrians' paths and the
    other poles (:meth:`_Builder.place_pole`), whose arm reaches 1.8 m in direction ``towards``
    (radians)."""
    x, y = builder.place_pole(x, y, towards + math.pi / 2)  # along the road: square to the arm
    c, s = math.cos(towards), math.sin(towards)
    builder.prop("pole", "cylinder", (0.08, 4.0), (x, y, z0 + 4.0), rgba=POLE_METAL)
    builder.prop("pole_arm", "box", (0.9, 0.04, 0.04), (x + 0.9 * c, y + 0.9 * s, z0 + 7.9),
                 yaw_quat(towards), rgba=POLE_METAL)
    builder.prop("pole_lamp", "box", (0.3, 0.15, 0.06), (x + 1.9 * c, y + 1.9 * s, z0 + 7.85),
                 yaw_quat(towards), rgba=(0.9, 0.9, 0.8, 1))


def _sign(builder: _Builder, x: float, y: float, facing: float, rng: np.random.Generator,
          height: float = 2.3, round_plate: bool | None = None) -> None:
    """A road sign at (x, y), moved along the road clear of the pedestrians' paths and the other
    poles (:meth:`_Builder.place_pole`): a pole and a plate (round or square) whose face looks
    along ``facing``."""
    x, y = builder.place_pole(x, y, facing)  # along the road: a sign faces along it
    plate = _pick(rng, SIGN_PLATES)
    round_plate = bool(rng.random() < 0.5) if round_plate is None else round_plate
    builder.prop("sign_pole", "cylinder", (0.04, height / 2), (x, y, height / 2), rgba=POLE_METAL)
    if round_plate:
        builder.prop("sign_plate", "cylinder", (0.32, 0.015), (x, y, height + 0.28),
                     yaw_quat(facing, math.pi / 2), rgba=plate)
    else:
        builder.prop("sign_plate", "box", (0.015, 0.3, 0.3), (x, y, height + 0.25),
                     yaw_quat(facing), rgba=plate)


def _bush(builder: _Builder, x: float, y: float, rng: np.random.Generator) -> None:
    """A bush at (x, y), left out (its draws made all the same) where a pedestrian would walk
    through it (:data:`BUSH_WALKER_CLEARANCE_M` beyond its widest half-axis)."""
    r = rng.uniform(0.5, 0.9)
    yaw = rng.uniform(0, math.pi)
    reach = r * 1.3 + BUSH_WALKER_CLEARANCE_M
    if builder.walker_distance(x, y, reach) < reach:
        return
    builder.prop("bush", "ellipsoid", (r * 1.3, r, r * 0.8), (x, y, r * 0.6), yaw_quat(yaw), rgba=HEDGE)


def _building(builder: _Builder, x: float, y: float, yaw: float, size, rng: np.random.Generator,
              roof: bool = False) -> None:
    """A building of full ``size`` (along yaw, across, height) centred at (x, y); left out (its
    draws made all the same, so the scenery after it is unchanged) where its footprint would
    overlap a building already placed (the corners of a junction, where two streets' rows meet)."""
    facade = int(rng.integers(len(FACADES)))
    colour = _pick(rng, ROOFS) if roof else None
    sx, sy, sz = size
    pitch = math.radians(32)
    top = sz + math.tan(pitch) * sy / 2 + 0.2 if roof else sz  # the ridge, slab thickness and all
    if not builder.building_fits(((float(x), float(y)), (sx / 2, sy / 2), float(yaw)), top):
        return
    builder.prop("building", "box", (sx / 2, sy / 2, sz / 2), (x, y, sz / 2), yaw_quat(yaw),
                 f"facade{facade}")
    if roof:  # a gable roof of two tilted slabs, ridge along the yaw direction
        half_span = sy / 2 / math.cos(pitch) + 0.3
        for side in (-1, 1):
            ox, oy = -math.sin(yaw) * side * sy / 4, math.cos(yaw) * side * sy / 4
            builder.prop("roof", "box", (sx / 2 + 0.3, half_span / 2, 0.08),
                         (x + ox, y + oy, sz + math.tan(pitch) * sy / 4),
                         yaw_quat(yaw, 0.0, -side * pitch), rgba=colour)


def _rectangles_overlap(first, second, margin: float = 0.05) -> bool:
    """Whether two rectangles ``((cx, cy), (half_x, half_y), yaw)`` in the ground plane overlap
    by more than ``margin`` metres (separating axes: the four edge directions)."""
    (c1, h1, yaw1), (c2, h2, yaw2) = first, second
    axes1 = np.array([[math.cos(yaw1), math.sin(yaw1)], [-math.sin(yaw1), math.cos(yaw1)]])
    axes2 = np.array([[math.cos(yaw2), math.sin(yaw2)], [-math.sin(yaw2), math.cos(yaw2)]])
    offset = np.subtract(c2, c1)
    for axis in (*axes1, *axes2):
        reach1 = h1[0] * abs(axes1[0] @ axis) + h1[1] * abs(axes1[1] @ axis)
        reach2 = h2[0] * abs(axes2[0] @ axis) + h2[1] * abs(axes2[1] @ axis)
        if abs(offset @ axis) >= reach1 + reach2 - margin:
            return False
    return True


def _cells_of(footprint) -> list[tuple[int, int]]:
    """The :data:`BUILDING_CELL_M` grid cells that the bounding box of a rectangle
    ``((x, y), (half_x, half_y), yaw)`` (any yaw) meets."""
    (x, y), (half_x, half_y), _ = footprint
    reach = math.hypot(half_x, half_y)
    return [(i, j)
            for i in range(math.floor((x - reach) / BUILDING_CELL_M), math.floor((x + reach) / BUILDING_CELL_M) + 1)
            for j in range(math.floor((y - reach) / BUILDING_CELL_M), math.floor((y + reach) / BUILDING_CELL_M) + 1)]


def _rectangle_distance(x: float, y: float, footprint) -> tuple[float, tuple[float, float]]:
    """Signed distance (m; negative inside) from the point (x, y) to the rectangle
    ``((cx, cy), (half_x, half_y), yaw)`` and the unit direction (dx, dy) from the rectangle's
    nearest boundary point outwards through the point (from its centre when inside)."""
    (cx, cy), (half_x, half_y), yaw = footprint
    c, s = math.cos(yaw), math.sin(yaw)
    u, v = c * (x - cx) + s * (y - cy), -s * (x - cx) + c * (y - cy)
    out_u, out_v = abs(u) - half_x, abs(v) - half_y
    if out_u <= 0.0 and out_v <= 0.0:  # inside: out through the nearer side
        du, dv = (math.copysign(1.0, u), 0.0) if out_u > out_v else (0.0, math.copysign(1.0, v))
        return max(out_u, out_v), (c * du - s * dv, s * du + c * dv)
    du, dv = math.copysign(max(out_u, 0.0), u), math.copysign(max(out_v, 0.0), v)
    distance = math.hypot(du, dv)
    return distance, ((c * du - s * dv) / distance, (s * du + c * dv) / distance)


TREE_FACADE_CLEARANCE_M = 0.15
"""How near a tree's crown may come to a building's wall (below the building's top)."""
TREE_CROWN_MIN_WIDTH = 0.45
"""The narrowest a crown is made beside a building: this share of its drawn width."""
TREE_CROWN_MAX_LEAN_M = 1.0
"""How far a crown may lean away from a wall over its trunk (towards the light of the street)."""


def _crown_lowest(part: Prop) -> float:
    return part.pos[2] - (part.size[2] if part.shape == "ellipsoid" else part.size[0])


def _crown_intrusion(trunk, parts, walls, scale: float, shift) -> tuple[float, tuple[float, float]]:
    """How far (m) the crown ``parts`` (ellipsoids and spheres about a vertical axis, their
    horizontal radius ``size[0]``), narrowed by ``scale`` about the ``trunk`` (x, y) and moved by
    ``shift`` (dx, dy), reaches into the most intruded wall of ``walls`` ((footprint, top) pairs)
    beyond :data:`TREE_FACADE_CLEARANCE_M` (<= 0: clear), and the direction out of that wall."""
    worst, away = -math.inf, (0.0, 0.0)
    for part in parts:
        x = trunk[0] + scale * (part.pos[0] - trunk[0]) + shift[0]
        y = trunk[1] + scale * (part.pos[1] - trunk[1]) + shift[1]
        for footprint, top in walls:
            if _crown_lowest(part) >= top:  # over the roof
                continue
            distance, direction = _rectangle_distance(x, y, footprint)
            intrusion = scale * part.size[0] + TREE_FACADE_CLEARANCE_M - distance
            if intrusion > worst:
                worst, away = intrusion, direction
    return worst, away


def _trunk_top(trunk: Prop) -> tuple[float, float]:
    """(height, radius) of the top of a tree's trunk, a vertical cylinder."""
    return trunk.pos[2] + trunk.size[1], trunk.size[0]


def _lean_limit(parts, trunk_top: tuple[float, float] | None, scale: float) -> float:
    """How far the crown ``parts`` narrowed by ``scale`` may lean off its trunk: at most
    :data:`TREE_CROWN_MAX_LEAN_M`, and no further than keeps the trunk's top (``trunk_top``:
    height, radius) inside the main crown (``parts[0]``, an ellipsoid) at that height, 5 cm
    clear."""
    if trunk_top is None:
        return TREE_CROWN_MAX_LEAN_M
    height, radius = trunk_top
    crown = parts[0]
    half_height = crown.size[2] if crown.shape == "ellipsoid" else crown.size[0]
    below = (crown.pos[2] - height) / half_height
    half_width = scale * crown.size[1 if crown.shape == "ellipsoid" else 0] * math.sqrt(max(0.0, 1.0 - below ** 2))
    return max(0.0, min(TREE_CROWN_MAX_LEAN_M, half_width - radius - 0.05))


def _crown_fit(trunk, parts, walls, trunk_top: tuple[float, float] | None = None
               ) -> tuple[float, tuple[float, float]]:
    """How to keep the crown ``parts`` (the main ellipsoid first) of the tree at ``trunk`` out of
    ``walls`` ((footprint, top) pairs, see :func:`_crown_intrusion`): the widest narrowing
    ``scale`` in [:data:`TREE_CROWN_MIN_WIDTH`, 1] (in steps of 0.05) for which leaning away from
    the walls, by at most :func:`_lean_limit` (1 m, and the trunk's top, ``trunk_top``
    (height, radius), kept inside the crown), clears them, and that lean (dx, dy); the narrowest
    with the longest lean where none does. (1.0, (0, 0)) when the crown is clear."""
    steps = round((1.0 - TREE_CROWN_MIN_WIDTH) / 0.05)
    for step in range(steps + 1):
        scale, shift = 1.0 - 0.05 * step, (0.0, 0.0)
        limit = _lean_limit(parts, trunk_top, scale)
        for _ in range(4):  # lean out of the deepest wall; a corner can take a second push
            intrusion, (dx, dy) = _crown_intrusion(trunk, parts, walls, scale, shift)
            if intrusion <= 0.0:
                return scale, shift
            shift = (shift[0] + dx * (intrusion + 1e-3), shift[1] + dy * (intrusion + 1e-3))
            length = math.hypot(*shift)
            if length > limit:
                shift = (0.0, 0.0) if length == 0.0 else (shift[0] * limit / length, shift[1] * limit / length)
                if step < steps:
                    break  # narrower, then
    return scale, shift


def _fitted_crown_part(part: Prop, trunk, scale: float, shift) -> Prop:
    """``part`` narrowed by ``scale`` about the vertical through ``trunk`` and moved by
    ``shift``: an ellipsoid keeps its height, a sphere (a lobe) shrinks whole."""
    x = trunk[0] + scale * (part.pos[0] - trunk[0]) + shift[0]
    y = trunk[1] + scale * (part.pos[1] - trunk[1]) + shift[1]
    if part.shape == "ellipsoid":
        size = (part.size[0] * scale, part.size[1] * scale, part.size[2])
    else:
        size = (part.size[0] * scale, part.size[1], part.size[2])
    return replace(part, pos=(float(x), float(y), part.pos[2]), size=tuple(float(v) for v in size))


# -- the layouts ---------------------------------------------------------------------------------

def _ego(config: ScenarioConfig, rng: np.random.Generator, speed_range, start, heading,
         pieces=()) -> Unit:
    speed = config.ego_speed if config.ego_speed is not None else rng.uniform(*speed_range)
    return Unit("ego", "ego", (float(start[0]), float(start[1])), float(heading), float(speed),
                EGO_DIMENSIONS, pieces=tuple(pieces))


def _lane_vehicles(b: _Builder, road: Road, count: int, speed_range, ahead=(12.0, 45.0),
                   prefix: str = "car", first: int = 0, heavy_first: bool = False) -> None:
    for index in range(count):
        def make_path(speed, length):
            direction = 1 if b.rng.random() < 0.5 else -1
            lane = int(b.rng.integers(road.lanes_each_way))
            lateral = -direction * road.lane_offset(lane)
            s0 = b.meet_s(road, speed, direction, ahead)
            start, heading, pieces = lane_path(road, s0, lateral, direction)
            return start, heading, pieces, 0.0, math.inf
        style = _pick(b.rng, ("bus", "truck")) if heavy_first and index == 0 else None
        b.vehicle(f"{prefix}{first + index}", make_path, speed_range, style=style,
                  what=f"vehicle {first + index}")


def _riders(b: _Builder, road: Road, bike_lateral: float | None, moto_speed=(6.0, 13.0),
            bike_speed=(3.5, 6.5)) -> None:
    counts = (("bicycle", b.config.num_bicycles if bike_lateral is not None else 0),
              ("motorcycle", b.config.num_motorcycles))
    for kind, count in counts:
        for index in range(count):
            def make() -> Unit:
                direction = 1 if b.rng.random() < 0.5 else -1
                if kind == "bicycle":
                    lateral = -direction * bike_lateral
                    speed = b.rng.uniform(*bike_speed)
                else:
                    lateral = -direction * road.lane_offset(int(b.rng.integers(road.lanes_each_way)))
                    speed = b.rng.uniform(*moto_speed)
                s0 = b.meet_s(road, speed, direction, (12.0, 40.0))
                start, heading, pieces = lane_path(road, s0, lateral, direction)
                return Unit(f"{kind}{index}", kind, start, heading, float(speed), FOOTPRINTS[kind],
                            colours=_rider_colours(b.rng), pieces=pieces)
            b.place(make, f"{kind} {index}",
                    ((BICYCLE if kind == "bicycle" else MOTORCYCLE, kind), (PERSON, "rider")))


def _sidewalk_walker(b: _Builder, road: Road, index: int, lateral_range,
                     ahead=(12.0, 40.0)) -> Unit:
    def make() -> Unit:
        side = float(_pick(b.rng, (-1.0, 1.0)))
        direction = 1 if b.rng.random() < 0.5 else -1
        speed = b.rng.uniform(0.9, 1.6)
        lateral = side * b.rng.uniform(*lateral_range)
        s0 = b.meet_s(road, speed, direction, ahead)
        start, heading, pieces = lane_path(road, s0, lateral, direction)
        return Unit(f"person{index}", "pedestrian", start, heading, float(speed),
                    FOOTPRINTS["pedestrian"], colours=_person_colours(b.rng),
                    stride_length=float(b.rng.uniform(1.2, 1.6)), pieces=pieces)
    return b.place(make, f"pedestrian {index}", ((PERSON, "pedestrian"),))


def _crosser(b: _Builder, index: int, road: Road, s: float, start_window=(0.0, 0.6),
             jitter: float = 1.5, side: float | None = None, required: bool = True) -> Unit | None:
    """A person crossing ``road`` at arc length ``s`` (+- jitter) from curb to curb; when
    ``required`` is False and traffic leaves no gap in 60 draws, None (nobody placed)."""
    def make() -> Unit:
        from_side = float(_pick(b.rng, (-1.0, 1.0))) if side is None else side
        at = s + b.rng.uniform(-jitter, jitter)
        x, y, h = road_pose(road, at, from_side * (road.half_width + 0.8))
        heading = _wrap(h - from_side * math.pi / 2)
        return Unit(f"person{index}", "pedestrian", (float(x), float(y)), heading,
                    float(b.rng.uniform(0.9, 1.6)), FOOTPRINTS["pedestrian"],
                    start_time=float(b.rng.uniform(*start_window) * b.duration),
                    max_distance=2 * road.half_width + 1.6, colours=_person_colours(b.rng),
                    stride_length=float(b.rng.uniform(1.2, 1.6)))
    if not required:
        return b.try_place(make, ((PERSON, "pedestrian"),), tries=60)
    return b.place(make, f"pedestrian {index}", ((PERSON, "pedestrian"),))


def _span(b: _Builder, road: Road, before: float = 40.0, after: float = 120.0) -> tuple[float, float]:
    """Arc-length range of ``road`` covering every placed unit (projected onto the nearest
    centreline point, 1 m grid) with ``before`` / ``after`` metres of margin."""
    reach = unit_distance(b.ego, b.duration) + max(u.speed for u in b.placed) * b.duration + 200
    grid = np.arange(-reach, reach, 1.0)
    centre = road_pose(road, grid)[:, :2]
    lo = hi = 0.0
    for unit in b.placed:
        nearest = grid[nearest_points(centre, unit_position(unit, b.times[::5]))]
        lo, hi = min(lo, float(nearest.min())), max(hi, float(nearest.max()))
    return lo - before, hi + after


NEAREST_BLOCK = 256
"""Points of a polyline :func:`nearest_points` bounds by one box."""
NEAREST_BUDGET = 1 << 22
"""Distances :func:`nearest_points` computes at once (4 Mi: about 130 MB of temporaries, the
points gathered for them included)."""


def nearest_points(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """For each of ``queries`` (Q, 2), the index into ``points`` (P, 2) of its nearest point,
    the first on a tie: ``argmin`` of the squared distances ``(qx - px) ** 2 + (qy - py) ** 2``,
    the same float64 values, without the (Q, P) matrix. Points are taken in blocks of
    :data:`NEAREST_BLOCK` with a bounding box each; a block whose box is farther from a query than
    the first point of some block is never the nearest (floating point rounds monotonically, so
    the box's distance is a lower bound of every computed distance inside it) and is skipped.
    Time about Q x (P / 256 + 256 x the blocks left); for points along a road, a few blocks each.
    """
    points = np.asarray(points, dtype=np.float64)
    queries = np.asarray(queries, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) == 0:
        raise ValueError(f"points: expected (P, 2) with P >= 1, got {points.shape}")
    if queries.ndim != 2 or queries.shape[1] != 2:
        raise ValueError(f"queries: expected (Q, 2), got {queries.shape}")
    blocks = -(-len(points) // NEAREST_BLOCK)
    padded = np.full((blocks * NEAREST_BLOCK, 2), np.inf)  # +inf: never the nearest
    padded[:len(points)] = points
    padded = padded.reshape(blocks, NEAREST_BLOCK, 2)
    low = padded.min(axis=1)  # (K, 2)
    high = padded.max(axis=1)  # +inf in a padded last block: a looser bound, still a bound
    first = padded[:, 0]  # (K, 2), finite
    result = np.empty(len(queries), dtype=np.int64)
    rows = max(1, NEAREST_BUDGET // blocks)
    for start in range(0, len(queries), rows):
        q = queries[start:start + rows]
        gap_x = np.maximum(np.maximum(low[None, :, 0] - q[:, 0, None], q[:, 0, None] - high[None, :, 0]), 0.0)
        gap_y = np.maximum(np.maximum(low[None, :, 1] - q[:, 1, None], q[:, 1, None] - high[None, :, 1]), 0.0)
        bound = gap_x ** 2 + gap_y ** 2  # (q, K) lower bounds
        reached = ((q[:, 0, None] - first[None, :, 0]) ** 2
                   + (q[:, 1, None] - first[None, :, 1]) ** 2).min(axis=1)  # distances that occur
        query, block = np.nonzero(bound <= reached[:, None])  # by query, then block: index order
        best = np.empty(len(query))
        where = np.empty(len(query), dtype=np.int64)
        step = max(1, NEAREST_BUDGET // NEAREST_BLOCK)
        for low_pair in range(0, len(query), step):
            pairs = slice(low_pair, low_pair + step)
            inside = padded[block[pairs]]  # (pairs, 256, 2)
            squared = ((q[query[pairs], 0, None] - inside[:, :, 0]) ** 2
                       + (q[query[pairs], 1, None] - inside[:, :, 1]) ** 2)
            where[pairs] = block[pairs] * NEAREST_BLOCK + squared.argmin(axis=1)
            best[pairs] = squared.min(axis=1)
        starts = np.flatnonzero(np.r_[True, query[1:] != query[:-1]])
        smallest = np.minimum.reduceat(best, starts)
        winners = np.flatnonzero(best == smallest[query])
        _, firsts = np.unique(query[winners], return_index=True)  # each query's first winner
        result[start:start + len(q)] = where[winners[firsts]]
    return result


def _sample_street(b: _Builder) -> None:
    """Today's street: 4 lanes, bicycle lanes, zebra crossing, sidewalks, buildings."""
    rng, config, ego, duration = b.rng, b.config, b.ego, b.duration
    road = Road((0.0, 0.0, 0.0), (), 2, LANE_WIDTH, SHOULDER_WIDTH, 0.0, SIDEWALK_WIDTH, (0, 0))
    crosswalk_x = float(unit_position(ego, rng.uniform(0.35, 0.6) * duration)[0] + 25.0)
    _lane_vehicles(b, road, config.num_cars, (4.0, 12.0))
    num_crossing = min(config.num_pedestrians, int(rng.integers(1, 3)))
    for index in range(config.num_pedestrians):
        if index < num_crossing:
            _crosser(b, index, road, crosswalk_x)
        else:
            _sidewalk_walker(b, road, index, (PEDESTRIAN_Y_RANGE[0], PEDESTRIAN_Y_RANGE[1]))
    _riders(b, road, BIKE_LANE_Y)
    x_min, x_max = _span(b, road, 40.0, 120.0)
    road = Road(road.start, (), 2, LANE_WIDTH, SHOULDER_WIDTH, 0.0, SIDEWALK_WIDTH, (x_min, x_max))
    b.roads.append(road)
    zebra = ((crosswalk_x - 4.0, crosswalk_x + 4.0),)
    _road_surface(b, road, "street", centre="double_yellow", dashes=False)
    for side in (-1, 1):
        _dashes(b, road, f"dash_{'lr'[side > 0]}", side * LANE_WIDTH, 9.0, 3.0, gaps=zebra)
    for y in np.arange(-ROAD_HALF_WIDTH + 0.5, ROAD_HALF_WIDTH - 0.2, 1.0):
        b.prop(f"zebra_{y:+.1f}", "box", (1.5, 0.25, STATIC_Z * 1.5), (crosswalk_x, y, 0.0),
               rgba=ZEBRA_PAINT, exact=True)
    for side in (-1.0, 1.0):
        x = x_min
        while x < x_max:
            width, depth = rng.uniform(10.0, 26.0), rng.uniform(10.0, 18.0)
            height = rng.uniform(7.0, 32.0)
            setback = SIDEWALK_OUTER + rng.uniform(0.5, 4.0)
            _building(b, x + width / 2, side * (setback + depth / 2), 0.0, (width, depth, height),
                      rng)
            x += width + (rng.uniform(2.0, 8.0) if rng.random() < 0.4 else 0.3)
    for side in (-1.0, 1.0):
        x = x_min + rng.uniform(0, 10)
        while x < x_max:
            _tree(b, x, side * TREE_Y)
            if rng.random() < 0.5:
                _bush(b, x + rng.uniform(3.0, 6.0), side * (TREE_Y + 0.2), rng)
            x += rng.uniform(12.0, 22.0)
        x = x_min + rng.uniform(0, 15)
        while x < x_max:
            if abs(x - crosswalk_x) > 4.0:
                _lamp(b, x, side * POLE_Y, -side * math.pi / 2)
            x += 30.0
        # signs by the curb, where the sidewalk walkers (PEDESTRIAN_Y_RANGE) pass them by 0.5 m
        for x in (crosswalk_x - side * 6.0,):  # crossing signs facing the oncoming traffic
            _sign(b, x, side * (POLE_Y + 0.1), math.pi if side < 0 else 0.0, rng, round_plate=False)
        x = x_min + rng.uniform(10, 40)
        while x < x_max:
            _sign(b, x, side * (POLE_Y + 0.1), math.pi if side < 0 else 0.0, rng)
            x += rng.uniform(50.0, 90.0)


def _turn_path(centre, approach_heading, d_in, d_out, radius, turn, lead):
    """(start, heading, pieces) of a vehicle approaching a junction at ``centre`` along
    ``approach_heading`` in the lane ``d_in`` right of the centreline, turning ``turn``
    (+1 left, -1 right) with ``radius`` into the lane ``d_out`` right of the other road's
    centreline; it starts ``lead`` metres before the turn."""
    x_turn = (d_out - radius) if turn > 0 else (-d_out - radius)
    local = np.array([x_turn - lead, -d_in])
    c, s = math.cos(approach_heading), math.sin(approach_heading)
    start = (float(centre[0] + c * local[0] - s * local[1]),
             float(centre[1] + s * local[0] + c * local[1]))
    pieces = ((float(lead), 0.0), (radius * math.pi / 2, turn / radius))
    return start, float(approach_heading), pieces


def _sample_intersection(b: _Builder) -> None:
    """A four-way junction: the ego's 4-lane road crossed by a 4-lane road at x = junction."""
    rng, config, ego, duration = b.rng, b.config, b.ego, b.duration
    main = Road((0.0, 0.0, 0.0), (), 2, LANE_WIDTH, SHOULDER_WIDTH, 0.0, SIDEWALK_WIDTH, (0, 0))
    junction_x = float(unit_position(ego, rng.uniform(0.4, 0.7) * duration)[0] + 20.0)
    cross_lanes = int(rng.integers(1, 3))
    cross = Road((junction_x, 0.0, math.pi / 2), (), cross_lanes, LANE_WIDTH, 1.0, 0.0, 3.0,
                 (0, 0))
    main_half, cross_half = main.half_width, cross.half_width
    crosswalks_main = (junction_x - cross_half - 3.0, junction_x + cross_half + 3.0)
    crosswalks_cross = (-(main_half + 3.0), main_half + 3.0)
    turning = min(config.num_cars, max(1, config.num_cars // 3))
    roads = (main, cross)
    for index in range(config.num_cars):
        if index < turning:
            def make_path(speed, length, index=index):
                road_index = int(rng.integers(2))
                direction = 1 if rng.random() < 0.5 else -1
                road, other = roads[road_index], roads[1 - road_index]
                heading = road.start[2] + (0.0 if direction > 0 else math.pi)
                turn = 1 if rng.random() < 0.5 else -1
                lane_in = 0 if turn > 0 else road.lanes_each_way - 1
                lane_out = 0 if turn > 0 else other.lanes_each_way - 1
                radius = rng.uniform(8.0, 12.0) if turn > 0 else rng.uniform(6.0, 8.0)
                if turn > 0:
                    radius = max(radius, road.lane_offset(lane_in) + other.lane_offset(lane_out)
                                 + 2.0)
                turn_time = rng.uniform(0.1, 0.8) * duration
                start, yaw, pieces = _turn_path((junction_x, 0.0), heading,
                                                road.lane_offset(lane_in),
                                                other.lane_offset(lane_out), radius, turn,
                                                speed * turn_time)
                return start, yaw, pieces, 0.0, math.inf
            # a short clip leaves the junction no gap for some: they drive along the main road
            if b.vehicle(f"car{index}", make_path, (3.0, 8.0), what=f"turning vehicle {index}",
                         required=False) is None:
                _lane_vehicles(b, main, 1, (4.0, 11.0), first=index)
        elif index % 2 == 0:
            _lane_vehicles(b, main, 1, (4.0, 11.0), first=index)
        else:
            def make_path(speed, length):
                direction = 1 if rng.random() < 0.5 else -1
                lane = int(rng.integers(cross.lanes_each_way))
                # it crosses the junction at a random time of the clip
                s0 = -direction * speed * rng.uniform(0.15, 0.85) * duration
                start, heading, pieces = lane_path(cross, s0, -direction * cross.lane_offset(lane),
                                                   direction)
                return start, heading, pieces, 0.0, math.inf
            if b.vehicle(f"car{index}", make_path, (4.0, 11.0), what=f"crossing vehicle {index}",
                         required=False) is None:
                _lane_vehicles(b, main, 1, (4.0, 11.0), first=index)
    num_crossing = min(config.num_pedestrians, max(1, config.num_pedestrians // 2))
    for index in range(config.num_pedestrians):
        if index < num_crossing:
            # busy crossings leave no gap for some: they walk along the sidewalk instead
            if rng.random() < 0.5:
                crossed = _crosser(b, index, main, _pick(rng, crosswalks_main), (0.0, 0.8), 1.0,
                                   required=False)
            else:
                crossed = _crosser(b, index, cross, _pick(rng, crosswalks_cross), (0.0, 0.8), 1.0,
                                   required=False)
            if crossed is None:
                _sidewalk_walker(b, main, index,
                                 (main_half + 0.9, main_half + SIDEWALK_WIDTH - 1.1))
        else:
            _sidewalk_walker(b, main, index, (main_half + 0.9, main_half + SIDEWALK_WIDTH - 1.1))
    _riders(b, main, BIKE_LANE_Y)
    s_lo, s_hi = _span(b, main, 40.0, 120.0)
    main = Road(main.start, (), 2, LANE_WIDTH, SHOULDER_WIDTH, 0.0, SIDEWALK_WIDTH, (s_lo, s_hi))
    arm = max(70.0, s_hi - junction_x)
    cross = Road(cross.start, (), cross_lanes, LANE_WIDTH, 1.0, 0.0, 3.0, (-arm, arm))
    b.roads.extend((main, cross))
    box_main = (junction_x - cross_half - 5.0, junction_x + cross_half + 5.0)
    box_cross = (-main_half - 5.0, main_half + 5.0)
    corner_main = (junction_x - cross_half, junction_x + cross_half)
    _road_surface(b, main, "main", gaps=(), sidewalk_gaps=(corner_main,), centre="double_yellow",
                  dashes=False, edge_lines=False)
    for side in (-1, 1):
        _strip(b, main, f"main_edge_line_{'lr'[side > 0]}", side * 2 * LANE_WIDTH, 0.075, STATIC_Z,
               0.002, gaps=(box_main,), rgba=WHITE_PAINT)
        _dashes(b, main, f"main_dash_{'lr'[side > 0]}", side * LANE_WIDTH, 9.0, 3.0,
                gaps=(box_main,))
    cross_gaps = ((-main_half, main_half),)
    cross_sidewalk_gaps = ((-(main_half + SIDEWALK_WIDTH), main_half + SIDEWALK_WIDTH),)
    _road_surface(b, cross, "cross", gaps=cross_gaps, sidewalk_gaps=cross_sidewalk_gaps,
                  centre="none", edge_lines=False, dashes=False)
    for offset in (-0.12, 0.12):
        _strip(b, cross, f"cross_centre_line_{'lr'[offset > 0]}", offset, 0.06, STATIC_Z, 0.002,
               gaps=(box_cross,), rgba=YELLOW_PAINT)
    # zebra crossings on all four arms and stop lines before them
    for x in crosswalks_main:
        for y in np.arange(-main_half + 0.5, main_half - 0.2, 1.0):
            b.prop("zebra", "box", (1.5, 0.25, STATIC_Z * 1.5), (x, y, 0.0), rgba=ZEBRA_PAINT)
        side = -1 if x < junction_x else 1
        b.prop("stop_line", "box", (0.2, main_half / 2 - 0.1, STATIC_Z),
               (x + side * 2.2, side * main_half / 2, 0.0), rgba=WHITE_PAINT)
    for y in crosswalks_cross:
        for x in np.arange(junction_x - cross_half + 0.5, junction_x + cross_half - 0.2, 1.0):
            b.prop("zebra", "box", (0.25, 1.5, STATIC_Z * 1.5), (x, y, 0.0), rgba=ZEBRA_PAINT)
        side = -1 if y < 0 else 1
        b.prop("stop_line", "box", (cross_half / 2 - 0.1, 0.2, STATIC_Z),
               (junction_x - side * cross_half / 2, y + side * 2.2, 0.0), rgba=WHITE_PAINT)
    # traffic lights on the four corners, facing the approaching traffic; where people pass the
    # corner, moved along either kerb away from the junction (at most 4 m) to where none passes
    # within POLE_WALKER_CLEARANCE_M (they were placed with no look at the walkers' paths: a
    # seed sweep found arms and umbrellas through them in 9 of 400 junctions)
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = b.place_pole_among(
                junction_x + sx * (cross_half + 0.6), sy * (main_half + 0.6),
                [(0.0, 0.0), *((offset[0] * sx, offset[1] * sy)
                               for k in range(1, 9) for offset in ((0.5 * k, 0.0), (0.0, 0.5 * k)))])
            facing = math.pi if sx > 0 else 0.0
            b.prop("signal_pole", "cylinder", (0.09, 2.6), (x, y, 2.6), rgba=POLE_METAL)
            b.prop("signal_head", "box", (0.15, 0.18, 0.5), (x, y, 5.4), rgba=(0.1, 0.1, 0.1, 1))
            for lamp, colour in enumerate(((0.8, 0.1, 0.1, 1), (0.8, 0.6, 0.1, 1),
                                           (0.1, 0.7, 0.3, 1))):
                b.prop("signal_lamp", "sphere", (0.1,),
                       (x + 0.16 * math.cos(facing), y, 5.75 - 0.33 * lamp), rgba=colour)
    # corner buildings, trees, lamps and signs along every arm
    for side in (-1.0, 1.0):
        for lo, hi in ((s_lo, corner_main[0] - SIDEWALK_WIDTH - 3.0),
                       (corner_main[1] + SIDEWALK_WIDTH + 3.0, s_hi)):
            x = lo
            while x < hi - 8.0:
                width = min(rng.uniform(10.0, 24.0), hi - x)
                depth, height = rng.uniform(10.0, 16.0), rng.uniform(6.0, 28.0)
                setback = main_half + SIDEWALK_WIDTH + rng.uniform(0.5, 3.0)
                _building(b, x + width / 2, side * (setback + depth / 2), 0.0,
                          (width, depth, height), rng)
                x += width + (rng.uniform(2.0, 8.0) if rng.random() < 0.4 else 0.3)
            x = lo + rng.uniform(2, 10)
            while x < hi - 2:
                _tree(b, x, side * (main_half + SIDEWALK_WIDTH - 0.5))
                x += rng.uniform(12.0, 22.0)
            x = lo + rng.uniform(0, 15)
            while x < hi - 2:
                _lamp(b, x, side * (main_half + 0.3), -side * math.pi / 2)
                x += 30.0
        for y_lo, y_hi in ((-arm, -(main_half + SIDEWALK_WIDTH + 3.0)),
                           (main_half + SIDEWALK_WIDTH + 3.0, arm)):
            y = y_lo + rng.uniform(2, 10)
            while y < y_hi - 2:
                _tree(b, junction_x + side * (cross_half + 2.5), y)
                y += rng.uniform(14.0, 24.0)
            y = y_lo
            while y < y_hi - 8.0:
                width = min(rng.uniform(10.0, 22.0), y_hi - y)
                depth, height = rng.uniform(10.0, 16.0), rng.uniform(6.0, 24.0)
                setback = cross_half + 3.0 + rng.uniform(0.5, 3.0)
                _building(b, junction_x + side * (setback + depth / 2), y + width / 2,
                          math.pi / 2, (width, depth, height), rng)
                y += width + rng.uniform(0.3, 6.0)
        _sign(b, junction_x - side * (cross_half + 7.0), side * (main_half + 0.3),
              math.pi if side < 0 else 0.0, rng, round_plate=False)


def _curve_pieces(rng: np.random.Generator, length_needed: float) -> tuple[tuple[float, float], ...]:
    """An S-curve: a straight lead, then alternating left/right arcs with straights between,
    until the path is ``length_needed`` metres long."""
    pieces = [(float(rng.uniform(15.0, 35.0)), 0.0)]
    turn = 1.0 if rng.random() < 0.5 else -1.0
    total = pieces[0][0]
    while total < length_needed:
        radius = rng.uniform(60.0, 120.0)
        sweep = math.radians(rng.uniform(25.0, 55.0))
        pieces.append((float(radius * sweep), float(turn / radius)))
        straight = float(rng.uniform(10.0, 35.0))
        pieces.append((straight, 0.0))
        total += radius * sweep + straight
        turn = -turn
    return tuple(pieces)


def _sample_curved(b: _Builder, road: Road) -> None:
    """An S-curved 2+2-lane suburban road with sidewalks; the ego follows its lane."""
    rng, config = b.rng, b.config
    _lane_vehicles(b, road, config.num_cars, (6.0, 13.0))
    num_crossing = min(config.num_pedestrians, 1)
    for index in range(config.num_pedestrians):
        if index < num_crossing:
            _crosser(b, index, road, unit_distance(b.ego, rng.uniform(0.3, 0.6) * b.duration)
                     + 25.0)
        else:
            _sidewalk_walker(b, road, index, (road.half_width + SIDEWALK_WALKER_KERB_M,
                                              road.half_width + road.sidewalk - 0.6))
    _riders(b, road, road.half_width - road.shoulder / 2)
    s_lo, s_hi = _span(b, road, 60.0, 150.0)
    road = Road(road.start, road.pieces, road.lanes_each_way, road.lane_width, road.shoulder,
                road.median, road.sidewalk, (s_lo, s_hi))
    b.roads.append(road)
    _road_surface(b, road, "curve", centre="double_yellow")
    outer = road.half_width + road.sidewalk
    bounds, curvatures, _ = _piece_table(road.start, road.pieces)
    for side in (-1.0, 1.0):
        s = s_lo + rng.uniform(0, 8)
        while s < s_hi:
            if rng.random() < 0.7:
                x, y, h = road_pose(road, s, side * (outer + rng.uniform(1.5, 4.0)))
                _tree(b, x, y, rng.uniform(0.8, 1.2))
            else:
                x, y, h = road_pose(road, s, side * (outer + 1.2))
                b.prop("hedge", "box", (rng.uniform(2.0, 5.0), 0.5, 0.6), (x, y, 0.6),
                       yaw_quat(h), rgba=HEDGE)
            s += rng.uniform(8.0, 16.0)
        s = s_lo + rng.uniform(0, 20)
        while s < s_hi:
            x, y, h = road_pose(road, s, side * (road.half_width + 0.35))
            _lamp(b, x, y, h - side * math.pi / 2)
            s += 35.0
        s = s_lo
        while s < s_hi:  # houses set back behind the verge
            width = rng.uniform(9.0, 14.0)
            if rng.random() < 0.6:
                depth = rng.uniform(8.0, 11.0)
                x, y, h = road_pose(road, s + width / 2, side * (outer + 9.0 + depth / 2))
                _building(b, x, y, h, (width, depth, rng.uniform(5.0, 8.0)), rng, roof=True)
            s += width + rng.uniform(6.0, 14.0)
    # chevron signs on the outside of every bend, facing the traffic that enters it
    for index, (lo, k) in enumerate(zip(bounds[:-1], curvatures[:-1])):
        if k == 0:
            continue
        side = -1.0 if k > 0 else 1.0
        for s in np.linspace(lo, bounds[index + 1], 4)[1:-1]:
            x, y, h = road_pose(road, s, side * (outer + 0.5))
            _sign(b, x, y, h + math.pi, rng, height=1.4, round_plate=False)


def _sample_highway(b: _Builder, lanes: int) -> None:
    """A straight motorway: ``lanes`` lanes each way, median barrier, hard shoulders, guard
    rails, an overpass with people on it, a broken-down car on the shoulder."""
    rng, config, ego, duration = b.rng, b.config, b.ego, b.duration
    road = Road((0.0, 0.0, 0.0), (), lanes, HIGHWAY_LANE_WIDTH, HIGHWAY_SHOULDER,
                HIGHWAY_MEDIAN, 0.0, (0, 0))
    half = road.half_width
    overpass_x = float(unit_position(ego, rng.uniform(0.35, 0.75) * duration)[0] + 30.0)
    # the broken-down car on the hard shoulder, hazard ahead of the ego
    breakdown_x = float(unit_position(ego, rng.uniform(0.3, 0.8) * duration)[0] + 40.0)
    if abs(breakdown_x - overpass_x) < 20.0:
        breakdown_x += 40.0
    shoulder_y = -(half - HIGHWAY_SHOULDER / 2 - 0.2)
    people = config.num_pedestrians
    if config.num_cars > 0:
        style = _pick(rng, ("sedan", "hatchback", "suv", "van", "pickup"))
        b.vehicle("car0", lambda speed, length: ((breakdown_x, shoulder_y), 0.0, (), 0.0, 0.0),
                  (0.0, 0.0), style=style, speed=0.0, what="broken-down vehicle")
        for index in range(min(people, 2)):  # its people wait behind the guard rail
            def make(index=index) -> Unit:
                x = breakdown_x + rng.uniform(-6.0, 4.0)
                return Unit(f"person{index}", "pedestrian",
                            (float(x), -(half + rng.uniform(1.2, 2.5))),
                            float(rng.uniform(-math.pi, math.pi)), 0.0, FOOTPRINTS["pedestrian"],
                            colours=_person_colours(rng))
            b.place(make, f"pedestrian {index}", ((PERSON, "pedestrian"),))
    # denser traffic than in town: 1.5 x num_cars moving vehicles, the first a bus or truck
    _lane_vehicles(b, road, max(0, (3 * config.num_cars) // 2 - 1), (22.0, 30.0),
                   ahead=(15.0, 60.0), first=1, heavy_first=True)
    on_bridge = min(max(0, people - 2 * (config.num_cars > 0)), 3)
    first = min(people, 2) if config.num_cars > 0 else 0
    deck_half = HIGHWAY_DECK_WIDTH / 2
    for index in range(first, first + on_bridge):
        def make(index=index) -> Unit:
            direction = float(_pick(rng, (-1.0, 1.0)))
            x = overpass_x + rng.uniform(-deck_half + 0.8, deck_half - 0.8)
            speed = rng.uniform(0.9, 1.5)
            y0 = -direction * rng.uniform(0.0, 1.0) * speed * duration * 0.5
            return Unit(f"person{index}", "pedestrian", (float(x), float(y0)),
                        direction * math.pi / 2, float(speed), FOOTPRINTS["pedestrian"],
                        colours=_person_colours(rng), stride_length=float(rng.uniform(1.2, 1.6)),
                        level=1)
        b.place(make, f"pedestrian {index} (overpass)", ((PERSON, "pedestrian"),))
    _riders(b, road, None, moto_speed=(22.0, 32.0))
    s_lo, s_hi = _span(b, road, 60.0, 200.0)
    view = (-30.0, unit_distance(ego, duration) + 220.0)  # dense roadside scenery only here
    road = Road(road.start, (), lanes, HIGHWAY_LANE_WIDTH, HIGHWAY_SHOULDER, HIGHWAY_MEDIAN, 0.0,
                (s_lo, s_hi))
    b.roads.append(road)
    _road_surface(b, road, "highway", centre="none", dash_range=view)
    for side in (-1, 1):  # the median's own edge lines (yellow, next to the barrier)
        _strip(b, road, f"median_line_{'lr'[side > 0]}", side * (HIGHWAY_MEDIAN - 0.3), 0.075,
               STATIC_Z, 0.002, rgba=YELLOW_PAINT)
    # jersey barrier: a wide foot and a narrower wall, in concrete
    _strip(b, road, "barrier_foot", 0.0, 0.32, 0.32, 0.32, material="concrete")
    _strip(b, road, "barrier_wall", 0.0, 0.15, 0.82, 0.52, material="concrete")
    # guard rails: a steel beam on posts beyond each hard shoulder; grass verge beyond
    for side in (-1, 1):
        tag = "lr"[side > 0]
        _strip(b, road, f"guard_rail_{tag}", side * (half + 0.4), 0.04, 0.75, 0.3,
               rgba=(0.72, 0.74, 0.76, 1))
        for x in np.arange(math.floor(view[0] / 4) * 4, view[1], 4.0):
            b.prop(f"guard_post_{tag}", "box", (0.06, 0.06, 0.35), (x, side * (half + 0.5), 0.35),
                   rgba=(0.5, 0.5, 0.52, 1))
    # median lamps with two arms
    for x in np.arange(s_lo + rng.uniform(0, 40), s_hi, 45.0):
        if abs(x - overpass_x) < HIGHWAY_DECK_WIDTH:
            continue
        b.prop("median_pole", "cylinder", (0.1, 5.0), (x, 0.0, 5.8), rgba=POLE_METAL)
        for side in (-1, 1):
            b.prop("median_arm", "box", (0.04, 1.2, 0.04), (x, side * 1.2, 10.7), rgba=POLE_METAL)
            b.prop("median_lamp", "box", (0.35, 0.16, 0.06), (x, side * 2.4, 10.65),
                   rgba=(0.9, 0.9, 0.8, 1))
    # the overpass: deck on pillars beyond the guard rails and in the median, parapets, a
    # sidewalk on the deck (people walk there, level 1), embankments at both ends
    span = half + 30.0
    deck_top = HIGHWAY_DECK_CLEARANCE + 1.0
    b.prop("overpass_deck", "box", (deck_half, span, 0.5), (overpass_x, 0.0, deck_top - 0.5),
           material="concrete", exact=True)
    b.prop("overpass_asphalt", "box", (deck_half - 1.6, span, 0.02),
           (overpass_x, 0.0, deck_top + 0.02), material="asphalt", exact=True)
    for side in (-1, 1):
        b.prop("overpass_parapet", "box", (0.2, span, 0.55),
               (overpass_x + side * (deck_half - 0.2), 0.0, deck_top + 0.55), material="concrete")
        for y in (-(half + 2.0), half + 2.0):
            b.prop("overpass_pillar", "box", (0.6, 0.6, HIGHWAY_DECK_CLEARANCE / 2),
                   (overpass_x + side * (deck_half - 1.5), y, HIGHWAY_DECK_CLEARANCE / 2),
                   material="concrete")
        b.prop("overpass_pillar", "cylinder", (0.55, HIGHWAY_DECK_CLEARANCE / 2),
               (overpass_x + side * (deck_half - 1.5), 0.0, HIGHWAY_DECK_CLEARANCE / 2),
               material="concrete")
        b.prop("overpass_embankment", "box", (deck_half + 4.0, 6.0, deck_top / 2),
               (overpass_x, side * (span + 2.0), deck_top / 2), material="grass")
    b.walkways.append(Slab((overpass_x, 0.0), deck_half, span + 8.0, 0.0, deck_top + 0.04))
    # warning triangle behind the broken-down car
    if config.num_cars > 0:
        _warning_triangle(b, breakdown_x - 30.0, shoulder_y)
    # roadside: big direction signs, trees and bushes beyond the verge
    for side in (-1.0, 1.0):
        boards = []  # the signs' x: a tree beside one stands out beyond its board
        x = s_lo + rng.uniform(0, 60)
        while x < s_hi:
            if abs(x - overpass_x) > 25:
                boards.append(x)
                y = side * (half + HIGHWAY_SIGN_OUT_M)
                for offset in (-1.5, 1.5):  # under the board's width (it faces along the road)
                    b.prop("sign_post", "cylinder", (0.08, 2.0), (x, y + offset, 2.0),
                           rgba=POLE_METAL)
                b.prop("sign_board", "box", (HIGHWAY_SIGN_HALF_DEPTH_M, HIGHWAY_SIGN_HALF_WIDTH_M, 1.0),
                       (x, y, 4.5),
                       rgba=(0.05, 0.35, 0.15, 1) if rng.random() < 0.5 else (0.05, 0.2, 0.6, 1))
            x += rng.uniform(120.0, 200.0)
        x = view[0] + rng.uniform(0, 10)
        while x < view[1]:
            y = side * (half + rng.uniform(7.0, 20.0))
            if rng.random() < 0.7:
                # under the deck a tree grew through it: it stands beside the deck instead; by a
                # sign its crown went through the board: it stands beyond the board's end (the
                # same draws, so everything after it is unchanged)
                scale = rng.uniform(0.9, 1.4)
                reach = TREE_CROWN_REACH_M * scale
                if any(abs(x - board) < reach + HIGHWAY_SIGN_HALF_DEPTH_M for board in boards):
                    y = side * max(abs(y), half + HIGHWAY_SIGN_OUTER_M + reach)
                _tree(b, _beside_deck(x, overpass_x, deck_half + HIGHWAY_DECK_TREE_CLEARANCE), y,
                      scale)
            else:
                _bush(b, x, y, rng)  # a bush (at most 1.8 m) fits under the 6 m clearance
            x += rng.uniform(6.0, 18.0)


WARNING_TRIANGLE_SIDE_M = 0.45
"""Side of the red warning triangle set up behind a broken-down car (ECE R27: 0.40-0.50 m)."""


def _warning_triangle(b: _Builder, x: float, y: float) -> None:
    """A warning triangle standing at (x, y), facing along the road (the traffic coming up): an
    upright equilateral frame of three red bars, hollow, as the real ones are."""
    side, bar = WARNING_TRIANGLE_SIDE_M, 0.025
    height = side * math.sqrt(3.0) / 2.0
    red = (0.9, 0.1, 0.05, 1)
    b.prop("warning_triangle", "box", (bar, side / 2, bar), (x, y, bar), yaw_quat(0.0), rgba=red)
    for sign in (-1.0, 1.0):  # the two slanted sides, turned 60 degrees about the road's axis
        b.prop("warning_triangle", "box", (bar, side / 2, bar),
               (x, y + sign * side / 4, bar + height / 2),
               yaw_quat(0.0, 0.0, -sign * math.pi / 3), rgba=red)


HIGHWAY_SIGN_HALF_DEPTH_M = 0.05
"""Half the thickness of a highway direction sign's board (it faces along the road)."""
HIGHWAY_SIGN_OUT_M = 4.0
"""How far beyond the hard shoulder's edge a highway direction sign's centre stands."""
HIGHWAY_SIGN_HALF_WIDTH_M = 2.2
"""Half the width of a highway direction sign's board (across the road)."""
HIGHWAY_SIGN_OUTER_M = HIGHWAY_SIGN_OUT_M + HIGHWAY_SIGN_HALF_WIDTH_M
"""How far beyond the hard shoulder's edge a highway direction sign's board reaches."""
TREE_CROWN_REACH_M = 3.2
"""The farthest a :func:`_tree`'s crown reaches from its trunk at scale 1 (a round crown's lobes:
at most 0.75 of its 2.1 m radius out, 0.75 of it in radius)."""


def _beside_deck(x: float, deck_x: float, reach: float) -> float:
    """``x``, or the nearer edge of [deck_x - reach, deck_x + reach] when it lies inside."""
    if abs(x - deck_x) >= reach:
        return x
    return deck_x + math.copysign(reach, x - deck_x)


HIGHWAY_LANE_WIDTH = 3.6
HIGHWAY_SHOULDER = 3.0
HIGHWAY_MEDIAN = 1.2
HIGHWAY_DECK_WIDTH = 12.0
HIGHWAY_DECK_CLEARANCE = 6.0
HIGHWAY_DECK_TREE_CLEARANCE = 4.5  # a roadside tree's crown reaches at most 4.4 m from its trunk (scale 1.4)
RESIDENTIAL_LANE = 3.0
RESIDENTIAL_PARKING = 2.2
RESIDENTIAL_SIDEWALK = 2.0


def _sample_residential(b: _Builder) -> None:
    """A narrow two-lane street with parked cars on both sides, driveways, front gardens with
    hedges, houses; people step out into the road between the parked cars."""
    rng, config, ego, duration = b.rng, b.config, b.ego, b.duration
    road = Road((0.0, 0.0, 0.0), (), 1, RESIDENTIAL_LANE, RESIDENTIAL_PARKING, 0.0,
                RESIDENTIAL_SIDEWALK, (0, 0))
    half = road.half_width
    ego_end = float(unit_position(ego, duration)[0])
    lo, hi = -25.0, ego_end + 70.0
    # lots along each side: a driveway per lot, parked cars in the gaps between driveways
    lots: dict[float, list[tuple[float, float]]] = {}
    driveways: dict[float, list[float]] = {}
    for side in (-1.0, 1.0):
        x = lo - 40.0
        lots[side], driveways[side] = [], []
        while x < hi + 60.0:
            width = rng.uniform(14.0, 22.0)
            lots[side].append((x, width))
            driveways[side].append(x + rng.uniform(2.5, width - 5.0))
            x += width
    parked_y = half - RESIDENTIAL_PARKING / 2 - 0.05
    gaps_for_people: list[tuple[float, float]] = []  # (x, side) of a gap between parked cars
    parked: dict[float, list[tuple[float, float]]] = {-1.0: [], 1.0: []}
    index = 0
    for side in (-1.0, 1.0):
        blocked = sorted(driveways[side])
        x = lo + rng.uniform(0.0, 3.0)
        while x < hi:
            style = _draw(rng, VEHICLE_STYLES, STYLE_WEIGHTS["residential"])
            size = vehicle_size(style, rng)
            length = size[0]
            centre = x + length / 2
            if any(abs(centre - d) < length / 2 + 2.2 for d in blocked) or rng.random() < 0.25:
                x += rng.uniform(2.0, 5.0)
                continue
            heading = 0.0 if side < 0 else math.pi
            b.vehicle(f"parked{index}",
                      lambda speed, length, c=centre, y=side * parked_y, h=heading:
                      ((c, y), h, (), 0.0, 0.0), (0.0, 0.0), style=style, speed=0.0,
                      what=f"parked vehicle {index}", size=size)
            index += 1
            parked[side].append((x, x + length))
            gap = rng.uniform(1.4, 2.6) if rng.random() < 0.45 else rng.uniform(0.6, 1.2)
            if gap >= 1.4:
                gaps_for_people.append((x + length + gap / 2, side))
            x += length + gap
    moving = min(config.num_cars, 4)
    for car in range(moving):
        def make_path(speed, length):
            direction = 1 if rng.random() < 0.5 else -1
            s0 = b.meet_s(road, speed, direction, (15.0, 45.0))
            start, heading, pieces = lane_path(road, s0, -direction * road.lane_offset(0), direction)
            return start, heading, pieces, 0.0, math.inf
        b.vehicle(f"car{car}", make_path, (3.5, 7.5), what=f"vehicle {car}")
    # people stepping out between parked cars (the ego's side first), the rest on the sidewalks
    stepping = min(config.num_pedestrians, max(1, (config.num_pedestrians + 1) // 2))
    # only where the far side is free of parked cars, so that the crossing can end on its curb
    gaps_for_people = [(x, side) for x, side in gaps_for_people
                       if not any(a - 1.2 < x < c + 1.2 for a, c in parked[-side])]
    ego_side = [g for g in gaps_for_people if g[1] < 0 and g[0] > 15.0]
    other = [g for g in gaps_for_people if not (g[1] < 0 and g[0] > 15.0)]
    for person in range(config.num_pedestrians):
        stepped = None
        if person < stepping and (ego_side or other):
            pool = ego_side if (person == 0 and ego_side) or not other else \
                (ego_side if rng.random() < 0.6 and ego_side else other)

            def make(person=person, pool=pool) -> Unit:
                x, side = pool[int(rng.integers(len(pool)))]
                # step out when the ego is 10-35 m short of the gap
                arrive = (x - rng.uniform(10.0, 35.0) - ego.start_xy[0]) / max(ego.speed, 0.5)
                start_time = float(np.clip(arrive, 0.0, 0.85 * duration))
                speed = rng.uniform(0.9, 1.5)
                return Unit(f"person{person}", "pedestrian",
                            (float(x + rng.uniform(-0.15, 0.15)), float(side * (half + 0.6))),
                            -side * math.pi / 2, float(speed), FOOTPRINTS["pedestrian"],
                            start_time=start_time, max_distance=2 * half + 1.2,
                            colours=_person_colours(rng),
                            stride_length=float(rng.uniform(1.1, 1.5)))
            stepped = b.try_place(make, ((PERSON, "pedestrian"),), tries=60)
        if stepped is None:  # no free gap: a walker on the sidewalk instead
            _sidewalk_walker(b, road, person, (half + SIDEWALK_WALKER_KERB_M,
                                               half + RESIDENTIAL_SIDEWALK - 0.6))
    _riders(b, road, road.lane_offset(0) - 0.8, moto_speed=(5.0, 9.0), bike_speed=(3.0, 5.5))
    s_lo, s_hi = _span(b, road, 40.0, 120.0)
    road = Road(road.start, (), 1, RESIDENTIAL_LANE, RESIDENTIAL_PARKING, 0.0,
                RESIDENTIAL_SIDEWALK, (s_lo, s_hi))
    b.roads.append(road)
    _road_surface(b, road, "residential", centre="dashed", edge_lines=False, dashes=False)
    for side in (-1, 1):  # parking strip lines
        _strip(b, road, f"parking_line_{'lr'[side > 0]}", side * RESIDENTIAL_LANE, 0.06, STATIC_Z,
               0.002, rgba=WHITE_PAINT)
    garden = half + RESIDENTIAL_SIDEWALK
    for side in (-1.0, 1.0):
        for (x, width), drive in zip(lots[side], driveways[side]):
            if x + width < s_lo or x > s_hi:
                continue
            depth = rng.uniform(7.0, 12.0)  # front garden depth
            b.prop("driveway", "box", (1.5, (depth + 0.3) / 2, 0.03),
                   (drive, side * (garden + depth / 2), 0.01), material="concrete")
            # hedges along the sidewalk, broken by the driveway and a garden gate
            for a, c in ((x + 0.2, drive - 1.7), (drive + 1.7, x + width - 0.2)):
                if c - a > 0.8:
                    b.prop("hedge", "box", ((c - a) / 2, 0.35, rng.uniform(0.55, 0.9)),
                           ((a + c) / 2, side * (garden + 0.5), 0.45), rgba=HEDGE)
            if rng.random() < 0.6:
                _tree(b, x + rng.uniform(2.0, width - 2.0),
                      side * (garden + rng.uniform(2.5, depth - 1.5)), rng.uniform(0.7, 1.1))
            for _ in range(int(rng.integers(0, 3))):
                _bush(b, x + rng.uniform(1.0, width - 1.0),
                      side * (garden + rng.uniform(1.5, depth - 0.5)), rng)
            house_w = min(width - 3.0, rng.uniform(9.0, 13.0))
            house_x = x + width / 2 + rng.uniform(-1.0, 1.0)
            if abs(house_x - drive) < house_w / 2 + 1.5:  # the driveway leads past the house
                towards = math.copysign(1.0, x + width / 2 - drive)
                # on the lot's wider side of the driveway, and inside the lot (it was pushed into
                # the neighbour's house): narrower where the side is short
                room = (x + width - 0.3) - (drive + 1.8) if towards > 0 else (drive - 1.8) - (x + 0.3)
                house_w = max(4.0, min(house_w, room))
                house_x = drive + towards * (house_w / 2 + 1.8)
            house_d = rng.uniform(8.0, 11.0)
            _building(b, house_x, side * (garden + depth + house_d / 2), 0.0,
                      (house_w, house_d, rng.uniform(4.5, 7.0)), rng, roof=True)
        x = s_lo + rng.uniform(0, 20)
        while x < s_hi:
            _lamp(b, x, side * (half + 0.3), -side * math.pi / 2)
            x += 40.0
        x = s_lo + rng.uniform(5, 40)
        while x < s_hi:  # by the curb like the lamps (0.5 m apart at least: place_pole)
            _sign(b, x, side * (half + 0.3), math.pi if side < 0 else 0.0, rng)
            x += rng.uniform(45.0, 80.0)


def sample_layout(seed: int, config: ScenarioConfig, rng: np.random.Generator) -> Layout:
    """Sample a complete layout. ``seed`` is recorded only; all randomness comes from ``rng``.

    Draw order: the layout (``config.layout`` or LAYOUT_PROBABILITIES; the draw is made either
    way), the camera rig (height, pitch), the sun, the layout's own road, traffic, people and
    scenery; last the base weather (sky), the time of day and the puddles, so that those
    leave every earlier draw unchanged. Units are placed by rejection so that no two footprints
    (oriented rectangles grown by COLLISION_MARGIN_M) overlap at any planning time of the clip.
    """
    duration = config.duration_s
    name = _draw(rng, tuple(LAYOUT_PROBABILITIES), tuple(LAYOUT_PROBABILITIES.values()))
    if config.layout is not None:
        name = check_layout(config.layout)
    camera_height = (config.camera_height if config.camera_height is not None
                     else rng.uniform(*CAMERA_HEIGHT_RANGE))
    camera_pitch = (config.camera_pitch_deg if config.camera_pitch_deg is not None
                    else rng.uniform(*CAMERA_PITCH_RANGE_DEG))
    azimuth = math.radians(
        config.sun_azimuth_deg if config.sun_azimuth_deg is not None else rng.uniform(0, 360))
    elevation = math.radians(
        config.sun_elevation_deg if config.sun_elevation_deg is not None else rng.uniform(25, 70))
    sun_direction = (
        -math.cos(elevation) * math.cos(azimuth),
        -math.cos(elevation) * math.sin(azimuth),
        -math.sin(elevation),
    )
    if name == "street":
        ego = _ego(config, rng, (7.0, 10.0), (0.0, _pick(rng, LANE_CENTRES[:2])), 0.0)
        builder = _Builder(seed, config, rng, name, ego)
        _sample_street(builder)
    elif name == "intersection":
        ego = _ego(config, rng, (6.0, 9.0), (0.0, _pick(rng, LANE_CENTRES[:2])), 0.0)
        builder = _Builder(seed, config, rng, name, ego)
        _sample_intersection(builder)
    elif name == "curved":
        speed = config.ego_speed if config.ego_speed is not None else rng.uniform(7.0, 11.0)
        pieces = _curve_pieces(rng, speed * duration + 20.0)
        road = Road((0.0, 0.0, 0.0), pieces, 2, LANE_WIDTH, 1.2, 0.0, 2.5, (0, 0))
        lane = int(rng.integers(2))
        start, heading, ego_pieces = lane_path(road, 0.0, -road.lane_offset(lane), 1)
        ego = Unit("ego", "ego", start, heading, float(speed), EGO_DIMENSIONS, pieces=ego_pieces)
        builder = _Builder(seed, config, rng, name, ego)
        _sample_curved(builder, road)
    elif name == "highway":
        lanes = int(rng.integers(3, 5))
        lane = int(rng.integers(lanes))
        ego = _ego(config, rng, (22.0, 28.0),
                   (0.0, -(HIGHWAY_MEDIAN + (lane + 0.5) * HIGHWAY_LANE_WIDTH)), 0.0)
        builder = _Builder(seed, config, rng, name, ego)
        _sample_highway(builder, lanes)
    else:
        ego = _ego(config, rng, (5.0, 8.0), (0.0, -RESIDENTIAL_LANE / 2), 0.0)
        builder = _Builder(seed, config, rng, name, ego)
        _sample_residential(builder)
    layout = builder.build(camera_height, camera_pitch, sun_direction)
    layout = replace(layout, units=tuple(_dress(unit, rng) for unit in layout.units))
    # Weather and time-of-day draws come last, so they leave every earlier draw unchanged.
    sky_draw = rng.random()
    sky = config.sky if config.sky is not None else SKIES[int(np.searchsorted(
        np.cumsum(SKY_PROBABILITIES), sky_draw, side="right"))]
    time_draw = _draw(rng, TIMES_OF_DAY, TIME_OF_DAY_PROBABILITIES)
    time_of_day = config.time_of_day if config.time_of_day is not None else time_draw
    units = tuple(_with_umbrella(unit, sky, rng) for unit in layout.units)
    return replace(layout, units=units, sky=sky, time_of_day=time_of_day,
                   puddles=_puddles(rng, layout.road_surfaces))


def _dress(unit: Unit, rng: np.random.Generator) -> Unit:
    """``unit`` with its people's looks drawn: a pedestrian's build (children to adults) and,
    when walking, gait (its gait cycle sets the stride length, so feet do not slide); a
    bicycle's or motorcycle's style and its rider's (adult) build. Vehicles are unchanged."""
    if unit.kind == "pedestrian":
        build = people.sample_person_build(rng)
        gait = people.sample_gait(rng, build)
        if unit.speed <= 0:
            return replace(unit, build=build)
        return replace(unit, build=build, gait=gait,
                       stride_length=float(people.gait_cycle_length(build, gait)))
    if unit.kind in ("bicycle", "motorcycle"):
        styles = people.BICYCLE_STYLES if unit.kind == "bicycle" else people.MOTORCYCLE_STYLES
        return replace(unit, style=_pick(rng, styles),
                       build=people.sample_person_build(rng, child_probability=0.0))
    return unit


def _with_umbrella(unit: Unit, sky: str, rng: np.random.Generator) -> Unit:
    """A pedestrian carries an open umbrella with the probability of the base sky
    (:data:`UMBRELLA_PROBABILITY`); the umbrella is part of the person (instance and box)."""
    if unit.kind != "pedestrian":
        return unit
    carries, colour = rng.random() < UMBRELLA_PROBABILITY[sky], _pick(rng, UMBRELLA_COLOURS)
    if not carries:
        return unit
    return replace(unit, colours={**unit.colours, "umbrella": colour})


def _puddles(rng: np.random.Generator, surfaces: tuple[Slab, ...]):
    """Puddles at full size on the road surfaces: one per PUDDLE_AREA_M2 on average."""
    if not surfaces:
        return ()
    areas = np.array([4 * s.half_length * s.half_width for s in surfaces])
    count = int(round(areas.sum() / PUDDLE_AREA_M2))
    puddles = []
    for _ in range(count):
        slab = surfaces[int(np.searchsorted(np.cumsum(areas) / areas.sum(), rng.random(),
                                            side="right").clip(0, len(surfaces) - 1))]
        along = rng.uniform(-slab.half_length, slab.half_length)
        across = rng.uniform(-slab.half_width + 0.8, slab.half_width - 0.8) \
            if slab.half_width > 0.8 else 0.0
        c, s = math.cos(slab.yaw), math.sin(slab.yaw)
        x = slab.centre[0] + c * along - s * across
        y = slab.centre[1] + s * along + c * across
        puddles.append((float(x), float(y), float(rng.uniform(1.2, 4.0)),
                        float(rng.uniform(0.5, 1.6)), float(slab.yaw + rng.uniform(-0.3, 0.3))))
    return tuple(puddles)
