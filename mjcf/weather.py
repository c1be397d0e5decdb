"""What a :class:`~rainbench.rain.weather.Weather` changes in the scene's model, as plain numbers.

:func:`scene_lighting` is the one definition: :func:`rainbench.mjcf.scene.build_spec` writes the
base weather's values into the spec (so an exported ``scene.xml`` shows the base weather), and
``rainbench.gen.weather.WeatherRig`` writes any weather's values into a compiled model between
renders. Every field below is a MuJoCo model field that the renderer reads at each render.
"""

from __future__ import annotations

from dataclasses import dataclass

from rainbench.rain.weather import (GRASS_WET_DARKENING, PAVEMENT_WET_DARKENING,
                                    ROAD_WET_DARKENING, Weather, airlight_rgb)

# The clear-sky sun (light "sun", directional, casts shadows) and the camera's headlight.
SUN_DIFFUSE = (0.75, 0.72, 0.66)
SUN_SPECULAR = 0.2
HEADLIGHT_AMBIENT_CLEAR = 0.38
HEADLIGHT_AMBIENT_CLOUD = 0.52
HEADLIGHT_DIFFUSE = 0.15
SKYLIGHT_DIFFUSE_CLOUD = 0.36
"""Light "skylight": a shadowless directional light from the zenith standing for the overcast
dome (tops of cars and people brighter than their sides); zero under a clear sky."""
PUDDLE_RGB = (0.07, 0.07, 0.08)
PUDDLE_ALPHA = 0.55
"""A puddle is a dark transparent film over the road in the plain render (standing water hides
the asphalt's grain and looks dark where it does not mirror); the mirror render leaves it out,
so puddles are dark near the camera and mirror the world at grazing angles."""


@dataclass(frozen=True)
class SceneLighting:
    """Model values of one weather. Colours are RGB factors in 0..1."""

    sun_diffuse: tuple[float, float, float]
    sun_specular: float
    sun_castshadow: bool
    skylight_diffuse: float
    headlight_ambient: tuple[float, float, float]  # a faint blue cast: diffuse skylight
    headlight_diffuse: float
    road_factor: float  # multiplies the asphalt material's colour
    pavement_factor: float  # sidewalks and curbs
    grass_factor: float
    road_reflectance: float
    puddle_scale: float  # linear size of the puddles, 0 = none
    puddle_rgba: tuple[float, float, float, float]
    cloud_deck: bool  # draw the emissive rain-cloud deck (sunless rain)
    cloud_deck_rgba: tuple[float, float, float, float]


def scene_lighting(weather: Weather) -> SceneLighting:
    """The model values of ``weather`` (laws in docs/rain.md, "Weather that follows the rate")."""
    cover, wet = weather.cloud_cover, weather.wetness
    ambient = HEADLIGHT_AMBIENT_CLEAR + (HEADLIGHT_AMBIENT_CLOUD - HEADLIGHT_AMBIENT_CLEAR) * cover
    deck = airlight_rgb(weather) / 255.0  # a uniform deck in the airlight's colour
    return SceneLighting(
        sun_diffuse=tuple(weather.sun * c for c in SUN_DIFFUSE),
        sun_specular=weather.sun * SUN_SPECULAR,
        sun_castshadow=weather.sun > 0.02,
        skylight_diffuse=SKYLIGHT_DIFFUSE_CLOUD * cover,
        headlight_ambient=(ambient, ambient, ambient + 0.02),
        headlight_diffuse=HEADLIGHT_DIFFUSE,
        road_factor=1.0 - ROAD_WET_DARKENING * wet,
        pavement_factor=1.0 - PAVEMENT_WET_DARKENING * wet,
        grass_factor=1.0 - GRASS_WET_DARKENING * wet,
        road_reflectance=weather.road_reflectance,
        puddle_scale=weather.puddle_fraction ** 0.5,
        puddle_rgba=PUDDLE_RGB + (PUDDLE_ALPHA if weather.puddle_fraction > 0 else 0.0,),
        cloud_deck=weather.rain_mm_h > 0 and weather.sun <= 0.02,
        # emission 1 plus the headlight's ambient light the deck also receives
        cloud_deck_rgba=tuple(float(c) for c in deck / (1.0 + ambient)) + (1.0,),
    )
