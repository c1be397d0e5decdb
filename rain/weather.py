"""The world under the rain: sky, light, wet road, spray and the camera's response, by rate.

Pure numpy/OpenCV, no MuJoCo: :func:`weather_at` maps (base sky, rain rate) to a
:class:`Weather`, every number of which is a documented law (docs/rain.md, "Weather that follows
the rate"; sources in shared/rain-physics.md section 5). The generator applies the scene part of a
Weather to the MuJoCo model between renders (``rainbench.gen.weather``); the image part is
applied here:

* :func:`sky_colours` -- the sky's colour by elevation (clear: blue gradient; cloud: the CIE
  overcast sky, grey-white, tone-mapped);
* :func:`spray_opacity` -- tyre spray behind moving vehicles, splatted with depth occlusion;
* :func:`camera_response` -- auto-exposure residual and Poissonian-Gaussian sensor noise.

Rate 0 of the base weather is the identity everywhere: the clean render is stored unchanged.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import cv2
import numpy as np

SKIES = ("clear", "cloudy", "overcast")
"""Base weathers a scene may have; the seed paper's CARLA clip was ``cloudy``."""

# -- base weathers --------------------------------------------------------------------------
# Illuminance on the road (lux), typical values (rain-physics.md section 5): direct sun plus sky
# 32 000-100 000 lux; a bright cloudy day ~10 000; an overcast day ~1 000-3 000.
BASE_ILLUMINANCE_LUX = {"clear": 50_000.0, "cloudy": 10_000.0, "overcast": 2_000.0}
BASE_CLOUD_COVER = {"clear": 0.0, "cloudy": 0.8, "overcast": 1.0}
BASE_SUN = {"clear": 1.0, "cloudy": 0.0, "overcast": 0.0}  # direct sun: only under a clear sky
# Displayed zenith luminance of a cloud sky (0..1 of white) before the camera's exposure; the
# overcast sky is a darker grey than the bright cloudy one.
CLOUD_SKY_WHITE = {"clear": 0.97, "cloudy": 0.97, "overcast": 0.82}
CLEAR_SKY_ZENITH = (0.42, 0.62, 0.90)
CLEAR_SKY_HORIZON = (0.88, 0.90, 0.95)
CLOUD_TINT = (0.97, 0.98, 1.0)  # a faint cool cast: overcast daylight is ~6500-7000 K
DISPLAY_GAMMA = 2.2  # camera tone curve applied to the CIE sky luminance

# -- laws of the rate -------------------------------------------------------------------------
RAIN_LUX_AT_1_MM_H = 10_000.0
"""Illuminance under rain clouds: E = 10 000 lux x (1 mm/h / R), so 1 000 lux (an overcast
day) at 10 mm/h and 100 lux (dark rain clouds) at 100 mm/h; never above the base weather's."""
CLOUD_RATE_MM_H = 1.0
"""Cloud cover closes and direct sun fades as exp(-R / 1 mm/h): rain falls from a closed deck."""
WETNESS_RATE_MM_H = 3.0
"""Water film: wetness = 1 - exp(-R / 3 mm/h) (a road is fully wet within minutes of 5 mm/h)."""
PUDDLE_ONSET_MM_H, PUDDLE_FULL_MM_H = 4.0, 40.0
"""Puddles (water standing in ruts and low spots) appear above 4 mm/h and reach full size at
40 mm/h, growing linearly in between (Gallaway et al. 1979: film depth grows with the rate)."""
SPRAY_ONSET_MM_H, SPRAY_FULL_MM_H = 2.0, 40.0
"""Tyre spray needs a water film: none below 2 mm/h, full density from 40 mm/h."""
ROAD_WET_DARKENING = 0.45
"""Wet asphalt reflects ~45 % less diffuse light (Lekner & Dorf 1988: water fills the pores)."""
PAVEMENT_WET_DARKENING = 0.35
GRASS_WET_DARKENING = 0.20
ROAD_FILM_REFLECTANCE = 0.30
ROAD_PUDDLE_REFLECTANCE = 0.12
"""Mirror strength of the road: 0.30 x wetness + 0.12 x puddle fraction, the reflectance at the
reference angle of 80 degrees from the normal (water's Fresnel reflectance there is 0.35). At
other angles it scales with water's Fresnel reflectance (:func:`road_mirror_weight`): a roof
camera sees the road 2.6 m ahead at 60 degrees (0.06: hardly a mirror) and 30 m ahead at 87
degrees (0.69)."""
WATER_INDEX = 1.333
FRESNEL_REFERENCE_DEG = 80.0

