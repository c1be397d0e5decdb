"""Rendering rain into a clean frame: ``render_rain`` (one rate) and ``render_rain_sweep`` (many).

Both are pure functions of (rgb, depth, rate, config, K, seed_sequence); the rate never enters
the seed, so the rain of a higher rate contains every drop of a lower one (see docs/rain.md,
"Nesting"). ``render_rain(..., r)`` equals ``render_rain_sweep(..., rates)[rates.index(r)]``
byte for byte for any rate set: per-pixel drop sums are exact integers, so adding drops rate by
rate gives the same numbers as adding them all at once.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numpy as np

from rainbench.rain import lens as lens_mod
from rainbench.rain import physical as phys
from rainbench.rain._seeding import check_seed_sequence
from rainbench.rain.config import RAIN_MODELS, RainConfig
from rainbench.rain.rates import MAX_RATE_MM_H


@dataclasses.dataclass(frozen=True)
class RainFrame:
    """One rainy image.

    Attributes:
        rgb: (H, W, 3) uint8, the rainy image.
        coverage: (H, W) float32 in [0, 1], per-pixel opacity of lens drops and streaks
            (0 where no drop). For the physical model it does not include the extinction.
        drop_count: drops drawn. jeon2022: the eq. 5 count scaled by area. physical: streaks with
            at least one visible pixel plus lens drops drawn.
    """

    rgb: np.ndarray
    coverage: np.ndarray
    drop_count: int


@dataclasses.dataclass(frozen=True)
class Drops:
    """The drops of one frame at one rate.

    Attributes:
        lens: lens drops (jeon2022; physical with ``lens_drops``), a prefix of the frame's sequence.
        air: falling drops drawn as streaks (physical), the candidates with threshold <= rate.
    """

    lens: lens_mod.LensDrops
    air: phys.AirDrops

    def __len__(self) -> int:
        return len(self.lens) + len(self.air)


def _check_rate(rate_mm_h: object) -> float:
    if isinstance(rate_mm_h, bool) or not isinstance(rate_mm_h, (int, float, np.integer, np.floating)):
        raise TypeError(f"rate_mm_h must be a number in mm/h, got {type(rate_mm_h).__name__}")
    rate = float(rate_mm_h)
    if not math.isfinite(rate) or rate < 0 or rate > MAX_RATE_MM_H:
        raise ValueError(f"rate_mm_h must be in [0, {MAX_RATE_MM_H:g}] mm/h, got {rate_mm_h!r}")
    return rate + 0.0


def _check_config(config: object) -> RainConfig:
    if not isinstance(config, RainConfig):
        raise TypeError(f"config must be a RainConfig, got {type(config).__name__}")
    return config


def _check_shape(shape: object) -> tuple[int, int]:
    if not isinstance(shape, (tuple, list)) or len(shape) < 2 or not all(isinstance(s, (int, np.integer)) and s > 0 for s in shape[:2]):
        raise ValueError(f"shape must be (H, W) or (H, W, 3) with positive ints, got {shape!r}")
    return int(shape[0]), int(shape[1])


def _check_K(K: object, required: bool) -> np.ndarray | None:
    if K is None:
        if required:
            raise ValueError("K must be a (3, 3) pinhole intrinsics array for the physical model, got None")
        return None
    matrix = np.asarray(K, dtype=np.float64)
    if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
        raise ValueError(f"K must be a finite (3, 3) intrinsics array, got shape {matrix.shape}")
    if matrix[0, 0] <= 0 or matrix[1, 1] <= 0:
        raise ValueError(f"K must have positive focal lengths fx = K[0, 0] and fy = K[1, 1] in pixels, got fx {matrix[0, 0]} and fy {matrix[1, 1]}")
    return matrix


def _check_rgb(rgb: object) -> np.ndarray:
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        got = f"{type(rgb).__name__} {getattr(rgb, 'shape', '')} {getattr(rgb, 'dtype', '')}".strip()
        raise ValueError(f"rgb must be an (H, W, 3) uint8 array, got {got}")
    return np.ascontiguousarray(rgb)


def _check_depth(depth: object, height: int, width: int, required: bool) -> np.ndarray | None:
    if depth is None:
        if required:
            raise ValueError(f"depth must be an ({height}, {width}) float array in metres for the physical model, got None")
        return None
    if not isinstance(depth, np.ndarray) or depth.shape != (height, width) or not np.issubdtype(depth.dtype, np.floating):
        got = f"{type(depth).__name__} {getattr(depth, 'shape', '')} {getattr(depth, 'dtype', '')}".strip()
        raise ValueError(f"depth must be an ({height}, {width}) float array in metres, got {got}")
    if np.isnan(depth).any() or (depth < 0).any():
        raise ValueError("depth must be >= 0 metres (+inf for sky), got NaN or negative values")
    return np.ascontiguousarray(depth)


def _lens_count(rate: float, config: RainConfig, height: int, width: int) -> int:
    count = lens_mod.jeon2022_drop_count(rate, height, width)
    if config.model == "jeon2022":
        return count
    if not config.lens_drops:
        return 0
    return int(math.floor(count * config.lens_drop_fraction + 0.5))


def sample_drops(rate_mm_h: float, *, config: RainConfig, K: np.ndarray | None, shape: tuple[int, ...], seed_sequence: np.random.SeedSequence) -> Drops:
    """The drops that :func:`render_rain` draws for one frame at one rate.

    Args:
        rate_mm_h: rain rate in mm/h, in [0, 1000].
        config: the rain configuration.
        K: (3, 3) float64 intrinsics (needed by the physical model; may be None for jeon2022).
        shape: (H, W) or (H, W, 3) image size in pixels.
        seed_sequence: the frame's ``np.random.SeedSequence`` (not mutated).

    Returns:
        Drops. jeon2022: ``lens`` = the first N(rate) drops of the frame's sequence, ``air``
        empty. physical: ``air`` = the candidates present at the rate (before occlusion), ``lens``
        as jeon2022 scaled by ``lens_drop_fraction`` if ``lens_drops`` else empty.
    """
    config = _check_config(config)
    rate = _check_rate(rate_mm_h)
    height, width = _check_shape(shape)
    check_seed_sequence(seed_sequence)
    matrix = _check_K(K, required=config.model == "physical")
    lens = lens_mod.sample_lens_drops(_lens_count(rate, config, height, width), config=config, height=height, width=width, seed_sequence=seed_sequence)
    if config.model == "jeon2022" or rate == 0:
        return Drops(lens=lens, air=phys.empty_air_drops())
    candidates = phys.sample_air_candidates(config=config, K=matrix, height=height, width=width, seed_sequence=seed_sequence)
    return Drops(lens=lens, air=candidates.at_rate(rate))


def render_rain(
    rgb: np.ndarray,
    depth: np.ndarray | None,
    rate_mm_h: float,
    *,
    config: RainConfig,
    K: np.ndarray | None,
    seed_sequence: np.random.SeedSequence,
) -> RainFrame:
    """Render rain at one rate into a clean frame.

    Args:
        rgb: (H, W, 3) uint8 clean render.
        depth: (H, W) float32 depth in metres along the optical axis, +inf for sky (physical
            model; may be None for jeon2022, which does not use it).
        rate_mm_h: rain rate in mm/h, in [0, 1000]. Rate 0 returns a copy of ``rgb``.
        config: which model and its parameters.
        K: (3, 3) float64 pinhole intrinsics, fx, fy, cx, cy in pixels (physical model; may be
            None for jeon2022).
        seed_sequence: ``np.random.SeedSequence`` of the frame, e.g.
            ``np.random.SeedSequence([rain_seed, scene_seed, frame])``; must not include the rate.

    Returns:
        RainFrame (new arrays; the inputs are not modified).
    """
    return render_rain_sweep(rgb, depth, (rate_mm_h,), config=config, K=K, seed_sequence=seed_sequence)[0]


def render_rain_sweep(
    rgb: np.ndarray,
    depth: np.ndarray | None,
    rates: Sequence[float],
    *,
    config: RainConfig,
    K: np.ndarray | None,
    seed_sequence: np.random.SeedSequence,
) -> list[RainFrame]:
    """Render one frame at several rates, sharing the work that does not depend on the rate.

    ``render_rain_sweep(rgb, depth, rates, ...)[i]`` equals ``render_rain(rgb, depth,
    rates[i], ...)`` byte for byte (rgb, coverage and drop_count).

    Args:
        rgb, depth, config, K, seed_sequence: as for :func:`render_rain`.
        rates: rain rates in mm/h, each in [0, 1000], any order, repeats allowed.

    Returns:
        list of RainFrame, one per entry of ``rates``, in the same order.
    """
    config = _check_config(config)
    check_seed_sequence(seed_sequence)
    rgb = _check_rgb(rgb)
    height, width = rgb.shape[:2]
    physical = config.model == "physical"
    matrix = _check_K(K, required=physical)
    depth = _check_depth(depth, height, width, required=physical)
    if isinstance(rates, (str, bytes)) or not isinstance(rates, Sequence) and not isinstance(rates, np.ndarray):
        raise TypeError(f"rates must be a sequence of numbers in mm/h, got {type(rates).__name__}")
    checked = [_check_rate(rate) for rate in rates]
    if not checked:
        return []
    ascending = sorted(set(checked))
    if physical:
        frames = _physical_sweep(rgb, depth, ascending, config, matrix, seed_sequence)
    else:
        frames = _jeon_sweep(rgb, ascending, config, seed_sequence)
    by_rate = dict(zip(ascending, frames))
    first_use: set[float] = set()
    out = []
    for rate in checked:
        frame = by_rate[rate]
        if rate in first_use:  # repeated rate: hand out independent arrays
            frame = RainFrame(frame.rgb.copy(), frame.coverage.copy(), frame.drop_count)
        first_use.add(rate)
        out.append(frame)
    return out


def _clean_frame(rgb: np.ndarray) -> RainFrame:
    return RainFrame(rgb.copy(), np.zeros(rgb.shape[:2], dtype=np.float32), 0)


class _LensAccumulator:
    """Lens drops of one frame for a sweep: rasterised once for the largest count."""

    def __init__(self, max_count: int, config: RainConfig, height: int, width: int, seed_sequence: np.random.SeedSequence) -> None:
        drops = lens_mod.sample_lens_drops(max_count, config=config, height=height, width=width, seed_sequence=seed_sequence)
        self.raster = lens_mod.rasterize_lens_drops(drops, config=config, height=height, width=width)
        self.pixels, self.inverse = lens_mod.compress_pixels(self.raster.pixel, height * width)
        self.config = config

    def sums(self, view: np.ndarray, low: int, high: int) -> tuple[np.ndarray, np.ndarray]:
        """Exact sums over drops ``low <= index < high`` with colours seen in ``view``."""
        alpha, alpha_color, _ = self.segment(view, low, high)
        return alpha, alpha_color

    def segment(self, view: np.ndarray, low: int, high: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact sums over drops ``low <= index < high`` and the compressed pixels they touch."""
        entries = slice(*np.searchsorted(self.raster.drop, [low, high]))  # entries are ordered by drop
        inverse = self.inverse[entries]
        colors = lens_mod.lens_colors(self.raster, view, entries)
        alpha, alpha_color = lens_mod.accumulate_lens(inverse, self.raster.alpha_units[entries], colors, self.pixels.shape[0])
        touched = np.zeros(self.pixels.shape[0], dtype=bool)
        touched[inverse] = True
        return alpha, alpha_color, np.flatnonzero(touched)


