"""Water on the lens: the jeon2022 model (seed paper eq. 5) and the physical model's lens water.

A lens drop is water on the lens or its cover glass, a few centimetres in front of a camera
focused far away. It is drawn as the camera sees it: out of focus (its outline and what it shows
are blurred by the defocus), semi-transparent where it is smaller than the defocus blur, showing
a blurred, point-reflected (flipped) and minified view of the scene around it, darker towards
its rim. Sizes, defocus and motion are documented with their sources in docs/rain.md.

Persistence: drops live on the glass for seconds and slide, they are not re-drawn each frame.
The lens of a clip holds a fixed sequence of *slots*; slot s always holds exactly one drop,
which is replaced when its life ends (every slot has its own life length and phase, so
replacements are spread over time). A drop is pinned for part of its life and may then slide
outwards at a constant speed. A frame's drops are a pure function of (the clip's seed, the
frame's time): nothing is carried from frame to frame, so any frame of any shard can be
rendered alone (:class:`LensClock`).

Nesting: a rate uses the first ``N(rate)`` slots (eq. 5), so a higher rate contains every drop
of a lower one, unchanged. Per-slot random numbers come from a counter-based hash of (clip key,
slot, generation, column), and every per-drop quantity that uses a transcendental function is
computed on whole blocks of :data:`LENS_BLOCK` slots, so drop i is identical however many drops
are asked for.

Exact accumulation: per-cell opacities, shades and colours are integers (alpha in 1/1024 steps,
shade in 1/256 steps, colours 0..255), so their sums are exact in float64 in any order. This lets ``render_rain_sweep`` add
drops rate by rate and still match single-rate calls byte for byte.

Drawing resolution: lens water is smooth (defocused), so the drops are rasterised on a grid of
cells half the defocus radius wide (5 px at 800x600) and the per-cell coverage and colour are
upsampled bilinearly before they are blended over the full-resolution image.
"""

from __future__ import annotations

import dataclasses
import fractions
import functools
import math

import cv2
import numpy as np

from rainbench.rain._seeding import STREAM_LENS, check_seed_sequence
from rainbench.rain.config import RainConfig
from rainbench.store.rates import rate_decimal

REFERENCE_HEIGHT = 600
REFERENCE_WIDTH = 800
REFERENCE_AREA = REFERENCE_HEIGHT * REFERENCE_WIDTH
"""Eq. 5 counts are for an 800x600 image; other sizes scale the count by area."""

EQ5_SLOPE_MM_H = 0.03
EQ5_OFFSET_MM_H = 3.88
"""Seed paper eq. 5: rate = 0.03 * N + 3.88 (rate in mm/h, N drops on 800x600)."""

LENS_BLOCK = 512
"""Slots are computed in blocks of this size (transcendental functions act on whole blocks)."""

ALPHA_UNITS = 1024
"""Opacity quantum: per-cell alpha is an integer number of 1/1024 steps."""

SHADE_UNITS = 256
"""Rim shading quantum: shade factor is an integer number of 1/256 steps."""

DEFAULT_FPS = 10.0
"""Frame rate of a :class:`LensClock` when none is given (the paper's clip: 10 frames/s)."""

_SLOT_COLUMNS = 2  # life, phase
_DROP_COLUMNS = 8  # x, y, radius, aspect, angle, slides, onset, speed
_SLOT_GENERATION = np.uint64(0xFFFFFFFFFFFFFFFF)  # generation id of the per-slot variates
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX_A = np.uint64(0xBF58476D1CE4E5B9)
_MIX_B = np.uint64(0x94D049BB133111EB)
_GENERATION_MULTIPLIER = np.uint64(0xD1B54A32D192ED03)


def image_scale(height: int, width: int) -> float:
    """Linear size of an image relative to 800x600: ``sqrt(H * W / (800 * 600))``."""
    return math.sqrt(height * width / REFERENCE_AREA)


def _round_half_up(value: fractions.Fraction) -> int:
    return math.floor(value + fractions.Fraction(1, 2))


def jeon2022_drop_count(rate_mm_h: float, height: int = REFERENCE_HEIGHT, width: int = REFERENCE_WIDTH) -> int:
    """Number of lens drops for a rain rate, seed paper eq. 5 scaled by image area.

    ``N800 = round((rate - 3.88) / 0.03)`` (round half up) for rate > 3.88 mm/h, else 0;
    ``N = round(N800 * H * W / (800 * 600))``.

    Args:
        rate_mm_h: rain rate in mm/h, finite and >= 0.
        height, width: image size in pixels.

    Returns:
        the drop count, an int >= 0, non-decreasing in the rate.
    """
    if not math.isfinite(rate_mm_h) or rate_mm_h < 0:
        raise ValueError(f"rate_mm_h must be a finite number >= 0, got {rate_mm_h!r}")
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got height {height} and width {width}")
    if rate_mm_h <= EQ5_OFFSET_MM_H:
        return 0
    # in exact decimals: (3.925 - 3.88) / 0.03 is 1.5, which floats make 1.4999999999999893; a
    # rate is the decimal it stands for (rate_decimal: float32 3.925 read from a shard too)
    rate = fractions.Fraction(rate_decimal(rate_mm_h))
    count_800x600 = _round_half_up((rate - fractions.Fraction(repr(EQ5_OFFSET_MM_H)))
                                   / fractions.Fraction(repr(EQ5_SLOPE_MM_H)))
    if height * width == REFERENCE_AREA:
        return count_800x600
    return _round_half_up(fractions.Fraction(count_800x600 * height * width, REFERENCE_AREA))


