"""Procedural mesh vehicles: cars (sedan, hatchback, SUV, van, pickup), buses and box trucks.

Each vehicle is a smooth body shell lofted from cross-sections along its length (rounded
bonnet, raked windscreen, rounded roof, boot or hatch, wheel arches cut out of the underside),
dark glass panes following the cabin, and primitive parts: tyres and rims, head and tail lamps,
side mirrors, bumpers, grille and number plates; a bus adds doors and a destination sign, a
truck a separate cargo box, a chassis frame and twin rear tyres.

:func:`sample_vehicle` draws a :class:`VehicleShape` (pure data) from an explicit ``rng``;
:func:`add_vehicle` builds it under a ``mujoco.MjSpec`` body. Every geom is named
``{prefix}{part}`` and never collides; mesh assets are named ``{prefix}shell``,
``{prefix}screen`` (windscreen and rear window, lighter: raked glass mirrors the sky),
``{prefix}glass`` (side windows), ``{prefix}cladding`` and ``{prefix}cargo``, so that several
vehicles share one spec and its exported MJCF. Body frame: x forward, y left, z up, origin on
the ground at the footprint centre; the vehicle spans x in [-length/2, length/2] (lamps on
rounded corners may poke out by a few mm), z in [0, height] and y in [-width/2, width/2]
(mirrors, arch flares and tyre rims stick out sideways).

Shell section: 17 points per station, ``_HALF`` = 8 on the left (y > 0) from the underside to
the roof edge, the top centre, then the right side mirrored. Points 0-1 chamfer the lower edge,
1-2 is the body side, 2-3 the shoulder at the belt line (the window sills), 3-4 the greenhouse
side (where the side windows are), 4-7 round the roof edge and 8 is the top centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np

from . import layout as L
from .parts import (GLASS, HEADLIGHT, RIM, SCREEN_GLASS, TAILLIGHT, TRIM, TYRE, Y_AXIS_QUAT, _geom,
                    rgba, unit_yaw_quat)

GEOM = mujoco.mjtGeom

VEHICLE_STYLES = L.VEHICLE_STYLES  # one definition: the layout's (style -> COCO class id too)
VEHICLE_CLASS = L.VEHICLE_CLASS
BUS_PAINTS: tuple[tuple[float, float, float], ...] = (
    (0.80, 0.10, 0.08), (0.95, 0.72, 0.08), (0.92, 0.92, 0.90), (0.10, 0.30, 0.65),
    (0.15, 0.50, 0.25), (0.85, 0.45, 0.10),
)
TRUCK_PAINTS: tuple[tuple[float, float, float], ...] = (
    (0.92, 0.92, 0.90), (0.75, 0.08, 0.08), (0.08, 0.20, 0.55), (0.45, 0.47, 0.50),
    (0.10, 0.10, 0.11), (0.90, 0.60, 0.05), (0.12, 0.40, 0.20),
)
CARGO_COLOURS: tuple[tuple[float, float, float], ...] = (
    (0.93, 0.93, 0.91), (0.80, 0.81, 0.82), (0.88, 0.86, 0.80),
)
PLATE = (0.93, 0.93, 0.88, 1.0)
SIGN = (1.0, 0.62, 0.12, 1.0)
BED = (0.13, 0.13, 0.14, 1.0)

# (length, width, height) ranges in metres that sample_vehicle draws from, per style.
SIZE_RANGES: dict[str, tuple[tuple[float, float], ...]] = {
    "sedan": ((4.5, 4.9), (1.78, 1.86), (1.40, 1.48)),
    "hatchback": ((3.9, 4.3), (1.72, 1.80), (1.44, 1.52)),
    "suv": ((4.5, 4.9), (1.85, 1.95), (1.70, 1.85)),
    "van": ((4.8, 5.3), (1.90, 2.00), (1.90, 2.00)),
    "pickup": ((5.2, 5.8), (1.90, 2.00), (1.78, 1.90)),
    "bus": ((10.0, 12.0), (2.45, 2.55), (2.95, 3.20)),
    "truck": ((7.0, 9.0), (2.40, 2.50), (3.20, 3.60)),
}
SIZE_SLACK = 0.15  # a requested size may leave its style's range by this fraction

_HALF = 8  # section points per side
SECTION_POINTS = 2 * _HALF + 1
SIDE_GLASS_T = (3.1, 3.88)  # section parameter of the left side windows (belt -> roof edge)
TOP_GLASS_T = (5.0, 11.0)  # windscreen / rear window: between the two roof-edge arcs
GLASS_GAP = (0.004, 0.014)  # inner and outer surface of a glass pane above the shell (m)
BUMPER_DEPTH = 0.04  # bumpers stick out this far beyond the shell's ends (m)


@dataclass(frozen=True)
class VehicleShape:
    """A sampled vehicle, metres in its body frame (x forward, z up, origin on the ground).

    ``length``, ``height``: bumper to bumper and ground to the top (roof; a truck's cargo box);
    ``width``: the body without mirrors. ``axles``: x of each axle, front first.
    ``roofline``: (x, z) points of the shell's top centreline from its front end to its back
    end (a truck's shell is its cab); the shell ends are ``BUMPER_DEPTH`` inside the length.
    ``clearance``: the shell's underside between the wheels; ``belt_height``: the window sills.
    ``windscreen``, ``rear_window`` and each of ``side_windows``: (front x, back x) of a glass
    pane on the shell (side panes are mirrored on both sides). ``doors``: (front x, back x) of
    the bus doors on the right (kerb) side. ``bed``: a pickup's load bed (front x, back x).
    ``cargo``: a truck's cargo box (front x, back x, floor z; its top is ``height``) painted
    ``cargo_colour``.
    """

    style: str
    length: float
    width: float
    height: float
    wheel_radius: float
    axles: tuple[float, ...]
    twin_rear: bool
    clearance: float
    belt_height: float
    roofline: tuple[tuple[float, float], ...]
    windscreen: tuple[float, float]
    rear_window: tuple[float, float] | None
    side_windows: tuple[tuple[float, float], ...]
    doors: tuple[tuple[float, float], ...] = ()
    bed: tuple[float, float] | None = None
    cargo: tuple[float, float, float] | None = None
    cargo_colour: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class _Section:
    """How a style's shell is rounded: plan-view corner radii at the nose and tail, radii of the
    lower and roof edges, the greenhouse's inward lean (``tumble`` + ``tumble_slope`` per metre
    of its height), the crown of roof and bonnet, how far the underside rises at the ends and
    how much the belt line rises from the front to the back."""

    nose_radius: float
    tail_radius: float
    bottom_radius: float
    top_radius: float
    tumble: float
    tumble_slope: float
    crown: float
    end_lift: float
    belt_rise: float = 0.0


_SECTIONS: dict[str, _Section] = {
    "sedan": _Section(0.34, 0.26, 0.07, 0.10, 0.03, 0.26, 0.025, 0.10, 0.04),
    "hatchback": _Section(0.32, 0.22, 0.07, 0.10, 0.03, 0.22, 0.025, 0.10, 0.08),
    "suv": _Section(0.30, 0.22, 0.08, 0.10, 0.03, 0.16, 0.025, 0.10, 0.03),
    "van": _Section(0.30, 0.16, 0.08, 0.12, 0.03, 0.10, 0.03, 0.08),
    "pickup": _Section(0.28, 0.14, 0.08, 0.10, 0.03, 0.14, 0.025, 0.10),
    "bus": _Section(0.22, 0.20, 0.08, 0.16, 0.02, 0.02, 0.04, 0.12),
    "truck": _Section(0.14, 0.10, 0.06, 0.10, 0.02, 0.04, 0.02, 0.10),
}
_CARGO_SECTION = _Section(0.06, 0.06, 0.04, 0.05, 0.0, 0.0, 0.0, 0.0)
# Sections across a wheel arch at axle + arch radius * step.
_ARCH_STEPS = (1.0, 0.75, 0.4, 0.0, -0.4, -0.75, -1.0)


# -- sampling ---------------------------------------------------------------------------------

def _check_style(style: str) -> None:
    if style not in VEHICLE_STYLES:
        raise ValueError(f"vehicle style: expected one of {', '.join(VEHICLE_STYLES)}, "
                         f"got {style!r}")


def _split(front: float, back: float, fractions: tuple[float, ...], pillar: float
           ) -> tuple[tuple[float, float], ...]:
    """Window panes (front x, back x) splitting ``front`` -> ``back`` at ``fractions`` of the
    span, with ``pillar``-wide gaps."""
    cuts = [front + (back - front) * f for f in fractions]
    edges = [front] + [c for cut in cuts for c in (cut + pillar / 2, cut - pillar / 2)] + [back]
    return tuple((edges[i], edges[i + 1]) for i in range(0, len(edges), 2))


def _x_at(p0: tuple[float, float], p1: tuple[float, float], z: float) -> float:
    """x where the roofline segment p0 -> p1 (points (x, z)) reaches height z."""
    (x0, z0), (x1, z1) = p0, p1
    return x0 + (x1 - x0) * (z - z0) / (z1 - z0)


def _draw_size(style: str, rng: np.random.Generator,
               size: tuple[float, float, float] | None) -> tuple[float, float, float]:
    """(length, width, height) drawn from the style's SIZE_RANGES, or ``size`` when given (the
    draws happen either way, so the rest of the shape comes from the same numbers)."""
    drawn = tuple(rng.uniform(*bounds) for bounds in SIZE_RANGES[style])
    if size is None:
        return drawn
    if len(size) != 3:
        raise ValueError(f"size: expected (length, width, height), got {size!r}")
    for name, value, (low, high) in zip(("length", "width", "height"), size,
                                        SIZE_RANGES[style]):
        low, high = low * (1 - SIZE_SLACK), high * (1 + SIZE_SLACK)
        if not low <= value <= high:
            raise ValueError(f"size: expected a {style} {name} in {low:.2f}..{high:.2f} m, "
                             f"got {value}")
    return tuple(float(value) for value in size)


def _sample_car(style: str, rng: np.random.Generator,
                size: tuple[float, float, float] | None) -> VehicleShape:
    """Sedan, hatchback, SUV, van and pickup: a bonnet, a raked windscreen and a roof."""
    u = rng.uniform
    length, width, height = _draw_size(style, rng, size)
    # wheel radius, front/rear overhang, clearance, belt, nose height
    dims = {
        "sedan": ((0.31, 0.34), (0.88, 0.98), (1.00, 1.12), (0.15, 0.18), (0.90, 0.95),
                  (0.72, 0.78)),
        "hatchback": ((0.30, 0.32), (0.78, 0.86), (0.62, 0.72), (0.14, 0.17), (0.92, 0.97),
                      (0.74, 0.80)),
        "suv": ((0.37, 0.40), (0.88, 0.98), (0.85, 0.95), (0.24, 0.28), (1.08, 1.15),
                (0.96, 1.03)),
        "van": ((0.33, 0.35), (0.85, 0.95), (0.95, 1.10), (0.18, 0.22), (1.02, 1.10),
                (0.82, 0.90)),
        "pickup": ((0.38, 0.41), (0.90, 1.00), (1.25, 1.45), (0.26, 0.30), (1.18, 1.25),
                   (1.00, 1.08)),
    }[style]
    radius, front_oh, rear_oh, clearance, belt, nose_z = (u(*bounds) for bounds in dims)
    xf, xr = length / 2 - BUMPER_DEPTH, -length / 2 + BUMPER_DEPTH
    axles = (length / 2 - front_oh, -length / 2 + rear_oh)
    base_z = belt + 0.02  # bonnet at the windscreen's foot
    if style == "sedan":
        bonnet, screen, roof, rear = (length * u(0.25, 0.28), length * u(0.16, 0.18),
                                      length * u(0.21, 0.24), length * u(0.13, 0.15))
        boot_z = u(0.98, 1.04)
    elif style == "hatchback":
        bonnet, screen = length * u(0.22, 0.25), length * u(0.19, 0.21)
        hatch_z = u(1.00, 1.06)
    elif style == "suv":
        bonnet, screen = length * u(0.22, 0.25), length * u(0.12, 0.14)
        hatch_z = u(1.14, 1.22)
    elif style == "van":
        bonnet, screen = u(0.50, 0.65), u(0.75, 0.90)
        hatch_z = u(0.95, 1.02)
    else:
        bonnet, screen, cab_roof = u(1.45, 1.60), u(0.60, 0.70), u(1.20, 1.40)
        rail_z = belt + u(0.0, 0.05)
    x_base = xf - bonnet
    x_top = x_base - screen
    front = ((xf, nose_z), (xf - 0.3 * bonnet, nose_z + 0.7 * (base_z - nose_z)),
             (x_base, base_z), (x_top, height - 0.035))
    if style == "sedan":
        x_roof = x_top - roof
        x_boot = x_roof - rear
        back = ((x_top - 0.45 * roof, height), (x_roof, height - 0.03), (x_boot, boot_z),
                (xr + 0.12, boot_z - 0.02), (xr, boot_z - 0.09))
        rear_window = (x_roof - 0.03, x_boot + 0.03)
        side = (x_base - 0.05, x_roof - 0.35 * rear)
        panes = _split(side[0], side[1], (0.5,), 0.09)
    elif style in ("hatchback", "suv", "van"):
        tail_gap = {"hatchback": length * u(0.11, 0.13), "suv": length * u(0.035, 0.05),
                    "van": u(0.06, 0.09)}[style]
        x_roof = xr + tail_gap
        roof_drop = {"hatchback": 0.09, "suv": 0.03, "van": 0.03}[style]
        hatch = (xr + {"hatchback": 0.09, "suv": 0.07, "van": 0.02}[style], hatch_z)
        back = ((x_top - 0.4 * (x_top - x_roof), height), (x_roof, height - roof_drop), hatch,
                (xr, hatch_z - {"hatchback": 0.12, "suv": 0.08, "van": 0.04}[style]))
        rear_window = (x_roof - 0.02, _x_at((x_roof, height - roof_drop), hatch, belt + 0.08))
        side = (x_base - 0.05, x_roof + {"hatchback": 0.30, "suv": 0.10, "van": 0.22}[style])
        cuts = {"hatchback": (0.52,), "suv": (0.40, 0.78), "van": (0.28, 0.70)}[style]
        panes = _split(side[0], side[1], cuts, 0.09)
    else:
        x_cab = x_top - cab_roof
        back = ((x_top - 0.5 * cab_roof, height), (x_cab, height - 0.03),
                (x_cab - 0.07, rail_z), (xr + 0.05, rail_z), (xr, rail_z - 0.05))
        cab_back = ((x_cab, height - 0.03), (x_cab - 0.07, rail_z))
        rear_window = (_x_at(*cab_back, height - 0.10), _x_at(*cab_back, rail_z + 0.10))
        side = (x_base - 0.05, x_cab + 0.12)
        panes = _split(side[0], side[1], (0.52,), 0.09)
    return VehicleShape(
        style=style, length=length, width=width, height=height, wheel_radius=radius,
        axles=axles, twin_rear=False, clearance=clearance, belt_height=belt,
        roofline=front + back, windscreen=(x_base - 0.03, x_top + 0.04),
        rear_window=rear_window, side_windows=panes,
        bed=(x_cab - 0.12, xr + 0.06) if style == "pickup" else None,
    )


def _sample_bus(rng: np.random.Generator, size: tuple[float, float, float] | None
                ) -> VehicleShape:
    u = rng.uniform
    length, width, height = _draw_size("bus", rng, size)
    radius, clearance, belt = u(0.47, 0.51), u(0.28, 0.34), u(1.05, 1.20)
    front_oh, rear_oh, nose_z = u(2.40, 2.70), u(3.00, 3.40), u(0.95, 1.05)
    xf, xr = length / 2 - BUMPER_DEPTH, -length / 2 + BUMPER_DEPTH
    axles = (length / 2 - front_oh, -length / 2 + rear_oh)
    roofline = ((xf, nose_z), (xf - 0.14, height - 0.22), (xf - 0.32, height),
                (xr + 0.30, height), (xr + 0.10, height - 0.22), (xr, 1.15))
    screen = (_x_at(roofline[0], roofline[1], nose_z + 0.06),
              _x_at(roofline[0], roofline[1], height - 0.26))
    rear = (_x_at(roofline[4], roofline[5], height - 0.35),
            _x_at(roofline[4], roofline[5], 1.60))
    side = (xf - 0.45, xr + 0.50)
    count = max(3, round((side[0] - side[1]) / 1.45))
    panes = _split(side[0], side[1], tuple(k / count for k in range(1, count)), 0.12)
    middle = axles[0] - 0.45 * (axles[0] - axles[1])
    doors = ((xf - 0.20, xf - 1.35), (middle + 0.62, middle - 0.62))
    return VehicleShape(
        style="bus", length=length, width=width, height=height, wheel_radius=radius,
        axles=axles, twin_rear=False, clearance=clearance, belt_height=belt,
        roofline=roofline, windscreen=screen, rear_window=rear, side_windows=panes, doors=doors,
    )


def _sample_truck(rng: np.random.Generator, size: tuple[float, float, float] | None
                  ) -> VehicleShape:
    u = rng.uniform
    length, width, height = _draw_size("truck", rng, size)
    radius, clearance, belt = u(0.48, 0.52), u(0.50, 0.58), u(1.45, 1.55)
    cab_len, cab_h, front_oh = u(2.00, 2.30), min(u(2.55, 2.85), height - 0.3), u(1.20, 1.40)
    rear_oh, nose_z, floor_z = length * u(0.22, 0.27), u(1.30, 1.42), u(1.12, 1.25)
    xf, xr = length / 2 - BUMPER_DEPTH, -length / 2 + BUMPER_DEPTH
    x_cab = length / 2 - cab_len
    roofline = ((xf, nose_z), (xf - 0.28, cab_h - 0.22), (xf - 0.45, cab_h),
                (x_cab + 0.08, cab_h), (x_cab, cab_h - 0.10))
    screen = (_x_at(roofline[0], roofline[1], nose_z + 0.05),
              _x_at(roofline[0], roofline[1], cab_h - 0.26))
    return VehicleShape(
        style="truck", length=length, width=width, height=height, wheel_radius=radius,
        axles=(length / 2 - front_oh, -length / 2 + rear_oh), twin_rear=True,
        clearance=clearance, belt_height=belt, roofline=roofline, windscreen=screen,
        rear_window=None, side_windows=((xf - 0.30, x_cab + 0.45),),
        cargo=(x_cab - 0.12, xr, floor_z),
        cargo_colour=CARGO_COLOURS[int(rng.integers(len(CARGO_COLOURS)))],
    )


def sample_vehicle(style: str, rng: np.random.Generator,
                   size: tuple[float, float, float] | None = None) -> VehicleShape:
    """A vehicle of ``style`` with dimensions drawn around realistic means (:data:`SIZE_RANGES`:
    sedan 4.5-4.9 m long, hatchback 3.9-4.3, SUV 4.5-4.9, van 4.8-5.3, pickup 5.2-5.8,
    bus 10-12, truck 7-9) and proportions drawn per style.

    ``size``: (length, width, height) in metres to build instead of drawn ones (for example a
    layout's planning dimensions), each within ``SIZE_SLACK`` of the style's range.
    """
    _check_style(style)
    if style == "bus":
        return _sample_bus(rng, size)
    if style == "truck":
        return _sample_truck(rng, size)
    return _sample_car(style, rng, size)


def sample_paint(style: str, rng: np.random.Generator,
                 palette: tuple[tuple[float, float, float], ...] | None = None
                 ) -> tuple[float, float, float]:
    """A paint colour (rgb 0..1) drawn from ``palette``, by default the style's own: cars
    :data:`rainbench.mjcf.layout.CAR_PAINTS`, buses :data:`BUS_PAINTS`, trucks
    :data:`TRUCK_PAINTS`."""
    _check_style(style)
    if palette is None:
        palette = {"bus": BUS_PAINTS, "truck": TRUCK_PAINTS}.get(style, L.CAR_PAINTS)
    if len(palette) == 0:
        raise ValueError("palette: expected at least one colour, got none")
    return tuple(float(c) for c in palette[int(rng.integers(len(palette)))])


# -- the lofted shell -------------------------------------------------------------------------

@dataclass(frozen=True)
class _Loft:
    """A closed lofted body: top centreline ``roofline`` ((x, z) front to back), plan width,
    underside height, belt height, wheel arches (axle x) of ``arch_radius`` about wheels of
    ``wheel_radius``, and its rounding."""

    roofline: tuple[tuple[float, float], ...]
    width: float
    clearance: float
    belt: float
    arches: tuple[float, ...]
    wheel_radius: float
    arch_radius: float
    section: _Section

    @property
    def front(self) -> float:
        return self.roofline[0][0]

    @property
    def back(self) -> float:
        return self.roofline[-1][0]


def _half_width(loft: _Loft, x: float) -> float:
    """Plan-view half width at x: full between the ends, rounded corners at nose and tail."""
    sec, half = loft.section, loft.width / 2
    for depth, radius in ((x - (loft.front - sec.nose_radius), sec.nose_radius),
                          ((loft.back + sec.tail_radius) - x, sec.tail_radius)):
        if depth > 0:
            half = min(half, loft.width / 2 - radius + math.sqrt(max(radius**2 - depth**2, 0)))
    return half


def _underside(loft: _Loft, x: float) -> float:
    """Underside height at x: the clearance, rising towards the ends, cut up by wheel arches."""
    lift_len = 0.45
    z = loft.clearance + loft.section.end_lift * max(
        0.0, (x - (loft.front - lift_len)) / lift_len, ((loft.back + lift_len) - x) / lift_len)
    for axle in loft.arches:
        dx = x - axle
        if abs(dx) < loft.arch_radius:
            z = max(z, loft.wheel_radius + math.sqrt(loft.arch_radius**2 - dx**2))
    return z


def _section_points(loft: _Loft, x: float) -> np.ndarray:
    """(SECTION_POINTS, 2) float64 (y, z) of the shell's section at x (see the module doc)."""
    sec = loft.section
    xs = [p[0] for p in loft.roofline][::-1]
    zs = [p[1] for p in loft.roofline][::-1]
    ztop = float(np.interp(x, xs, zs))
    half = _half_width(loft, x)
    zedge = ztop - sec.crown
    zb = _underside(loft, x)
    rt = min(sec.top_radius, 0.3 * (zedge - zb))
    belt = loft.belt + sec.belt_rise * (loft.front - x) / (loft.front - loft.back)
    zbelt = min(belt, zedge - rt - 0.01)
    zb = min(zb, zbelt - 0.06)  # arches never cut through the shoulder
    rb = min(sec.bottom_radius, 0.4 * (zbelt - 0.03 - zb))
    top_half = half - sec.tumble - sec.tumble_slope * (zedge - rt - zbelt)
    c30 = math.cos(math.pi / 6)
    left = [
        (half - rb, zb), (half, zb + rb),
        (half, zbelt - 0.03), (half - min(0.015, sec.tumble), zbelt), (top_half, zedge - rt),
        (top_half - rt + rt * c30, zedge - rt + rt * 0.5),
        (top_half - rt + rt * 0.5, zedge - rt + rt * c30), (top_half - rt, zedge),
    ]
    right = [(-y, z) for y, z in reversed(left)]
    return np.array(left + [(0.0, ztop)] + right)


def _stations(loft: _Loft) -> np.ndarray:
    """(N,) float64 x of the shell's sections, front to back: every roofline point, the plan
    rounding at both ends, the ends of the underside's rise, and each wheel arch."""
    sec = loft.section
    xs = [p[0] for p in loft.roofline]
    for angle in (0.0, 30.0, 60.0):
        s = math.sin(math.radians(angle))
        xs += [loft.front - sec.nose_radius * (1 - s), loft.back + sec.tail_radius * (1 - s)]
    xs += [loft.front - 0.45, loft.back + 0.45]
    ra = loft.arch_radius
    for axle in loft.arches:
        xs += [axle + ra * step for step in _ARCH_STEPS]
        xs += [axle - ra + 0.005, axle + ra - 0.005]  # the arch's vertical ends
    xs = np.array(sorted({round(x, 5) for x in xs if loft.back <= x <= loft.front})[::-1])
    keep = np.concatenate([[True], np.diff(-xs) > 0.002])
    return xs[keep]


def _loft_rings(loft: _Loft) -> np.ndarray:
    """(N, SECTION_POINTS, 3) float64 vertices of the shell's sections, front to back."""
    rings = []
    for x in _stations(loft):
        yz = _section_points(loft, x)
        rings.append(np.column_stack([np.full(len(yz), x), yz]))
    return np.array(rings)


# Smoothing bands of the shell's section segments (segment j joins points j and j + 1): the
# lower-edge chamfers, body sides and shoulders are creased from each other; the greenhouse
# sides, roof-edge arcs and top are one smooth band. Caps are bands 8 and 9.
_SEGMENT_BAND = np.array([0, 1, 2] + [3] * 10 + [4, 5, 6, 7])
_CAP_BANDS = (8, 9)
CREASE_DEG = 45.0  # faces of one band meeting at a larger angle are shaded with a crease


class Mesh(NamedTuple):
    """A closed triangle mesh: vertices (V, 3) float64, outward faces (F, 3) int64 and each
    face's smoothing band (F,) int64 (faces of different bands never share a shading normal)."""

    verts: np.ndarray
    faces: np.ndarray
    bands: np.ndarray


def _grid_faces(rows: int, cols: int, wrap: bool) -> tuple[np.ndarray, np.ndarray]:
    """Faces (F, 3) int64 of a rows x cols vertex grid (row-major), outward for the loft's
    orientation (rows front to back, columns along the section; ``wrap`` closes the columns),
    and the column segment (F,) of each face."""
    i, j = np.meshgrid(np.arange(rows - 1), np.arange(cols if wrap else cols - 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    a, b = i * cols + j, i * cols + (j + 1) % cols
    c, d = a + cols, b + cols
    faces = np.stack([np.column_stack([a, d, b]), np.column_stack([a, c, d])], axis=1)
    return faces.reshape(-1, 3).astype(np.int64), np.repeat(j, 2).astype(np.int64)


def _loft_mesh(loft: _Loft) -> Mesh:
    """The closed shell of ``loft``: its sections joined front to back, fans closing the ends."""
    rings = _loft_rings(loft)
    rows, cols = rings.shape[:2]
    verts = rings.reshape(-1, 3)
    grid, segments = _grid_faces(rows, cols, wrap=True)
    faces, bands = [grid], [_SEGMENT_BAND[segments]]
    for row, flip, band in ((0, True, _CAP_BANDS[0]), (rows - 1, False, _CAP_BANDS[1])):
        centre = len(verts)
        verts = np.vstack([verts, rings[row].mean(axis=0)])
        ring = row * cols + np.arange(cols)
        fan = np.column_stack([np.full(cols, centre), np.roll(ring, -1), ring])
        faces.append(fan[:, [0, 2, 1]] if flip else fan)
        bands.append(np.full(cols, band))
    return Mesh(verts, np.vstack(faces), np.concatenate(bands))


def _surface(rings: np.ndarray, xs: np.ndarray, x: float, t: float) -> np.ndarray:
    """(3,) point of the shell at x (between stations ``xs``, descending) and section
    parameter t (fractional point index), bilinear in the rings."""
    i = min(max(int(np.searchsorted(-xs, -x, side="right")) - 1, 0), len(xs) - 2)
    w = (xs[i] - x) / (xs[i] - xs[i + 1])
    j = min(max(math.floor(t), 0), SECTION_POINTS - 2)
    f = t - j
    near = (1 - f) * rings[i, j] + f * rings[i, j + 1]
    far = (1 - f) * rings[i + 1, j] + f * rings[i + 1, j + 1]
    return (1 - w) * near + w * far


def _drop_straight_rows(grid: np.ndarray, tolerance: float = 1e-3) -> np.ndarray:
    """(R', C, 3) ``grid`` (R, C, 3) without the inner rows that lie within ``tolerance`` (m) of
    the straight line between their neighbours (fewer triangles, same surface)."""
    rows = list(range(len(grid)))
    k = 1
    while k < len(rows) - 1:
        before, row, after = grid[rows[k - 1]], grid[rows[k]], grid[rows[k + 1]]
        span = after[:, 0] - before[:, 0]
        w = (row[:, 0] - before[:, 0]) / np.where(span == 0, 1.0, span)
        straight = before + w[:, None] * (after - before)
        if np.abs(straight - row).max() < tolerance:
            rows.pop(k)
        else:
            k += 1
    return grid[rows]


def _pane(rings: np.ndarray, xs: np.ndarray, x_range: tuple[float, float],
          t_range: tuple[float, float]) -> Mesh:
    """A closed glass slab over the shell patch x_range (front, back) x t_range (section
    parameters), lifted by ``GLASS_GAP`` along the shell's outward normal."""
    x0, x1 = x_range
    t0, t1 = t_range
    grid_x = [x0] + [x for x in xs if x1 + 0.005 < x < x0 - 0.005] + [x1]
    grid_t = [t0] + [float(j) for j in range(math.floor(t0) + 1, math.ceil(t1))] + [t1]
    grid = np.array([[_surface(rings, xs, x, t) for t in grid_t] for x in grid_x])
    grid = _drop_straight_rows(grid)
    along_x = np.gradient(grid, axis=0)
    along_t = np.gradient(grid, axis=1)
    normal = np.cross(along_x, along_t)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return _slab(grid + GLASS_GAP[1] * normal, grid + GLASS_GAP[0] * normal)


def _signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Volume (m^3) enclosed by a closed mesh; negative when its faces point inwards."""
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _slab(outer: np.ndarray, inner: np.ndarray) -> Mesh:
    """A closed slab between two (R, C, 3) vertex grids: the outer and inner surfaces (bands 0
    and 1) joined by walls along their border (band 2), faces turned outwards."""
    rows, cols = outer.shape[:2]
    top, _ = _grid_faces(rows, cols, wrap=False)
    n = rows * cols
    # Walls along the border: each boundary edge a -> b of the top gets b, a, a' and b, a', b'.
    edges = {(int(a), int(b)) for face in top for a, b in zip(face, np.roll(face, -1))}
    border = [(a, b) for a, b in sorted(edges) if (b, a) not in edges]
    walls = np.array([(b, a, a + n) for a, b in border] + [(b, a + n, b + n) for a, b in border],
                     dtype=np.int64)
    verts = np.vstack([outer.reshape(-1, 3), inner.reshape(-1, 3)])
    faces = np.vstack([top, top[:, [0, 2, 1]] + n, walls])
    if _signed_volume(verts, faces) < 0:
        faces = faces[:, [0, 2, 1]]
    bands = np.concatenate([np.zeros(len(top), np.int64), np.ones(len(top), np.int64),
                            np.full(len(walls), 2)])
    return Mesh(verts, faces, bands)


def _merge(pieces: list[Mesh]) -> Mesh:
    """One mesh of several closed pieces."""
    offsets = np.cumsum([0] + [len(piece.verts) for piece in pieces[:-1]])
    return Mesh(np.vstack([piece.verts for piece in pieces]),
                np.vstack([piece.faces + offset for piece, offset in zip(pieces, offsets)]),
                np.concatenate([piece.bands for piece in pieces]))


def _shading_normals(mesh: Mesh, crease_deg: float = CREASE_DEG
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices split along creases, with their shading normals: (verts (V', 3), faces (F, 3),
    normals (V', 3)). A face corner's normal is the area-weighted mean of the normals of the
    faces around its vertex that share its band and meet it at less than ``crease_deg``."""
    verts, faces, bands = mesh
    area_normals = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]],
                            verts[faces[:, 2]] - verts[faces[:, 0]])
    unit = area_normals / np.maximum(np.linalg.norm(area_normals, axis=1, keepdims=True), 1e-12)
    corner_vertex = faces.ravel()
    corner_face = np.repeat(np.arange(len(faces)), 3)
    # Faces around each vertex, padded with -1: (V, K).
    order = np.argsort(corner_vertex, kind="stable")
    counts = np.bincount(corner_vertex, minlength=len(verts))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(len(order)) - np.repeat(starts, counts)
    around = np.full((len(verts), max(int(counts.max()), 1)), -1, np.int64)
    around[corner_vertex[order], rank] = corner_face[order]
    neighbours = around[corner_vertex]  # (3F, K)
    valid = neighbours >= 0
    safe = np.where(valid, neighbours, 0)
    joined = (valid & (bands[safe] == bands[corner_face][:, None])
              & (np.einsum("ckd,cd->ck", unit[safe], unit[corner_face])
                 > math.cos(math.radians(crease_deg))))
    normals = np.einsum("ck,ckd->cd", joined.astype(np.float64), area_normals[safe])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    keys = np.column_stack([corner_vertex, np.round(normals * 1e4).astype(np.int64)])
    _, first, new_index = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return verts[corner_vertex[first]], new_index.reshape(-1, 3), normals[first]