# -- camera -----------------------------------------------------------------------------------
AE_REFERENCE_LUX = 50_000.0
AE_REFERENCE_EXPOSURE_S = 1.0 / 1000.0
MAX_EXPOSURE_S = 1.0 / 60.0
AE_RESIDUAL = 0.10
"""Auto-exposure compensates all but 10 % of a change of illuminance in log terms: the image
level follows (E / E_base) ** 0.10, so a 100x darker scene is a 0.63x image, not a 0.01x one.
The total exposure (time x gain) is X = 1/1000 s x (50 000 lux / E) ** 0.9: exposure time first
(up to 1/60 s, the motion-blur limit), then analogue gain."""
NOISE_SIGNAL_DN = 0.02
NOISE_FLOOR_DN2 = 0.06
CHROMA_NOISE_SHARE = 0.15
"""Poissonian-Gaussian sensor noise (Foi et al. 2008), variance a G I + b G^2 in 8-bit units
(I the signal in DN, G the gain). Only the excess over the rate-0 image's own gain is added:
a (G - G0) I + b (G^2 - G0^2), so rate 0 stays the clean render. A camera's ISP suppresses
chroma noise: 85 % of the variance is shared by the three channels (luma noise), 15 % is per
channel."""


@dataclasses.dataclass(frozen=True)
class Weather:
    """The weather of one image. Every field is recorded per rate in the shard (``/weather``).

    Attributes:
        sky: the scene's base weather, one of :data:`SKIES`.
        rain_mm_h: the rain rate in mm/h this weather belongs to (0: the base weather, also for
            every rate when the weather does not follow the rate).
        cloud_cover: 0 (clear) .. 1 (closed overcast).
        sun: direct sun, fraction of the clear-sky sun (0: no hard shadows).
        illuminance_lux: illuminance on the road.
        wetness: 0 (dry) .. 1 (water film everywhere).
        puddle_fraction: 0 (none) .. 1 (full size) of the scene's puddles.
        road_reflectance: mirror reflectance of the road surface.
        spray: 0 .. 1 density of tyre spray.
        exposure_s: camera exposure time in seconds.
        gain: analogue gain (1 = base).
        image_level: mean image level relative to the base weather after auto-exposure (<= 1).
    """

    sky: str
    rain_mm_h: float
    cloud_cover: float
    sun: float
    illuminance_lux: float
    wetness: float
    puddle_fraction: float
    road_reflectance: float
    spray: float
    exposure_s: float
    gain: float
    image_level: float

    def as_record(self) -> dict[str, float]:
        """Numeric fields by name (what the shard stores per rate)."""
        record = dataclasses.asdict(self)
        del record["sky"]
        return record


RECORD_FIELDS = tuple(f.name for f in dataclasses.fields(Weather) if f.name != "sky")


def check_sky(sky: object) -> str:
    if sky not in SKIES:
        raise ValueError(f"SKY: expected one of {', '.join(SKIES)}, got {sky!r}")
    return str(sky)


def _ramp(rate: float, onset: float, full: float) -> float:
    return min(max((rate - onset) / (full - onset), 0.0), 1.0)


def _exposure(illuminance_lux: float) -> tuple[float, float]:
    """(exposure time s, gain) the auto-exposure chooses at ``illuminance_lux``."""
    total = AE_REFERENCE_EXPOSURE_S * (AE_REFERENCE_LUX / illuminance_lux) ** (1.0 - AE_RESIDUAL)
    time_s = min(total, MAX_EXPOSURE_S)
    return time_s, max(total / time_s, 1.0)