# --------------------------------------------------------------------------------------------
# time


@dataclasses.dataclass(frozen=True)
class LensClock:
    """Which clip and which moment a frame's lens water belongs to.

    Attributes:
        seed_sequence: the clip's ``np.random.SeedSequence`` (e.g. ``SeedSequence([rain_seed,
            scene_seed])``); the same for every frame of the clip, never including the frame or
            the rate. Not mutated.
        frame: index of the frame in the clip, an int >= 0 (the global index, not the index
            within a shard, so shards at any frame offset agree).
        fps: frames per second of the clip, > 0. The frame's time is ``frame / fps`` seconds.
    """

    seed_sequence: np.random.SeedSequence
    frame: int = 0
    fps: float = DEFAULT_FPS

    def __post_init__(self) -> None:
        check_seed_sequence(self.seed_sequence)
        if isinstance(self.frame, bool) or not isinstance(self.frame, (int, np.integer)) or self.frame < 0:
            raise ValueError(f"LensClock.frame must be an int >= 0, got {self.frame!r}")
        if isinstance(self.fps, bool) or not isinstance(self.fps, (int, float, np.integer, np.floating)) or not math.isfinite(self.fps) or self.fps <= 0:
            raise ValueError(f"LensClock.fps must be a finite number > 0, got {self.fps!r}")
        object.__setattr__(self, "frame", int(self.frame))
        object.__setattr__(self, "fps", float(self.fps))

    @property
    def time_s(self) -> float:
        """The frame's time in seconds from the start of the clip."""
        return self.frame / self.fps

    def key(self) -> np.uint64:
        """The clip's 64-bit key of the lens-water hash (from the seed sequence's lens stream)."""
        child = np.random.SeedSequence(
            entropy=self.seed_sequence.entropy,
            spawn_key=tuple(self.seed_sequence.spawn_key) + (STREAM_LENS,),
            pool_size=self.seed_sequence.pool_size,
        )
        return np.uint64(child.generate_state(1, dtype=np.uint64)[0])


def lens_clock_or_default(lens_clock: LensClock | None, seed_sequence: np.random.SeedSequence) -> LensClock:
    """``lens_clock``, or frame 0 of a clip seeded by ``seed_sequence`` when it is None."""
    if lens_clock is None:
        return LensClock(seed_sequence, 0, DEFAULT_FPS)
    if not isinstance(lens_clock, LensClock):
        raise TypeError(f"lens_clock must be a LensClock or None, got {type(lens_clock).__name__}")
    return lens_clock


