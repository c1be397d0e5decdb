"""The world under the rain: sky, light, wet road, spray and the camera's response, by rate.

Pure numpy/OpenCV, no MuJoCo: :func:`weather_at` maps (base sky, rain rate) to a
:class:`Weather`, every number of which is a documented law (docs/rain.md, "Weather that follows
the rate"; sources in docs/rain-physics.md section 5). The generator applies the scene part of a
Weather to the MuJoCo model between renders (``rainbench.gen.weather``); the image part is
applied here:

* :func:`sky_colours` -- the sky's colour by elevation (clear: blue gradient; cloud: the CIE
  overcast sky, grey-white, tone-mapped);
* :func:`spray_opacity` -- tyre spray behind moving vehicles, splatted with depth occlusion;
* :func:`road_mirror_weight` and :func:`puddle_coverage` -- how much of the mirror render the wet
  road and its puddles show per pixel (Fresnel), and where the puddles lie in the image;
  :func:`plane_pixels` -- which pixels show the road (the mirror is blended there only);
* :func:`streak_reflection` -- the wet film's and the rippled puddles' mirror, smeared along the
  vertical (:func:`film_streak_sigma_px`, :func:`puddle_ripple_slope`);
* :func:`camera_response` -- auto-exposure residual and Poissonian-Gaussian sensor noise.

Every weather has a time of day (:data:`TIMES_OF_DAY`): dusk and night lower the daylight, add
street lights, and the auto-exposure recovers part of the loss up to its limits (docs/rain.md,
"Time of day"); :func:`display_light` turns a light level in lux into the renderer's light units.

Rate 0 of the base weather is the identity by day: the clean render is stored unchanged. At dusk
and night the base weather's own gain is above the daytime one, so its sensor noise is not zero.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import cv2
import numpy as np

from rainbench.rain.physical import extinction_coefficient
from rainbench.rain.tone import DISPLAY_LIGHT_GAMMA, linear_value, to_display, to_linear

SKIES = ("clear", "cloudy", "overcast")
"""Base weathers a scene may have; the seed paper's CARLA clip was ``cloudy``."""
TIMES_OF_DAY = ("day", "dusk", "night")
"""Times of day a scene may have; every law below is the daytime one unless it says otherwise."""

# -- base weathers --------------------------------------------------------------------------
# Illuminance on the road (lux), typical values (docs/rain-physics.md section 5): direct sun plus sky
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
# Dusk sky (display values at the dusk exposure): a deep blue zenith over a warm band low down
# (clear), a dimmer blue-grey cloud deck warming towards the horizon (cloud).
DUSK_CLEAR_ZENITH = (0.24, 0.33, 0.58)
DUSK_CLEAR_HORIZON = (0.96, 0.62, 0.40)
DUSK_BAND_EXPONENT = 0.45  # the warm band hugs the horizon
DUSK_CLOUD_LEVEL = 0.62  # the dusk deck is darker than the noon deck, after auto-exposure
DUSK_CLOUD_HORIZON_TINT = (1.0, 0.84, 0.70)
DUSK_CLOUD_ZENITH_TINT = (0.78, 0.83, 1.0)
# Night sky: near black, a brown-grey city glow at the horizon (clear) or over the whole deck,
# brightest low (cloud: clouds reflect the city's light; Kyba et al. 2011).
NIGHT_CLEAR_ZENITH = (0.010, 0.012, 0.022)
NIGHT_GLOW_HORIZON = (0.13, 0.10, 0.075)
NIGHT_GLOW_SIN_ELEVATION = 0.12  # the glow fades over the lowest ~7 degrees
NIGHT_CLOUD = (0.075, 0.064, 0.056)
NIGHT_CLOUD_HORIZON_GAIN = 0.6
NIGHT_CLOUD_GLOW_SIN_ELEVATION = 0.25
# Clouds drawn from a scene's cloud field (ranks 0..1, uniform over the field): the sky's
# ``cloud_cover`` is the fraction of it under cloud, the texels of the highest ranks.
CLOUD_EDGE_RANKS = 0.08  # feathered cloud edges, in ranks
CLOUD_SHADE = 0.12  # a cloud's thickest parts (rank 1) are 12 % darker, its thinnest lighter
CLOUD_FADE_SIN_ELEVATION = 0.12  # the clouds' structure fades into the haze below ~7 degrees
CLOUD_BASE_M = 1500.0
"""Height of the layer the sky's clouds lie on: cumulus and stratocumulus bases lie at about
0.5-2 km. The skybox is at infinity, so the clouds show no parallax as the camera moves."""
CLOUD_TILE_M = 20_000.0
"""Width of one tile of the scene's cloud field on that layer (78 m a texel of a 256 px tile)."""
# A cloudy sky hides the sun (BASE_SUN), so its gaps are not open sky: a thin high veil
# (altostratus translucidus) pales the blue between the clouds by this share of the cloud's colour.
GAP_VEIL = {"clear": 0.0, "cloudy": 0.6, "overcast": 0.0}

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
"""Wet asphalt reflects ~45 % less diffuse light (Lekner & Dorf 1988: water fills the pores).
A share of the light, not of the display value: :func:`wet_display_factor`."""
PAVEMENT_WET_DARKENING = 0.35
GRASS_WET_DARKENING = 0.20


def wet_display_factor(darkening: float, wetness: float) -> float:
    """The factor on a surface material's colour that makes it reflect ``darkening x wetness``
    less light: ``(1 - darkening x wetness)^(1 / 2.2)``. The renderer's output is a display
    value, proportional to the material colour, so the light's share goes through the tone
    curve (asphalt fully wet: 0.55 of the light, 0.76 of the display value; 0.55 of the display
    value would be 0.27 of the light, until 2026-11-27)."""
    return (1.0 - float(darkening) * float(wetness)) ** (1.0 / DISPLAY_LIGHT_GAMMA)
ROAD_FILM_REFLECTANCE = 0.30
ROAD_PUDDLE_REFLECTANCE = 0.12
"""Mirror strength of the road: 0.30 x wetness + 0.12 x puddle fraction, the reflectance at the
reference angle of 80 degrees from the normal (water's Fresnel reflectance there is 0.35). At
other angles it scales with water's Fresnel reflectance (:func:`road_mirror_weight`): a roof
camera sees the road 2.6 m ahead at 60 degrees (0.06: hardly a mirror) and 30 m ahead at 87
degrees (0.72)."""
ROAD_FILM_SLOPE_RAD = 0.02
"""RMS slope of the wet film's surface, asphalt's texture showing through a thin film. A facet
tilted by d in the plane of incidence turns the mirrored ray by 2 d, one tilted across it by only
2 d sin(e), e the ray's angle below the horizon: at the grazing angles a road is seen at, the
film's reflection is smeared along the image's vertical ~1 / sin(e) times more than across it
(the streaks under lights on a wet road). The vertical spread is kept (Gaussian sigma 2 x 0.02 x
the focal length in pixels: 16 px at 800x600 and 90 degrees), the horizontal one (under 1.5 px
beyond 5 degrees) left out. The slope is chosen for the look: no measurement of it was found.
Puddles are smeared by their rain ripples instead (:func:`puddle_ripple_slope`)."""
CLIPPED_LEVEL = 250
"""A mirror pixel with a channel at or above this 8-bit level is clipped: a lamp, a head or tail
light or a glint, whose true radiance is unknown and far above 255."""
CLIPPED_GAIN = 8.0
"""When the lamps and head and tail lights are on (dusk, night, and the vehicle lamps by day in
dark rain), clipped mirror pixels count this many times brighter in the film's smear, so the
streak of a light on a wet road stays bright where smearing its clipped value would fade it to a
glow (the streak is clipped to 255 again after blending). With the lights off the gain is 1.
Only the mirror images of the lamps are boosted (:func:`mirrored_light_pixels`): a surface lit
past the sensor's range (a light car body under a street lamp) clips as well, and boosting it
would lay a saturated block on the road. Chosen for the look."""
WATER_INDEX = 1.333
FRESNEL_REFERENCE_DEG = 80.0

