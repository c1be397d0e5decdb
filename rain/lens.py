"""Water drops on the lens: the jeon2022 model (seed paper eq. 5) and the physical model's option.

A lens drop is a small, out-of-focus water lens stuck to the lens or its cover glass. It is
drawn as a soft-edged ellipse that shows a blurred, point-reflected (flipped) and minified view
of the scene around it, darkened towards its rim (after Roser & Geiger 2009 and the darkened
rims of ROLE; see docs/rain.md for every choice and its reason).

Nesting: the drops of one frame form one fixed sequence, generated in blocks of
:data:`LENS_BLOCK` drops from per-block child seeds; a rate uses the first ``N(rate)`` drops,
so a higher rate always contains every drop of a lower one, unchanged.

Exact accumulation: per-pixel opacities and colours are integers (alpha in 1/1024 steps,
colours 0..255), so their sums are exact in float64 in any order. This lets
``render_rain_sweep`` add drops rate by rate and still match single-rate calls byte for byte.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from rainbench.rain._seeding import STREAM_LENS, child_generator
from rainbench.rain.config import RainConfig

REFERENCE_HEIGHT = 600
REFERENCE_WIDTH = 800
REFERENCE_AREA = REFERENCE_HEIGHT * REFERENCE_WIDTH
"""Eq. 5 counts are for an 800x600 image; other sizes scale the count by area."""

EQ5_SLOPE_MM_H = 0.03
EQ5_OFFSET_MM_H = 3.88
"""Seed paper eq. 5: rate = 0.03 * N + 3.88 (rate in mm/h, N drops on 800x600)."""

LENS_BLOCK = 512
"""Drops are generated in blocks of this size; block b has its own child seed."""

ALPHA_UNITS = 1024
"""Opacity quantum: per-pixel alpha is an integer number of 1/1024 steps."""

SHADE_UNITS = 256
"""Rim shading quantum: shade factor is an integer number of 1/256 steps."""

_UNIFORM_COLUMNS = 5  # x, y, radius, aspect, angle


def image_scale(height: int, width: int) -> float:
    """Linear size of an image relative to 800x600: ``sqrt(H * W / (800 * 600))``."""
    return math.sqrt(height * width / REFERENCE_AREA)


def _round_half_up(value: float) -> int:
    return int(math.floor(value + 0.5))


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
    count_800x600 = _round_half_up((rate_mm_h - EQ5_OFFSET_MM_H) / EQ5_SLOPE_MM_H)
    if height * width == REFERENCE_AREA:
        return count_800x600
    return _round_half_up(count_800x600 * (height * width) / REFERENCE_AREA)


@dataclasses.dataclass(frozen=True)
class LensDrops:
    """A sequence of lens drops; all arrays have shape (N,) and dtype float64.

    Image coordinates are continuous pixel units: pixel column i spans [i, i + 1).

    Attributes:
        x_px, y_px: drop centre in pixels.
        radius_px: semi-major axis in pixels.
        aspect: minor/major axis ratio in (0, 1].
        cos_angle, sin_angle: direction of the major axis.
    """

    x_px: np.ndarray
    y_px: np.ndarray
    radius_px: np.ndarray
    aspect: np.ndarray
    cos_angle: np.ndarray
    sin_angle: np.ndarray

    def __len__(self) -> int:
        return int(self.x_px.shape[0])

    def head(self, count: int) -> LensDrops:
        """The first ``count`` drops (the drops of a lower rate)."""
        return LensDrops(*(getattr(self, f.name)[:count] for f in dataclasses.fields(self)))

    def as_array(self) -> np.ndarray:
        """(N, 6) float64 array of the fields in declaration order (for comparisons in tests)."""
        return np.stack([getattr(self, f.name) for f in dataclasses.fields(self)], axis=1)


def empty_lens_drops() -> LensDrops:
    """A LensDrops with zero drops."""
    empty = np.zeros(0, dtype=np.float64)
    return LensDrops(empty, empty, empty, empty, empty, empty)


def lens_drops_from_uniforms(uniforms: np.ndarray, *, config: RainConfig, height: int, width: int) -> LensDrops:
    """Turn uniform variates into lens drops (pure inverse-CDF transforms).

    Args:
        uniforms: (N, 5) float64 in [0, 1): columns x, y, radius, aspect, angle.
        config: radius range/exponent and aspect range are read from it.
        height, width: image size in pixels.

    Returns:
        LensDrops with N drops: centre uniform over the image; radius from the truncated power
        law ``p(r) ~ r^-exponent`` on [r_min, r_max] * image_scale; aspect uniform in
        [aspect_min, 1]; angle uniform in [0, pi).
    """
    scale = image_scale(height, width)
    r_min = config.lens_radius_min_px * scale
    r_max = config.lens_radius_max_px * scale
    exponent = config.lens_radius_exponent
    u_radius = uniforms[:, 2]
    if r_max == r_min:
        radius = np.full(u_radius.shape, r_min)
    elif abs(exponent - 1.0) < 1e-12:
        radius = r_min * (r_max / r_min) ** u_radius
    else:
        power = 1.0 - exponent
        low, high = r_min**power, r_max**power
        radius = (low + u_radius * (high - low)) ** (1.0 / power)
    angle = np.pi * uniforms[:, 4]
    return LensDrops(
        x_px=uniforms[:, 0] * width,
        y_px=uniforms[:, 1] * height,
        radius_px=radius,
        aspect=1.0 - (1.0 - config.lens_aspect_min) * uniforms[:, 3],
        cos_angle=np.cos(angle),
        sin_angle=np.sin(angle),
    )


def sample_lens_drops(count: int, *, config: RainConfig, height: int, width: int, seed_sequence: np.random.SeedSequence) -> LensDrops:
    """The first ``count`` drops of the frame's fixed lens-drop sequence.

    Block b (drops ``512 b .. 512 b + 511``) is drawn from its own generator
    ``child_generator(seed_sequence, STREAM_LENS, b)`` and transformed as a whole block, so
    drop i is identical whatever ``count`` is asked for: ``sample_lens_drops(n)`` is a prefix of
    ``sample_lens_drops(m)`` for n <= m.

    Args:
        count: number of drops, >= 0.
        config, height, width: as for :func:`lens_drops_from_uniforms`.
        seed_sequence: the frame's SeedSequence (not mutated).

    Returns:
        LensDrops with ``count`` drops.
    """
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    if count == 0:
        return empty_lens_drops()
    blocks = []
    for block in range(-(-count // LENS_BLOCK)):
        rng = child_generator(seed_sequence, STREAM_LENS, block)
        uniforms = rng.random((LENS_BLOCK, _UNIFORM_COLUMNS))
        blocks.append(lens_drops_from_uniforms(uniforms, config=config, height=height, width=width))
    fields = [f.name for f in dataclasses.fields(LensDrops)]
    joined = LensDrops(*(np.concatenate([getattr(b, name) for b in blocks]) for name in fields))
    return joined.head(count)


@dataclasses.dataclass(frozen=True)
class LensRaster:
    """The pixels touched by a set of lens drops; every array has shape (E,), one entry per
    (drop, pixel) pair with non-zero opacity, ordered by drop. Independent of the image content.

    Attributes:
        pixel: int64 flat pixel index ``y * W + x``.
        drop: int64 index of the drop in its LensDrops.
        alpha_units: int64 opacity in 1/1024 steps, 1..1024.
        shade_units: int64 rim shading in 1/256 steps (256 = no darkening).
        source: int64 flat index into the low-resolution view image (see :func:`lens_view`).
        view_height, view_width: size of the view image.
    """

    pixel: np.ndarray
    drop: np.ndarray
    alpha_units: np.ndarray
    shade_units: np.ndarray
    source: np.ndarray
    view_height: int
    view_width: int


def _view_factor(config: RainConfig, height: int, width: int) -> int:
    return max(1, int(round(config.lens_view_blur_px * image_scale(height, width))))


def lens_view_shape(config: RainConfig, height: int, width: int) -> tuple[int, int]:
    """(h, w) of the blurred view image seen through lens drops: the frame box-averaged by
    ``round(lens_view_blur_px * image_scale)`` pixels."""
    factor = _view_factor(config, height, width)
    return max(1, -(-height // factor)), max(1, -(-width // factor))


def lens_view(rgb: np.ndarray, config: RainConfig) -> np.ndarray:
    """The blurred scene that lens drops refract.

    Args:
        rgb: (H, W, 3) uint8 image.
        config: gives ``lens_view_blur_px``.

    Returns:
        (h, w, 3) uint8, the image area-averaged down to :func:`lens_view_shape`.
    """
    height, width = rgb.shape[:2]
    view_height, view_width = lens_view_shape(config, height, width)
    if (view_height, view_width) == (height, width):
        return rgb.copy()
    return cv2.resize(rgb, (view_width, view_height), interpolation=cv2.INTER_AREA)


def _smoothstep(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def rasterize_lens_drops(drops: LensDrops, *, config: RainConfig, height: int, width: int) -> LensRaster:
    """Footprints of lens drops: opacity, rim shade and the flipped view position per pixel.

    For a pixel centre p and a drop with centre c, radius r, aspect a and major-axis angle t:
    ``rho = |R(-t) (p - c) / (r, a r)|`` (1 on the drop edge); opacity
    ``smoothstep(clip((1 - rho) / s, 0, 1))`` with ``s = max(lens_edge_softness, 1 px / r)``;
    shade ``1 - lens_rim_darkening * smoothstep(clip((rho - 0.5) / 0.5, 0, 1))``; the pixel shows
    the view image at ``c - lens_view_scale * (p - c)`` (point reflection, minified).

    Only arithmetic and sqrt act on per-pixel values, and every per-drop value comes from
    :class:`LensDrops`, so a drop's footprint does not depend on which other drops are drawn.

    Args:
        drops: the drops to draw.
        config: drawing parameters.
        height, width: image size in pixels.

    Returns:
        LensRaster of all (drop, pixel) pairs with opacity > 0 inside the image.
    """
    view_height, view_width = lens_view_shape(config, height, width)
    if len(drops) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return LensRaster(empty, empty, empty, empty, empty, view_height, view_width)
    # a pixel can only be inside if |px + 0.5 - cx| <= r, i.e. px - floor(cx) in [-h, h - 1]
    half = np.ceil(drops.radius_px + 0.5).astype(np.int64)
    half = np.where(half > 5, half + (half + 1) % 2, half)  # above 5 px, odd sizes only: fewer groups
    x_floor = np.floor(drops.x_px)
    y_floor = np.floor(drops.y_px)
    # per-drop constants of the ellipse test
    along_x = drops.cos_angle / drops.radius_px
    along_y = drops.sin_angle / drops.radius_px
    across_x = -drops.sin_angle / (drops.radius_px * drops.aspect)
    across_y = drops.cos_angle / (drops.radius_px * drops.aspect)
    inverse_softness = 1.0 / np.maximum(config.lens_edge_softness, 1.0 / drops.radius_px)
    pieces: list[tuple[np.ndarray, ...]] = []
    for half_size in np.unique(half):
        index = np.flatnonzero(half == half_size)
        side = 2 * int(half_size)
        offsets = np.arange(-half_size, half_size, dtype=np.float64)
        offset_x = np.tile(offsets, side)  # (side * side,), row-major cells
        offset_y = np.repeat(offsets, side)
        # pixel-centre offsets from the drop centre, (n, side * side)
        dx = (x_floor[index] + 0.5 - drops.x_px[index])[:, None] + offset_x[None, :]
        dy = (y_floor[index] + 0.5 - drops.y_px[index])[:, None] + offset_y[None, :]
        along = dx * along_x[index][:, None] + dy * along_y[index][:, None]
        across = dx * across_x[index][:, None] + dy * across_y[index][:, None]
        rho_squared = along * along + across * across
        px = x_floor[index][:, None] + offset_x[None, :]
        py = y_floor[index][:, None] + offset_y[None, :]
        inside = (rho_squared < 1.0) & (px >= 0) & (px < width) & (py >= 0) & (py < height)
        flat = np.flatnonzero(inside)
        rows = flat // (side * side)
        rho = np.sqrt(rho_squared.take(flat))
        drop_index = index.take(rows)
        alpha = _smoothstep(np.minimum((1.0 - rho) * inverse_softness.take(drop_index), 1.0))
        alpha_units = np.rint(alpha * ALPHA_UNITS).astype(np.int64)
        keep = np.flatnonzero(alpha_units > 0)
        flat, rho, drop_index, alpha_units = flat.take(keep), rho.take(keep), drop_index.take(keep), alpha_units.take(keep)
        rim = _smoothstep(np.clip((rho - 0.5) * 2.0, 0.0, 1.0))
        shade_units = np.rint((1.0 - config.lens_rim_darkening * rim) * SHADE_UNITS).astype(np.int64)
        source_x = drops.x_px.take(drop_index) - config.lens_view_scale * dx.take(flat)
        source_y = drops.y_px.take(drop_index) - config.lens_view_scale * dy.take(flat)
        view_x = np.clip(np.floor(source_x * (view_width / width)).astype(np.int64), 0, view_width - 1)
        view_y = np.clip(np.floor(source_y * (view_height / height)).astype(np.int64), 0, view_height - 1)
        pixel = (py.take(flat) * width + px.take(flat)).astype(np.int64)
        pieces.append((pixel, drop_index, alpha_units, shade_units, view_y * view_width + view_x))
    pixel, drop, alpha_units, shade_units, source = (np.concatenate(column) for column in zip(*pieces))
    order = np.argsort(drop, kind="stable")  # entries ordered by drop: a drop range is a slice
    return LensRaster(pixel[order], drop[order], alpha_units[order], shade_units[order], source[order], view_height, view_width)


def lens_colors(raster: LensRaster, view: np.ndarray, entries: slice | np.ndarray | None = None) -> np.ndarray:
    """Colour of each raster entry: the view pixel times the rim shade, rounded to integers.

    Args:
        raster: footprints from :func:`rasterize_lens_drops`.
        view: (h, w, 3) uint8 from :func:`lens_view`.
        entries: optional slice or (E,) bool mask selecting entries.

    Returns:
        (E', 3) int64 colours in 0..255 for the selected entries.
    """
    if view.shape[:2] != (raster.view_height, raster.view_width):
        raise ValueError(f"view must have shape ({raster.view_height}, {raster.view_width}, 3), got {view.shape}")
    source = raster.source if entries is None else raster.source[entries]
    shade = raster.shade_units if entries is None else raster.shade_units[entries]
    seen = view.reshape(-1, 3).take(source, axis=0).astype(np.int64)
    return (seen * shade[:, None] + SHADE_UNITS // 2) // SHADE_UNITS


@dataclasses.dataclass
class LensSums:
    """Per-pixel integer sums over lens-drop entries, on a compressed pixel set.

    Attributes:
        pixels: (P,) int64 flat pixel indices that any entry may touch.
        alpha: (P,) float64 sum of alpha_units (integer valued, exact).
        alpha_color: (P, 3) float64 sum of alpha_units * colour (integer valued, exact).
    """

    pixels: np.ndarray
    alpha: np.ndarray
    alpha_color: np.ndarray


def compress_pixels(pixel: np.ndarray, n_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique pixels and each entry's position among them.

    Args:
        pixel: (E,) int64 flat pixel indices in [0, n_pixels).
        n_pixels: H * W.

    Returns:
        (unique (P,) int64 ascending, inverse (E,) int64 with unique[inverse] == pixel).
    """
    touched = np.zeros(n_pixels, dtype=bool)
    touched[pixel] = True
    unique = np.flatnonzero(touched)
    lookup = np.zeros(n_pixels, dtype=np.int64)
    lookup[unique] = np.arange(unique.shape[0], dtype=np.int64)
    return unique, lookup[pixel]


def accumulate_lens(inverse: np.ndarray, alpha_units: np.ndarray, colors: np.ndarray, n_unique: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact per-pixel sums of alpha and alpha * colour.

    Args:
        inverse: (E,) int64 compressed pixel position of each entry.
        alpha_units: (E,) int64.
        colors: (E, 3) int64.
        n_unique: number of compressed pixels P.

    Returns:
        (alpha (P,) float64, alpha_color (P, 3) float64), both integer valued.
    """
    weights = alpha_units.astype(np.float64)
    alpha = np.bincount(inverse, weights, minlength=n_unique)
    alpha_color = np.empty((n_unique, 3), dtype=np.float64)
    for channel in range(3):
        alpha_color[:, channel] = np.bincount(inverse, weights * colors[:, channel], minlength=n_unique)
    return alpha, alpha_color


def apply_lens(base: np.ndarray, sums: LensSums) -> tuple[np.ndarray, np.ndarray]:
    """Composite lens water over an image.

    Per pixel: coverage ``c = min(sum alpha / 1024, 1)``, drop colour ``m = sum(alpha colour) /
    sum alpha`` (alpha-weighted mean of the overlapping drops), result ``round(I + c (m - I))``.
    Order independent, so nested drop sets add up consistently.

    Args:
        base: (H, W, 3) uint8 image under the drops.
        sums: exact sums from :func:`accumulate_lens`.

    Returns:
        (rgb (H, W, 3) uint8 new array, coverage (H, W) float32 in [0, 1]).
    """
    height, width = base.shape[:2]
    out = base.copy()
    coverage = np.zeros((height, width), dtype=np.float32)
    update_lens(out, coverage, base, sums, np.flatnonzero(sums.alpha > 0))
    return out, coverage


def update_lens(out: np.ndarray, coverage: np.ndarray, base: np.ndarray, sums: LensSums, index: np.ndarray) -> None:
    """Recompute the composite of :func:`apply_lens` in place at some compressed pixels.

    Args:
        out: (H, W, 3) uint8 image to write into.
        coverage: (H, W) float32 coverage to write into.
        base: (H, W, 3) uint8 image under the drops.
        sums: exact sums.
        index: (K,) int64 positions into ``sums.pixels`` with ``sums.alpha > 0``.
    """
    if index.shape[0] == 0:
        return
    pixels = sums.pixels[index]
    alpha = sums.alpha[index]
    opacity = np.minimum(alpha * (1.0 / ALPHA_UNITS), 1.0).astype(np.float32)
    under = base.reshape(-1, 3).take(pixels, axis=0).astype(np.float32)
    mix = (sums.alpha_color[index] / alpha[:, None]).astype(np.float32)
    # a convex combination of values in 0..255, so no clipping is needed
    out.reshape(-1, 3)[pixels] = np.rint(under + opacity[:, None] * (mix - under)).astype(np.uint8)
    coverage.reshape(-1)[pixels] = opacity