def weather_at(sky: str, rate_mm_h: float, follows_rate: bool = True) -> Weather:
    """The weather of a scene whose base weather is ``sky`` when it rains ``rate_mm_h``.

    With ``follows_rate=False`` the base weather is returned whatever the rate (the seed paper's
    method: rain drawn over an unchanged scene). Every field is monotonic in the rate.
    """
    sky = check_sky(sky)
    rate = float(rate_mm_h) if follows_rate else 0.0
    if not (math.isfinite(rate) and rate >= 0):
        raise ValueError(f"rate_mm_h: expected a finite rate >= 0 mm/h, got {rate_mm_h!r}")
    clearing = math.exp(-rate / CLOUD_RATE_MM_H)
    base_lux = BASE_ILLUMINANCE_LUX[sky]
    lux = base_lux if rate == 0 else min(base_lux, RAIN_LUX_AT_1_MM_H / rate)
    # Scene quantities are rounded (cover 1e-6, sun 0.01, wetness 1e-4) so that rates whose scene
    # no longer changes visibly share one render: from 40 mm/h on, only light and camera change.
    wetness = round(1.0 - math.exp(-rate / WETNESS_RATE_MM_H), 4)
    puddles = _ramp(rate, PUDDLE_ONSET_MM_H, PUDDLE_FULL_MM_H)
    exposure_s, gain = _exposure(lux)
    _, base_gain = _exposure(base_lux)
    return Weather(
        sky=sky, rain_mm_h=rate,
        cloud_cover=round(1.0 - (1.0 - BASE_CLOUD_COVER[sky]) * clearing, 6),
        sun=round(BASE_SUN[sky] * clearing, 2), illuminance_lux=lux, wetness=wetness,
        puddle_fraction=puddles,
        road_reflectance=ROAD_FILM_REFLECTANCE * wetness + ROAD_PUDDLE_REFLECTANCE * puddles,
        spray=_ramp(rate, SPRAY_ONSET_MM_H, SPRAY_FULL_MM_H), exposure_s=exposure_s,
        gain=gain / base_gain, image_level=(lux / base_lux) ** AE_RESIDUAL,
    )


def sky_colours(weather: Weather, sin_elevation: np.ndarray) -> np.ndarray:
    """Sky colour (N, 3) float64 in 0..1 for directions with elevation sine ``sin_elevation``.

    Clear: a blue gradient, zenith to horizon. Cloud: the CIE standard overcast sky (sky type 1),
    luminance ``L_z (1 + 2 sin e) / 3`` (the horizon a third of the zenith), grey-white, through
    the camera's 1/2.2 tone curve. The two are blended by ``cloud_cover``. Below the horizon the
    horizon colour is kept.
    """
    sky, cover, closing = sky_key(weather)
    s = np.clip(np.asarray(sin_elevation, dtype=np.float64), 0.0, 1.0)[..., None]
    zenith, horizon = np.asarray(CLEAR_SKY_ZENITH), np.asarray(CLEAR_SKY_HORIZON)
    # the clear gradient is linear in (1 + sin e) / 2 (what MuJoCo's builtin gradient does)
    weight = (1.0 + s) / 2.0
    clear = horizon + (zenith - horizon) * (2.0 * weight - 1.0)
    # under rain the deck closes into the darker grey of an overcast sky
    white = CLOUD_SKY_WHITE[sky] + (CLOUD_SKY_WHITE["overcast"] - CLOUD_SKY_WHITE[sky]) * closing
    cie = ((1.0 + 2.0 * s) / 3.0) ** (1.0 / DISPLAY_GAMMA)
    cloud = white * cie * np.asarray(CLOUD_TINT)
    return np.clip(clear * (1.0 - cover) + cloud * cover, 0.0, 1.0)


def sky_key(weather: Weather) -> tuple[str, float, float]:
    """What the sky's colours depend on: (base sky, cloud cover, how far rain has closed the
    deck), rounded to 1e-6 so that heavy rates, whose sky no longer changes, share one sky."""
    closing = 1.0 - math.exp(-weather.rain_mm_h / CLOUD_RATE_MM_H)
    return weather.sky, weather.cloud_cover, round(closing, 6)