def _jeon_sweep(rgb: np.ndarray, ascending: list[float], config: RainConfig, seed_sequence: np.random.SeedSequence) -> list[RainFrame]:
    height, width = rgb.shape[:2]
    counts = [lens_mod.jeon2022_drop_count(rate, height, width) for rate in ascending]
    if max(counts) == 0:
        return [_clean_frame(rgb) for _ in ascending]
    accumulator = _LensAccumulator(max(counts), config, height, width, seed_sequence)
    view = lens_mod.lens_view(rgb, config)
    n_unique = accumulator.pixels.shape[0]
    sums = lens_mod.LensSums(accumulator.pixels, np.zeros(n_unique, dtype=np.float64), np.zeros((n_unique, 3), dtype=np.float64))
    image = rgb.copy()
    coverage = np.zeros((height, width), dtype=np.float32)
    drawn = 0
    frames = []
    for count in counts:
        if count == 0:
            frames.append(_clean_frame(rgb))
            continue
        if count > drawn:
            segment_alpha, segment_color, touched = accumulator.segment(view, drawn, count)
            sums.alpha += segment_alpha  # integer-valued float64: exact in any order
            sums.alpha_color += segment_color
            # only pixels under the new drops change; their values depend only on their own sums
            lens_mod.update_lens(image, coverage, rgb, sums, touched)
            drawn = count
        frames.append(RainFrame(image.copy(), coverage.copy(), count))
    return frames