# -- time of day ------------------------------------------------------------------------------
DUSK_DAYLIGHT_LUX = {"clear": 700.0, "cloudy": 300.0, "overcast": 150.0}
"""Daylight (sun + sky) on the road at dusk, the sun a few degrees above the horizon: 400 lux at
sunset under a clear sky (Wikipedia, "Lux"), more while the sun is still up, less under cloud
(the low sun's direct share is small, so cloud takes less away than at noon). Under rain the
deck is closed whatever the base sky, so the rain takes the overcast dusk's share of the rainy
day's light: dusk light = min(this, daytime light at the rate x 150 / 2 000) (0.075, the
overcast dusk over the overcast noon), the same for every base sky once it rains hard enough
(as the daytime rain law): 30 lux at 25 mm/h, 7.5 lux at 100 mm/h."""
DUSK_SUN_ELEVATION_DEG = 4.0
"""The dusk sun is near the horizon: 4 degrees up (long shadows; light through 14 air masses is
orange)."""
NIGHT_SKY_LUX = {"clear": 0.05, "cloudy": 0.1, "overcast": 0.2}
"""Sky light on the road at night, no moon: the urban sky glow. A clear city sky gives a few
hundredths of a lux; clouds reflect the city's light back down and brighten it several times
(Kyba et al. 2011, PLoS ONE 6(3) e17307). Starlight alone is ~0.001 lux."""
STREET_LIGHT_LUX = 15.0
"""Mean illuminance of a lit urban street (EN 13201-2 class C3 / P1: 15 lux, overall uniformity
>= 0.4), on at dusk and at night. What the camera's auto-exposure meters after dark."""
STRAY_LIGHT_LUX = 0.5
"""Light that street lights, shop windows and other cars spill everywhere (inter-reflections,
the lamps the renderer does not draw as light sources): the floor of the night ambient."""
# DISPLAY_LIGHT_GAMMA (rainbench.rain.tone): the tone curve of :func:`display_light` and of every
# mix of light done here.


def check_time_of_day(time_of_day: object) -> str:
    if time_of_day not in TIMES_OF_DAY:
        raise ValueError(f"time_of_day: expected one of {', '.join(TIMES_OF_DAY)}, got "
                         f"{time_of_day!r}")
    return str(time_of_day)


def _light_sources(sky: str, time_of_day: str, daytime_lux: float) -> tuple[float, float]:
    """(daylight lux, street light lux) at ``time_of_day`` when the daytime light would be
    ``daytime_lux`` (the daytime rain law of ``sky``)."""
    if time_of_day == "day":
        return daytime_lux, 0.0
    if time_of_day == "dusk":
        under_deck = daytime_lux * DUSK_DAYLIGHT_LUX["overcast"] / BASE_ILLUMINANCE_LUX["overcast"]
        return min(DUSK_DAYLIGHT_LUX[sky], under_deck), STREET_LIGHT_LUX
    return NIGHT_SKY_LUX[sky], STREET_LIGHT_LUX


# -- camera -----------------------------------------------------------------------------------
AE_REFERENCE_LUX = 50_000.0
AE_REFERENCE_EXPOSURE_S = 1.0 / 1000.0
MAX_EXPOSURE_S = 1.0 / 60.0
AE_RESIDUAL = 0.10
"""Auto-exposure compensates all but 10 % of a change of illuminance in log terms: the image
level follows (E / E_base) ** 0.10, so a 100x darker scene is a 0.63x image, not a 0.01x one.
The total exposure (time x gain) is X = 1/1000 s x (50 000 lux / E) ** 0.9: exposure time first
(up to 1/60 s, the motion-blur limit), then analogue gain."""
MAX_GAIN = 32.0
"""The most analogue gain the camera has (30 dB, a typical automotive sensor's analogue range);
beyond it the image darkens with the light. Never reached by day (at most 16x, at 100 mm/h)."""
LOW_LIGHT_MAX_EXPOSURE_S = 1.0 / 30.0
"""At dusk and night the camera trades motion blur for signal: its exposure time may grow to the
frame time of a 30 frame/s stream (by day it stops at :data:`MAX_EXPOSURE_S`)."""
NOISE_SIGNAL_DN = 0.02
NOISE_FLOOR_DN2 = 0.06
CHROMA_NOISE_SHARE = 0.15
"""Poissonian-Gaussian sensor noise (Foi et al. 2008), variance a G I + b G^2 in 8-bit units
(I the signal in DN, G the gain). Only the excess over the rate-0 image's own gain is added:
a (G - G0) I + b (G^2 - G0^2), so rate 0 stays the clean render. A camera's ISP suppresses
chroma noise: 85 % of the variance is shared by the three channels (luma noise), 15 % is per
channel."""
ISP_NOISE_REDUCTION = 0.45
"""The camera's noise reduction (an automotive ISP denoises in space and over frames) leaves
this fraction of the sensor noise's standard deviation in its output image: 5.2 DN at mid-grey
at the night's 32x gain instead of the sensor's 11.6. Chosen for the look (the output of a
denoised night camera, fine grain rather than snow); no particular camera was measured."""
ISP_NOISE_SIGMA_PX = 0.7
"""What the noise reduction leaves is grain a pixel or two across, not independent pixels: the
noise field is smoothed by a Gaussian of this sigma (pixels) and scaled back to unit variance."""


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
        gain: analogue gain relative to the sky's daytime base weather (1 by day at rate 0; above
            1 at dusk and night): drives the sensor noise.
        image_level: mean image level relative to the base weather (same sky and time of day)
            after auto-exposure (<= 1), applied to the render by :func:`camera_response`.
        time_of_day: one of :data:`TIMES_OF_DAY`.
        daylight_lux: the sun and sky's part of ``illuminance_lux`` (the city sky glow at night).
        street_light_lux: the street lights' part of ``illuminance_lux`` (0 by day).
        light_level: image level of the base weather (same sky and time of day) relative to the
            sky's daytime base, built into the render's lights and sky (1 by day).
        noise_dn: standard deviation in 8-bit units of the sensor noise :func:`camera_response`
            adds where its output is mid-grey (118), at this weather's gain.
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
    time_of_day: str = "day"
    daylight_lux: float = 0.0
    street_light_lux: float = 0.0
    light_level: float = 1.0
    noise_dn: float = 0.0

    def as_record(self) -> dict[str, float]:
        """Numeric fields by name (what the shard stores per rate)."""
        record = dataclasses.asdict(self)
        del record["sky"], record["time_of_day"]
        return record


RECORD_FIELDS = tuple(f.name for f in dataclasses.fields(Weather)
                      if f.name not in ("sky", "time_of_day"))
MID_GREY_DN = 118.0
"""An 18 % grey card in 8-bit display units (the usual 118 of an sRGB camera; 0.18^(1/2.2) x 255 is
117): where :attr:`Weather.noise_dn` is measured."""


def check_sky(sky: object) -> str:
    if sky not in SKIES:
        raise ValueError(f"SKY: expected one of {', '.join(SKIES)}, got {sky!r}")
    return str(sky)


def _ramp(rate: float, onset: float, full: float) -> float:
    return min(max((rate - onset) / (full - onset), 0.0), 1.0)


def _exposure(illuminance_lux: float, max_time_s: float = MAX_EXPOSURE_S
              ) -> tuple[float, float, float]:
    """(exposure time s, gain, shortfall) the auto-exposure chooses at ``illuminance_lux``.

    The total exposure ``X = 1/1000 s x (50 000 lux / E)^0.9`` is reached with the exposure time
    first (up to ``max_time_s``), then gain up to :data:`MAX_GAIN`; ``shortfall`` is the part of
    X reached (1 unless the gain is at its limit).
    """
    total = AE_REFERENCE_EXPOSURE_S * (AE_REFERENCE_LUX / illuminance_lux) ** (1.0 - AE_RESIDUAL)
    time_s = min(total, max_time_s)
    gain = max(total / time_s, 1.0)
    if gain <= MAX_GAIN:
        return time_s, gain, 1.0
    return time_s, MAX_GAIN, MAX_GAIN / gain


def _metered_lux(sky: str, time_of_day: str, rate: float) -> tuple[float, float]:
    """(daylight lux, street light lux) of ``sky`` at ``time_of_day`` under ``rate`` mm/h."""
    base_lux = BASE_ILLUMINANCE_LUX[sky]
    daytime = base_lux if rate == 0 else min(base_lux, RAIN_LUX_AT_1_MM_H / rate)
    return _light_sources(sky, time_of_day, daytime)


