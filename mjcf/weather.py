"""What a :class:`~rainbench.rain.weather.Weather` changes in the scene's model, as plain numbers.

:func:`scene_lighting` is the one definition: :func:`rainbench.mjcf.scene.build_spec` writes the
base weather's values into the spec (so an exported ``scene.xml`` shows the base weather), and
``rainbench.gen.weather.WeatherRig`` writes any weather's values into a compiled model between
renders. Every field below is a MuJoCo model field that the renderer reads at each render.

At dusk and night (docs/rain.md, "Time of day") the daylight lights dim and change colour, and the
lights of :mod:`rainbench.mjcf.lights` (street lights, headlights) get their levels from here.
"""

from __future__ import annotations

from dataclasses import dataclass

from rainbench.rain.weather import (GRASS_WET_DARKENING, NIGHT_SKY_LUX, PAVEMENT_WET_DARKENING,
                                    ROAD_WET_DARKENING, STRAY_LIGHT_LUX, Weather, airlight_rgb,
                                    daylight_level, display_light, wet_display_factor)

# The clear-sky sun (light "sun", directional, casts shadows) and the camera's headlight.
SUN_DIFFUSE = (0.75, 0.72, 0.66)
SUN_SPECULAR = 0.2
HEADLIGHT_AMBIENT_CLEAR = 0.38
HEADLIGHT_AMBIENT_CLOUD = 0.52
HEADLIGHT_DIFFUSE = 0.15
SKYLIGHT_DIFFUSE_CLOUD = 0.36
"""Light "skylight": a shadowless directional light from the zenith standing for the overcast
dome (tops of cars and people brighter than their sides); zero under a clear sky."""
PUDDLE_RGBA = (0.07, 0.07, 0.08, 0.55)
"""The ``puddle`` material of the ``scenery/puddle*`` geoms (group 3, which rainbench never draws):
the geoms only mark where puddles are, at full size; the renderer lays the water over the image
(:func:`rainbench.rain.weather.puddle_coverage`). A viewer that shows group 3 draws them as dark
films."""


# -- dusk and night ---------------------------------------------------------------------------
DUSK_SUN_RGB = (1.0, 0.56, 0.26)
"""The low sun's colour: through ~14 air masses blue is scattered away (~2000-2500 K)."""
DUSK_SUN_STRENGTH = 1.25
"""Direct sun at dusk relative to the sky light, in display terms: the low sun still gives a
sun-facing wall several times the sky's light; the horizontal road gets sin(4 deg) of it."""
DUSK_SKY_RGB = (0.72, 0.80, 1.0)
"""Ambient and sky light at dusk: the sky is the light source and it is blue (the blue hour)."""
STREET_LIGHT_RGB = (1.0, 0.80, 0.58)
"""Warm-white street lights (~3000 K LED, the usual urban retrofit; sodium lamps were oranger)."""
HEADLAMP_RGB = (1.0, 0.94, 0.84)
"""Headlights: white with a trace of yellow (halogen ~3200 K to LED ~5500 K)."""
STREET_LIGHT_PEAK_LUX = 30.0
"""Illuminance under a street light: twice the street's mean (uniformity U0 = min/mean >= 0.4)."""
HEADLAMP_PEAK_LUX = 200.0
"""Low beam on a surface facing the car 10 m ahead on the beam's axis: 20 000 cd / (10 m)^2 (a
halogen low beam's hot spot just below the cut-off; UN ECE R112 asks at least 12 000 cd at
point 75R)."""
VEHICLE_LAMPS_BELOW_LUX = 1000.0
"""By day the vehicles' head and tail lamps are on where the daylight is below 1 000 lux: the
level at which UN ECE R48 (6.2.7.6.2) has automatic headlamp switching turn the dipped beams
(and with them the position lamps) on, in rain above 10 mm/h (docs/rain.md). At dusk and night
they are always on."""