def _physical_sweep(
    rgb: np.ndarray, depth: np.ndarray, ascending: list[float], config: RainConfig, K: np.ndarray, seed_sequence: np.random.SeedSequence
) -> list[RainFrame]:
    height, width = rgb.shape[:2]
    top_rate = ascending[-1]
    if top_rate == 0:
        return [_clean_frame(rgb) for _ in ascending]

    # falling drops: candidates are rate independent; draw those present at the top rate once,
    # ordered by threshold rate so that each rate adds a contiguous run of raster entries
    candidates = phys.sample_air_candidates(config=config, K=K, height=height, width=width, seed_sequence=seed_sequence)
    air = candidates.at_rate(top_rate)
    air = air.select(np.argsort(air.threshold_rate_mm_h, kind="stable"))
    raster = phys.rasterize_streaks(air, depth)
    element_threshold = air.threshold_rate_mm_h[raster.drop]  # ascending
    streaks = _StreakAccumulator(raster, height, width)

    # extinction and airlight, channel-planar float32 for fast per-rate blending
    path_m = phys.ray_length_m(depth, K, config.sky_distance_m)
    airlight = np.asarray(config.airlight_rgb, dtype=np.float64) if config.airlight_rgb is not None else phys.estimate_airlight(rgb, depth)
    drop_radiance = np.asarray(cv2.mean(rgb)[:3], dtype=np.float64)  # mean environment radiance
    scene_minus_air = [rgb[..., channel].astype(np.float32) - np.float32(airlight[channel]) for channel in range(3)]
    radiance_minus_air = [float(drop_radiance[channel] - airlight[channel]) for channel in range(3)]

    lens_counts = [_lens_count(rate, config, height, width) for rate in ascending]
    lens_accumulator = _LensAccumulator(max(lens_counts), config, height, width, seed_sequence) if max(lens_counts) > 0 else None

    frames = []
    drawn = 0
    for rate, lens_count in zip(ascending, lens_counts):
        if rate == 0:
            frames.append(_clean_frame(rgb))
            continue
        upto = int(np.searchsorted(element_threshold, rate, side="right"))
        streaks.add(drawn, upto)
        drawn = upto
        streak_opacity = streaks.opacity()

        # I' = A + (I - A) T (1 - E) + (S - A) E: extinction/airlight, then streaks over it
        beta_per_m = phys.extinction_coefficient(rate) * 1e-3
        gain = cv2.exp(path_m * np.float32(-beta_per_m))
        gain = cv2.multiply(gain, np.float32(1.0) - streak_opacity)
        channels = []
        for channel in range(3):
            plane = cv2.multiply(scene_minus_air[channel], gain)
            plane = cv2.scaleAdd(streak_opacity, radiance_minus_air[channel], plane)
            channels.append(cv2.convertScaleAbs(plane, alpha=1.0, beta=float(airlight[channel])))
        rainy = cv2.merge(channels)
        coverage = streak_opacity
        drop_count = int(np.count_nonzero(raster.visible & (air.threshold_rate_mm_h <= rate)))

        if lens_accumulator is not None and lens_count > 0:
            view = lens_mod.lens_view(rainy, config)
            alpha, alpha_color = lens_accumulator.sums(view, 0, lens_count)
            rainy, lens_coverage = lens_mod.apply_lens(rainy, lens_mod.LensSums(lens_accumulator.pixels, alpha, alpha_color))
            coverage = (1.0 - (1.0 - coverage) * (1.0 - lens_coverage)).astype(np.float32)
            drop_count += lens_count
        frames.append(RainFrame(rainy, coverage, drop_count))
    return frames