@functools.lru_cache(maxsize=256)
def _mean_sky(weather: Weather) -> tuple[float, float, float]:
    s = np.linspace(0.0, 1.0, 65)  # uniform in sin(elevation) = uniform in solid angle
    return tuple(float(c) for c in sky_colours(weather, s).mean(axis=0) * 255.0)



def mean_sky_rgb(weather: Weather) -> np.ndarray:
    """(3,) float64 0..255: the sky's mean colour over the upper hemisphere (solid-angle mean)."""
    return np.array(_mean_sky(weather))


AIRLIGHT_SIN_ELEVATION = 0.25
"""The airlight of rain extinction, and the uniform rain-cloud deck the renderer draws in sunless
rain, take the sky's colour at 14.5 degrees elevation: the middle of what a level camera sees."""


def airlight_rgb(weather: Weather) -> np.ndarray:
    """(3,) float64 0..255: the colour rain extinction fades towards (the overcast sky's)."""
    return sky_colours(weather, np.array([AIRLIGHT_SIN_ELEVATION]))[0] * 255.0


def water_fresnel(cos_incidence: np.ndarray) -> np.ndarray:
    """Unpolarised Fresnel reflectance of an air-water surface (n = 1.333) for the cosine of the
    angle of incidence (from the normal): the mean of the s and p reflectances."""
    cos_i = np.clip(np.asarray(cos_incidence, dtype=np.float64), 0.0, 1.0)
    sin_t = np.sqrt(1.0 - cos_i ** 2) / WATER_INDEX
    cos_t = np.sqrt(1.0 - sin_t ** 2)
    r_s = (cos_i - WATER_INDEX * cos_t) / (cos_i + WATER_INDEX * cos_t)
    r_p = (cos_t - WATER_INDEX * cos_i) / (cos_t + WATER_INDEX * cos_i)
    return (r_s ** 2 + r_p ** 2) / 2.0


def road_mirror_weight(K: np.ndarray, rotation_world_cam: np.ndarray, height: int, width: int,
                       road_reflectance: float) -> np.ndarray:
    """(H, W) float32 in [0, 1]: how much of the mirror image a horizontal wet road shows at each
    pixel, ``min(1, road_reflectance x F(theta) / F(80 deg))`` with theta the angle between the
    pixel's ray and the road's normal (pixels whose ray does not go down get F(90 deg) = 1,
    harmless: no road is seen there).

    Args:
        K: (3, 3) intrinsics. rotation_world_cam: (3, 3) camera-to-world rotation (OpenCV axes).
    """
    u = (np.arange(width, dtype=np.float64) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(height, dtype=np.float64) + 0.5 - K[1, 2]) / K[1, 1]
    rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((1, 1))), axis=-1)
    world = rays @ np.asarray(rotation_world_cam).T
    cos_incidence = np.abs(world[..., 2]) / np.linalg.norm(world, axis=-1)
    reference = water_fresnel(np.cos(np.radians(FRESNEL_REFERENCE_DEG)))
    weight = road_reflectance * water_fresnel(cos_incidence) / reference
    return np.minimum(weight, 1.0).astype(np.float32)


# -- spray ------------------------------------------------------------------------------------
SPRAY_PARTICLE_RADIUS_M = 0.18
"""A spray particle is a cloud of droplets drawn as a Gaussian of this radius (1 sigma)."""
SPRAY_OPACITY = 0.05
"""Opacity of one particle at full spray density."""
SPRAY_BLUR_SIGMAS_PX = (1.5, 4.0, 10.0, 24.0)
SPRAY_BRIGHTNESS = 0.9
"""Spray is lit by the sky: its colour is 0.9 x the sky's mean colour."""