def weather_at(sky: str, rate_mm_h: float, follows_rate: bool = True,
               time_of_day: str = "day") -> Weather:
    """The weather of a scene whose base weather is ``sky`` at ``time_of_day`` when it rains
    ``rate_mm_h``.

    With ``follows_rate=False`` the base weather is returned whatever the rate (the seed paper's
    method: rain drawn over an unchanged scene). Every field is monotonic in the rate. By day the
    values are those of the daytime laws alone (docs/rain.md, "Weather that follows the rate");
    dusk and night change the light and the camera (docs/rain.md, "Time of day").
    """
    sky = check_sky(sky)
    time_of_day = check_time_of_day(time_of_day)
    rate = float(rate_mm_h)  # checked whether or not the weather follows it
    if not (math.isfinite(rate) and rate >= 0):
        raise ValueError(f"rate_mm_h: expected a finite rate >= 0 mm/h, got {rate_mm_h!r}")
    rate = rate if follows_rate else 0.0
    clearing = math.exp(-rate / CLOUD_RATE_MM_H)
    day_base_lux = BASE_ILLUMINANCE_LUX[sky]
    daylight, street = _metered_lux(sky, time_of_day, rate)
    lux = daylight + street
    base_lux = sum(_metered_lux(sky, time_of_day, 0.0))
    max_time = MAX_EXPOSURE_S if time_of_day == "day" else LOW_LIGHT_MAX_EXPOSURE_S
    # Scene quantities are rounded (cover 1e-6, sun 0.01, wetness 1e-4) so that rates whose scene
    # no longer changes visibly share one render: from 40 mm/h on, only light and camera change.
    wetness = round(1.0 - math.exp(-rate / WETNESS_RATE_MM_H), 4)
    puddles = _ramp(rate, PUDDLE_ONSET_MM_H, PUDDLE_FULL_MM_H)
    exposure_s, gain, shortfall = _exposure(lux, max_time)
    _, _, base_shortfall = _exposure(base_lux, max_time)
    _, day_gain, _ = _exposure(day_base_lux)
    # image level (display values) = (E / E0)^0.1 while the gain is below its limit: the AE law
    # is set on the display level (docs/rain.md). X, which sets exposure time, gain and noise,
    # leaves the signal E X at (E / E0)^0.1 too, not the (E / E0)^0.22 that the 2.2 tone curve
    # would make of a display level of (E / E0)^0.1: a simplification, kept (gains up to 16x
    # by day at 100 mm/h where a signal-consistent X would give 7.6x).
    image_level = (lux / base_lux) ** AE_RESIDUAL * (shortfall / base_shortfall)
    light_level = 1.0 if time_of_day == "day" else (
        (base_lux / day_base_lux) ** AE_RESIDUAL * base_shortfall)
    relative_gain = gain / day_gain
    noise = ISP_NOISE_REDUCTION * math.sqrt(NOISE_SIGNAL_DN * (relative_gain - 1.0) * MID_GREY_DN
                                            + NOISE_FLOOR_DN2 * (relative_gain ** 2 - 1.0))
    return Weather(
        sky=sky, rain_mm_h=rate,
        cloud_cover=round(1.0 - (1.0 - BASE_CLOUD_COVER[sky]) * clearing, 6),
        sun=0.0 if time_of_day == "night" else round(BASE_SUN[sky] * clearing, 2),
        illuminance_lux=lux, wetness=wetness, puddle_fraction=puddles,
        road_reflectance=ROAD_FILM_REFLECTANCE * wetness + ROAD_PUDDLE_REFLECTANCE * puddles,
        spray=_ramp(rate, SPRAY_ONSET_MM_H, SPRAY_FULL_MM_H), exposure_s=exposure_s,
        gain=relative_gain, image_level=image_level, time_of_day=time_of_day,
        daylight_lux=daylight, street_light_lux=street, light_level=light_level,
        noise_dn=noise,
    )


def display_light(weather: Weather, lux: float) -> float:
    """Display level, in the renderer's light units (1 = the light on a horizontal surface in the
    daytime base weather), of a surface lit by ``lux`` under ``weather``, before the camera's
    ``image_level``: ``light_level x (lux / E)^(1 / 2.2)``, E the light the camera meters in this
    weather (``illuminance_lux``).

    The renderer adds lights linearly in display values, so each light source is given its own
    tone-mapped level (exact for one source, a fair approximation where two overlap). E is the
    base weather's own at rate 0, by day and at night (where rain leaves the street lights as
    they are); at dusk rain takes daylight away, the camera exposes for less light and the lamps
    gain on the fading day (:func:`daylight_level`).
    """
    return weather.light_level * (max(float(lux), 0.0) / weather.illuminance_lux) ** (
        1.0 / DISPLAY_LIGHT_GAMMA)


def daylight_level(weather: Weather) -> float:
    """Display level of the daylight (sun, sky light, ambient and the sky itself) in the render of
    ``weather``, before the camera's ``image_level``: ``light_level`` times how much the
    daylight's share of the metered light has changed from the base weather's, through the tone
    curve, ``((D / E) / (D0 / E0))^(1 / 2.2)``.

    1 by day (daylight is all the light), ``light_level`` at night (rain changes neither part);
    at dusk under rain below ``light_level``: 0.84 x at 25 mm/h under a clear sky, where 30 lux
    of daylight is left beside 15 lux of street light.
    """
    base_daylight, base_street = _metered_lux(weather.sky, weather.time_of_day, 0.0)
    if weather.daylight_lux <= 0.0 or base_daylight <= 0.0:
        return weather.light_level
    share = weather.daylight_lux / weather.illuminance_lux
    base_share = base_daylight / (base_daylight + base_street)
    return weather.light_level * (share / base_share) ** (1.0 / DISPLAY_LIGHT_GAMMA)


