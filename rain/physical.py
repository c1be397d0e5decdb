"""Physically based rain: falling drops drawn as streaks, extinction and airlight.

Formulas and sources (all listed in docs/rain-physics.md and docs/rain.md):

* Marshall-Palmer (1948) drop sizes: N(D) = N0 exp(-Lambda D), N0 = 8000 m^-3 mm^-1,
  Lambda = 4.1 R^-0.21 mm^-1 (R in mm/h, D diameter in mm).
* Terminal velocity, Atlas et al. (1973): v(D) = 9.65 - 10.3 exp(-0.6 D) m/s.
* Streak in the image (exposure T, focal length f px, depth z): length f v T / z, width f D / z,
  thin-lens defocus circle c = |z - z_f| f^2 / (z (z_f - f) N) / pitch.
* Extinction (Weber et al. 2015): beta = 0.312 R^0.67 km^-1; visibility V = 3.912 / beta;
  I = I0 exp(-beta d) + A (1 - exp(-beta d)).

Nesting: the candidate drops are a Poisson process with the Marshall-Palmer spectrum of the
largest rate R_max = 1000 mm/h. Each candidate carries a uniform u and is kept at rate R iff
``u <= exp(-(Lambda(R) - Lambda(R_max)) D)``. Since Lambda decreases with R, the kept set grows
with R (nested, drops unchanged), and by Poisson thinning the kept drops at every R are exactly a
Marshall-Palmer Poisson process for R. Each drop therefore has a threshold rate
``R_i = ((Lambda_max - ln(u) / D) / 4.1) ** (-1 / 0.21)``: present iff ``R_i <= R``.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from rainbench.rain._seeding import STREAM_AIR, child_generator
from rainbench.rain.config import RainConfig
from rainbench.store.rates import MAX_RATE_MM_H

MP_N0_PER_M3_MM = 8000.0
MP_LAMBDA_COEF = 4.1
MP_LAMBDA_EXP = 0.21
VELOCITY_MAX_M_S = 9.65
VELOCITY_COEF_M_S = 10.3
VELOCITY_RATE_PER_MM = 0.6
EXTINCTION_COEF_PER_KM = 0.312
EXTINCTION_EXP = 0.67
VISIBILITY_CONTRAST_LN = 3.912  # -ln(0.02): Koschmieder's 2 % contrast threshold

WEIGHT_UNITS = float(2**24)
"""Streak opacity quantum: per-pixel streak weights are integer numbers of 2^-24 steps."""

BLUR_LEVELS_PX = 0.5 * 2.0 ** (np.arange(11) / 2.0)
"""Defocus blur sigmas (px) of the blur layers: 0.5 * sqrt(2)^k, k = 0..10 (0.5 .. 16 px)."""

MIN_BLUR_SIGMA_PX = 0.35
"""Drops whose defocus sigma is below this are not blurred (the bilinear splat is ~0.5 px wide)."""


def _rates(rate_mm_h: float | np.ndarray) -> np.ndarray:
    """``rate_mm_h`` as float64 if every rate is finite and >= 0 mm/h; else a one-line ValueError
    (a negative rate gave NaN, silently)."""
    rate = np.asarray(rate_mm_h, dtype=np.float64)
    bad = ~(np.isfinite(rate) & (rate >= 0))
    if bad.any():
        got = f"{rate_mm_h!r}" if rate.ndim == 0 else f"{rate[bad].ravel()[0]!r} among {rate.size} rates"
        raise ValueError(f"rate_mm_h: expected finite rates >= 0 mm/h, got {got}")
    return rate


def marshall_palmer_slope(rate_mm_h: float | np.ndarray) -> float | np.ndarray:
    """Lambda(R) = 4.1 R^-0.21 in mm^-1 for a rate R in mm/h (inf at R = 0).

    Scalar in, float out; array in, float64 array of the same shape out.
    """
    rate = _rates(rate_mm_h)
    with np.errstate(divide="ignore"):
        slope = MP_LAMBDA_COEF * np.power(rate, -MP_LAMBDA_EXP)
    return float(slope) if slope.ndim == 0 else slope


def marshall_palmer_density(rate_mm_h: float, min_diameter_mm: float) -> float:
    """Drops per m^3 with diameter > D_min: (N0 / Lambda) exp(-Lambda D_min); 0 at rate 0."""
    if rate_mm_h <= 0:
        return 0.0
    slope = marshall_palmer_slope(rate_mm_h)
    return MP_N0_PER_M3_MM / slope * math.exp(-slope * min_diameter_mm)


def lens_drop_count(rate_mm_h: float, *, config: RainConfig, K: np.ndarray, height: int, width: int) -> int:
    """Drops on the camera's cover glass at a rate: the physical model's lens water count.

    The glass, ``lens_glass_distance_m`` (u) in front of the lens, faces forward and moves
    through the rain at ``lens_sweep_speed_m_s`` (v); a hood keeps the vertical fall off it.
    Drops of diameter >= ``lens_min_diameter_mm`` land on the part the camera sees, the
    pyramid's section ``A = u^2 (W / fx) (H / fy)``, at ``n(R) v A`` per second (n from
    Marshall-Palmer) and stay for the mean life of a lens slot, ``tau = (lens_life_min_s +
    lens_life_max_s) / 2``, so the glass holds on average
    ``N = round(lens_drop_fraction * n(R) * v * A * tau)`` drops (at 800x600, 90 degrees:
    193 at 10 mm/h, 508 at 100 mm/h). Non-decreasing in the rate; independent of the image's
    resolution for a given field of view.

    Args:
        rate_mm_h: rain rate in mm/h, >= 0.
        config: the rain configuration (its lens_* fields).
        K: (3, 3) intrinsics in pixels.
        height, width: image size in pixels.

    Returns:
        the drop count, an int >= 0 (0 at rate 0).
    """
    density_per_m3 = marshall_palmer_density(rate_mm_h, config.lens_min_diameter_mm)
    glass_area_m2 = config.lens_glass_distance_m**2 * (width / float(K[0, 0])) * (height / float(K[1, 1]))
    mean_life_s = 0.5 * (config.lens_life_min_s + config.lens_life_max_s)
    expected = config.lens_drop_fraction * density_per_m3 * config.lens_sweep_speed_m_s * glass_area_m2 * mean_life_s
    return int(math.floor(expected + 0.5))


def sample_marshall_palmer_diameters(rng: np.random.Generator, count: int, rate_mm_h: float, min_diameter_mm: float) -> np.ndarray:
    """Draw drop diameters from Marshall-Palmer truncated below at D_min.

    ``D = D_min - ln(U) / Lambda(R)``, U ~ Uniform(0, 1].

    Args:
        rng: the generator to draw from.
        count: number of drops.
        rate_mm_h: rain rate R > 0 in mm/h.
        min_diameter_mm: D_min in mm.

    Returns:
        (count,) float64 diameters in mm.
    """
    if rate_mm_h <= 0:
        raise ValueError(f"rate_mm_h must be > 0 to have drops, got {rate_mm_h!r}")
    uniform = 1.0 - rng.random(count)  # (0, 1]
    return min_diameter_mm - np.log(uniform) / marshall_palmer_slope(rate_mm_h)


def terminal_velocity(diameter_mm: float | np.ndarray) -> float | np.ndarray:
    """Atlas et al. (1973): v = 9.65 - 10.3 exp(-0.6 D) m/s (D in mm), floored at 0.

    Scalar in, float out; array in, float64 array of the same shape out.
    """
    velocity = np.maximum(VELOCITY_MAX_M_S - VELOCITY_COEF_M_S * np.exp(-VELOCITY_RATE_PER_MM * np.asarray(diameter_mm, dtype=np.float64)), 0.0)
    return float(velocity) if velocity.ndim == 0 else velocity


def extinction_coefficient(rate_mm_h: float | np.ndarray) -> float | np.ndarray:
    """Weber et al. (2015): beta = 0.312 R^0.67 in km^-1 for a rate R in mm/h (0 at R = 0).

    Scalar in, float out; array in, float64 array of the same shape out.
    """
    beta = EXTINCTION_COEF_PER_KM * np.power(_rates(rate_mm_h), EXTINCTION_EXP)
    return float(beta) if beta.ndim == 0 else beta


def visibility_km(rate_mm_h: float | np.ndarray) -> float | np.ndarray:
    """Meteorological visibility V = 3.912 / beta in km (inf at rate 0).

    Scalar in, float out; array in, float64 array of the same shape out."""
    beta = np.asarray(extinction_coefficient(rate_mm_h), dtype=np.float64)
    with np.errstate(divide="ignore"):
        visibility = np.where(beta == 0, np.inf, VISIBILITY_CONTRAST_LN / beta)
    return float(visibility) if visibility.ndim == 0 else visibility


def frustum_volume_m3(K: np.ndarray, height: int, width: int, z_near_m: float, z_far_m: float) -> float:
    """Volume in m^3 of the camera frustum (K (3, 3) intrinsics in pixels, image H x W) between
    two depths in metres.

    ``(1/3) (W / fx) (H / fy) (z_far^3 - z_near^3)``, equal to
    ``(4/3) tan(hfov/2) tan(vfov/2) (z_far^3 - z_near^3)`` for a centred principal point.
    """
    fx, fy = float(K[0, 0]), float(K[1, 1])
    return (width / fx) * (height / fy) * (z_far_m**3 - z_near_m**3) / 3.0


PITCH_REFERENCE_WIDTH_PX = 800
"""``RainConfig.pixel_pitch_um`` is the pitch of the image resized to this width."""


def pixel_pitch_m(config: RainConfig, width: int) -> float:
    """The pixel pitch of a ``width``-pixel image in metres: ``pixel_pitch_um`` is the pitch at
    800 px, and the same sensor behind the same lens has pixels 800 / width times that as the
    image grows, so the focal length ``fx * pitch`` stays that of the lens at any size."""
    return config.pixel_pitch_um * 1e-6 * PITCH_REFERENCE_WIDTH_PX / width


def defocus_diameter_px(depth_m: np.ndarray, *, focus_distance_m: float, focal_length_m: float, f_number: float, pixel_pitch_m: float) -> np.ndarray:
    """Thin-lens circle of confusion in pixels: |z - z_f| f^2 / (z (z_f - f) N) / pitch.

    Args:
        depth_m: (N,) depths z in metres.
        focus_distance_m: z_f in metres; focal_length_m: f in metres; f_number: N;
        pixel_pitch_m: sensor pixel pitch in metres.

    Returns:
        (N,) float64 blur-circle diameters in pixels.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    return np.abs(depth - focus_distance_m) * focal_length_m**2 / (depth * (focus_distance_m - focal_length_m) * f_number) / pixel_pitch_m