def _greenhouse_span(rings: np.ndarray, xs: np.ndarray, x_range: tuple[float, float],
                     min_height: float = 0.08) -> tuple[float, float] | None:
    """The part of x_range (front, back) where the greenhouse side (section points 3 -> 4) is
    at least ``min_height`` tall (to 1 cm), or None."""
    heights = rings[:, 4, 2] - rings[:, 3, 2]  # linear between the stations xs (descending)
    samples = np.arange(x_range[0], x_range[1], -0.01)
    ok = np.flatnonzero(np.interp(samples, xs[::-1], heights[::-1]) >= min_height)
    if ok.size < 2:
        return None
    return float(samples[ok[0]]), float(samples[ok[-1]])


def _shell_loft(shape: VehicleShape) -> _Loft:
    arch_gap = 0.04 + 0.05 * shape.wheel_radius
    arches = shape.axles if shape.cargo is None else shape.axles[:1]
    return _Loft(roofline=shape.roofline, width=shape.width, clearance=shape.clearance,
                 belt=shape.belt_height, arches=arches, wheel_radius=shape.wheel_radius,
                 arch_radius=shape.wheel_radius + arch_gap, section=_SECTIONS[shape.style])


def _cargo_loft(shape: VehicleShape) -> _Loft:
    front, back, floor = shape.cargo
    return _Loft(roofline=((front, shape.height), (back, shape.height)), width=shape.width,
                 clearance=floor, belt=shape.height, arches=(), wheel_radius=0.0,
                 arch_radius=0.0, section=_CARGO_SECTION)