def cloud_cover_and_shade(cover: float, cloud_ranks: np.ndarray | None,
                          sin_elevation: np.ndarray, edge_ranks: np.ndarray | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Where the clouds are: (N, 1) float64 each ``(share under cloud 0..1, brightness factor of
    that cloud)`` for directions of elevation sine ``sin_elevation`` (N,) whose cloud field
    reads ``cloud_ranks`` (N,) in 0..1.

    About a fraction ``cover`` of the field is under cloud, the highest ranks, with edges
    feathered over ``edge_ranks`` (N,) (e; None: ``CLOUD_EDGE_RANKS`` everywhere; a skybox
    passes wider ramps where its texels step further in rank,
    :func:`rainbench.gen.weather.skybox_edge_ranks`, so that no edge is sharper than the texels
    can draw): cover 0 leaves no cloud, cover 1 no gap; between, the mean share is ``cover + e
    (cover - 1/2)`` where the ramp lies inside the ranks (0.824 for the cloudy sky's 0.8 and the
    default e), fading to ``cover`` itself towards the horizon. Within the cloud the thickest
    parts are darker, the thinnest lighter (``1 +- CLOUD_SHADE``: the grey bases of a closed
    deck). Low down, where the layer's cells shrink below what the sky texture resolves, both
    fade into their means (``cover`` and 1) with the haze, over ``CLOUD_FADE_SIN_ELEVATION``.
    ``cloud_ranks`` None: the mean sky, ``(cover, 1)`` everywhere.
    """
    s = np.clip(np.asarray(sin_elevation, dtype=np.float64), 0.0, 1.0)[..., None]
    if cloud_ranks is None:
        return np.full_like(s, cover), np.ones_like(s)
    ranks = np.asarray(cloud_ranks, dtype=np.float64)[..., None]
    if ranks.shape != s.shape:
        raise ValueError(f"cloud_ranks: expected shape {s.shape[:-1]}, got {ranks.shape[:-1]}")
    if edge_ranks is None:
        edge = CLOUD_EDGE_RANKS
    else:
        edge = np.asarray(edge_ranks, dtype=np.float64)[..., None]
        if edge.shape != s.shape or not np.all(edge > 0.0):
            raise ValueError(f"edge_ranks: expected shape {s.shape[:-1]} of positive widths, "
                             f"got {edge.shape[:-1]}, least {edge.min(initial=np.inf):g}")
    fade = np.clip(s / CLOUD_FADE_SIN_ELEVATION, 0.0, 1.0)
    lower = (1.0 - cover) * (1.0 + edge) - edge
    under = np.clip((ranks - lower) / edge, 0.0, 1.0)
    share = cover + (under - cover) * fade
    shade = 1.0 + CLOUD_SHADE * (1.0 - 2.0 * ranks) * fade
    return share, shade


def sky_colours(weather: Weather, sin_elevation: np.ndarray,
                cloud_ranks: np.ndarray | None = None,
                edge_ranks: np.ndarray | None = None) -> np.ndarray:
    """Sky colour (N, 3) float64 in 0..1 for directions with elevation sine ``sin_elevation``.

    Day: clear, a blue gradient, zenith to horizon; cloud, the CIE standard overcast sky (sky type
    1), luminance ``L_z (1 + 2 sin e) / 3`` (the horizon a third of the zenith), grey-white,
    through the camera's 1/2.2 tone curve. The two are blended by ``cloud_cover``. Dusk: a deep
    blue zenith over a warm horizon band (clear) and a dimmer blue-grey CIE sky warming towards the
    horizon (cloud). Night: near black, with the city's brown-grey glow at the horizon (clear) or
    over the whole cloud deck, brightest low. Below the horizon the horizon colour is kept.

    ``cloud_ranks`` (N,) in 0..1: each direction's rank in the scene's cloud field; the clear and
    the cloud sky are then mixed texel by texel (:func:`cloud_cover_and_shade`: clouds and gaps)
    rather than blended by ``cloud_cover`` everywhere, with cloud edges feathered over
    ``edge_ranks`` (N,) (None: ``CLOUD_EDGE_RANKS``). ``cloud_ranks`` None: the mean sky of that
    blend.
    """
    sky, cover, closing, time_of_day, dimming = sky_key(weather)
    s = np.clip(np.asarray(sin_elevation, dtype=np.float64), 0.0, 1.0)[..., None]
    share, shade = cloud_cover_and_shade(cover, cloud_ranks, sin_elevation, edge_ranks)
    if time_of_day == "night":
        clear = (np.asarray(NIGHT_CLEAR_ZENITH)
                 + np.asarray(NIGHT_GLOW_HORIZON) * np.exp(-s / NIGHT_GLOW_SIN_ELEVATION))
        cloud = np.asarray(NIGHT_CLOUD) * (1.0 + NIGHT_CLOUD_HORIZON_GAIN
                                           * np.exp(-s / NIGHT_CLOUD_GLOW_SIN_ELEVATION))
        return _mix_sky(clear, cloud, share, shade, GAP_VEIL[sky])
    white = CLOUD_SKY_WHITE[sky] + (CLOUD_SKY_WHITE["overcast"] - CLOUD_SKY_WHITE[sky]) * closing
    cie = ((1.0 + 2.0 * s) / 3.0) ** (1.0 / DISPLAY_GAMMA)
    if time_of_day == "dusk":
        band = s ** DUSK_BAND_EXPONENT  # 0 at the horizon, 1 at the zenith; warm low down
        clear = (np.asarray(DUSK_CLEAR_HORIZON)
                 + (np.asarray(DUSK_CLEAR_ZENITH) - np.asarray(DUSK_CLEAR_HORIZON)) * band)
        tint = (np.asarray(DUSK_CLOUD_HORIZON_TINT)
                + (np.asarray(DUSK_CLOUD_ZENITH_TINT) - np.asarray(DUSK_CLOUD_HORIZON_TINT)) * band)
        cloud = DUSK_CLOUD_LEVEL * white * cie * tint
        return _mix_sky(clear, cloud, share, shade, GAP_VEIL[sky], dimming)
    zenith, horizon = np.asarray(CLEAR_SKY_ZENITH), np.asarray(CLEAR_SKY_HORIZON)
    # the clear gradient is linear in sin e
    weight = (1.0 + s) / 2.0
    clear = horizon + (zenith - horizon) * (2.0 * weight - 1.0)
    # under rain the deck closes into the darker grey of an overcast sky
    cloud = white * cie * np.asarray(CLOUD_TINT)
    return _mix_sky(clear, cloud, share, shade, GAP_VEIL[sky])


def _mix_sky(clear, cloud, share, shade, veil: float, dimming: float = 1.0) -> np.ndarray:
    """The clear sky (veiled by ``veil`` of the cloud's colour) where there is no cloud, the
    cloud shaded by ``shade`` over a share ``share``; clipped to 0..1."""
    gaps = clear + (cloud - clear) * veil if veil else clear
    return np.clip((gaps * (1.0 - share) + cloud * shade * share) * dimming, 0.0, 1.0)


def sky_key(weather: Weather) -> tuple[str, float, float, str, float]:
    """What the sky's colours depend on: (base sky, cloud cover, how far rain has closed the
    deck, time of day, the daylight's dimming ``daylight_level / light_level``: below 1 only at
    dusk under rain), rounded to 1e-6 so that heavy rates, whose sky no longer changes, share
    one sky."""
    closing = 1.0 - math.exp(-weather.rain_mm_h / CLOUD_RATE_MM_H)
    dimming = daylight_level(weather) / weather.light_level
    return (weather.sky, weather.cloud_cover, round(closing, 6), weather.time_of_day,
            round(dimming, 6))


@functools.lru_cache(maxsize=256)
def _mean_sky(weather: Weather) -> tuple[float, float, float]:
    s = np.linspace(0.0, 1.0, 65)  # uniform in sin(elevation) = uniform in solid angle
    return tuple(float(c) for c in sky_colours(weather, s).mean(axis=0) * 255.0)



def mean_sky_rgb(weather: Weather) -> np.ndarray:
    """(3,) float64 0..255: the sky's mean colour over the upper hemisphere (solid-angle mean)."""
    return np.array(_mean_sky(weather))


AIRLIGHT_SIN_ELEVATION = 0.25
"""The airlight of rain extinction, and the uniform rain-cloud deck the renderer draws in the wet
road's mirror, take the sky's colour at 14.5 degrees elevation: the middle of what a level camera sees."""


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
    pixel's ray and the road's normal (a pixel whose ray does not go down gets the F of its
    mirrored ray's angle: harmless, no road is seen there).

    Args:
        K: (3, 3) intrinsics. rotation_world_cam: (3, 3) camera-to-world rotation (OpenCV axes).
    """
    u = (np.arange(width, dtype=np.float64) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(height, dtype=np.float64) + 0.5 - K[1, 2]) / K[1, 1]
    up = np.asarray(rotation_world_cam, np.float64)[2]  # only the rays' world z matters
    world_z = u[None, :] * up[0] + v[:, None] * up[1] + up[2]
    cos_incidence = np.abs(world_z) / np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
    reference = water_fresnel(np.cos(np.radians(FRESNEL_REFERENCE_DEG)))
    weight = road_reflectance * water_fresnel(cos_incidence) / reference
    return np.minimum(weight, 1.0).astype(np.float32)


RIPPLE_MIN_DROP_MM = 1.0
"""Drops from 1 mm raise the rings seen on a puddle (smaller ones barely dimple it)."""
RIPPLE_SPEED_M_S = 0.23
RIPPLE_WAVELENGTH_M = 0.017
"""A ring spreads at the minimum phase speed of capillary-gravity waves on water, 0.23 m/s at a
wavelength of 1.7 cm (the waves a drop's impact sends out are near it)."""
RIPPLE_LIFETIME_S = 0.25
"""A ring fades over about a quarter of a second (it has spread ~6 cm)."""
RIPPLE_SLOPE = 0.05
"""RMS slope of a puddle's surface once its rings overlap (chosen for the look: ring waves ~0.15
mm high over 1.7 cm slope ~0.05)."""


def ripple_impacts_per_m2_s(rate_mm_h: float) -> float:
    """Drops of :data:`RIPPLE_MIN_DROP_MM` and more landing on a square metre each second:
    the Marshall-Palmer number density times the Atlas et al. (1973) fall speed, integrated,
    ``N0 [a e^(-L D) / L - b e^(-(L + c) D) / (L + c)]`` with N0 = 8 000 m^-3 mm^-1, L =
    4.1 R^-0.21 mm^-1, a = 9.65 m/s, b = 10.3 m/s, c = 0.6 mm^-1 and D = 1 mm (0 at rate 0)."""
    from rainbench.rain import physical  # noqa: PLC0415 -- the drop laws live there

    if rate_mm_h <= 0:
        return 0.0
    slope = physical.marshall_palmer_slope(rate_mm_h)
    fast = physical.VELOCITY_MAX_M_S * math.exp(-slope * RIPPLE_MIN_DROP_MM) / slope
    decay = slope + physical.VELOCITY_RATE_PER_MM
    slow = physical.VELOCITY_COEF_M_S * math.exp(-decay * RIPPLE_MIN_DROP_MM) / decay
    return physical.MP_N0_PER_M3_MM * (fast - slow)


def puddle_ripple_slope(rate_mm_h: float) -> float:
    """RMS slope of a puddle's surface under rain of ``rate_mm_h``: :data:`RIPPLE_SLOPE` times
    the square root of the share of the surface the live rings cover (capped at 1): impacts per
    m^2 and second x lifetime x a ring's area at half its life (2 pi r x one wavelength, r the
    distance spread in half the lifetime): about half the surface at 4 mm/h, where puddles
    appear, all of it from about 10 mm/h."""
    radius = RIPPLE_SPEED_M_S * RIPPLE_LIFETIME_S / 2.0
    covered = (ripple_impacts_per_m2_s(rate_mm_h) * RIPPLE_LIFETIME_S
               * 2.0 * math.pi * radius * RIPPLE_WAVELENGTH_M)
    return RIPPLE_SLOPE * math.sqrt(min(1.0, covered))


def film_streak_sigma_px(focal_px: float) -> float:
    """Vertical Gaussian sigma in pixels of the wet film's reflection for a camera of focal
    length ``focal_px`` (pixels): ``2 x ROAD_FILM_SLOPE_RAD x focal_px``."""
    return 2.0 * ROAD_FILM_SLOPE_RAD * float(focal_px)


def streak_reflection(mirror: np.ndarray, road: np.ndarray, sigma_px: float,
                      clipped_gain: float = 1.0, lights: np.ndarray | None = None) -> np.ndarray:
    """(h, w, 3) float32: ``mirror`` smeared along the image's vertical by a Gaussian of
    ``sigma_px`` rows, averaging over the road only, so nothing off it (cars, kerbs, the sky) is
    smeared in; where no road is near the mirror is kept. Clipped pixels (a channel at or
    above :data:`CLIPPED_LEVEL`) among ``lights`` weigh ``clipped_gain`` times their value
    (:data:`CLIPPED_GAIN` at dusk and night), so the result may exceed 255.

    Args:
        mirror: (h, w, 3) uint8 or float, the mirror render.
        road: (h, w) float in [0, 1], how much of each pixel shows the mirrored road
            (:func:`plane_pixels`, resized to ``mirror``'s size).
        sigma_px: the Gaussian's standard deviation in rows of ``mirror`` (0: no smear).
        clipped_gain: the weight of clipped light pixels (1: none).
        lights: (h, w) bool, where the mirror shows lights (:func:`mirrored_light_pixels`);
            None: every clipped pixel is a light.
    """
    mirror = np.asarray(mirror, np.float32)
    if sigma_px <= 0:
        return mirror.copy()
    road = np.asarray(road, np.float32)
    radiance = mirror
    if clipped_gain != 1.0:
        boosted = mirror.max(axis=-1) >= CLIPPED_LEVEL
        if lights is not None:
            if np.shape(lights) != boosted.shape:
                raise ValueError(f"lights: expected shape {boosted.shape}, got {np.shape(lights)}")
            boosted &= np.asarray(lights, bool)
        radiance = np.where(boosted[..., None], mirror * np.float32(clipped_gain), mirror)
    radius = max(1, int(math.ceil(3.0 * sigma_px)))
    rows = np.arange(-radius, radius + 1, dtype=np.float32)
    kernel = np.exp(-0.5 * (rows / np.float32(sigma_px)) ** 2)
    kernel /= kernel.sum()
    one = np.ones(1, np.float32)
    weighted = cv2.sepFilter2D(radiance * road[..., None], -1, one, kernel,
                               borderType=cv2.BORDER_REPLICATE)
    norm = cv2.sepFilter2D(road, -1, one, kernel, borderType=cv2.BORDER_REPLICATE)
    out = mirror.copy()
    np.divide(weighted, norm[..., None], out=out, where=(norm > 1e-3)[..., None])
    return out


_BOX_CORNERS = np.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)
                         for sz in (-1.0, 1.0)])


