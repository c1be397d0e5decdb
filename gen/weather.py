"""Weather between renders: writes a :class:`~rainbench.rain.weather.Weather` into a compiled
model (lights, materials, puddle sizes, sky texels) without rebuilding it.

:class:`WeatherRig` changes only model fields that MuJoCo's renderer reads at every render
(``light_*``, ``vis.headlight``, ``mat_rgba``, ``mat_reflectance``, ``geom_size``/``geom_rgba``
of the puddles) plus the sky texture, which it re-uploads to the GL context when the sky changes.
Actors, poses and the camera are never touched, so labels of the clean geometry hold at every rate.
"""

from __future__ import annotations

import mujoco
import numpy as np

from rainbench.mjcf.weather import scene_lighting
from rainbench.rain.weather import Weather, sky_colours, sky_key

_SKY_ELEVATION_CACHE: dict[int, np.ndarray] = {}


def skybox_sin_elevation(size: int) -> np.ndarray:
    """(6 * size * size,) sine of the elevation of every skybox texel, as MuJoCo lays them out.

    MuJoCo's builtin skybox gradient is linear in (1 + sin e) / 2 (checked on mujoco 4.0.0), so
    compiling it once from white to black gives every texel's elevation.
    """
    if size not in _SKY_ELEVATION_CACHE:
        spec = mujoco.MjSpec()
        spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                         builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT, rgb1=[1, 1, 1],
                         rgb2=[0, 0, 0], width=size, height=size)
        spec.worldbody.add_geom(size=[1, 1, 1])
        model = spec.compile()
        weight = model.tex_data.reshape(-1, 3)[:, 0].astype(np.float64) / 255.0
        _SKY_ELEVATION_CACHE[size] = 2.0 * weight - 1.0
    return _SKY_ELEVATION_CACHE[size]


def _ids(model: mujoco.MjModel, kind: mujoco.mjtObj, names) -> dict[str, int]:
    """Ids of the named objects that ``model`` has (a custom scene may lack some)."""
    found = {name: mujoco.mj_name2id(model, kind, name) for name in names}
    return {name: index for name, index in found.items() if index >= 0}


def render_key(weather: Weather) -> tuple:
    """Everything a weather changes in a render: two weathers with one key render the same
    image (heavy rates differ only in light level and camera, applied after the render)."""
    return scene_lighting(weather), sky_key(weather)


class WeatherRig:
    """Applies weathers to ``model``: a scene of :func:`rainbench.mjcf.scene.build_spec`, or any
    scene with a skybox texture ``sky`` and lights ``sun`` and ``skylight``; the materials
    ``asphalt`` (the mirroring road), ``concrete``, ``grass``, ``puddle`` and ``cloud_deck`` are
    used when present."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        lights = _ids(model, mujoco.mjtObj.mjOBJ_LIGHT, ("sun", "skylight"))
        if len(lights) != 2 or mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, "sky") < 0:
            raise ValueError("weather: expected lights 'sun' and 'skylight' and a skybox texture "
                             "'sky' in the scene (see rainbench.mjcf.scene.build_spec)")
        self._sun, self._skylight = lights["sun"], lights["skylight"]
        self._materials = _ids(model, mujoco.mjtObj.mjOBJ_MATERIAL,
                               ("asphalt", "concrete", "grass", "puddle", "cloud_deck"))
        self._puddles = np.array([g for g in range(model.ngeom)
                                  if model.geom(g).name.startswith("scenery/puddle")], np.int64)
        self._puddle_size = model.geom_size[self._puddles].copy()
        sky = model.texture("sky")
        self._sky_id = int(sky.id)
        size = int(model.tex_width[self._sky_id])
        self._sky_slice = slice(int(model.tex_adr[self._sky_id]),
                                int(model.tex_adr[self._sky_id]) + 6 * size * size * 3)
        self._sky_sin = skybox_sin_elevation(size)
        self._sky_key: tuple | None = None
        self._sky_texels: dict[tuple, np.ndarray] = {}
        self.cloud_deck = self.puddles_visible = False
        self.road_reflectance = 0.0

    def set_mirror(self, on: bool) -> None:
        """Full mirror reflectance on the road (``on``), or none."""
        if "asphalt" in self._materials:
            self.model.mat_reflectance[self._materials["asphalt"]] = 1.0 if on else 0.0

    def apply(self, weather: Weather, context: mujoco.MjrContext | None) -> None:
        """Write ``weather`` into the model; upload the sky to ``context`` if it changed."""
        model, lighting = self.model, scene_lighting(weather)
        model.light_diffuse[self._sun] = lighting.sun_diffuse
        model.light_specular[self._sun] = lighting.sun_specular
        model.light_castshadow[self._sun] = lighting.sun_castshadow
        model.light_diffuse[self._skylight] = lighting.skylight_diffuse
        model.vis.headlight.ambient = lighting.headlight_ambient
        model.vis.headlight.diffuse = [lighting.headlight_diffuse] * 3
        materials = self._materials
        for name, factor in (("asphalt", lighting.road_factor),
                             ("concrete", lighting.pavement_factor),
                             ("grass", lighting.grass_factor)):
            if name in materials:
                model.mat_rgba[materials[name]] = [factor, factor, factor, 1.0]
        self.road_reflectance = lighting.road_reflectance if "asphalt" in materials else 0.0
        if "asphalt" in materials:  # the renderer draws the mirror itself (FrameRenderer)
            model.mat_reflectance[materials["asphalt"]] = 0.0
        if "puddle" in materials:
            model.mat_rgba[materials["puddle"]] = lighting.puddle_rgba
            model.geom_size[self._puddles] = self._puddle_size * [
                max(lighting.puddle_scale, 1e-3), max(lighting.puddle_scale, 1e-3), 1.0]
        self.puddles_visible = "puddle" in materials and lighting.puddle_rgba[3] > 0
        if "cloud_deck" in materials:
            model.mat_rgba[materials["cloud_deck"]] = lighting.cloud_deck_rgba
        self.cloud_deck = "cloud_deck" in materials and lighting.cloud_deck
        key = sky_key(weather)
        if key != self._sky_key:
            if key not in self._sky_texels:  # a clip's sweep has a handful of skies
                self._sky_texels[key] = np.rint(sky_colours(weather, self._sky_sin) * 255.0
                                                ).astype(np.uint8).reshape(-1)
            model.tex_data[self._sky_slice] = self._sky_texels[key]
            if context is not None:
                mujoco.mjr_uploadTexture(model, context, self._sky_id)
            self._sky_key = key
