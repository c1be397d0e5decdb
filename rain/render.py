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
from rainbench.rain.config import RainConfig
from rainbench.rain.tone import DISPLAY_LIGHT_GAMMA, linear_value, to_linear
from rainbench.store.rates import MAX_RATE_MM_H


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
        lens: lens drops (jeon2022; physical with ``lens_drops``), the drops in the first slots of the clip's lens at the frame's time.
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


def _lens_count(rate: float, config: RainConfig, K: np.ndarray | None, height: int, width: int) -> int:
    if config.model == "jeon2022":
        return lens_mod.jeon2022_drop_count(rate, height, width)
    if not config.lens_drops:
        return 0
    return phys.lens_drop_count(rate, config=config, K=K, height=height, width=width)


def sample_drops(
    rate_mm_h: float,
    *,
    config: RainConfig,
    K: np.ndarray | None,
    shape: tuple[int, ...],
    seed_sequence: np.random.SeedSequence,
    lens_clock: lens_mod.LensClock | None = None,
) -> Drops:
    """The drops that :func:`render_rain` draws for one frame at one rate.

    Args:
        rate_mm_h: rain rate in mm/h, in [0, 1000].
        config: the rain configuration.
        K: (3, 3) float64 intrinsics (needed by the physical model; may be None for jeon2022).
        shape: (H, W) or (H, W, 3) image size in pixels.
        seed_sequence: the frame's ``np.random.SeedSequence`` (not mutated).
        lens_clock: the clip's seed and the frame's time for the lens water (see
            :func:`render_rain`); None: frame 0 of a clip seeded by ``seed_sequence``.

    Returns:
        Drops. jeon2022: ``lens`` = the drops in the first N(rate) slots of the clip's lens at the
        clock's frame, ``air`` empty. physical: ``air`` = the candidates present at the rate
        (before occlusion), ``lens`` the first :func:`physical.lens_drop_count` slots of the
        same lens if ``lens_drops`` else empty.
    """
    config = _check_config(config)
    rate = _check_rate(rate_mm_h)
    height, width = _check_shape(shape)
    check_seed_sequence(seed_sequence)
    clock = lens_mod.lens_clock_or_default(lens_clock, seed_sequence)
    matrix = _check_K(K, required=config.model == "physical")
    lens = lens_mod.sample_lens_drops(_lens_count(rate, config, matrix, height, width), config=config, height=height, width=width, lens_clock=clock)
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
    lens_clock: lens_mod.LensClock | None = None,
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
            Seeds what is re-drawn every frame (the physical model's falling drops).
        lens_clock: ``LensClock(clip_seed_sequence, frame, fps)``: the lens water persists and
            slides over a clip, so it depends on the clip's seed and the frame's time, e.g.
            ``LensClock(np.random.SeedSequence([rain_seed, scene_seed]), frame, 10.0)``. None:
            frame 0 of a clip seeded by ``seed_sequence``.

    Returns:
        RainFrame (new arrays; the inputs are not modified).
    """
    return render_rain_sweep(rgb, depth, (rate_mm_h,), config=config, K=K, seed_sequence=seed_sequence, lens_clock=lens_clock)[0]


def render_rain_sweep(
    rgb: np.ndarray,
    depth: np.ndarray | None,
    rates: Sequence[float],
    *,
    config: RainConfig,
    K: np.ndarray | None,
    seed_sequence: np.random.SeedSequence,
    lens_clock: lens_mod.LensClock | None = None,
    scenes: Sequence[np.ndarray] | None = None,
    airlights: Sequence[Sequence[float]] | None = None,
) -> list[RainFrame]:
    """Render one frame at several rates, sharing the work that does not depend on the rate.

    ``render_rain_sweep(rgb, depth, rates, ...)[i]`` equals ``render_rain(rgb, depth,
    rates[i], ...)`` byte for byte (rgb, coverage and drop_count); with ``scenes`` it equals
    ``render_rain(scenes[i], depth, rates[i], ...)``; with ``airlights`` it equals the same
    with ``config.airlight_rgb = airlights[i]``.

    Args:
        rgb, depth, config, K, seed_sequence, lens_clock: as for :func:`render_rain`.
        rates: rain rates in mm/h, each in [0, 1000], any order, repeats allowed.
        scenes: optional (H, W, 3) uint8 images, one per entry of ``rates``: the scene the rain
            of that rate is drawn over (the frame re-rendered in that rate's weather); ``rgb``
            otherwise. A rate given twice must come with the same scene.
        airlights: optional (R, G, B) in 0..255, one per entry of ``rates`` (physical model
            only): the airlight that rate's extinction and streaks blend towards, in place of
            ``config.airlight_rgb`` (weather light that changes with the rate; the falling
            drops and their streaks are still drawn once for all rates). A rate given twice must
            come with the same airlight.

    Returns:
        list of RainFrame, one per entry of ``rates``, in the same order.
    """
    config = _check_config(config)
    check_seed_sequence(seed_sequence)
    clock = lens_mod.lens_clock_or_default(lens_clock, seed_sequence)
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
    scene_of: dict[float, np.ndarray] | None = None
    if scenes is not None:
        if len(scenes) != len(checked):
            raise ValueError(f"scenes: expected one image per rate ({len(checked)}), got {len(scenes)}")
        scene_of = {}
        for rate, scene in zip(checked, scenes):
            scene = _check_rgb(scene)
            if scene.shape != rgb.shape:
                raise ValueError(f"scenes: expected {rgb.shape} images like rgb, got {scene.shape}")
            if rate in scene_of and not np.array_equal(scene_of[rate], scene):
                raise ValueError(f"scenes: rate {rate:g} mm/h is given twice with different scenes")
            scene_of[rate] = scene
    airlight_of: dict[float, tuple[float, float, float]] | None = None
    if airlights is not None:
        if not physical:
            raise ValueError(f"airlights: only the physical model blends towards an airlight, got model {config.model!r}")
        if len(airlights) != len(checked):
            raise ValueError(f"airlights: expected one (R, G, B) per rate ({len(checked)}), got {len(airlights)}")
        airlight_of = {}
        for rate, airlight in zip(checked, airlights):
            # RainConfig checks an airlight as it checks its own airlight_rgb
            airlight = dataclasses.replace(config, airlight_rgb=airlight).airlight_rgb
            if airlight_of.setdefault(rate, airlight) != airlight:
                raise ValueError(f"airlights: rate {rate:g} mm/h is given twice with different airlights")
    if physical:
        frames = _physical_sweep(rgb, depth, ascending, config, matrix, seed_sequence, clock, scene_of,
                                 airlight_of)
    elif scene_of is not None:  # lens water over a different scene at every rate
        frames = _jeon_scenes(scene_of, ascending, config, clock)
    else:
        frames = _jeon_sweep(rgb, ascending, config, clock)
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


LENS_RASTER_BUDGET = 1 << 21
"""Lens-drop raster entries (bounded by :func:`lens_mod.lens_entry_bound`) rasterised at once.
More drops are drawn in consecutive runs, so the rasteriser's temporaries (about 200 bytes an
entry) stay near 0.4 GB whatever the options and image size; the sums are exact, so the pixels
are the same however the drops are split. The defaults fit one run at 800x600 up to 1000 mm/h
and at 1920x1080 up to 100 mm/h."""

LENS_RASTER_KEEP = 1 << 23
"""Lens-drop raster entries kept between the rates of a sweep that draws the drops again for
each rate (the physical model's, and lens water over each rate's own scene): 48 bytes an entry,
0.4 GB. Runs are kept from the first drop on (every rate draws those); later runs are rasterised
again each time a rate draws them."""


STREAK_SAMPLE_BUDGET = 1 << 21
"""Streak samples (:func:`phys.streak_sample_counts`) rasterised at once, about 370 bytes each
(0.8 GB at the budget; each sample splats into 2 x 2 pixels; 2^22 until they splatted into 2).
Beyond it (long exposures on large images: 1/30 s at 3840x2160 and 1000 mm/h takes 24 million)
the streaks are drawn in runs into dense per-layer sums (:class:`_StreakRuns`), the same
numbers. One raster holds up to 1000 mm/h at 2560x1440 with the default 1/250 s, and at
800x600 with the 1/60 s of rain light."""


class _LensAccumulator:
    """Lens water of one frame for a sweep: the drops sampled once for the largest count, and
    rasterised in runs of at most :data:`LENS_RASTER_BUDGET` entries (bounded memory; the same
    sums). The last run drawn is reused; with ``keep_runs`` (a sweep that draws the drops again
    for every rate) runs are also kept while :data:`LENS_RASTER_KEEP` allows."""

    def __init__(self, max_count: int, config: RainConfig, height: int, width: int, lens_clock: lens_mod.LensClock,
                 keep_runs: bool) -> None:
        self.drops = lens_mod.sample_lens_drops(max_count, config=config, height=height, width=width, lens_clock=lens_clock)
        self.config, self.height, self.width = config, height, width
        bounds = lens_mod.lens_entry_bound(self.drops, config=config, height=height, width=width)
        self.runs = lens_mod.lens_drop_chunks(bounds, LENS_RASTER_BUDGET)
        self.keep_runs = keep_runs
        self.kept: dict[int, lens_mod.LensRaster] = {}
        self.kept_entries = 0
        self.last: tuple[int, lens_mod.LensRaster] | None = None
        self.grid = lens_mod.lens_view_shape(config, height, width) + (lens_mod.lens_grid_factor(config, height, width),)
        self.workspace: dict = {}  # scratch buffers of apply_lens for this sweep

    def _raster(self, run: int) -> lens_mod.LensRaster:
        if run in self.kept:
            return self.kept[run]
        if self.last is not None and self.last[0] == run:
            return self.last[1]
        low, high = self.runs[run]
        raster = lens_mod.rasterize_lens_drops(self.drops.range(low, high), config=self.config, height=self.height, width=self.width)
        # runs are kept in order from the first, so every kept run is one each rate draws
        if self.keep_runs and len(self.kept) == run and self.kept_entries + raster.pixel.shape[0] <= LENS_RASTER_KEEP:
            self.kept[run] = raster
            self.kept_entries += raster.pixel.shape[0]
        else:
            self.last = (run, raster)
        return raster

    def empty_sums(self) -> lens_mod.LensSums:
        """Zero sums on the drawing grid."""
        return lens_mod.LensSums.zeros(*self.grid)

    def add(self, sums: lens_mod.LensSums, view: np.ndarray, low: int, high: int) -> None:
        """Add the exact sums over drops ``low <= index < high`` (colours seen in ``view``, the
        channel planes of :func:`lens_mod.planar_view`)."""
        for run, (run_low, run_high) in enumerate(self.runs):
            if run_high <= low or run_low >= high:
                continue
            raster = self._raster(run)
            # entries are ordered by drop (indices within the run): a drop range is a slice
            entries = slice(*np.searchsorted(raster.drop, [max(low, run_low) - run_low, min(high, run_high) - run_low]))
            sums.add(raster, view, entries)

    def composite(self, base: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
        """``base`` under the first ``count`` drops, each showing the view of ``base``."""
        sums = self.empty_sums()
        self.add(sums, lens_mod.planar_view(lens_mod.lens_view(base, self.config)), 0, count)
        return lens_mod.apply_lens(base, sums, self.workspace)


def _jeon_sweep(rgb: np.ndarray, ascending: list[float], config: RainConfig, lens_clock: lens_mod.LensClock) -> list[RainFrame]:
    height, width = rgb.shape[:2]
    counts = [lens_mod.jeon2022_drop_count(rate, height, width) for rate in ascending]
    if max(counts) == 0:
        return [_clean_frame(rgb) for _ in ascending]
    accumulator = _LensAccumulator(max(counts), config, height, width, lens_clock, keep_runs=False)
    view = lens_mod.planar_view(lens_mod.lens_view(rgb, config))
    sums = accumulator.empty_sums()
    drawn = 0
    frames: list[RainFrame] = []
    for count in counts:
        if count == 0:
            frames.append(_clean_frame(rgb))
            continue
        if count == drawn and frames:  # the same count as the previous rate: the same image
            previous = frames[-1]
            frames.append(RainFrame(previous.rgb.copy(), previous.coverage.copy(), count))
            continue
        accumulator.add(sums, view, drawn, count)
        drawn = count
        image, coverage = lens_mod.apply_lens(rgb, sums, accumulator.workspace)
        frames.append(RainFrame(image, coverage, count))
    return frames


def _jeon_scenes(scene_of: dict[float, np.ndarray], ascending: list[float], config: RainConfig,
                 lens_clock: lens_mod.LensClock) -> list[RainFrame]:
    """Lens water over each rate's own scene: the drops sampled once, for the largest count, and
    rasterised once while they fit the kept runs (:data:`LENS_RASTER_KEEP`; runs beyond are
    rasterised again for each rate); each rate composites its first ``count`` drops over its
    scene (what a sweep of that rate alone draws, since a drop's footprint does not depend on the
    others)."""
    height, width = scene_of[ascending[0]].shape[:2]
    counts = [lens_mod.jeon2022_drop_count(rate, height, width) for rate in ascending]
    if max(counts) == 0:
        return [_clean_frame(scene_of[rate]) for rate in ascending]
    accumulator = _LensAccumulator(max(counts), config, height, width, lens_clock, keep_runs=True)
    frames = []
    for rate, count in zip(ascending, counts):
        if count == 0:
            frames.append(_clean_frame(scene_of[rate]))
            continue
        image, coverage = accumulator.composite(scene_of[rate], count)
        frames.append(RainFrame(image, coverage, count))
    return frames


def _physical_sweep(
    rgb: np.ndarray,
    depth: np.ndarray,
    ascending: list[float],
    config: RainConfig,
    K: np.ndarray,
    seed_sequence: np.random.SeedSequence,
    lens_clock: lens_mod.LensClock,
    scene_of: dict[float, np.ndarray] | None = None,
    airlight_of: dict[float, tuple[float, float, float]] | None = None,
) -> list[RainFrame]:
    height, width = rgb.shape[:2]
    top_rate = ascending[-1]
    if top_rate == 0:
        return [_clean_frame(scene_of[rate] if scene_of else rgb) for rate in ascending]

    # falling drops: candidates are rate independent; draw those present at the top rate once,
    # ordered by threshold rate so that each rate adds a contiguous run of raster entries
    candidates = phys.sample_air_candidates(config=config, K=K, height=height, width=width, seed_sequence=seed_sequence)
    air = candidates.at_rate(top_rate)
    air = air.select(np.argsort(air.threshold_rate_mm_h, kind="stable"))
    samples = phys.streak_sample_counts(air)
    streaks: _StreakAccumulator | _StreakRuns
    if int(samples.sum()) <= STREAK_SAMPLE_BUDGET:
        streaks = _StreakAccumulator(phys.rasterize_streaks(air, depth), air, height, width)
    else:
        streaks = _StreakRuns(air, depth, samples)

    # extinction and airlight, channel-planar float32 for fast per-rate blending
    path_m = phys.ray_length_m(depth, K, config.sky_distance_m)

    def blend_terms(scene: np.ndarray, airlight_rgb: tuple[float, float, float] | None):
        # in linear light (rainbench.rain.tone): extinction, airlight and streaks mix radiance
        airlight = np.asarray(airlight_rgb, dtype=np.float64) if airlight_rgb is not None else phys.estimate_airlight(scene, depth)
        airlight_linear = linear_value(airlight)
        scene_linear = to_linear(scene)
        # a drop refracts a ~165 degree view, mostly of the sky: streak radiance is a blend of
        # the sky's radiance (the airlight) and the frame's mean radiance (Garg & Nayar)
        sky_weight = config.streak_sky_weight
        drop_radiance = sky_weight * airlight_linear + (1.0 - sky_weight) * np.asarray(cv2.mean(scene_linear)[:3], dtype=np.float64)
        scene_minus_air = [scene_linear[..., channel] - np.float32(airlight_linear[channel]) for channel in range(3)]
        radiance_minus_air = [float(drop_radiance[channel] - airlight_linear[channel]) for channel in range(3)]
        return airlight_linear, scene_minus_air, radiance_minus_air

    shared_terms = blend_terms(rgb, config.airlight_rgb) if scene_of is None and airlight_of is None else None

    lens_counts = [_lens_count(rate, config, K, height, width) for rate in ascending]
    lens_accumulator = _LensAccumulator(max(lens_counts), config, height, width, lens_clock, keep_runs=True) if max(lens_counts) > 0 else None

    frames = []
    for rate, lens_count in zip(ascending, lens_counts):
        scene = scene_of[rate] if scene_of is not None else rgb
        if rate == 0:
            frames.append(_clean_frame(scene))
            continue
        airlight, scene_minus_air, radiance_minus_air = shared_terms or blend_terms(
            scene, airlight_of[rate] if airlight_of is not None else config.airlight_rgb)
        streaks.add_rate(rate)
        streak_opacity = streaks.opacity()

        # I' = A + (I - A) T (1 - E) + (S - A) E in linear light: extinction/airlight, then
        # streaks over it; back to display values once
        beta_per_m = phys.extinction_coefficient(rate) * 1e-3
        gain = cv2.exp(path_m * np.float32(-beta_per_m))
        gain = cv2.multiply(gain, np.float32(1.0) - streak_opacity)
        channels = []
        for channel in range(3):
            plane = cv2.multiply(scene_minus_air[channel], gain)
            plane = cv2.scaleAdd(streak_opacity, radiance_minus_air[channel], plane)
            # + A, then the tone curve plane by plane (rainbench.rain.tone.to_display, without its
            # copies: the terms are >= 0 but for float rounding, which OpenCV's pow takes as |x|,
            # and values above 1 saturate at 255)
            cv2.add(plane, float(airlight[channel]), dst=plane)
            cv2.pow(plane, 1.0 / DISPLAY_LIGHT_GAMMA, dst=plane)
            channels.append(cv2.convertScaleAbs(plane, alpha=255.0))
        rainy = cv2.merge(channels)
        coverage = streak_opacity
        drop_count = streaks.visible_count()

        if lens_accumulator is not None and lens_count > 0:
            rainy, lens_coverage = lens_accumulator.composite(rainy, lens_count)  # drops show the rainy scene
            coverage = (1.0 - (1.0 - coverage) * (1.0 - lens_coverage)).astype(np.float32)
            drop_count += lens_count
        frames.append(RainFrame(rainy, coverage, drop_count))
    return frames


class _StreakAccumulator:
    """Exact per-pixel streak sums of the drops ``air`` (ordered by threshold rate), grown rate
    by rate from one raster of them all.

    Sums are integer-valued float64 (exact in any order). The unblurred layer is kept as a
    float32 image updated only where a run touched it, which equals recomputing it from the sums.
    Blurred layers (defocus) are re-blurred from their sums at every rate.
    """

    def __init__(self, raster: phys.StreakRaster, air: phys.AirDrops, height: int, width: int) -> None:
        self.height, self.width = height, width
        self.raster = raster
        self.air = air
        self.element_threshold = air.threshold_rate_mm_h[raster.drop]  # ascending
        self.drawn = 0  # raster entries added
        self.rate = -1.0
        self.pixels, inverse = lens_mod.compress_pixels(raster.pixel, height * width)
        n_unique = self.pixels.shape[0]
        self.layers = np.flatnonzero(np.bincount(raster.layer, minlength=len(phys.BLUR_LEVELS_PX) + 1))
        slot = np.zeros(len(phys.BLUR_LEVELS_PX) + 1, dtype=np.int64)
        slot[self.layers] = np.arange(self.layers.shape[0])
        self.keys = slot[raster.layer] * n_unique + inverse
        self.sums = np.zeros((self.layers.shape[0], n_unique), dtype=np.float64)
        self.sharp = np.zeros(height * width, dtype=np.float32)

    def add_rate(self, rate: float) -> None:
        """Add the drops of threshold rate <= ``rate`` not yet added (rates ascending)."""
        self.rate = rate
        upto = int(np.searchsorted(self.element_threshold, rate, side="right"))
        low, high = self.drawn, upto
        self.drawn = max(self.drawn, upto)
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

    def visible_count(self) -> int:
        """Drops added so far with at least one pixel drawn."""
        return int(np.count_nonzero(self.raster.visible & (self.air.threshold_rate_mm_h <= self.rate)))

    def opacity(self) -> np.ndarray:
        """(H, W) float32 streak opacity in [0, 1]: sharp layer plus blurred layers, clipped."""
        opacity = self.sharp.copy()
        for row, layer in enumerate(self.layers):
            if layer == 0 or not self.sums[row].any():
                continue
            opacity += _blurred_layer(self.sums[row], self.pixels, layer, self.height, self.width)
        np.minimum(opacity, np.float32(1.0), out=opacity)
        return opacity.reshape(self.height, self.width)


def _blurred_layer(sums: np.ndarray, pixels: np.ndarray | None, layer: int, height: int, width: int) -> np.ndarray:
    """(H * W,) float32: blur layer ``layer``'s opacity sums (at ``pixels``, or dense when None)
    blurred by its Gaussian."""
    if pixels is None:
        buffer = (sums * (1.0 / phys.WEIGHT_UNITS)).astype(np.float32)
    else:
        buffer = np.zeros(height * width, dtype=np.float32)
        buffer[pixels] = (sums * (1.0 / phys.WEIGHT_UNITS)).astype(np.float32)
    sigma = float(phys.BLUR_LEVELS_PX[layer - 1])
    return cv2.GaussianBlur(buffer.reshape(height, width), (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_CONSTANT).reshape(-1)


class _StreakRuns:
    """The sums of :class:`_StreakAccumulator` when the drops take more than
    :data:`STREAK_SAMPLE_BUDGET` samples: each rate rasterises its new drops in runs of at most
    that many samples and adds them to dense per-layer sums (one (H * W,) float64 row per blur
    layer the drops use), so memory is bounded by the image, not by the streaks' length. The same
    numbers: the sums are exact integers and a drop's splats depend on it and the depth alone."""

    def __init__(self, air: phys.AirDrops, depth: np.ndarray, samples: np.ndarray) -> None:
        self.height, self.width = depth.shape
        self.air, self.depth, self.samples = air, depth, samples
        self.threshold = air.threshold_rate_mm_h  # ascending
        self.layers = np.unique(phys.blur_layer(air.blur_sigma_px))
        self.sums = np.zeros((self.layers.shape[0], self.height * self.width), dtype=np.float64)
        self.visible = np.zeros(len(air), dtype=bool)
        self.drawn = 0  # drops added

    def add_rate(self, rate: float) -> None:
        """Add the drops of threshold rate <= ``rate`` not yet added (rates ascending)."""
        upto = max(int(np.searchsorted(self.threshold, rate, side="right")), self.drawn)
        pixels = self.height * self.width
        for low, high in lens_mod.lens_drop_chunks(self.samples[self.drawn:upto], STREAK_SAMPLE_BUDGET):
            low, high = low + self.drawn, high + self.drawn
            raster = phys.rasterize_streaks(self.air.select(slice(low, high)), self.depth)
            self.visible[low:high] = raster.visible
            slot = np.searchsorted(self.layers, raster.layer)
            for row in np.unique(slot):
                mine = slot == row
                self.sums[row] += np.bincount(raster.pixel[mine], raster.weight_units[mine], minlength=pixels)
        self.drawn = upto

    def visible_count(self) -> int:
        """Drops added so far with at least one pixel drawn."""
        return int(np.count_nonzero(self.visible[:self.drawn]))

    def opacity(self) -> np.ndarray:
        """(H, W) float32 streak opacity in [0, 1], as :meth:`_StreakAccumulator.opacity`."""
        opacity = np.zeros(self.height * self.width, dtype=np.float32)
        for row, layer in enumerate(self.layers):
            if layer == 0:
                opacity = (self.sums[row] * (1.0 / phys.WEIGHT_UNITS)).astype(np.float32)
            elif self.sums[row].any():
                opacity += _blurred_layer(self.sums[row], None, int(layer), self.height, self.width)
        np.minimum(opacity, np.float32(1.0), out=opacity)
        return opacity.reshape(self.height, self.width)