def mirrored_light_pixels(K: np.ndarray, pose_world_cam: np.ndarray, spheres: np.ndarray,
                          plane_z: float, height: int, width: int,
                          boxes: np.ndarray | None = None) -> np.ndarray:
    """(height, width) bool: where a level water plane at ``plane_z`` shows the mirror images of
    light sources, each reflected through the plane (z -> 2 plane_z - z) and projected: a box
    lamp as the convex hull of its 8 corners (its footprint), any other as a disc of its
    bounding sphere's projected radius plus one pixel. Lamps behind the camera are left out.
    Streaks are boosted here only (:data:`CLIPPED_GAIN`).

    The disc of a vehicle's flat lamp box covered 3-4 times the lamp, and the car body around
    it where that clipped too (a pink car at night: its mirror streaked brighter than the car,
    a visual audit of seed 14 at the junction); the hull covers the lamp.

    Args:
        K: (3, 3) intrinsics. pose_world_cam: (4, 4) T_world_cam, OpenCV axes.
        spheres: (N, 4) float ``(x, y, z, radius)`` in metres, world frame: each lamp geom's
            centre and bounding radius.
        plane_z: the water's height in metres.
        boxes: None, or (N, 15) float: each lamp's box as its centre (3), rotation (9, row-major,
            world from box axes) and half sizes (3), metres; a row of NaN for a lamp that is not
            a box (drawn as its sphere's disc).
    """
    spheres = np.asarray(spheres, np.float64).reshape(-1, 4)
    if boxes is None:
        boxes = np.full((spheres.shape[0], 15), np.nan)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 15)
    if boxes.shape[0] != spheres.shape[0]:
        raise ValueError(f"boxes: expected one row per sphere ({spheres.shape[0]}), got {boxes.shape[0]}")
    mask = np.zeros((height, width), np.uint8)
    flip = np.array([1.0, 1.0, -1.0])
    rotation, origin = pose_world_cam[:3, :3], pose_world_cam[:3, 3]

    def to_camera(world: np.ndarray) -> np.ndarray:
        """Rows of R^T (p - t) of the mirror images of the world points ``world`` (M, 3)."""
        return (world * flip + [0.0, 0.0, 2.0 * plane_z] - origin) @ rotation

    for sphere, box in zip(spheres, boxes):
        if not np.isnan(box).any():
            corners = box[:3] + (_BOX_CORNERS * box[12:15]) @ box[3:12].reshape(3, 3).T
            points = to_camera(corners)
            if (points[:, 2] <= 1e-3).any():
                continue  # a corner at or behind the camera: its image is not a polygon
            pixels = np.column_stack([K[0, 0] * points[:, 0] / points[:, 2] + K[0, 2],
                                      K[1, 1] * points[:, 1] / points[:, 2] + K[1, 2]])
            hull = cv2.convexHull(np.round(pixels - 0.5).astype(np.int32))
            cv2.fillConvexPoly(mask, hull, 1)
            continue
        x, y, z = to_camera(sphere[None, :3])[0]
        if z <= 1e-3:
            continue
        u = K[0, 0] * x / z + K[0, 2]
        v = K[1, 1] * y / z + K[1, 2]
        pixels = K[0, 0] * sphere[3] / z + 1.0
        if -pixels <= u <= width + pixels and -pixels <= v <= height + pixels:
            cv2.circle(mask, (int(round(u)), int(round(v))), int(math.ceil(pixels)), 1, -1)
    return mask.astype(bool)