def _cladding(shape: VehicleShape, loft: _Loft) -> Mesh:
    """Dark plastic flares around the wheel arches and strips along the sills (SUV, pickup):
    thin slabs on both body sides."""
    ra, band, radius = loft.arch_radius, 0.07, shape.wheel_radius
    low, sill_top = shape.clearance + 0.03, shape.clearance + 0.13
    angles = np.arccos(_ARCH_STEPS)  # the shell's arch sections: the inner edge follows it
    outlines = []  # (R, 2, 2) (x, z) rows of an inner and an outer edge
    for axle in loft.arches:
        edge = [[(axle + r * math.cos(a), radius + r * math.sin(a)) for r in (ra, ra + band)]
                for a in angles]
        outlines.append([[(axle + ra, low), (axle + ra + band, low)]] + edge
                        + [[(axle - ra, low), (axle - ra - band, low)]])
    front, back = loft.arches[0] - ra - band / 2, loft.arches[-1] + ra + band / 2
    outlines.append([[(front, low), (front, sill_top)], [(back, low), (back, sill_top)]])
    pieces = []
    for outline in outlines:
        xz = np.array(outline, dtype=np.float64)
        for side in (1.0, -1.0):
            def at(y: float) -> np.ndarray:
                return np.stack([xz[..., 0], np.full(xz.shape[:2], y), xz[..., 1]], axis=-1)
            pieces.append(_slab(at(side * (shape.width / 2 + 0.015)),
                                at(side * (shape.width / 2 - 0.02))))
    return _merge(pieces)