def streak_depth_range(config: RainConfig, K: np.ndarray, height: int, width: int) -> tuple[float, float]:
    """(z_near, z_far) in metres of the streak volume after the candidate bound.

    z_far is pulled in when the expected number of candidates at 1000 mm/h,
    ``n(1000, D_min) * frustum_volume``, would exceed ``max_streak_candidates``.
    """
    z_near, z_far = config.streak_z_near_m, config.streak_z_far_m
    density = marshall_palmer_density(MAX_RATE_MM_H, config.streak_min_diameter_mm)
    expected = density * frustum_volume_m3(K, height, width, z_near, z_far)
    if expected > config.max_streak_candidates:
        unit_volume = frustum_volume_m3(K, height, width, 0.0, 1.0)
        z_far = (z_near**3 + config.max_streak_candidates / (density * unit_volume)) ** (1.0 / 3.0)
    return z_near, z_far


@dataclasses.dataclass(frozen=True)
class AirDrops:
    """Falling drops in the streak volume; every array has shape (N,) and dtype float64.

    Attributes:
        x_px, y_px: image position of the drop at mid-exposure (continuous pixel units).
        z_m: depth along the optical axis in metres.
        diameter_mm: drop diameter in mm.
        threshold_rate_mm_h: the drop exists at every rate >= this (nesting).
        diameter_px: projected diameter f D / z in pixels.
        fall_px, drift_px: image displacement during the exposure, down (+y) and sideways (+x).
        streak_length_px: hypot(fall_px, drift_px) = f v T / (z cos(slant)).
        blur_sigma_px: defocus blur, circle-of-confusion diameter / 4 (std of a uniform disc).
    """

    x_px: np.ndarray
    y_px: np.ndarray
    z_m: np.ndarray
    diameter_mm: np.ndarray
    threshold_rate_mm_h: np.ndarray
    diameter_px: np.ndarray
    fall_px: np.ndarray
    drift_px: np.ndarray
    streak_length_px: np.ndarray
    blur_sigma_px: np.ndarray

    def __len__(self) -> int:
        return int(self.x_px.shape[0])

    def select(self, index: np.ndarray) -> AirDrops:
        """The drops at ``index`` (bool mask or int indices), in order."""
        return AirDrops(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))

    def at_rate(self, rate_mm_h: float) -> AirDrops:
        """The drops present at a rate: ``threshold_rate_mm_h <= rate``."""
        return self.select(self.threshold_rate_mm_h <= rate_mm_h)

    def as_array(self) -> np.ndarray:
        """(N, 10) float64 array of the fields in declaration order (for comparisons in tests)."""
        return np.stack([getattr(self, f.name) for f in dataclasses.fields(self)], axis=1)