def _mix64(value: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on uint64 arrays (wrapping arithmetic)."""
    value = (value ^ (value >> np.uint64(30))) * _MIX_A
    value = (value ^ (value >> np.uint64(27))) * _MIX_B
    return value ^ (value >> np.uint64(31))


def hash_uniforms(key: np.uint64, slots: np.ndarray, generation: np.ndarray, columns: int) -> np.ndarray:
    """Counter-based uniform variates: a pure function of (key, slot, generation, column).

    Args:
        key: the clip's key (:meth:`LensClock.key`).
        slots: (n,) uint64 slot indices.
        generation: (n,) uint64 generation of each slot's drop.
        columns: number of variates per slot.

    Returns:
        (n, columns) float64 in [0, 1), 53-bit resolution.
    """
    with np.errstate(over="ignore"):
        head = _mix64(slots * _GOLDEN + key)
        head = _mix64(head ^ (generation * _GENERATION_MULTIPLIER + _MIX_B))
        column = (np.arange(1, columns + 1, dtype=np.uint64) * _GOLDEN)[None, :]
        bits = _mix64(head[:, None] + column)
    return (bits >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


# --------------------------------------------------------------------------------------------
# drops


@dataclasses.dataclass(frozen=True)
class LensDrops:
    """The lens drops of one frame, one per slot; all arrays have shape (N,).

    Image coordinates are continuous pixel units: pixel column i spans [i, i + 1).

    Attributes:
        x_px, y_px: drop centre in pixels (float64; may lie outside the image for a drop that
            slid off it).
        radius_px: semi-major axis of the drop's footprint on the glass, in pixels (float64).
        aspect: minor/major axis ratio in (0, 1] (float64).
        cos_angle, sin_angle: direction of the major axis (float64).
        strength: opacity factor in [0, 1] of the drop's life: it fades in over ``lens_fade_s``
            after the drop lands and out over ``lens_fade_s`` before it is replaced (float64).
        generation: int64 index of the drop in its slot's sequence of drops; a slot's drop is
            the same drop in two frames iff its generation is the same.
    """

    x_px: np.ndarray
    y_px: np.ndarray
    radius_px: np.ndarray
    aspect: np.ndarray
    cos_angle: np.ndarray
    sin_angle: np.ndarray
    strength: np.ndarray
    generation: np.ndarray

    def __len__(self) -> int:
        return int(self.x_px.shape[0])

    def head(self, count: int) -> LensDrops:
        """The first ``count`` drops (the drops of a lower rate)."""
        return self.range(0, count)

    def range(self, low: int, high: int) -> LensDrops:
        """Drops ``low <= index < high`` (views of these arrays)."""
        return LensDrops(*(getattr(self, f.name)[low:high] for f in dataclasses.fields(self)))

    def as_array(self) -> np.ndarray:
        """(N, 8) float64 array of the fields in declaration order (for comparisons in tests)."""
        return np.stack([getattr(self, f.name).astype(np.float64) for f in dataclasses.fields(self)], axis=1)


def empty_lens_drops() -> LensDrops:
    """A LensDrops with zero drops."""
    empty = np.zeros(0, dtype=np.float64)
    return LensDrops(empty, empty, empty, empty, empty, empty, empty, np.zeros(0, dtype=np.int64))


def single_lens_drop(x: float, y: float, radius: float, *, aspect: float = 1.0, angle: float = 0.0, strength: float = 1.0) -> LensDrops:
    """One drop with the given geometry (for tests and illustrations)."""
    values = (x, y, radius, aspect, math.cos(angle), math.sin(angle), strength)
    return LensDrops(*(np.array([float(v)]) for v in values), np.zeros(1, dtype=np.int64))


def _smoothstep(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def _radius_from_uniform(u: np.ndarray, r_min: float, r_max: float, exponent: float) -> np.ndarray:
    if r_max == r_min:
        return np.full(u.shape, r_min)
    if abs(exponent - 1.0) < 1e-12:
        return r_min * (r_max / r_min) ** u
    power = 1.0 - exponent
    low, high = r_min**power, r_max**power
    return (low + u * (high - low)) ** (1.0 / power)


def lens_block(block: int, *, key: np.uint64, time_s: float, config: RainConfig, height: int, width: int) -> LensDrops:
    """The drops of slots ``512 block .. 512 block + 511`` at time ``time_s``.

    Slot s has a life ``P_s`` uniform in [lens_life_min_s, lens_life_max_s] and a phase
    ``phi_s`` uniform in [0, 1); at time t it holds drop number ``g = floor(t / P_s + phi_s)``
    of its sequence, aged ``a = (t / P_s + phi_s - g) P_s``. Drop g of slot s has: a landing
    point uniform over the image; a radius from the truncated power law ``p(r) ~ r^-exponent``
    on [lens_radius_min_px, lens_radius_max_px]; an aspect uniform in [lens_aspect_min, 1] and a
    uniform orientation; with probability ``lens_slide_fraction`` it depins at a uniform time
    of its life and then runs outwards from the image centre at a speed uniform in
    [0, lens_slide_max_px_s]. Its strength fades in and out over ``lens_fade_s`` (smoothstep).
    Lengths scale with :func:`image_scale`.
    """
    scale = image_scale(height, width)
    slots = np.arange(block * LENS_BLOCK, (block + 1) * LENS_BLOCK, dtype=np.uint64)
    per_slot = hash_uniforms(key, slots, np.full(LENS_BLOCK, _SLOT_GENERATION), _SLOT_COLUMNS)
    life_s = config.lens_life_min_s + (config.lens_life_max_s - config.lens_life_min_s) * per_slot[:, 0]
    cycles = time_s / life_s + per_slot[:, 1]
    generation = np.floor(cycles)
    age_s = (cycles - generation) * life_s
    generation = generation.astype(np.int64)
    u = hash_uniforms(key, slots, generation.astype(np.uint64), _DROP_COLUMNS)

    x0 = u[:, 0] * width
    y0 = u[:, 1] * height
    radius = _radius_from_uniform(u[:, 2], config.lens_radius_min_px * scale, config.lens_radius_max_px * scale, config.lens_radius_exponent)
    aspect = 1.0 - (1.0 - config.lens_aspect_min) * u[:, 3]
    angle = np.pi * u[:, 4]

    # depinned drops run outwards from the centre (air flow over a forward-facing glass)
    outward_x = x0 - 0.5 * width
    outward_y = y0 - 0.5 * height
    norm = np.sqrt(outward_x * outward_x + outward_y * outward_y)
    far = norm > 1e-9
    direction_x = np.where(far, outward_x / np.where(far, norm, 1.0), 0.0)
    direction_y = np.where(far, outward_y / np.where(far, norm, 1.0), 1.0)
    slides = u[:, 5] < config.lens_slide_fraction
    onset_s = u[:, 6] * life_s
    speed = config.lens_slide_max_px_s * scale * u[:, 7]
    travel = np.where(slides, speed * np.maximum(age_s - onset_s, 0.0), 0.0)

    fade = config.lens_fade_s
    if fade > 0:
        strength = _smoothstep(np.minimum(age_s / fade, 1.0)) * _smoothstep(np.minimum((life_s - age_s) / fade, 1.0))
    else:
        strength = np.ones(LENS_BLOCK)
    return LensDrops(
        x_px=x0 + direction_x * travel,
        y_px=y0 + direction_y * travel,
        radius_px=radius,
        aspect=aspect,
        cos_angle=np.cos(angle),
        sin_angle=np.sin(angle),
        strength=strength,
        generation=generation,
    )


def max_slide_px_per_frame(config: RainConfig, height: int, width: int, fps: float = DEFAULT_FPS) -> float:
    """The farthest a drop moves between two consecutive frames of its life, in pixels:
    ``lens_slide_max_px_s * image_scale / fps`` (3 px at 800x600 and 10 fps by default)."""
    return config.lens_slide_max_px_s * image_scale(height, width) / fps


def sample_lens_drops(count: int, *, config: RainConfig, height: int, width: int, lens_clock: LensClock) -> LensDrops:
    """The drops in the first ``count`` slots of the clip's lens at the clock's frame.

    Block b (slots ``512 b .. 512 b + 511``) is computed as a whole by :func:`lens_block`, so
    drop i is identical whatever ``count`` is asked for: ``sample_lens_drops(n)`` is a prefix of
    ``sample_lens_drops(m)`` for n <= m.

    Args:
        count: number of drops, >= 0.
        config: drawing and motion parameters.
        height, width: image size in pixels.
        lens_clock: the clip's seed and the frame's time (not mutated).

    Returns:
        LensDrops with ``count`` drops.
    """
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    if count == 0:
        return empty_lens_drops()
    key = lens_clock.key()
    blocks = [
        lens_block(block, key=key, time_s=lens_clock.time_s, config=config, height=height, width=width) for block in range(-(-count // LENS_BLOCK))
    ]
    fields = [f.name for f in dataclasses.fields(LensDrops)]
    joined = LensDrops(*(np.concatenate([getattr(b, name) for b in blocks]) for name in fields))
    return joined.head(count)


# --------------------------------------------------------------------------------------------
# drawing


GRID_PER_DEFOCUS = 0.5
"""Drawing cell side as a fraction of the defocus radius (5 px for the default 10 px)."""


def lens_grid_factor(config: RainConfig, height: int, width: int) -> int:
    """Side of a drawing cell in pixels: ``round(0.5 * lens_defocus_px * image_scale)``, >= 1.

    Lens water is blurred by the defocus (radius b), so cells of b / 2 lose nothing visible."""
    return max(1, int(round(GRID_PER_DEFOCUS * config.lens_defocus_px * image_scale(height, width))))


def lens_view_shape(config: RainConfig, height: int, width: int) -> tuple[int, int]:
    """(h, w) of the drawing grid and of the blurred view image seen through lens drops: the
    frame box-averaged by :func:`lens_grid_factor` pixels."""
    factor = lens_grid_factor(config, height, width)
    return -(-height // factor), -(-width // factor)


def lens_view(rgb: np.ndarray, config: RainConfig) -> np.ndarray:
    """The blurred scene that lens drops refract, one pixel per drawing cell.

    Args:
        rgb: (H, W, 3) uint8 image.
        config: gives ``lens_view_blur_px`` and ``lens_defocus_px`` (the cell size).

    Returns:
        (h, w, 3) uint8: the image area-averaged down to :func:`lens_view_shape`, then blurred
        by a Gaussian of sigma ``lens_view_blur_px * image_scale`` pixels (reflected borders;
        a sigma of 4 cells or more is applied on a 4x coarser copy, then upsampled bilinearly).
    """
    height, width = rgb.shape[:2]
    view_height, view_width = lens_view_shape(config, height, width)
    if (view_height, view_width) == (height, width):
        view = rgb.copy()
    else:
        view = cv2.resize(rgb, (view_width, view_height), interpolation=cv2.INTER_AREA)
    sigma_cells = config.lens_view_blur_px * image_scale(height, width) * view_width / width
    if sigma_cells < 0.3:
        return view
    # a wide blur is done 4x coarser (area-average, blur, bilinear back): the same look, 16x cheaper
    coarse = 4 if sigma_cells >= 4.0 and min(view_height, view_width) >= 16 else 1
    small = view if coarse == 1 else cv2.resize(view, (-(-view_width // coarse), -(-view_height // coarse)), interpolation=cv2.INTER_AREA)
    sigma = sigma_cells / coarse
    small = cv2.GaussianBlur(small, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    if coarse == 1:
        return small
    return cv2.resize(small, (view_width, view_height), interpolation=cv2.INTER_LINEAR)


@dataclasses.dataclass(frozen=True)
class LensRaster:
    """The drawing cells touched by a set of lens drops; every entry array has shape (E,), one
    entry per (drop, cell) pair with non-zero opacity, ordered by drop. Independent of the image
    content.

    Attributes:
        pixel: int64 flat cell index ``i * w + j`` on the drawing grid.
        drop: int64 index of the drop in its LensDrops.
        alpha_units: int64 opacity in 1/1024 steps, 1..1024.
        shade_units: int64 rim shading in 1/256 steps (256 = no darkening).
        weight: float64 ``alpha_units * shade_units`` (an integer).
        source: int64 flat index into the view image (see :func:`lens_view`).
        view_height, view_width: size of the drawing grid and of the view image (h, w).
        factor: side of a cell in image pixels.
    """

    pixel: np.ndarray
    drop: np.ndarray
    alpha_units: np.ndarray
    shade_units: np.ndarray
    source: np.ndarray
    view_height: int
    view_width: int
    factor: int
    weight: np.ndarray = dataclasses.field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.weight is None:
            object.__setattr__(self, "weight", (self.alpha_units * self.shade_units).astype(np.float64))


def _reach_px(drops: LensDrops, config: RainConfig, height: int, width: int) -> np.ndarray:
    """(N,) float64: how far from its centre each drop's blurred footprint reaches, in pixels."""
    return drops.radius_px + config.lens_defocus_px * image_scale(height, width)


def _half_extent(reach: np.ndarray, factor: int) -> np.ndarray:
    """(N,) int64 half side, in cells, of the square of cells a drop of this reach can touch:
    a cell centre at offset o from the drop's cell is within the reach only if ``|o| < reach / k
    + 0.5``."""
    return np.ceil(reach / factor + 0.5).astype(np.int64) - 1


def _stencil(half_size: int) -> tuple[np.ndarray, np.ndarray]:
    """Cell offsets (x, y), int64 arrays of shape (S,), that a drop of half extent ``half_size``
    can touch: the square without the corners that no such drop reaches (a cell centre is at
    least ``k (|o| - 0.5)+`` from the drop centre along each axis, and ``reach / k < half_size +
    0.5``). Row-major order; read only (small ones are shared)."""
    return _small_stencil(half_size) if half_size <= _SHARED_STENCIL_MAX else _build_stencil(half_size)


_SHARED_STENCIL_MAX = 64  # stencils up to 129 x 129 cells are cached (at most 65 of them, 4.4 MB)


def _build_stencil(half_size: int) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.arange(-half_size, half_size + 1, dtype=np.int64)
    offset_x = np.tile(offsets, offsets.shape[0])
    offset_y = np.repeat(offsets, offsets.shape[0])
    gap_x = np.maximum(np.abs(offset_x) - 0.5, 0.0)
    gap_y = np.maximum(np.abs(offset_y) - 0.5, 0.0)
    corner = gap_x * gap_x + gap_y * gap_y < (half_size + 0.5) ** 2
    offset_x, offset_y = offset_x[corner], offset_y[corner]
    offset_x.flags.writeable = False
    offset_y.flags.writeable = False
    return offset_x, offset_y


_small_stencil = functools.lru_cache(maxsize=None)(_build_stencil)


def _stencil_size(half_size: int) -> int:
    """``_stencil(half_size)[0].shape[0]`` without building it: for each row, the offsets whose
    squared gap is under the circle's (quarter-integers, so the comparison is exact)."""
    offsets = np.arange(-half_size, half_size + 1, dtype=np.int64)
    gap = np.maximum(np.abs(offsets) - 0.5, 0.0)
    squared = np.sort(gap * gap)
    return int(np.searchsorted(squared, (half_size + 0.5) ** 2 - squared, side="left").sum())


def lens_entry_bound(drops: LensDrops, *, config: RainConfig, height: int, width: int) -> np.ndarray:
    """(N,) int64: at most how many raster entries (cells) each drop can have in
    :func:`rasterize_lens_drops`, whatever its position and shape (its stencil's size).

    Bounds the work and memory of rasterising drops before doing it: a raster of drops with
    bound sum B holds at most B entries and its largest per-cell temporary has B elements."""
    half = _half_extent(_reach_px(drops, config, height, width), lens_grid_factor(config, height, width))
    unique, inverse = np.unique(half, return_inverse=True)
    sizes = np.array([_stencil_size(int(h)) for h in unique], dtype=np.int64)
    return sizes[inverse.reshape(-1)]


def lens_drop_chunks(bounds: np.ndarray, budget: int) -> list[tuple[int, int]]:
    """Consecutive drop ranges ``(low, high)`` covering ``0..len(bounds)`` whose entry bounds
    (from :func:`lens_entry_bound`) sum to at most ``budget`` each; a drop whose own bound
    exceeds the budget is a range alone. Empty for no drops.

    Args:
        bounds: (N,) int64 per-drop entry bounds, >= 0.
        budget: entries per range, >= 1.
    """
    if budget < 1:
        raise ValueError(f"budget must be >= 1 entry, got {budget}")
    cumulative = np.cumsum(bounds)
    chunks: list[tuple[int, int]] = []
    low = 0
    while low < bounds.shape[0]:
        before = int(cumulative[low - 1]) if low else 0
        high = max(int(np.searchsorted(cumulative, before + budget, side="right")), low + 1)
        chunks.append((low, high))
        low = high
    return chunks


def rasterize_lens_drops(drops: LensDrops, *, config: RainConfig, height: int, width: int) -> LensRaster:
    """Footprints of lens drops on the drawing grid: opacity, rim shade and view position.

    For a cell centre p (cell (i, j) is centred on ``((j + 0.5) k, (i + 0.5) k)`` px) and a drop
    with centre c, radius r, aspect a and major-axis angle t: ``rho = |R(-t) (p - c) / (r, a r)|``
    (1 on the drop's edge) and ``d = rho r``. Defocus spreads the drop over a disc of radius
    ``b = lens_defocus_px * image_scale`` (the blur circle of a point on the glass), so the
    opacity is the overlap of the drop's disc with that blur disc, approximated without
    transcendental functions: ``alpha = lens_opacity * strength * (m / b)^2 * smoothstep((r + b -
    d) / (2 m))``, ``m = min(r, b)`` -- fully opaque inside ``d < r - b`` for drops larger than
    the blur, at most ``(r / b)^2`` (semi-transparent) for smaller ones, 0 beyond ``r + b``.
    Shade ``1 - lens_rim_darkening * smoothstep(clip((d / (r + b) - 0.5) / 0.5, 0, 1))`` (a dark
    rim, blurred with the drop); the cell shows the view image at ``c - F (p - c) / (max(r, b)
    max(rho, 1))`` with ``F = lens_view_field_px * image_scale``: a drop's disc shows the scene
    within F pixels of its centre, point-reflected (flipped) and minified; a drop smaller than
    the blur shows a proportionally smaller field (its own image is blurred away), and the halo
    outside the edge shows what the edge shows.

    Only arithmetic and sqrt act on per-cell values, and every per-drop value comes from
    :class:`LensDrops`, so a drop's footprint does not depend on which other drops are drawn.

    Args:
        drops: the drops to draw.
        config: drawing parameters.
        height, width: image size in pixels.

    Returns:
        LensRaster of all (drop, cell) pairs with opacity > 0 inside the grid.
    """
    factor = lens_grid_factor(config, height, width)
    view_height, view_width = lens_view_shape(config, height, width)
    empty = np.zeros(0, dtype=np.int64)
    if len(drops) == 0:
        return LensRaster(empty, empty, empty, empty, empty, view_height, view_width, factor)
    blur = config.lens_defocus_px * image_scale(height, width)
    # per-drop values in float64; per-cell arithmetic in float32 (elementwise, so a cell's value
    # does not depend on which other drops are drawn)
    radius = drops.radius_px
    reach = _reach_px(drops, config, height, width)
    # cells whose centre can be within the reach: |(j + 0.5) k - x| < reach, so the offset
    # o = j - floor(x / k) has |o| < reach / k + 0.5
    half = _half_extent(reach, factor)
    cell_x = np.floor(drops.x_px / factor)
    cell_y = np.floor(drops.y_px / factor)
    # offset of the drop centre from the centre of its cell, in pixels
    shift_x = ((cell_x + 0.5) * factor - drops.x_px).astype(np.float32)
    shift_y = ((cell_y + 0.5) * factor - drops.y_px).astype(np.float32)
    along_x = (drops.cos_angle / reach).astype(np.float32)  # rho in units of the reach
    along_y = (drops.sin_angle / reach).astype(np.float32)
    across_x = (-drops.sin_angle / (reach * drops.aspect)).astype(np.float32)
    across_y = (drops.cos_angle / (reach * drops.aspect)).astype(np.float32)
    small = np.minimum(radius, blur)
    peak = ((small / blur) ** 2 * config.lens_opacity * drops.strength).astype(np.float32)
    edge = (reach / (2.0 * small)).astype(np.float32)  # smoothstep argument = (1 - d / reach) * edge
    inner = (radius / reach).astype(np.float32)  # the drop's edge, in units of the reach
    # the drop's disc shows its field, point-reflected; a drop smaller than the blur shows less
    minification = (config.lens_view_field_px * image_scale(height, width) / np.maximum(radius, blur)).astype(np.float32)
    visible = (peak * ALPHA_UNITS >= 0.5) & (drops.x_px + reach > 0) & (drops.x_px - reach < width) & (drops.y_px + reach > 0) & (drops.y_px - reach < height)
    rim_strength = np.float32(config.lens_rim_darkening)
    view_scale_x = np.float32(view_width / width)
    view_scale_y = np.float32(view_height / height)
    pieces: list[tuple[np.ndarray, ...]] = []
    for half_size in np.unique(half[visible]):
        index = np.flatnonzero((half == half_size) & visible)
        offset_x, offset_y = _stencil(int(half_size))
        cells = offset_x.shape[0]
        dx = shift_x[index][:, None] + (offset_x * factor).astype(np.float32)[None, :]
        dy = shift_y[index][:, None] + (offset_y * factor).astype(np.float32)[None, :]
        along = dx * along_x[index][:, None] + dy * along_y[index][:, None]
        across = dx * across_x[index][:, None] + dy * across_y[index][:, None]
        q_squared = along * along + across * across  # (d / reach)^2
        flat = np.flatnonzero(q_squared < 1.0)
        rows = flat // cells
        columns = flat - rows * cells
        drop_index = index.take(rows)
        gx = cell_x.take(drop_index).astype(np.int64) + offset_x.take(columns)
        gy = cell_y.take(drop_index).astype(np.int64) + offset_y.take(columns)
        on_grid = np.flatnonzero((gx >= 0) & (gx < view_width) & (gy >= 0) & (gy < view_height))
        if on_grid.shape[0] < flat.shape[0]:
            flat, drop_index, gx, gy = flat.take(on_grid), drop_index.take(on_grid), gx.take(on_grid), gy.take(on_grid)
        q = np.sqrt(q_squared.take(flat))
        ramp = np.minimum((np.float32(1.0) - q) * edge.take(drop_index), np.float32(1.0))
        alpha_units = np.rint(peak.take(drop_index) * _smoothstep(ramp) * np.float32(ALPHA_UNITS)).astype(np.int64)
        keep = np.flatnonzero(alpha_units > 0)
        flat, drop_index, alpha_units, q, gx, gy = flat.take(keep), drop_index.take(keep), alpha_units.take(keep), q.take(keep), gx.take(keep), gy.take(keep)
        # the dark rim is blurred with the rest of the drop: it is placed on the blurred footprint
        rim = _smoothstep(np.clip((q - np.float32(0.5)) * np.float32(2.0), np.float32(0.0), np.float32(1.0)))
        shade_units = np.rint((np.float32(1.0) - rim_strength * rim) * np.float32(SHADE_UNITS)).astype(np.int64)
        # cells in the blurred halo outside the drop's edge (rho > 1) see what the edge sees
        step = minification.take(drop_index) / np.maximum(q / inner.take(drop_index), np.float32(1.0))
        source_x = (drops.x_px.take(drop_index) - step * dx.take(flat)) * view_scale_x
        source_y = (drops.y_px.take(drop_index) - step * dy.take(flat)) * view_scale_y
        view_x = np.clip(np.floor(source_x), 0, view_width - 1).astype(np.int64)
        view_y = np.clip(np.floor(source_y), 0, view_height - 1).astype(np.int64)
        pixel = gy * view_width + gx
        pieces.append((pixel, drop_index, alpha_units, shade_units, view_y * view_width + view_x))
    if not pieces:
        return LensRaster(empty, empty, empty, empty, empty, view_height, view_width, factor)
    pixel, drop, alpha_units, shade_units, source = (np.concatenate(column) for column in zip(*pieces))
    order = np.argsort(drop, kind="stable")  # entries ordered by drop: a drop range is a slice
    return LensRaster(pixel[order], drop[order], alpha_units[order], shade_units[order], source[order], view_height, view_width, factor)


def planar_view(view: np.ndarray) -> np.ndarray:
    """(3, h * w) float64 channel planes of a (h, w, 3) uint8 view (for :meth:`LensSums.add`)."""
    return np.ascontiguousarray(view.reshape(-1, 3).T, dtype=np.float64)


@dataclasses.dataclass
class LensSums:
    """Per-cell integer sums over lens-drop entries, dense on the drawing grid.

    Attributes:
        alpha: (h * w,) float64 sum of alpha_units (integer valued, exact).
        alpha_color: (3, h * w) float64 sum of alpha_units * shade_units * view colour per
            channel (integer valued, below 2^53, so exact in any order).
        grid_height, grid_width: the drawing grid (h, w).
        factor: side of a cell in image pixels.
    """

    alpha: np.ndarray
    alpha_color: np.ndarray
    grid_height: int
    grid_width: int
    factor: int

    @classmethod
    def zeros(cls, grid_height: int, grid_width: int, factor: int) -> LensSums:
        """Zero sums on a grid."""
        cells = grid_height * grid_width
        return cls(np.zeros(cells, dtype=np.float64), np.zeros((3, cells), dtype=np.float64), grid_height, grid_width, factor)

    def add(self, raster: LensRaster, view_planes: np.ndarray, entries: slice = slice(None), alpha: bool = True) -> None:
        """Add raster entries (a slice of them) seeing the view ``view_planes`` (from
        :func:`planar_view`); ``alpha=False`` adds the colours only (the alphas are already in)."""
        if view_planes.shape != (3, raster.view_height * raster.view_width):
            raise ValueError(f"view_planes must have shape (3, {raster.view_height * raster.view_width}), got {view_planes.shape}")
        cells = raster.pixel[entries]
        source = raster.source[entries]
        weight = raster.weight[entries]
        n_cells = self.alpha.shape[0]
        if alpha:
            self.alpha += np.bincount(cells, raster.alpha_units[entries].astype(np.float64), minlength=n_cells)
        for channel in range(3):
            self.alpha_color[channel] += np.bincount(cells, weight * view_planes[channel].take(source), minlength=n_cells)


def compress_pixels(pixel: np.ndarray, n_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique pixels and each entry's position among them (used by the physical model's streaks).

    Args:
        pixel: (E,) int64 flat pixel indices in [0, n_pixels).
        n_pixels: number of pixels.

    Returns:
        (unique (P,) int64 ascending, inverse (E,) int64 with unique[inverse] == pixel).
    """
    touched = np.zeros(n_pixels, dtype=bool)
    touched[pixel] = True
    unique = np.flatnonzero(touched)
    lookup = np.zeros(n_pixels, dtype=np.int64)
    lookup[unique] = np.arange(unique.shape[0], dtype=np.int64)
    return unique, lookup[pixel]


def apply_lens(base: np.ndarray, sums: LensSums, workspace: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Composite lens water over an image.

    Per cell: coverage ``c = min(sum alpha / 1024, 1)`` and water colour ``m = sum(alpha shade
    view) / (256 sum alpha)`` (the alpha-weighted mean of the shaded views of the overlapping
    drops). The transmitted fraction
    ``T = round(255 (1 - c))`` and the premultiplied water ``P = round(c m)`` (uint8) are
    upsampled bilinearly to the image (``cv2.resize`` by the cell factor, then cropped), and the
    result is ``round(I T / 255) + P`` (saturated). Order independent, so nested drop sets add up
    consistently; pixels away from water (T = 255, P = 0) keep their value exactly.

    Args:
        base: (H, W, 3) uint8 image under the drops.
        sums: exact sums from :meth:`LensSums.add`.
        workspace: optional dict in which intermediate buffers are kept between calls (one per
            thread; the results never alias them).

    Returns:
        (rgb (H, W, 3) uint8 new array, coverage (H, W) float32 in [0, 1]: ``1 - T / 255`` with
        the upsampled T, the weight the water has in each pixel).
    """
    height, width = base.shape[:2]
    grid_height, grid_width, factor = sums.grid_height, sums.grid_width, sums.factor
    alpha = sums.alpha
    opacity = np.minimum(alpha * (1.0 / ALPHA_UNITS), 1.0)
    gain = opacity / (SHADE_UNITS * np.maximum(alpha, 1.0))  # alpha_color is 0 where alpha is 0
    transmitted = np.rint(255.0 * (1.0 - opacity)).astype(np.uint8).reshape(grid_height, grid_width)
    # c * (alpha-weighted mean colour): a convex combination, at most 255
    water = cv2.merge([np.rint(sums.alpha_color[channel] * gain).astype(np.uint8).reshape(grid_height, grid_width) for channel in range(3)])
    scratch = _Scratch(workspace)
    if factor > 1:
        size = (grid_width * factor, grid_height * factor)
        transmitted = cv2.resize(transmitted, size, dst=scratch.get("transmitted", (size[1], size[0]), 1), interpolation=cv2.INTER_LINEAR)
        water = cv2.resize(water, size, dst=scratch.get("water", (size[1], size[0]), 3), interpolation=cv2.INTER_LINEAR)
    transmitted = transmitted[:height, :width]
    # the coverage is exactly the blend weight of the water: 1 - T / 255
    coverage = np.divide(cv2.bitwise_not(transmitted, dst=scratch.get("inverse", (height, width), 1)), np.float32(255.0), dtype=np.float32)  # exact 0 and 1
    transmitted3 = cv2.cvtColor(transmitted, cv2.COLOR_GRAY2RGB, dst=scratch.get("transmitted3", (height, width), 3))
    kept = cv2.multiply(base, transmitted3, dst=scratch.get("kept", (height, width), 3), scale=1.0 / 255.0)
    out = cv2.add(kept, water[:height, :width])
    return out, coverage


class _Scratch:
    """Reusable uint8 buffers for the intermediates of :func:`apply_lens` (fewer page faults)."""

    def __init__(self, workspace: dict | None) -> None:
        self.workspace = workspace

    def get(self, name: str, shape: tuple[int, int], channels: int) -> np.ndarray | None:
        if self.workspace is None:
            return None
        full = shape + ((channels,) if channels > 1 else ())
        buffer = self.workspace.get(name)
        if buffer is None or buffer.shape != full:
            buffer = self.workspace[name] = np.empty(full, dtype=np.uint8)
        return buffer