def vehicle_meshes(shape: VehicleShape) -> dict[str, Mesh]:
    """The vehicle's closed meshes by part name ("shell"; "screen", the windscreen and rear
    window; "glass", the side windows, when it has any; an SUV's or pickup's "cladding", a
    truck's "cargo"), in the body frame."""
    loft = _shell_loft(shape)
    rings = _loft_rings(loft)
    xs = rings[:, 0, 0]
    screens = [_pane(rings, xs, shape.windscreen, TOP_GLASS_T)]
    if shape.rear_window is not None:
        screens.append(_pane(rings, xs, shape.rear_window, TOP_GLASS_T))
    panes = []
    for x_range in shape.side_windows:
        span = _greenhouse_span(rings, xs, x_range)
        if span is None:
            continue
        right_t = (SECTION_POINTS - 1 - SIDE_GLASS_T[1], SECTION_POINTS - 1 - SIDE_GLASS_T[0])
        panes += [_pane(rings, xs, span, SIDE_GLASS_T), _pane(rings, xs, span, right_t)]
    meshes = {"shell": _loft_mesh(loft), "screen": _merge(screens)}
    if panes:
        meshes["glass"] = _merge(panes)
    if shape.style in ("suv", "pickup"):
        meshes["cladding"] = _cladding(shape, loft)
    if shape.cargo is not None:
        meshes["cargo"] = _loft_mesh(_cargo_loft(shape))
    return meshes