def spray_opacity(depth: np.ndarray, K: np.ndarray, points_cam: np.ndarray,
                  weights: np.ndarray) -> np.ndarray:
    """Opacity (H, W) float32 in [0, 1] of spray particles seen by a pinhole camera.

    Args:
        depth: (H, W) float depth in metres along the optical axis, +inf for sky.
        K: (3, 3) float64 intrinsics.
        points_cam: (N, 3) float64 particle centres in OpenCV camera coordinates (metres).
        weights: (N,) float64 opacity of each particle (before the blur), >= 0.

    A particle is drawn where it projects inside the image and is in front of the surface seen
    there (``depth >= z``: occluded particles vanish), as a Gaussian whose size in pixels is
    ``fx * SPRAY_PARTICLE_RADIUS_M / z`` (grouped into a few blur layers). Opacities add,
    clipped to 1.
    """
    height, width = depth.shape
    opacity = np.zeros((height, width), np.float32)
    points = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        return opacity
    z = points[:, 2]
    ok = z > 0.3
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(fx * points[:, 0] / z + cx)
        v = np.floor(fy * points[:, 1] / z + cy)
    ok &= (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z, w = u[ok].astype(np.int64), v[ok].astype(np.int64), z[ok], np.asarray(weights)[ok]
    visible = depth[v, u] >= z
    u, v, z, w = u[visible], v[visible], z[visible], w[visible]
    sigma_px = fx * SPRAY_PARTICLE_RADIUS_M / z
    layer = np.abs(np.log(sigma_px[:, None] / np.asarray(SPRAY_BLUR_SIGMAS_PX)[None])).argmin(axis=1)
    for index, sigma in enumerate(SPRAY_BLUR_SIGMAS_PX):
        chosen = layer == index
        if not chosen.any():
            continue
        # a Gaussian of sigma s spreads a unit weight over 2 pi s^2 pixels; weights are the
        # particle's peak opacity, so the splat carries weight x 2 pi s^2
        buffer = np.bincount(v[chosen] * width + u[chosen], w[chosen] * (2 * math.pi * sigma * sigma),
                             minlength=height * width).astype(np.float32).reshape(height, width)
        opacity += cv2.GaussianBlur(buffer, (0, 0), sigmaX=sigma, sigmaY=sigma,
                                    borderType=cv2.BORDER_CONSTANT)
    np.minimum(opacity, np.float32(1.0), out=opacity)
    return opacity


def composite_spray(rgb: np.ndarray, opacity: np.ndarray, colour_rgb: np.ndarray) -> np.ndarray:
    """``rgb + opacity (colour - rgb)``, rounded: spray lit by the sky. Returns a new array."""
    if not opacity.any():
        return rgb.copy()
    base = rgb.astype(np.float32)
    out = base + opacity[..., None] * (np.asarray(colour_rgb, np.float32)[None, None] - base)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def noise_field(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float32 unit-variance noise: luma noise shared by the channels plus
    :data:`CHROMA_NOISE_SHARE` of the variance per channel."""
    shared = rng.standard_normal((height, width, 1), dtype=np.float32)
    per_channel = rng.standard_normal((height, width, 3), dtype=np.float32)
    return (np.float32(math.sqrt(1 - CHROMA_NOISE_SHARE)) * shared
            + np.float32(math.sqrt(CHROMA_NOISE_SHARE)) * per_channel)


# -- camera response --------------------------------------------------------------------------
def camera_response(rgb: np.ndarray, weather: Weather, noise: np.ndarray | None) -> np.ndarray:
    """Auto-exposure residual and sensor noise of ``weather`` applied to ``rgb``; a new array.

    Args:
        rgb: (H, W, 3) uint8 image as rendered at the base weather's exposure.
        weather: gives ``image_level`` and ``gain``.
        noise: (H, W, 3) float32 unit-variance noise field from :func:`noise_field` (the
            frame's, shared by all rates, so the noise of one frame is the same pattern scaled
            by each rate's gain), or None.

    Returns:
        (H, W, 3) uint8: ``I' = level I + n sqrt(a (G - 1) level I + b (G^2 - 1))``, rounded and
        clipped. Identity when level = G = 1.
    """
    if weather.image_level == 1.0 and weather.gain == 1.0:
        return rgb.copy()
    signal = rgb.astype(np.float32) * np.float32(weather.image_level)
    if noise is not None and weather.gain > 1.0:
        gain = np.float32(weather.gain)
        variance = (np.float32(NOISE_SIGNAL_DN) * (gain - 1) * signal
                    + np.float32(NOISE_FLOOR_DN2) * (gain * gain - 1))
        signal += noise * np.sqrt(variance)
    return np.clip(np.rint(signal), 0, 255).astype(np.uint8)