class _StreakAccumulator:
    """Exact per-pixel streak sums, grown run by run of raster entries.

    Sums are integer-valued float64 (exact in any order). The unblurred layer is kept as a
    float32 image updated only where a run touched it, which equals recomputing it from the sums.
    Blurred layers (defocus) are re-blurred from their sums at every rate.
    """

    def __init__(self, raster: phys.StreakRaster, height: int, width: int) -> None:
        self.height, self.width = height, width
        self.raster = raster
        self.pixels, inverse = lens_mod.compress_pixels(raster.pixel, height * width)
        n_unique = self.pixels.shape[0]
        self.layers = np.flatnonzero(np.bincount(raster.layer, minlength=len(phys.BLUR_LEVELS_PX) + 1))
        slot = np.zeros(len(phys.BLUR_LEVELS_PX) + 1, dtype=np.int64)
        slot[self.layers] = np.arange(self.layers.shape[0])
        self.keys = slot[raster.layer] * n_unique + inverse
        self.sums = np.zeros((self.layers.shape[0], n_unique), dtype=np.float64)
        self.sharp = np.zeros(height * width, dtype=np.float32)

    def add(self, low: int, high: int) -> None:
        """Add raster entries ``low:high``."""
        if high <= low:
            return
        keys = self.keys[low:high]
        self.sums += np.bincount(keys, self.raster.weight_units[low:high], minlength=self.sums.size).reshape(self.sums.shape)
        if self.layers[0] == 0:
            n_unique = self.pixels.shape[0]
            sharp_keys = keys[keys < n_unique]
            touched = np.zeros(n_unique, dtype=bool)
            touched[sharp_keys] = True
            index = np.flatnonzero(touched)
            self.sharp[self.pixels[index]] = (self.sums[0, index] * (1.0 / phys.WEIGHT_UNITS)).astype(np.float32)

    def opacity(self) -> np.ndarray:
        """(H, W) float32 streak opacity in [0, 1]: sharp layer plus blurred layers, clipped."""
        opacity = self.sharp.copy()
        for row, layer in enumerate(self.layers):
            if layer == 0 or not self.sums[row].any():
                continue
            buffer = np.zeros(self.height * self.width, dtype=np.float32)
            buffer[self.pixels] = (self.sums[row] * (1.0 / phys.WEIGHT_UNITS)).astype(np.float32)
            sigma = float(phys.BLUR_LEVELS_PX[layer - 1])
            opacity += cv2.GaussianBlur(buffer.reshape(self.height, self.width), (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_CONSTANT).reshape(-1)
        np.minimum(opacity, np.float32(1.0), out=opacity)
        return opacity.reshape(self.height, self.width)