def empty_air_drops() -> AirDrops:
    """An AirDrops with zero drops."""
    empty = np.zeros(0, dtype=np.float64)
    return AirDrops(*([empty] * len(dataclasses.fields(AirDrops))))


def sample_air_candidates(*, config: RainConfig, K: np.ndarray, height: int, width: int, seed_sequence: np.random.SeedSequence) -> AirDrops:
    """All candidate falling drops of a frame (the Marshall-Palmer process at 1000 mm/h).

    Count ~ Poisson(n(1000 mm/h, D_min) * frustum volume); per drop: mid-exposure image
    position uniform over the image, depth with density ~ z^2 on [z_near, z_far] (uniform in the
    frustum volume), diameter D_min - ln(U) / Lambda(1000), and the threshold rate of the thinning
    (module docstring). Uses ``child_generator(seed_sequence, STREAM_AIR)``; independent of any
    rate, so use :meth:`AirDrops.at_rate` for the drops of one rate.

    Args:
        config: streak volume and camera parameters.
        K: (3, 3) float64 intrinsics (fx, fy in pixels).
        height, width: image size in pixels.
        seed_sequence: the frame's SeedSequence (not mutated).

    Returns:
        AirDrops with all candidates.
    """
    z_near, z_far = streak_depth_range(config, K, height, width)
    slope_max = marshall_palmer_slope(MAX_RATE_MM_H)
    expected = marshall_palmer_density(MAX_RATE_MM_H, config.streak_min_diameter_mm) * frustum_volume_m3(K, height, width, z_near, z_far)
    rng = child_generator(seed_sequence, STREAM_AIR)
    count = int(rng.poisson(expected))
    if count == 0:
        return empty_air_drops()
    uniforms = rng.random((count, 5))
    x_px = uniforms[:, 0] * width
    y_px = uniforms[:, 1] * height
    z_m = np.cbrt(z_near**3 + uniforms[:, 2] * (z_far**3 - z_near**3))
    diameter_mm = config.streak_min_diameter_mm - np.log1p(-uniforms[:, 3]) / slope_max
    keep_uniform = 1.0 - uniforms[:, 4]  # (0, 1]
    slope_threshold = slope_max - np.log(keep_uniform) / diameter_mm
    # u = 1 gives exactly R_max; the clip only removes rounding above it
    threshold = np.minimum(np.power(slope_threshold / MP_LAMBDA_COEF, -1.0 / MP_LAMBDA_EXP), MAX_RATE_MM_H)

    fx, fy = float(K[0, 0]), float(K[1, 1])
    velocity = terminal_velocity(diameter_mm)
    slant = math.radians(config.wind_slant_deg)
    fall_px = fy * velocity * config.exposure_s / z_m
    drift_px = fx * velocity * math.tan(slant) * config.exposure_s / z_m
    pitch_m = pixel_pitch_m(config, width)
    focal_length_m = 0.5 * (fx + fy) * pitch_m
    if config.focus_distance_m <= focal_length_m:
        raise ValueError(f"RainConfig.focus_distance_m must exceed the focal length {focal_length_m:.4g} m (fx * pixel pitch), got {config.focus_distance_m!r}")
    defocus = defocus_diameter_px(z_m, focus_distance_m=config.focus_distance_m, focal_length_m=focal_length_m, f_number=config.f_number, pixel_pitch_m=pitch_m)
    return AirDrops(
        x_px=x_px,
        y_px=y_px,
        z_m=z_m,
        diameter_mm=diameter_mm,
        threshold_rate_mm_h=threshold,
        diameter_px=fx * diameter_mm * 1e-3 / z_m,
        fall_px=fall_px,
        drift_px=drift_px,
        streak_length_px=np.hypot(fall_px, drift_px),
        blur_sigma_px=defocus / 4.0,
    )