# -- lamps and small parts --------------------------------------------------------------------

def _front_point(loft: _Loft, y: float, front: bool) -> tuple[float, float]:
    """(x, yaw) of the shell's plan outline at lateral y on its front (or back) end; yaw turns
    +x (front) or -x (back) to the outline's outward normal."""
    radius = loft.section.nose_radius if front else loft.section.tail_radius
    corner = loft.width / 2 - radius
    depth = max(0.0, abs(y) - corner)
    angle = math.asin(min(depth / radius, 1.0)) * math.copysign(1.0, y)
    inset = radius - math.sqrt(max(radius**2 - depth**2, 0.0))
    if front:
        return loft.front - inset, angle
    return loft.back + inset, -angle


def _lamp_boxes(shape: VehicleShape) -> dict[str, list[tuple[tuple[float, float, float],
                                                           tuple[float, float, float], float]]]:
    """{"head": [...], "tail": [...]}: (centre, half sizes (depth, width, height), yaw) of the
    left and right lamps, in the body frame."""
    loft = _shell_loft(shape)
    rear_loft = _cargo_loft(shape) if shape.cargo is not None else loft
    nose_z, tail_z = shape.roofline[0][1], rear_loft.roofline[-1][1]
    if shape.style == "bus":
        head, tail = (0.62, 0.30, 0.16, 0.07), (1.05, 0.16, 0.08, 0.20)
    elif shape.style == "truck":
        head, tail = (0.82, 0.28, 0.17, 0.08), (shape.cargo[2] + 0.14, 0.20, 0.12, 0.07)
    else:
        head = (nose_z - 0.14, 0.26 + 0.05 * (shape.width - 1.8), 0.15, 0.05)
        tail = (tail_z - 0.16, 0.22, 0.14, 0.055)
    depth = 0.03
    boxes = {}
    for kind, (z, inset, half_w, half_h), end, front in (
            ("head", head, loft, True), ("tail", tail, rear_loft, False)):
        lamps = []
        for side in (1, -1):
            y = side * (shape.width / 2 - inset)
            x, yaw = _front_point(end, y, front)
            normal = np.array([math.cos(yaw), math.sin(yaw)]) * (1 if front else -1)
            cx, cy = np.array([x, y]) - normal * (depth - 0.01)
            lamps.append(((float(cx), float(cy), float(z)), (depth, half_w, half_h), yaw))
        boxes[kind] = lamps
    return boxes


