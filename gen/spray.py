"""Tyre spray: where the water thrown up by moving vehicles is, as particles in the world.

:func:`spray_particles` is a pure function of the layout, the time and an explicit ``rng``;
:func:`rainbench.rain.weather.spray_opacity` draws the particles into an image with depth
occlusion. The spray's density at a rate is the weather's ``spray`` (docs/rain.md).
"""

from __future__ import annotations

import math

import numpy as np

from rainbench.mjcf import layout as L

PARTICLES = {"car": 160, "motorcycle": 60}
MIN_SPEED_M_S = 2.0
PLUME_LENGTH_S = 0.35  # plume length in metres per m/s of speed (10 m/s: 3.5 m)
PLUME_HEIGHT_M = 1.2  # the plume rises to this height at its end
FULL_SPEED_M_S = 12.0  # spray opacity grows linearly with speed up to this


def spray_particles(layout: L.Layout, t: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Spray behind every moving car and motorcycle of ``layout`` at time ``t``.

    Returns (points (N, 3) float64 world metres, weights (N,) float64 peak opacity of each
    particle at full spray density). Each vehicle throws a plume from its two rear wheel tracks,
    ``0.35 s x speed`` metres long, widening and rising to 1.2 m with distance behind the wheels;
    particles thin out towards the plume's end.
    """
    points, weights = [], []
    for unit in layout.units:
        count = PARTICLES.get(unit.kind)
        if count is None or unit.speed < MIN_SPEED_M_S:
            continue
        travelled = unit.speed * (t - unit.start_time)
        if travelled <= 0 or travelled >= unit.max_distance:
            continue
        x, y, yaw = L.unit_pose(unit, t)
        centre = np.array([x, y])
        heading = np.array([math.cos(yaw), math.sin(yaw)])
        side = np.array([-heading[1], heading[0]])
        length, width = unit.footprint
        plume = PLUME_LENGTH_S * unit.speed
        behind = plume * rng.random(count) ** 1.5  # denser near the wheels
        track = (width / 2 - 0.25) * rng.choice([-1.0, 1.0], count) if unit.kind == "car" else np.zeros(count)
        lateral = track + rng.normal(0.0, 0.12 + 0.25 * behind)
        height = np.abs(rng.normal(0.0, 0.25 + PLUME_HEIGHT_M * behind / max(plume, 1e-6) / 2.0, count))
        xy = centre[None] - heading[None] * (length / 2 + behind)[:, None] + side[None] * lateral[:, None]
        points.append(np.column_stack([xy, height]))
        weights.append(min(unit.speed / FULL_SPEED_M_S, 1.0) * (1.0 - behind / max(plume, 1e-6)) ** 0.5)
    if not points:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(points), np.concatenate(weights)