def plane_pixels(K: np.ndarray, pose_world_cam: np.ndarray, depth: np.ndarray,
                 rectangles: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels that show any of ``rectangles``, level rectangles on one plane (the
    tops of a road's slabs): where the pixel's ray meets the plane inside a rectangle (to half a
    pixel at its edges: the rectangles' images are filled as polygons) and ``depth`` is the
    plane's (within :data:`PUDDLE_ON_ROAD_TOLERANCE`), so whatever stands on or over the road
    (cars, people, kerbs, an overpass) and the sky are False.

    The wet road's mirror is blended only here: off the road the mirror render is the plain
    scene at half size, and blending it there would blur actors and buildings.

    Args:
        K: (3, 3) intrinsics. pose_world_cam: (4, 4) T_world_cam, OpenCV axes.
        depth: (H, W) float metres along the optical axis, +inf where no geometry is.
        rectangles: (N, 6) or (6,) float, each ``(x, y, z, half_length, half_width, yaw)``:
            centre in world metres (z the plane's height, the same for all), half sides in
            metres (inf: unbounded), yaw in radians about +z.
    """
    rectangles = np.asarray(rectangles, np.float64).reshape(-1, 6)
    height, width = depth.shape
    if not len(rectangles):
        return np.zeros((height, width), bool)
    z = float(rectangles[0, 2])
    if np.ptp(rectangles[:, 2]) > 1e-6:
        raise ValueError(f"rectangles: expected one plane, got heights "
                         f"{rectangles[:, 2].min():.6g} to {rectangles[:, 2].max():.6g} m")
    rotation, origin = np.asarray(pose_world_cam, np.float64)[:3, :3], pose_world_cam[:3, 3]
    u = ((np.arange(width, dtype=np.float64) + 0.5 - K[0, 2]) / K[0, 0]).astype(np.float32)
    v = ((np.arange(height, dtype=np.float64) + 0.5 - K[1, 2]) / K[1, 1]).astype(np.float32)
    mask = np.zeros((height, width), bool)
    # rows some ray of which goes down (the camera's z row of the rotation; float64 bound)
    lowest = (min(u[0] * rotation[2, 0], u[-1] * rotation[2, 0])
              + v.astype(np.float64) * rotation[2, 1] + rotation[2, 2])
    below = np.flatnonzero(lowest < -1e-6)
    if not below.size:
        return mask
    first, last = int(below[0]), int(below[-1]) + 1
    v = v[first:last]
    ray_z = (u[None, :] * np.float32(rotation[2, 0])
             + (v[:, None] * np.float32(rotation[2, 1]) + np.float32(rotation[2, 2])))
    down = ray_z < -1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        along = np.float32(z - origin[2]) / np.where(down, ray_z, np.float32(-1.0))
    shown = down & (along > 0) & _on_plane(depth[first:last], along)
    if np.isinf(rectangles[:, 3:5]).any():  # a plane unbounded along a side: all of it
        mask[first:last] = shown
        return mask
    # the rectangles' images, filled as polygons (clipped at 5 cm in front of the camera) at
    # 1/16 px: the pixels whose centres lie inside one, to half a pixel at its edges
    inside = np.zeros((height, width), np.uint8)
    for x, y, _, half_length, half_width, yaw in rectangles:
        along_axis = np.array([math.cos(yaw), math.sin(yaw), 0.0]) * half_length
        across_axis = np.array([-math.sin(yaw), math.cos(yaw), 0.0]) * half_width
        centre = np.array([x, y, z])
        corners = np.array([centre + along_axis + across_axis, centre + along_axis - across_axis,
                            centre - along_axis - across_axis, centre - along_axis + across_axis])
        camera = _clip_near((corners - origin) @ rotation, 0.05)
        if len(camera) < 3:
            continue
        pixels = np.column_stack([K[0, 0] * camera[:, 0] / camera[:, 2] + K[0, 2] - 0.5,
                                  K[1, 1] * camera[:, 1] / camera[:, 2] + K[1, 2] - 0.5])
        pixels = np.clip(pixels, -1e6, 1e6)  # int32 at 1/16 px; reached only edge-on
        cv2.fillPoly(inside, [np.rint(pixels * 16).astype(np.int32)], 1, lineType=cv2.LINE_8,
                     shift=4)
    mask[first:last] = shown & inside[first:last].astype(bool)
    return mask


# -- puddles ----------------------------------------------------------------------------------
PUDDLE_MIRROR_REFLECTANCE = float(water_fresnel(math.cos(math.radians(FRESNEL_REFERENCE_DEG))))
"""A puddle's mirror strength at the 80 degree reference angle: water's own Fresnel reflectance
there (0.35), so that :func:`road_mirror_weight` gives a puddle water's reflectance F(theta) at
every angle (0.06 at 60 degrees, 0.13 at 70, 0.35 at 80, 0.58 at 85), which
:func:`puddle_water` blends in linear light: standing water is a smooth mirror, neither more
nor less."""
PUDDLE_UNDERLAY = 0.8
"""What a puddle transmits of the wet road beneath it, as a factor on its display value (0.61 of
its light): the road under standing water, seen through it, is a little darker than the wet
film around it (light lost at the two surfaces)."""
PUDDLE_OUTLINE = ((2, 0.14), (3, 0.09), (5, 0.05))
"""(harmonic, amplitude) of each puddle's outline: its radius, relative to the ellipse, is
``1 + sum(a_k sin(k phi + phase_k))`` with phases drawn per puddle, so no two are the same blob
and none is a plain ellipse (a puddle fills a rut or a low spot, not a drawn curve)."""
PUDDLE_EDGE = 0.22
"""Width of a puddle's soft edge, relative to its radius: water thins to a wet film over about a
fifth of the radius (a hard edge looked like a painted disc)."""
PUDDLE_ON_ROAD_TOLERANCE = 0.01
"""A pixel shows the road plane when its depth is within 1 % (+ 2 cm) of where its ray meets the
plane: cars, people and kerbs in front of a puddle hide it."""
PUDDLE_ON_ROAD_SLACK_M = 0.02
"""The 2 cm added to :data:`PUDDLE_ON_ROAD_TOLERANCE` (depth-buffer precision near the camera)."""


def _on_plane(seen: np.ndarray, along: np.ndarray) -> np.ndarray:
    """Where the depth ``seen`` is the depth ``along`` at which each pixel's ray meets a plane,
    within :data:`PUDDLE_ON_ROAD_TOLERANCE` (+ 2 cm): the pixel shows that plane (same shapes,
    float32 or float64)."""
    tolerance = along.dtype.type(PUDDLE_ON_ROAD_TOLERANCE)
    return np.abs(seen - along) <= tolerance * along + along.dtype.type(PUDDLE_ON_ROAD_SLACK_M)


PUDDLE_OUTLINE_SEED = 0x9D
"""Seed of the outline phases: puddle ``i`` draws from ``default_rng([PUDDLE_OUTLINE_SEED, i])``,
so its shape is a function of the scene alone (the exported scene.xml renders the same)."""


def puddle_outline_phases(count: int) -> np.ndarray:
    """(count, len(PUDDLE_OUTLINE)) float64 phases in [0, 2 pi) of each puddle's outline."""
    return np.array([np.random.default_rng([PUDDLE_OUTLINE_SEED, index])
                     .uniform(0.0, 2.0 * math.pi, len(PUDDLE_OUTLINE)) for index in range(count)],
                    np.float64).reshape(count, len(PUDDLE_OUTLINE))


def _clip_near(points: np.ndarray, near: float) -> np.ndarray:
    """The part of the convex polygon ``points`` ((N, 3) camera coordinates, in order) with
    z >= ``near`` (Sutherland-Hodgman against one plane); (M, 3), M = 0 when none is."""
    kept = []
    for index in range(len(points)):
        p, q = points[index], points[(index + 1) % len(points)]
        if p[2] >= near:
            kept.append(p)
        if (p[2] >= near) != (q[2] >= near):
            kept.append(p + (near - p[2]) / (q[2] - p[2]) * (q - p))
    return np.array(kept, np.float64).reshape(-1, 3)


def _ground_window(K: np.ndarray, pose: np.ndarray, centre: np.ndarray, half: float,
                   height: int, width: int) -> tuple[int, int, int, int] | None:
    """Pixel rows and columns (r0, r1, c0, c1) holding the image of the level square of
    half-side ``half`` metres around world point ``centre`` (3,), or None when none of it is
    in view."""
    corners = centre + np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0],
                                 [-half, half, 0]], np.float64)
    camera = (corners - pose[:3, 3]) @ pose[:3, :3]
    visible = _clip_near(camera, 1e-3)
    if not len(visible):
        return None
    u = K[0, 0] * visible[:, 0] / visible[:, 2] + K[0, 2]
    v = K[1, 1] * visible[:, 1] / visible[:, 2] + K[1, 2]
    c0, c1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())) + 1, width)
    r0, r1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())) + 1, height)
    return (r0, r1, c0, c1) if r0 < r1 and c0 < c1 else None


@dataclasses.dataclass(frozen=True)
class PuddlePixels:
    """Where a frame's puddles can lie at full size (:func:`puddle_pixels`): per puddle, the
    pixels ``rows``, ``cols`` (int64) that show its plane within the outline's reach, their
    radius in the full-size ellipse's units (``radius``, float64: 1 on the ellipse) and the
    outline's radius at their angle (``outline``). Shared by every weather of the frame: only
    the scale differs."""

    shape: tuple[int, int]
    rows: tuple[np.ndarray, ...]
    cols: tuple[np.ndarray, ...]
    radius: tuple[np.ndarray, ...]
    outline: tuple[np.ndarray, ...]