@dataclasses.dataclass(frozen=True)
class StreakRaster:
    """Streak footprints after occlusion; arrays of shape (E,) unless noted.

    Attributes:
        pixel: int64 flat pixel index.
        drop: int64 index of the drop in the AirDrops that was rasterised.
        weight_units: float64 integer-valued opacity in 2^-24 steps (exact sums).
        layer: int64 blur layer: 0 = no blur, k >= 1 = Gaussian sigma BLUR_LEVELS_PX[k - 1].
        visible: (N,) bool per drop: at least one pixel drawn (not fully occluded / off-image).
    """

    pixel: np.ndarray
    drop: np.ndarray
    weight_units: np.ndarray
    layer: np.ndarray
    visible: np.ndarray


def blur_layer(blur_sigma_px: np.ndarray) -> np.ndarray:
    """Blur layer of each drop.

    Args:
        blur_sigma_px: (N,) float64 defocus sigma in pixels.

    Returns:
        (N,) int64: 0 below MIN_BLUR_SIGMA_PX (no blur), else 1 + the index of the nearest level
        of BLUR_LEVELS_PX in log scale.
    """
    sigma = np.asarray(blur_sigma_px, dtype=np.float64)
    with np.errstate(divide="ignore"):
        level = np.clip(np.rint(2.0 * np.log2(np.maximum(sigma, 1e-12) / BLUR_LEVELS_PX[0])), 0, len(BLUR_LEVELS_PX) - 1).astype(np.int64)
    return np.where(sigma < MIN_BLUR_SIGMA_PX, 0, level + 1)


