"""Scene layouts: what a seed decides, as plain data, and how every unit moves in time.

A layout is sampled once from an explicit ``rng`` (:func:`sample_layout`) and is then a pure
description: the road, the scenery, the ego vehicle and the moving units (cars, pedestrians,
bicycles and motorcycles with their riders). :func:`unit_pose` gives a unit's pose at time ``t``
as a pure function, so the generator and the tests share one definition of the motion.

World frame: x along the road (the ego drives towards +x), y to the left, z up; metres, seconds.
Traffic keeps to the right: lanes at y < 0 drive towards +x, lanes at y > 0 towards -x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rainbench.rain.weather import SKIES

# COCO-80 indices, so any COCO-pretrained YOLO matches them directly.
CLASS_NAMES: tuple[str, ...] = ("person", "bicycle", "car", "motorcycle")
PERSON, BICYCLE, CAR, MOTORCYCLE = 0, 1, 2, 3

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

CAR_STYLES: tuple[str, ...] = ("sedan", "hatchback", "suv")
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
PUDDLE_SPACING_M = 9.0  # mean distance between puddles along the road

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


@dataclass(frozen=True)
class ScenarioConfig:
    """What a user may ask of a scenario; every ``None`` is decided by the seed.

    Defaults are the paper's scenario: 20 s at 10 frames/s, 6 cars, 8 people, 2 bicycles and
    1 motorcycle placed along the ego vehicle's straight route (seed paper, Table I).
    """

    duration_s: float = 20.0
    num_cars: int = 6
    num_pedestrians: int = 8
    num_bicycles: int = 2
    num_motorcycles: int = 1
    ego_speed: float | None = None  # m/s; seed: uniform 7..10
    camera_height: float | None = None  # m above the road; seed: 1.55 +- 0.10 (car roof)
    sun_azimuth_deg: float | None = None  # seed: uniform 0..360
    sun_elevation_deg: float | None = None  # seed: uniform 25..70
    sky: str | None = None  # base weather; seed: clear 40 %, cloudy 35 %, overcast 25 %

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


@dataclass(frozen=True)
class Unit:
    """One moving unit: a rigid root (a mocap body) travelling in a straight line.

    Position at time t: ``start + direction * clip(speed * (t - start_time), 0, max_distance)``.
    ``kind`` is "car", "pedestrian", "bicycle" or "motorcycle"; ``style`` the car body style.
    ``footprint`` is (length along the heading, width) in metres, used for collision planning.
    """

    name: str
    kind: str
    start_xy: tuple[float, float]
    heading: float  # radians about +z; 0 = towards +x
    speed: float
    footprint: tuple[float, float]
    start_time: float = 0.0
    max_distance: float = math.inf
    style: str = ""
    colours: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    stride_length: float = 1.4  # pedestrians: metres per full gait cycle


@dataclass(frozen=True)
class Actor:
    """A labelled instance: one unit may carry two (a bicycle and its rider)."""

    instance_id: int
    class_id: int
    unit: int  # index into Layout.units
    role: str  # "car", "pedestrian", "bicycle", "motorcycle", "rider"


@dataclass(frozen=True)
class Building:
    centre: tuple[float, float]
    size: tuple[float, float, float]  # full x, y, z extents
    facade: tuple[float, float, float]


@dataclass(frozen=True)
class Layout:
    seed: int
    config: ScenarioConfig
    ego: Unit
    camera_height: float
    sun_direction: tuple[float, float, float]  # unit vector the light travels along
    units: tuple[Unit, ...]
    actors: tuple[Actor, ...]
    buildings: tuple[Building, ...]
    tree_xs: tuple[tuple[float, float], ...]  # (x, side) with side +1/-1
    pole_xs: tuple[tuple[float, float], ...]
    crosswalk_x: float
    road_x_range: tuple[float, float]
    sky: str = "cloudy"  # base weather, one of rainbench.rain.weather.SKIES
    # Puddles on the road at full size: (x, y, half length, half width, yaw radians) each.
    puddles: tuple[tuple[float, float, float, float, float], ...] = ()


def unit_position(unit: Unit, t: np.ndarray | float) -> np.ndarray:
    """World (x, y) of ``unit`` at times ``t``: shape ``t.shape + (2,)``."""
    t = np.asarray(t, dtype=np.float64)
    distance = np.clip(unit.speed * (t - unit.start_time), 0.0, unit.max_distance)
    direction = np.array([math.cos(unit.heading), math.sin(unit.heading)])
    return np.asarray(unit.start_xy) + distance[..., None] * direction


def unit_distance(unit: Unit, t: float) -> float:
    """Metres travelled by ``unit`` at time ``t`` (drives the walking gait)."""
    return float(np.clip(unit.speed * (t - unit.start_time), 0.0, unit.max_distance))


def ground_height(y: float) -> float:
    """Height of the walkable surface at lateral position y: road 0, sidewalk the curb height."""
    return CURB_HEIGHT if abs(y) >= ROAD_HALF_WIDTH else 0.0


def _footprint_boxes(unit: Unit, times: np.ndarray, margin: float) -> np.ndarray:
    """Axis-aligned footprint rectangles (T, 4) = x0, y0, x1, y1 over ``times``.

    Headings are multiples of 90 degrees in every layout we sample, so axis-aligned boxes are exact.
    """
    centre = unit_position(unit, times)
    length, width = unit.footprint
    along_x = abs(math.cos(unit.heading)) > 0.5
    half = np.array([length, width] if along_x else [width, length]) / 2 + margin
    return np.concatenate([centre - half, centre + half], axis=-1)


def units_collide(a: Unit, b: Unit, times: np.ndarray, margin: float = 0.4) -> bool:
    """True when the footprints of ``a`` and ``b`` (grown by ``margin``) overlap at any time."""
    box_a = _footprint_boxes(a, times, margin / 2)
    box_b = _footprint_boxes(b, times, margin / 2)
    overlap_x = (box_a[:, 0] < box_b[:, 2]) & (box_b[:, 0] < box_a[:, 2])
    overlap_y = (box_a[:, 1] < box_b[:, 3]) & (box_b[:, 1] < box_a[:, 3])
    return bool(np.any(overlap_x & overlap_y))


def _pick(rng: np.random.Generator, options: tuple):
    return options[int(rng.integers(len(options)))]


def _meet_start(
    rng: np.random.Generator, ego: Unit, speed: float, heading: float, duration: float,
    ahead_range: tuple[float, float],
) -> float:
    """Start x such that the unit is ``ahead`` metres in front of the ego at a random time."""
    meet_time = rng.uniform(0.1 * duration, 0.9 * duration)
    ahead = rng.uniform(*ahead_range)
    ego_x = float(unit_position(ego, meet_time)[0])
    return ego_x + ahead - math.cos(heading) * speed * meet_time


def _place(
    rng: np.random.Generator, make, placed: list[Unit], times: np.ndarray, what: str, seed: int
) -> Unit:
    for _ in range(200):
        unit = make()
        if not any(units_collide(unit, other, times) for other in placed):
            placed.append(unit)
            return unit
    raise RuntimeError(
        f"layout: could not place {what} without collisions for seed {seed} after 200 tries; "
        "lower the actor counts (num_cars, num_pedestrians, ...)"
    )


def sample_layout(seed: int, config: ScenarioConfig, rng: np.random.Generator) -> Layout:
    """Sample a complete layout. ``seed`` is recorded only; all randomness comes from ``rng``.

    The seed decides: ego speed and lane, camera height jitter, sun direction, base weather
    (sky) and where puddles form when it rains, every unit's
    lane or sidewalk, start position, speed and heading, car styles and paints, clothing and
    skin colours, which pedestrians use the crosswalk, and the buildings, trees and poles.
    Units are placed by rejection so that no two footprints ever overlap during the clip.
    """
    duration = config.duration_s
    times = np.linspace(0.0, duration, int(duration * 20) + 1)

    ego_speed = config.ego_speed if config.ego_speed is not None else rng.uniform(7.0, 10.0)
    ego_lane = float(_pick(rng, (LANE_CENTRES[0], LANE_CENTRES[1])))
    camera_height = (
        config.camera_height if config.camera_height is not None else 1.55 + rng.uniform(-0.1, 0.1)
    )
    azimuth = math.radians(
        config.sun_azimuth_deg if config.sun_azimuth_deg is not None else rng.uniform(0, 360)
    )
    elevation = math.radians(
        config.sun_elevation_deg if config.sun_elevation_deg is not None else rng.uniform(25, 70)
    )
    sun_direction = (
        -math.cos(elevation) * math.cos(azimuth),
        -math.cos(elevation) * math.sin(azimuth),
        -math.sin(elevation),
    )
    ego = Unit("ego", "ego", (0.0, ego_lane), 0.0, float(ego_speed), EGO_DIMENSIONS)
    placed: list[Unit] = [ego]
    units: list[Unit] = []
    actors: list[Actor] = []
    crosswalk_x = float(unit_position(ego, rng.uniform(0.35, 0.6) * duration)[0] + 25.0)

    def add_actor(class_id: int, role: str) -> None:
        actors.append(Actor(len(actors), class_id, len(units) - 1, role))

    for index in range(config.num_cars):
        def make_car() -> Unit:
            lane = float(_pick(rng, LANE_CENTRES))
            heading = 0.0 if lane < 0 else math.pi
            speed = rng.uniform(4.0, 12.0)
            style = _pick(rng, CAR_STYLES)
            length, width, _ = CAR_DIMENSIONS[style]
            x0 = _meet_start(rng, ego, speed, heading, duration, (12.0, 45.0))
            paint = _pick(rng, CAR_PAINTS)
            return Unit(f"car{index}", "car", (x0, lane), heading, speed, (length, width),
                        style=style, colours={"paint": paint})
        units.append(_place(rng, make_car, placed, times, f"car {index}", seed))
        add_actor(CAR, "car")

    num_crossing = min(config.num_pedestrians, int(rng.integers(1, 3)))
    for index in range(config.num_pedestrians):
        crossing = index < num_crossing

        def make_pedestrian() -> Unit:
            side = float(_pick(rng, (-1.0, 1.0)))
            speed = rng.uniform(0.9, 1.6)
            colours = {
                "shirt": _pick(rng, CLOTHING), "trousers": _pick(rng, CLOTHING),
                "skin": _pick(rng, SKIN), "hair": _pick(rng, CLOTHING[2::7] + CLOTHING[9:]),
            }
            stride = rng.uniform(1.2, 1.6)
            if crossing:
                start = (crosswalk_x + rng.uniform(-1.5, 1.5), side * (ROAD_HALF_WIDTH + 0.8))
                return Unit(f"person{index}", "pedestrian", start, -side * math.pi / 2, speed,
                            FOOTPRINTS["pedestrian"], start_time=rng.uniform(0.0, 0.6 * duration),
                            max_distance=2 * ROAD_HALF_WIDTH + 1.6, colours=colours,
                            stride_length=stride)
            heading = float(_pick(rng, (0.0, math.pi)))
            y = side * rng.uniform(*PEDESTRIAN_Y_RANGE)
            x0 = _meet_start(rng, ego, speed, heading, duration, (12.0, 40.0))
            return Unit(f"person{index}", "pedestrian", (x0, y), heading, speed,
                        FOOTPRINTS["pedestrian"], colours=colours, stride_length=stride)
        units.append(_place(rng, make_pedestrian, placed, times, f"pedestrian {index}", seed))
        add_actor(PERSON, "pedestrian")

    for kind, count in (("bicycle", config.num_bicycles), ("motorcycle", config.num_motorcycles)):
        for index in range(count):
            def make_ride() -> Unit:
                if kind == "bicycle":
                    side = float(_pick(rng, (-1.0, 1.0)))
                    y = side * BIKE_LANE_Y
                    speed = rng.uniform(3.5, 6.5)
                else:
                    y = float(_pick(rng, LANE_CENTRES))
                    side = 1.0 if y > 0 else -1.0
                    speed = rng.uniform(6.0, 13.0)
                heading = 0.0 if side < 0 else math.pi
                x0 = _meet_start(rng, ego, speed, heading, duration, (12.0, 40.0))
                colours = {
                    "frame": _pick(rng, CAR_PAINTS), "shirt": _pick(rng, CLOTHING),
                    "trousers": _pick(rng, CLOTHING), "skin": _pick(rng, SKIN),
                    "helmet": _pick(rng, CAR_PAINTS),
                }
                return Unit(f"{kind}{index}", kind, (x0, y), heading, speed, FOOTPRINTS[kind],
                            colours=colours)
            units.append(_place(rng, make_ride, placed, times, f"{kind} {index}", seed))
            add_actor(BICYCLE if kind == "bicycle" else MOTORCYCLE, kind)
            add_actor(PERSON, "rider")

    # The road spans every position any unit (and the ego's view) reaches, plus margins.
    xs = [unit_position(u, times)[:, 0] for u in placed]
    x_min = float(min(x.min() for x in xs)) - 40.0
    x_max = float(max(x.max() for x in xs)) + 120.0
    buildings = []
    for side in (-1.0, 1.0):
        x = x_min
        while x < x_max:
            width = rng.uniform(10.0, 26.0)
            depth = rng.uniform(10.0, 18.0)
            height = rng.uniform(7.0, 32.0)
            setback = SIDEWALK_OUTER + rng.uniform(0.5, 4.0)
            buildings.append(Building(
                (x + width / 2, side * (setback + depth / 2)), (width, depth, height),
                _pick(rng, FACADES)))
            x += width + (rng.uniform(2.0, 8.0) if rng.random() < 0.4 else 0.3)
    tree_xs, pole_xs = [], []
    for side in (-1.0, 1.0):
        x = x_min + rng.uniform(0, 10)
        while x < x_max:
            tree_xs.append((x, side))
            x += rng.uniform(12.0, 22.0)
        x = x_min + rng.uniform(0, 15)
        while x < x_max:
            if abs(x - crosswalk_x) > 4.0:
                pole_xs.append((x, side))
            x += 30.0
    # Weather draws come last, so they leave every earlier draw (the layout) unchanged.
    sky_draw = rng.random()
    sky = config.sky if config.sky is not None else SKIES[int(np.searchsorted(
        np.cumsum(SKY_PROBABILITIES), sky_draw, side="right"))]
    puddles = []
    x = x_min + rng.uniform(0.0, PUDDLE_SPACING_M)
    while x < x_max:
        y = rng.uniform(-ROAD_HALF_WIDTH + 0.8, ROAD_HALF_WIDTH - 0.8)
        puddles.append((float(x), float(y), float(rng.uniform(1.2, 4.0)),
                        float(rng.uniform(0.5, 1.6)), float(rng.uniform(-0.3, 0.3))))
        x += rng.uniform(0.5, 1.5) * PUDDLE_SPACING_M
    return Layout(
        seed=seed, config=config, ego=ego, camera_height=float(camera_height),
        sun_direction=sun_direction, units=tuple(units), actors=tuple(actors),
        buildings=tuple(buildings), tree_xs=tuple(tree_xs), pole_xs=tuple(pole_xs),
        crosswalk_x=crosswalk_x, road_x_range=(x_min, x_max), sky=sky, puddles=tuple(puddles),
    )