@dataclass(frozen=True)
class SceneLighting:
    """Model values of one weather. Colours are RGB factors in 0..1."""

    sun_diffuse: tuple[float, float, float]
    sun_specular: float
    sun_castshadow: bool
    skylight_diffuse: float
    headlight_ambient: tuple[float, float, float]  # a faint blue cast: diffuse skylight
    headlight_diffuse: float
    road_factor: float  # multiplies the asphalt material's colour (wet_display_factor)
    pavement_factor: float  # sidewalks and curbs
    grass_factor: float
    road_reflectance: float
    puddle_scale: float  # linear size of the puddles, 0 = none
    cloud_deck: bool  # draw the emissive rain-cloud deck in the wet road's mirror (any rain)
    cloud_deck_rgba: tuple[float, float, float, float]
    # dusk and night: lights "sun" and "skylight" are switched off at night (no sun; the city's
    # ambient stands for the sky), which frees OpenGL light slots for street and head lights
    sun_active: bool = True
    skylight_active: bool = True
    lamp_diffuse: tuple[float, float, float] = (0.0, 0.0, 0.0)  # street light at its peak
    beam_diffuse: tuple[float, float, float] = (0.0, 0.0, 0.0)  # head light at its peak
    # the vehicles' head and tail lamp geoms glow (dusk, night, and by day in dark rain)
    vehicle_lamps: bool = False


def _scaled(colour, factor: float) -> tuple[float, float, float]:
    return tuple(float(c) * factor for c in colour)


def scene_lighting(weather: Weather) -> SceneLighting:
    """The model values of ``weather`` (laws in docs/rain.md, "Weather that follows the rate" and
    "Time of day"). By day exactly the daytime values; the lamp and beam levels are 0."""
    cover, wet = weather.cloud_cover, weather.wetness
    ambient = HEADLIGHT_AMBIENT_CLEAR + (HEADLIGHT_AMBIENT_CLOUD - HEADLIGHT_AMBIENT_CLEAR) * cover
    deck = airlight_rgb(weather) / 255.0  # a uniform deck in the airlight's colour
    sun_diffuse = tuple(weather.sun * c for c in SUN_DIFFUSE)
    sun_specular = weather.sun * SUN_SPECULAR
    skylight = SKYLIGHT_DIFFUSE_CLOUD * cover
    ambient_rgb = (ambient, ambient, ambient + 0.02)
    headlight_diffuse = HEADLIGHT_DIFFUSE
    lamp = beam = (0.0, 0.0, 0.0)
    if weather.time_of_day != "day":
        lamp = _scaled(STREET_LIGHT_RGB, display_light(weather, STREET_LIGHT_PEAK_LUX))
        beam = _scaled(HEADLAMP_RGB, display_light(weather, HEADLAMP_PEAK_LUX))
    if weather.time_of_day == "dusk":
        # daylight dims to the dusk level (after auto-exposure; lower still under rain, where
        # the lamps gain on it) and turns blue; the sun is low and orange (its direction is set
        # once in the scene: rainbench.mjcf.lights)
        level = daylight_level(weather)
        sun_diffuse = _scaled(DUSK_SUN_RGB, weather.sun * level * DUSK_SUN_STRENGTH
                              * SUN_DIFFUSE[0])
        sun_specular = weather.sun * SUN_SPECULAR * level
        skylight = skylight * level
        ambient_rgb = _scaled(DUSK_SKY_RGB, ambient * level)
        headlight_diffuse = HEADLIGHT_DIFFUSE * level
    elif weather.time_of_day == "night":
        # no sun and no sky light: the ambient is the city's (sky glow and stray street light)
        sun_diffuse, sun_specular, skylight, headlight_diffuse = (0.0, 0.0, 0.0), 0.0, 0.0, 0.0
        glow = display_light(weather, NIGHT_SKY_LUX[weather.sky] + STRAY_LIGHT_LUX)
        ambient_rgb = _scaled(STREET_LIGHT_RGB, glow)
    night = weather.time_of_day == "night"
    return SceneLighting(
        sun_diffuse=sun_diffuse,
        sun_specular=sun_specular,
        sun_castshadow=weather.sun > 0.02,
        skylight_diffuse=skylight,
        headlight_ambient=ambient_rgb,
        headlight_diffuse=headlight_diffuse,
        road_factor=wet_display_factor(ROAD_WET_DARKENING, wet),
        pavement_factor=wet_display_factor(PAVEMENT_WET_DARKENING, wet),
        grass_factor=wet_display_factor(GRASS_WET_DARKENING, wet),
        road_reflectance=weather.road_reflectance,
        puddle_scale=weather.puddle_fraction ** 0.5,
        cloud_deck=weather.rain_mm_h > 0,
        # emission 1 plus the headlight's ambient light the deck also receives
        cloud_deck_rgba=tuple(float(c) for c in deck / (1.0 + ambient_rgb[0])) + (1.0,),
        sun_active=not night, skylight_active=not night, lamp_diffuse=lamp, beam_diffuse=beam,
        vehicle_lamps=(weather.time_of_day != "day"
                       or weather.daylight_lux < VEHICLE_LAMPS_BELOW_LUX),
    )