def _cell_and_fraction(coordinate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(int64 pixel index, weight of the next pixel) of pixel-edge coordinates for a linear
    splat between the pixel centres on either side: pixel i's centre is at i + 0.5."""
    shifted = coordinate - 0.5
    cell = np.floor(shifted)
    return cell.astype(np.int64), shifted - cell


def _streak_geometry(drops: AirDrops) -> tuple[np.ndarray, ...]:
    """Per drop: (extent px, dir_x, dir_y, vertical_major, n_along, n_across) of its streak."""
    length = drops.streak_length_px
    extent = length + drops.diameter_px
    safe_length = np.where(length > 0, length, 1.0)
    dir_x = np.where(length > 0, drops.drift_px / safe_length, 0.0)
    dir_y = np.where(length > 0, drops.fall_px / safe_length, 1.0)
    vertical_major = np.abs(dir_y) >= np.abs(dir_x)
    major = np.maximum(np.abs(dir_x), np.abs(dir_y))
    n_along = np.maximum(np.ceil(extent * major), 1.0).astype(np.int64)
    n_across = np.maximum(np.ceil(drops.diameter_px), 1.0).astype(np.int64)
    return extent, dir_x, dir_y, vertical_major, n_along, n_across


def streak_sample_counts(drops: AirDrops) -> np.ndarray:
    """(N,) int64: the samples :func:`rasterize_streaks` takes of each drop (each splats into
    at most 4 pixels), to bound its work and memory before drawing: about 370 bytes a sample."""
    _, _, _, _, n_along, n_across = _streak_geometry(drops)
    return n_along * n_across


def rasterize_streaks(drops: AirDrops, depth: np.ndarray) -> StreakRaster:
    """Streak footprints with occlusion by the depth render.

    A drop sweeps a segment of length ``L + d`` (streak length plus its own diameter, px)
    centred on its mid-exposure position, along (drift, fall). It is sampled at most 1 px apart
    along the streak's major image axis and, for d > 1 px, on ``ceil(d)`` parallel lines across
    it weighted by the chord of the drop disc (how long a pixel stays behind the drop). Each
    sample is split bilinearly between the 2 x 2 pixels whose centres surround it (anti-aliased
    across the streak and even along it: samples are under 1 px apart, and whole samples into
    one row gave some rows twice the opacity of their neighbours). The total opacity of a drop is its disc area ``pi d^2 / 4`` px^2 (area x time
    conservation: a pixel's opacity is the fraction of the exposure it is covered, about
    d / (L + d) for d >= 1 px). A splat into pixel p is dropped where ``depth[p] < z`` (the drop
    is behind the surface).

    Entries are ordered by drop (all entries of drop i before those of drop i + 1), and each
    drop's entries depend only on that drop and the depth map.

    Args:
        drops: the drops to draw (their blur_sigma_px selects the layer).
        depth: (H, W) float32/float64 depth in metres along the optical axis, +inf for sky.

    Returns:
        StreakRaster of all non-zero splats.
    """
    height, width = depth.shape
    count = len(drops)
    if count == 0:
        empty = np.zeros(0, dtype=np.int64)
        return StreakRaster(empty, empty, np.zeros(0, dtype=np.float64), empty, np.zeros(0, dtype=bool))
    diameter = drops.diameter_px
    extent, dir_x, dir_y, _, n_along, n_across = _streak_geometry(drops)
    per_drop = n_along * n_across
    total = int(per_drop.sum())
    drop = np.repeat(np.arange(count, dtype=np.int64), per_drop)
    local = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(per_drop) - per_drop, per_drop)
    # sum of the chords over one drop's across lines, in closed form per drop
    chord_sum = np.ones(count, dtype=np.float64)
    for lines in np.unique(n_across[n_across > 1]):
        offsets = (np.arange(lines) + 0.5) / lines - 0.5
        chord_sum[n_across == lines] = np.sqrt(np.maximum(1.0 - 4.0 * offsets * offsets, 0.0)).sum()
    area = 0.25 * np.pi * diameter * diameter
    weight = (area / (chord_sum * n_along))[drop]
    step_x = (extent * dir_x / n_along)[drop]  # along-streak step between samples, px
    step_y = (extent * dir_y / n_along)[drop]
    # first sample at t = 1/(2 n) - 1/2 of the extent from the centre
    start_x = (drops.x_px - 0.5 * extent * dir_x)[drop] + 0.5 * step_x
    start_y = (drops.y_px - 0.5 * extent * dir_y)[drop] + 0.5 * step_y
    if (n_across > 1).any():
        along_count = n_along[drop]
        k_along = local % along_count
        s_across = (local // along_count + 0.5) / n_across[drop] - 0.5  # in (-1/2, 1/2)
        weight = weight * np.sqrt(np.maximum(1.0 - 4.0 * s_across * s_across, 0.0))
        offset = s_across * diameter[drop]
        start_x = start_x - offset * dir_y[drop]
        start_y = start_y + offset * dir_x[drop]
    else:
        k_along = local
    sample_x = start_x + k_along * step_x
    sample_y = start_y + k_along * step_y
    # bilinear splat: each sample shares its weight between the 2 x 2 pixels around it (samples
    # are under 1 px apart along the streak: whole samples into one row across the streak gave
    # a row in about three streaks twice the opacity of its neighbours)
    x_floor, x_frac = _cell_and_fraction(sample_x)
    y_floor, y_frac = _cell_and_fraction(sample_y)
    taps = 4
    base = weight * WEIGHT_UNITS
    units = np.empty((total, taps), dtype=np.float64)
    np.multiply(base * (1.0 - x_frac), 1.0 - y_frac, out=units[:, 0])
    np.multiply(base * x_frac, 1.0 - y_frac, out=units[:, 1])
    np.multiply(base * (1.0 - x_frac), y_frac, out=units[:, 2])
    np.multiply(base * x_frac, y_frac, out=units[:, 3])
    np.rint(units, out=units)
    units = units.reshape(-1)
    px = np.empty((total, taps), dtype=np.int64)
    px[:, 0::2] = x_floor[:, None]
    px[:, 1::2] = x_floor[:, None] + 1
    px = px.reshape(-1)
    py = np.empty((total, taps), dtype=np.int64)
    py[:, :2] = y_floor[:, None]
    py[:, 2:] = y_floor[:, None] + 1
    py = py.reshape(-1)
    entry_drop = np.repeat(drop, taps)
    inside = (px >= 0) & (px < width) & (py >= 0) & (py < height)
    flat = np.clip(py, 0, height - 1) * width + np.clip(px, 0, width - 1)
    in_front = depth.reshape(-1)[flat] >= drops.z_m[entry_drop]
    keep = inside & in_front & (units > 0)
    flat = flat[keep]
    entry_drop = entry_drop[keep]
    units = units[keep]
    visible = np.zeros(count, dtype=bool)
    visible[entry_drop] = True
    return StreakRaster(flat, entry_drop, units, blur_layer(drops.blur_sigma_px)[entry_drop], visible)


def ray_length_m(depth: np.ndarray, K: np.ndarray, sky_distance_m: float) -> np.ndarray:
    """Path length through the air for each pixel.

    Args:
        depth: (H, W) depth in metres along the optical axis, +inf for sky.
        K: (3, 3) intrinsics.
        sky_distance_m: path assigned to sky pixels.

    Returns:
        (H, W) float32 metres: ``depth * sqrt(1 + ((u + .5 - cx)/fx)^2 + ((v + .5 - cy)/fy)^2)``,
        ``sky_distance_m`` where depth is +inf.
    """
    height, width = depth.shape
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    ray_x = ((np.arange(width, dtype=np.float64) + 0.5 - cx) / fx) ** 2
    ray_y = ((np.arange(height, dtype=np.float64) + 0.5 - cy) / fy) ** 2
    norm = np.sqrt(1.0 + ray_y[:, None] + ray_x[None, :]).astype(np.float32)
    length = depth.astype(np.float32) * norm  # +inf stays +inf
    length[np.isinf(length)] = np.float32(sky_distance_m)
    return length


def estimate_airlight(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Airlight colour A: mean colour of the sky (depth +inf), else of the farthest 1 % of pixels.

    Args:
        rgb: (H, W, 3) uint8.
        depth: (H, W) metres, +inf for sky.

    Returns:
        (3,) float64 RGB in 0..255.
    """
    sky = ~np.isfinite(depth)
    if not sky.any():
        sky = depth >= np.quantile(depth, 0.99)
    return np.asarray(cv2.mean(rgb, mask=sky.astype(np.uint8))[:3], dtype=np.float64)