def lamp_positions(shape: VehicleShape) -> dict[str, list[tuple[float, float, float]]]:
    """{"head": [left, right], "tail": [left, right]}: lamp centres (x, y, z) in the body frame,
    the positions of the ``headlight_l/_r`` and ``taillight_l/_r`` geoms."""
    return {kind: [centre for centre, _, _ in lamps]
            for kind, lamps in _lamp_boxes(shape).items()}


def _pitch_quat(pitch: float) -> list[float]:
    return [math.cos(pitch / 2), 0.0, math.sin(pitch / 2), 0.0]


def _add_mesh(spec: mujoco.MjSpec, name: str, mesh: Mesh) -> None:
    verts, faces, normals = _shading_normals(mesh)
    added = spec.add_mesh(name=name, uservert=verts.ravel().tolist(),
                          userface=faces.ravel().tolist(), usernormal=normals.ravel().tolist())
    # Exact inertia: MuJoCo rejects a mesh whose faces point inwards (negative volume).
    added.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_EXACT


def add_vehicle(spec: mujoco.MjSpec, body, prefix: str, shape: VehicleShape,
                paint: tuple[float, float, float]) -> None:
    """Build ``shape`` under ``body`` of ``spec`` with ``paint`` (rgb 0..1) bodywork.

    Adds mesh assets ``{prefix}shell``, ``{prefix}screen``, ``{prefix}glass`` (and
    ``{prefix}cladding``, ``{prefix}cargo``; see :func:`vehicle_meshes`) to ``spec``;
    every geom is named ``{prefix}{part}`` with contype = conaffinity = 0.
    """
    _check_style(shape.style)
    if len(paint) != 3 or not all(0.0 <= float(c) <= 1.0 for c in paint):
        raise ValueError(f"paint: expected an rgb triple in 0..1, got {paint!r}")
    body_rgba = rgba(paint)
    meshes = vehicle_meshes(shape)
    colours = {"shell": body_rgba, "glass": list(GLASS), "screen": list(SCREEN_GLASS),
               "cladding": list(BED),
               "cargo": rgba(shape.cargo_colour or paint)}
    for part, mesh in meshes.items():
        _add_mesh(spec, f"{prefix}{part}", mesh)
        _geom(body, f"{prefix}{part}", GEOM.mjGEOM_MESH, [], colours[part],
              meshname=f"{prefix}{part}")
    length, width, radius = shape.length, shape.width, shape.wheel_radius
    loft = _shell_loft(shape)
    rear_loft = _cargo_loft(shape) if shape.cargo is not None else loft

    # Wheels: tyres just inside the body side, rims on the outer faces; twin rear tyres.
    big = shape.style in ("bus", "truck")
    tyre_half = 0.14 if big else 0.11
    outer_y = width / 2 - 0.03 - tyre_half
    for index, axle in enumerate(shape.axles):
        front_tag = "f" if index == 0 else ("r" if index == len(shape.axles) - 1 else f"{index}")
        for side in (1, -1):
            tag = f"{front_tag}{'lr'[side < 0]}"
            centre = [axle, side * outer_y, radius]
            _geom(body, f"{prefix}tyre_{tag}", GEOM.mjGEOM_CYLINDER, [radius, tyre_half], TYRE,
                  pos=centre, quat=Y_AXIS_QUAT)
            _geom(body, f"{prefix}rim_{tag}", GEOM.mjGEOM_CYLINDER,
                  [radius * 0.62, tyre_half + 0.006], RIM, pos=centre, quat=Y_AXIS_QUAT)
            if shape.twin_rear and index == len(shape.axles) - 1:
                inner = [axle, side * (outer_y - 2 * tyre_half - 0.03), radius]
                _geom(body, f"{prefix}tyre_{tag}_inner", GEOM.mjGEOM_CYLINDER,
                      [radius, tyre_half], TYRE, pos=inner, quat=Y_AXIS_QUAT)

    # Lamps.
    for kind, name in (("head", "headlight"), ("tail", "taillight")):
        colour = HEADLIGHT if kind == "head" else TAILLIGHT
        for (centre, half, yaw), tag in zip(_lamp_boxes(shape)[kind], "lr"):
            _geom(body, f"{prefix}{name}_{tag}", GEOM.mjGEOM_BOX, half, colour,
                  pos=list(centre), quat=unit_yaw_quat(yaw).tolist())

    # Bumpers (their outer faces are the vehicle's length), number plates and the grille.
    bumper_z = {end: _underside(end_loft, x) + (0.10 if big else 0.07)
                for end, end_loft, x in (("f", loft, loft.front), ("r", rear_loft,
                                                                    rear_loft.back))}
    if shape.style == "truck":
        bumper_z["r"] = 0.62
    for end, sign, end_loft in (("f", 1, loft), ("r", -1, rear_loft)):
        radius_end = end_loft.section.nose_radius if sign > 0 else end_loft.section.tail_radius
        half_y = width / 2 - 0.45 * radius_end - (0.12 if shape.style == "truck" and sign < 0
                                                  else 0.0)
        half_x = 0.06
        x = sign * (length / 2 - 0.006 - half_x)
        _geom(body, f"{prefix}bumper_{end}", GEOM.mjGEOM_BOX, [half_x, half_y, 0.09 if big
                                                             else 0.075],
              TRIM, pos=[x, 0.0, bumper_z[end]])
        _geom(body, f"{prefix}plate_{end}", GEOM.mjGEOM_BOX, [0.005, 0.26, 0.056], PLATE,
              pos=[sign * (length / 2 - 0.005), 0.0, bumper_z[end]])
    head = _lamp_boxes(shape)["head"][0]
    grille_half_y = head[0][1] - head[1][1] - 0.05
    grille_z = {"bus": 0.48, "truck": 1.05}.get(shape.style, head[0][2] - 0.01)
    grille_half_z = {"bus": 0.06, "truck": 0.22}.get(shape.style, 0.07)
    _geom(body, f"{prefix}grille", GEOM.mjGEOM_BOX, [0.02, grille_half_y, grille_half_z], TRIM,
          pos=[loft.front - 0.012, 0.0, grille_z])

    # Side mirrors.
    if big:
        mirror_x = loft.front - 0.30
        mirror_z = shape.roofline[2][1] - 0.95
        for side, tag in ((1, "l"), (-1, "r")):
            y = side * (width / 2 + 0.20)
            _geom(body, f"{prefix}mirror_{tag}", GEOM.mjGEOM_BOX, [0.04, 0.08, 0.20], TRIM,
                  pos=[mirror_x, y, mirror_z])
            _geom(body, f"{prefix}mirror_arm_{tag}", GEOM.mjGEOM_CAPSULE, [0.02], TRIM,
                  fromto=[mirror_x - 0.05, side * (width / 2 - 0.02), mirror_z + 0.30,
                          mirror_x, y, mirror_z + 0.18])
    else:
        mirror_x = shape.windscreen[0] - 0.12
        for side, tag in ((1, "l"), (-1, "r")):
            _geom(body, f"{prefix}mirror_{tag}", GEOM.mjGEOM_BOX, [0.045, 0.085, 0.05], body_rgba,
                  pos=[mirror_x, side * (width / 2 + 0.055), shape.belt_height + 0.06])

    # Bus: doors on the kerb side and a destination sign over the windscreen.
    for index, (front, back) in enumerate(shape.doors):
        bottom = max(_underside(loft, front), _underside(loft, back)) + 0.04
        top = shape.height - 0.40
        _geom(body, f"{prefix}door{index}", GEOM.mjGEOM_BOX,
              [(front - back) / 2, 0.012, (top - bottom) / 2], GLASS,
              pos=[(front + back) / 2, -(width / 2 + 0.004), (top + bottom) / 2])
    if shape.style == "bus":
        (x0, z0), (x1, z1) = shape.roofline[0], shape.roofline[1]
        normal = np.array([z1 - z0, x0 - x1]) / math.hypot(z1 - z0, x0 - x1)
        z = shape.height - 0.36
        x = _x_at((x0, z0), (x1, z1), z)
        pos = np.array([x, z]) + 0.02 * normal
        _geom(body, f"{prefix}sign", GEOM.mjGEOM_BOX, [0.008, width * 0.3, 0.08], SIGN,
              pos=[pos[0], 0.0, pos[1]], quat=_pitch_quat(math.atan2(-normal[1], normal[0])))

    # Pickup: the load bed's dark floor inset in the top; truck: chassis frame under the box.
    if shape.bed is not None:
        front, back = shape.bed
        rail, crown = rear_loft.roofline[-2][1], loft.section.crown  # the bed's top, centre
        _geom(body, f"{prefix}bed", GEOM.mjGEOM_BOX,
              [(front - back) / 2, width / 2 - 0.09, crown / 2 + 0.004], BED,
              pos=[(front + back) / 2, 0.0, rail - crown / 2 + 0.001])
    if shape.cargo is not None:
        front, back, floor = shape.cargo
        front, back = front + 0.3, back + 0.25  # from under the cab to the rear bumper
        _geom(body, f"{prefix}frame", GEOM.mjGEOM_BOX, [(front - back) / 2, 0.45, 0.14], TRIM,
              pos=[(front + back) / 2, 0.0, floor - 0.14])