def puddle_pixels(K: np.ndarray, pose_world_cam: np.ndarray, depth: np.ndarray,
                  puddles: np.ndarray, phases: np.ndarray) -> PuddlePixels:
    """The pixels of full-size ``puddles`` (arguments as :func:`puddle_coverage`'s), for
    :func:`puddle_coverage_at`."""
    height, width = depth.shape
    puddles = np.asarray(puddles, np.float64).reshape(-1, 6)
    K = np.asarray(K, np.float64)
    rotation, origin = pose_world_cam[:3, :3], pose_world_cam[:3, 3]
    reach = 1.0 + sum(amplitude for _, amplitude in PUDDLE_OUTLINE)
    found: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    for (x, y, z, half_length, half_width, yaw), phase in zip(puddles, phases):
        axes = np.array([half_length, half_width])
        window = _ground_window(K, pose_world_cam, np.array([x, y, z]),
                                float(axes.max()) * reach, height, width)
        if window is None:
            continue
        r0, r1, c0, c1 = window
        u = (np.arange(c0, c1, dtype=np.float64) + 0.5 - K[0, 2]) / K[0, 0]
        v = (np.arange(r0, r1, dtype=np.float64) + 0.5 - K[1, 2]) / K[1, 1]
        # each pixel's ray in world axes, scaled so that its camera z is 1: u R0 + v R1 + R2
        ray_z = u[None, :] * rotation[2, 0] + v[:, None] * rotation[2, 1] + rotation[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            along = (z - origin[2]) / ray_z  # depth at which the ray meets the puddle's plane
        rows, cols = np.nonzero((ray_z < -1e-9) & _on_plane(depth[r0:r1, c0:c1], along))
        if not rows.size:
            continue
        distance = along[rows, cols]
        dx = origin[0] - x + distance * (u[cols] * rotation[0, 0] + v[rows] * rotation[0, 1]
                                         + rotation[0, 2])
        dy = origin[1] - y + distance * (u[cols] * rotation[1, 0] + v[rows] * rotation[1, 1]
                                         + rotation[1, 2])
        cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
        local = ((cos_yaw * dx + sin_yaw * dy) / axes[0]
                 + 1j * (-sin_yaw * dx + cos_yaw * dy) / axes[1])
        radius = np.abs(local)
        near = radius < reach
        rows, cols, local, radius = rows[near], cols[near], local[near], radius[near]
        if not rows.size:
            continue
        # the outline's radius at each pixel's angle phi: sin(k phi + p) = Im(e^(i p) z^k)
        direction = np.where(radius > 0, local / np.maximum(radius, 1e-300), 1.0)
        outline = np.ones_like(radius)
        for (harmonic, amplitude), offset in zip(PUDDLE_OUTLINE, phase):
            outline += amplitude * (np.exp(1j * offset) * direction ** harmonic).imag
        found.append((rows + r0, cols + c0, radius, outline))
    return PuddlePixels((height, width), *(tuple(part) for part in zip(*found))
                        if found else ((), (), (), ()))


def puddle_coverage_at(pixels: PuddlePixels, scale: float) -> np.ndarray:
    """(H, W) float32 :func:`puddle_coverage` of the puddles in ``pixels`` at ``scale``."""
    coverage = np.zeros(pixels.shape, np.float32)
    if scale <= 0:
        return coverage
    for rows, cols, radius, outline in zip(pixels.rows, pixels.cols, pixels.radius,
                                           pixels.outline):
        inside = np.clip((outline - radius / scale) / (PUDDLE_EDGE * outline), 0.0, 1.0)
        inside = (inside * inside * (3.0 - 2.0 * inside)).astype(np.float32)
        coverage[rows, cols] = np.maximum(coverage[rows, cols], inside)
    return coverage


def puddle_coverage(K: np.ndarray, pose_world_cam: np.ndarray, depth: np.ndarray,
                    puddles: np.ndarray, scale: float, phases: np.ndarray) -> np.ndarray:
    """(H, W) float32 in [0, 1]: how much of each pixel is puddle.

    A pixel is puddle where its ray meets a puddle's level plane inside the puddle's outline
    and the surface it shows is that plane (``depth`` within :data:`PUDDLE_ON_ROAD_TOLERANCE`),
    so whatever stands in front hides the water. The outline is the puddle's ellipse, scaled by
    ``scale``, with :data:`PUDDLE_OUTLINE` harmonics; coverage falls smoothly from 1 to 0 over
    :data:`PUDDLE_EDGE` of the radius (smoothstep). Overlapping puddles take the larger value.
    The same as ``puddle_coverage_at(puddle_pixels(...), scale)``, which a renderer splits to
    share the first step between the weathers of a frame.

    Args:
        K: (3, 3) intrinsics. pose_world_cam: (4, 4) T_world_cam, OpenCV axes (x right, y down,
            z forward).
        depth: (H, W) float metres along the optical axis, +inf where no geometry is.
        puddles: (N, 6) float, each ``(x, y, z, half_length, half_width, yaw)`` at full size:
            centre in world metres, half axes in metres, yaw in radians about +z.
        scale: linear size of the puddles in this weather, 0 (none) .. 1 (full size).
        phases: (N, len(PUDDLE_OUTLINE)) outline phases (:func:`puddle_outline_phases`).
    """
    if scale <= 0 or not np.size(puddles):
        return np.zeros(np.shape(depth), np.float32)
    if scale > 1:
        raise ValueError(f"scale: expected 0..1 (full size), got {scale!r}")
    return puddle_coverage_at(puddle_pixels(K, pose_world_cam, depth, puddles, phases), scale)


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
    """Spray lit by the sky over ``rgb`` ((H, W, 3) uint8): ``L + opacity (C - L)`` in linear
    light (:mod:`rainbench.rain.tone`), ``colour_rgb`` (3,) display values in [0, 255], opacity
    (H, W) float32 in [0, 1]. Returns a new (H, W, 3) uint8 array."""
    if not opacity.any():
        return rgb.copy()
    base = to_linear(rgb)
    colour = linear_value(colour_rgb).astype(np.float32)[None, None]
    return to_display(base + opacity[..., None] * (colour - base))


# -- lights seen through rain -----------------------------------------------------------------
GLOW_SHARE = 0.5 * 0.88
"""Share of the light a lamp loses to rain (extinction, 1 - exp(-beta d)) that reaches the camera
as a glow around it: half the extinction of drops this large is diffraction, within a fraction
of a degree (it stays on the lamp's own pixels), and of the geometric half, 88 % passes through
the drop once (refraction, deviated 0-82 degrees; Fresnel-weighted over the drop's disc, computed
by :func:`refraction_phase`); the rest is reflected, mostly away from the camera."""
GLOW_SCALE = 8
"""The glow is computed on a grid this many times coarser than the image and upsampled: it
varies over tens of pixels."""


@functools.lru_cache(maxsize=1)
def refraction_phase() -> tuple[np.ndarray, np.ndarray]:
    """Where light passing once through a water drop goes: ``(deviation_rad, density_per_sr)``,
    (N,) float64 each, the deviation angle from the incoming direction and the light's density
    per steradian there, integrating to 1 over the sphere.

    Geometric optics of a sphere (n = 1.333): a ray at impact parameter b = sin(i) is refracted
    to r (sin i = n sin r) and leaves deviated by 2 (i - r), weighted by its share of the disc
    (2 b db) and the Fresnel transmittance (unpolarised) on entering and leaving; 88 % of the
    light falling on the disc passes this way. Near the forward direction the deviation is ~2 b
    (1 - 1 / n), so the density is flat there: (4 / pi) (1 - R0)^2 / 0.88 = 1.39 per sr, R0 the
    reflectance at normal incidence. Half the light is deviated by more than 24 degrees, none by
    more than 82.
    """
    impact = (np.arange(200_000, dtype=np.float64) + 0.5) / 200_000.0
    incidence = np.arcsin(impact)
    refracted = np.arcsin(impact / WATER_INDEX)
    # leaving, the ray meets the surface at r inside, which reflects as much as i outside
    weight = 2.0 * impact * (1.0 - water_fresnel(np.cos(incidence))) ** 2
    deviation = 2.0 * (incidence - refracted)
    edges = np.linspace(0.0, math.radians(90.0), 181)
    energy, _ = np.histogram(deviation, bins=edges, weights=weight)
    solid_angle = 2.0 * math.pi * (np.cos(edges[:-1]) - np.cos(edges[1:]))
    density = energy / energy.sum() / solid_angle
    return 0.5 * (edges[:-1] + edges[1:]), density


def light_glow(K: np.ndarray, pose_world_cam: np.ndarray, lamps: np.ndarray, intensity_cd: np.ndarray,
               colours: np.ndarray, depth: np.ndarray, weather: Weather) -> np.ndarray:
    """(H, W, 3) float32: the glow rain lays around lights, in linear display units (a Lambertian
    white surface lit by the light the camera meters shows as ``light_level ** 2.2``), before the
    camera's ``image_level``; zeros when it does not rain.

    A lamp of luminous intensity I (towards the camera) d metres away lights the camera with
    ``E = I / d^2`` lux; rain takes ``1 - exp(-beta d)`` of it off the direct path
    (:func:`rainbench.rain.physical.extinction_coefficient`), and :data:`GLOW_SHARE` of that
    reaches the camera deviated by theta with the density ``p(theta)`` of
    :func:`refraction_phase`, so a pixel theta from the lamp sees ``L = E GLOW_SHARE (1 -
    exp(-beta d)) p(theta)`` cd/m^2, which shows like a white surface under ``pi L`` lux. Single
    scattering, as if the drops that scatter were at the camera's end of the path (the light
    reaching drops near the lamp is stronger, but they turn it by more than theta). A lamp the
    depth map hides (its pixel nearer than the lamp) glows not at all; a lamp outside the image
    is taken as seen.

    Args:
        K: (3, 3) intrinsics. pose_world_cam: (4, 4) T_world_cam, OpenCV axes.
        lamps: (N, 3) float, each light's centre in world metres.
        intensity_cd: (N,) float >= 0, each light's luminous intensity towards the camera (cd).
        colours: (N, 3) float in 0..1, each light's colour (the glow takes it).
        depth: (H, W) float metres along the optical axis, +inf for sky.
        weather: the image's weather (its rate and the light its camera meters).
    """
    height, width = depth.shape
    glow = np.zeros((height, width, 3), np.float32)
    lamps = np.asarray(lamps, np.float64).reshape(-1, 3)
    intensity_cd = np.asarray(intensity_cd, np.float64).reshape(-1)
    colours = np.asarray(colours, np.float64).reshape(-1, 3)
    beta_per_m = extinction_coefficient(weather.rain_mm_h) / 1000.0
    if beta_per_m <= 0 or not len(lamps):
        return glow
    points = (lamps - pose_world_cam[:3, 3]) @ pose_world_cam[:3, :3]  # camera frame
    distance = np.linalg.norm(points, axis=1)
    in_front = (points[:, 2] > 1e-3) & (intensity_cd > 0)
    u = K[0, 0] * points[:, 0] / np.where(in_front, points[:, 2], 1.0) + K[0, 2]
    v = K[1, 1] * points[:, 1] / np.where(in_front, points[:, 2], 1.0) + K[1, 2]
    inside = in_front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    col = np.clip(u, 0, width - 1).astype(np.int64)
    row = np.clip(v, 0, height - 1).astype(np.int64)
    hidden = inside & (depth[row, col] < points[:, 2] * 0.98)  # something stands in front of it
    seen = in_front & ~hidden
    if not seen.any():
        return glow
    small_h, small_w = -(-height // GLOW_SCALE), -(-width // GLOW_SCALE)
    cols = ((np.arange(small_w) + 0.5) * GLOW_SCALE - K[0, 2]) / K[0, 0]
    rows = ((np.arange(small_h) + 0.5) * GLOW_SCALE - K[1, 2]) / K[1, 1]
    rays = np.stack(np.broadcast_arrays(cols[None, :], rows[:, None], 1.0), axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    deviation, density = refraction_phase()
    radiance = np.zeros((small_h, small_w, 3), np.float64)
    for point, dist, candela, colour in zip(points[seen], distance[seen], intensity_cd[seen], colours[seen]):
        scattered = candela / dist**2 * GLOW_SHARE * -math.expm1(-beta_per_m * dist)
        angle = np.arccos(np.clip(rays @ (point / dist), -1.0, 1.0))
        radiance += (scattered * np.interp(angle, deviation, density, right=0.0))[..., None] * colour
    # a luminance L shows like a white surface lit by pi L lux: display_light, in linear units
    level = radiance * (math.pi * display_light(weather, 1.0) ** DISPLAY_LIGHT_GAMMA)
    return cv2.resize(level.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)


def puddle_water(surface: np.ndarray, mirror: np.ndarray, fresnel: np.ndarray) -> np.ndarray:
    """(..., 3) float32 display values of standing water, pixel by pixel: in linear light,
    water's Fresnel reflectance ``F`` of the mirror image plus the rest of the road seen through
    the water, ``F M + (1 - F) u S`` with ``u = PUDDLE_UNDERLAY^2.2``, back through the 1/2.2
    tone curve.

    Args:
        surface: (..., 3) uint8 or float display values (0..255) of the plain render.
        mirror: (..., 3) float display values of the mirror render, the same shape; above 255
            where the lamps' mirror images are boosted (:data:`CLIPPED_GAIN`), so the result may
            be too.
        fresnel: (..., 1) float32 in [0, 1], F(theta) per pixel (:func:`road_mirror_weight`
            with :data:`PUDDLE_MIRROR_REFLECTANCE`).
    """
    inverse = np.float32(1.0 / 255.0)
    plain = cv2.pow(np.asarray(surface, np.float32) * inverse, DISPLAY_LIGHT_GAMMA)
    mirrored = cv2.pow(np.maximum(np.asarray(mirror, np.float32), 0.0) * inverse,
                       DISPLAY_LIGHT_GAMMA)
    weight = np.asarray(fresnel, np.float32)
    linear = weight * mirrored + (np.float32(1.0) - weight) * (
        np.float32(PUDDLE_UNDERLAY ** DISPLAY_LIGHT_GAMMA) * plain)
    return cv2.pow(linear, 1.0 / DISPLAY_LIGHT_GAMMA) * np.float32(255.0)


def add_glow(rgb: np.ndarray, glow: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: ``rgb`` (display values) with ``glow`` ((H, W, 3) float32 linear display
    units, :func:`light_glow`) added in linear light: ``255 ((rgb / 255)^2.2 + glow)^(1 / 2.2)``,
    rounded and clipped (a pixel without glow keeps its value)."""
    return to_display(cv2.add(to_linear(rgb), glow))


def noise_field(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float32 unit-variance noise: luma noise shared by the channels plus
    :data:`CHROMA_NOISE_SHARE` of the variance per channel, smoothed into grain of
    :data:`ISP_NOISE_SIGMA_PX` (what a camera's noise reduction leaves)."""
    shared = rng.standard_normal((height, width, 1), dtype=np.float32)
    per_channel = rng.standard_normal((height, width, 3), dtype=np.float32)
    white = (np.float32(math.sqrt(1 - CHROMA_NOISE_SHARE)) * shared
             + np.float32(math.sqrt(CHROMA_NOISE_SHARE)) * per_channel)
    kernel, gain = _grain_kernel()
    grain = cv2.sepFilter2D(white, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT_101)
    return grain * gain


@functools.lru_cache(maxsize=1)
def _grain_kernel() -> tuple[np.ndarray, np.float32]:
    """(1-D Gaussian kernel of :data:`ISP_NOISE_SIGMA_PX`, the factor that brings white noise
    smoothed by it in both directions back to unit variance: 1 / the sum of the 1-D kernel's
    squared weights, since the separable 2-D smoothing scales the standard deviation by that
    sum)."""
    radius = max(1, math.ceil(3 * ISP_NOISE_SIGMA_PX))
    kernel = cv2.getGaussianKernel(2 * radius + 1, ISP_NOISE_SIGMA_PX, cv2.CV_32F)
    return kernel, np.float32(1.0 / float((kernel.astype(np.float64) ** 2).sum()))


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
        (H, W, 3) uint8: ``I' = level I + r n sqrt(a (G - 1) level I + b (G^2 - 1))``, r the
        ISP's :data:`ISP_NOISE_REDUCTION`, rounded and clipped. Identity when level = G = 1.
    """
    if weather.image_level == 1.0 and weather.gain == 1.0:
        return rgb.copy()
    signal = rgb.astype(np.float32) * np.float32(weather.image_level)
    if noise is not None and weather.gain > 1.0:
        gain = np.float32(weather.gain)
        variance = (np.float32(NOISE_SIGNAL_DN) * (gain - 1) * signal
                    + np.float32(NOISE_FLOOR_DN2) * (gain * gain - 1))
        signal += noise * (np.float32(ISP_NOISE_REDUCTION) * np.sqrt(variance))
    return np.clip(np.rint(signal), 0, 255).astype(np.uint8)
