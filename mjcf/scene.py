"""Compose the road scene as a ``mujoco.MjSpec`` from a :class:`~rainbench.mjcf.layout.Layout`.

:func:`build_spec` is the one pure builder: the same layout and image size give the same spec
(and the same MJCF text). :func:`export_scene` writes it as a standalone ``scene.xml`` with its
PNG textures beside it, loadable with ``mujoco.MjModel.from_xml_path`` and MuJoCo's viewer.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np

from rainbench.rain.weather import sky_colours, weather_at

from . import layout as L
from . import lights, parts, textures, vehicles
from .weather import PUDDLE_RGBA, scene_lighting

GEOM = mujoco.mjtGeom
EGO_CAMERA = "ego"
ACTOR_PREFIX = "actor{:03d}/"
# Render margin (fraction of width/height added on every side) of the unoccluded
# "actor alone" pass that measures truncation; the framebuffer is sized for it.
TRUNCATION_MARGIN = 0.25
PUDDLE_GROUP = 3  # puddle outlines: never drawn; the renderer lays the water over the image
CLOUD_DECK_GROUP = 4  # the rain-cloud deck: drawn only in the road mirror's pass, in rain
CLOUD_DECK_HEIGHT_M = 60.0  # the mirror pass reaches it to the horizon (gen.render.MIRROR_SKY_REACH_M)
CLOUD_DECK_GEOM = "scenery/cloud_deck"
SKY_TEXTURE_SIZE = 128  # skybox face size: re-uploaded whenever the weather changes the sky
CLOUD_TEXTURE = "clouds"  # the cloud field the sky is drawn from (rainbench.gen.weather)
CLOUD_STREAM = 13  # the cloud field draws from default_rng([seed, CLOUD_STREAM])
PLAIN_GREY = (0.5, 0.5, 0.5, 1.0)  # a prop with neither a material nor a colour
SHADOW_HALF_SIZE_M = 45.0  # half the sun's shadow box (MuJoCo's shadowclip x stat.extent)
SHADOW_CENTER_AHEAD_M = 35.0  # the box's centre ahead of the ego: it spans -10..80 m
SHADOW_MAP_SIZE = 3072
"""Texels a side of the sun's shadow map: 2.9 cm over the 90 m box. At 2048 (4.4 cm, until
2026-11-28) a visual audit found car shadows stair-stepped and thin lamp arms' shadows broken
into dashes; 3072 renders a residential frame (seed 143, 800x600, llvmpipe) in 167-172 ms
against 155 ms, 4096 in 184-206 ms."""


def padded_size(width: int, height: int) -> tuple[int, int, int, int]:
    """(padded width, padded height, margin x, margin y) of the actor-alone canvas: the one
    definition of the framebuffer size (``build_spec``) and of the canvas (``FrameRenderer``)."""
    margin_x = math.ceil(width * TRUNCATION_MARGIN)
    margin_y = math.ceil(height * TRUNCATION_MARGIN)
    return width + 2 * margin_x, height + 2 * margin_y, margin_x, margin_y


def horizontal_to_vertical_fov(hfov_deg: float, width: int, height: int) -> float:
    """Vertical FOV (degrees) of square pixels with horizontal FOV ``hfov_deg`` at W x H."""
    return math.degrees(2 * math.atan(math.tan(math.radians(hfov_deg) / 2) * height / width))


def _camera_quat(pitch: float = 0.0) -> list[float]:
    """MuJoCo camera looking along +x of its body, tilted up by ``pitch`` radians (camera x =
    -y of the body, camera y = up)."""
    xaxis = np.array([0.0, -1.0, 0.0])
    yaxis = np.array([-math.sin(pitch), 0.0, math.cos(pitch)])
    zaxis = np.cross(xaxis, yaxis)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.column_stack([xaxis, yaxis, zaxis]).ravel())
    return quat.tolist()


def _add_texture_material(spec, name: str, image: np.ndarray, repeat_per_m: float,
                          specular: float = 0.1) -> None:
    filename = f"{name}.png"
    spec.assets[filename] = textures.encode_png(image)
    spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, file=filename)
    material = spec.add_material(name=name, texrepeat=[repeat_per_m, repeat_per_m],
                                 texuniform=True, specular=specular, shininess=0.1)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name


def sun_rig_position(ego_x: float, ego_y: float, ego_yaw: float) -> list[float]:
    """World position (x, y, 0) of the "sun_rig" mocap body for an ego at (``ego_x``, ``ego_y``)
    heading ``ego_yaw`` (radians): SHADOW_CENTER_AHEAD_M ahead of it, where the sun's shadow
    box is centred."""
    return [ego_x + SHADOW_CENTER_AHEAD_M * math.cos(ego_yaw),
            ego_y + SHADOW_CENTER_AHEAD_M * math.sin(ego_yaw), 0.0]


def _static_box(body, name, size, pos, *, material=None, rgba=None, quat=None):
    kwargs = {"material": material} if material else {"rgba": list(rgba)}
    if quat is not None:
        kwargs["quat"] = list(quat)
    body.add_geom(name=name, type=GEOM.mjGEOM_BOX, size=list(size), pos=list(pos),
                  contype=0, conaffinity=0, **kwargs)


def build_spec(layout: L.Layout, width: int, height: int, hfov_deg: float = 90.0) -> mujoco.MjSpec:
    """The scene of ``layout`` for a W x H ego camera with horizontal FOV ``hfov_deg``.

    Static scenery is named ``scenery/...``; actor geoms ``actor{instance:03d}/...``; moving units
    are mocap bodies named after :attr:`Unit.name`; the ego camera is named ``ego``.
    """
    if width < 16 or height < 16:
        raise ValueError(f"image size: expected at least 16x16 pixels, got {width}x{height}")
    spec = mujoco.MjSpec()
    spec.modelname = f"rainbench_road_seed{layout.seed}"
    spec.compiler.degree = False
    spec.option.timestep = 0.02
    spec.visual.global_.offwidth, spec.visual.global_.offheight = padded_size(width, height)[:2]
    # 4x multisampling: anti-aliased edges in RGB. Segmentation passes stay exact (MuJoCo draws
    # them without blending; tested), and boxes come from them.
    spec.visual.quality.offsamples = 4
    spec.visual.quality.shadowsize = SHADOW_MAP_SIZE
    # Tessellation of spheres, capsules and cylinders: 16 x 8 instead of MuJoCo's 28 x 16 halves
    # the software-rendered frame time (measured 183 -> 94 ms at 800x600) with no visible facets
    # at road distances.
    spec.visual.quality.numslices = 16
    spec.visual.quality.numstacks = 8
    spec.stat.extent = 100.0
    spec.stat.center = [0.0, 0.0, 0.0]
    spec.visual.map.znear = 0.001  # 0.1 m
    spec.visual.map.zfar = 10.0  # 1000 m
    # The sun's shadow box: +-SHADOW_HALF_SIZE_M (shadowclip x extent) around a point
    # SHADOW_CENTER_AHEAD_M ahead of the ego (the sun rig, below), so its SHADOW_MAP_SIZE texels
    # cover 10 m behind to 80 m ahead: 2.9 cm texels (+-80 m, the box before: 7.8 cm at 2048,
    # whose steps showed as 20-60 px blocks on the road under a low sun). Shadows beyond 80 m end
    # within a few pixels of the horizon.
    spec.visual.map.shadowclip = SHADOW_HALF_SIZE_M / spec.stat.extent
    base = weather_at(layout.sky, 0.0, time_of_day=layout.time_of_day)
    lighting = scene_lighting(base)
    spec.visual.headlight.ambient = list(lighting.headlight_ambient)
    spec.visual.headlight.diffuse = [lighting.headlight_diffuse] * 3
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]

    tex_rng = np.random.default_rng([layout.seed, 7])
    # The base weather's sky as MuJoCo's builtin gradient (zenith rgb1, horizon rgb2); the
    # renderer overwrites the texels with the exact sky of each weather (gen/weather.py).
    zenith, horizon = weather_sky_endpoints(base)
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT, rgb1=zenith, rgb2=horizon,
                     width=SKY_TEXTURE_SIZE, height=SKY_TEXTURE_SIZE)
    _add_texture_material(spec, "asphalt", textures.asphalt(tex_rng), 0.25)
    _add_texture_material(spec, "concrete", textures.concrete(tex_rng), 0.5)
    _add_texture_material(spec, "grass", textures.grass(tex_rng), 0.2)
    spec.material("asphalt").reflectance = lighting.road_reflectance
    for name, factor in (("asphalt", lighting.road_factor), ("concrete", lighting.pavement_factor),
                         ("grass", lighting.grass_factor)):
        spec.material(name).rgba = [factor, factor, factor, 1.0]
    spec.add_material(name="puddle", rgba=list(PUDDLE_RGBA), specular=0.6, shininess=0.9)
    for index, wall in enumerate(L.FACADES):
        # One tile = 4 floors x 4 windows, 12.8 m square.
        _add_texture_material(spec, f"facade{index}", textures.facade(tex_rng, wall), 1 / 12.8)
    # Leaves: one 2 m tile of clumps, tinted per crown (the crowns' rgba); drawn last from
    # tex_rng so that the textures above stay as they were.
    _add_texture_material(spec, "foliage", textures.foliage(tex_rng), 0.5, specular=0.05)
    # The cloud field of the sky: no material draws it; the weather rig reads it to draw the
    # clouds into the skybox (rainbench.gen.weather). Its own stream, so that the textures above
    # and every other draw stay as they were.
    cloud_field = textures.clouds(np.random.default_rng([layout.seed, CLOUD_STREAM]))
    spec.assets[f"{CLOUD_TEXTURE}.png"] = textures.encode_png(cloud_field)
    spec.add_texture(name=CLOUD_TEXTURE, type=mujoco.mjtTexture.mjTEXTURE_2D,
                     file=f"{CLOUD_TEXTURE}.png")

    world = spec.worldbody
    x0, y0, x1, y1 = layout.extent
    x_mid, y_mid = (x0 + x1) / 2, (y0 + y1) / 2
    x_half, y_half = (x1 - x0) / 2, (y1 - y0) / 2
    _static_box(world, "scenery/ground", [x_half + 200, y_half + 200, 0.05], [x_mid, y_mid, -0.07],
                material="grass")
    scenery = [_add_prop(world, prop) for prop in layout.props]  # in spec order
    # The rain-cloud deck: an emissive ceiling that stands for the sky in the wet road's mirror
    # (MuJoCo's mirror pass does not draw the skybox).
    spec.add_material(name="cloud_deck", rgba=[0.5, 0.5, 0.5, 1.0], emission=1.0, specular=0.0)
    world.add_geom(name=CLOUD_DECK_GEOM, type=GEOM.mjGEOM_BOX,
                   size=[x_half + 2000.0, y_half + 2000.0, 1.0],
                   pos=[x_mid, y_mid, CLOUD_DECK_HEIGHT_M],
                   material="cloud_deck", group=CLOUD_DECK_GROUP, contype=0, conaffinity=0)
    for index, (x, y, half_length, half_width, yaw) in enumerate(layout.puddles):
        # full-size puddle outlines; the renderer scales them with the weather's puddle
        # fraction and lays the water over the image (rain/weather.py puddle_coverage)
        world.add_geom(name=f"scenery/puddle{index}", type=GEOM.mjGEOM_ELLIPSOID,
                       size=[half_length, half_width, 0.001], pos=[x, y, L.STATIC_Z * 2],
                       quat=parts.unit_yaw_quat(yaw).tolist(), material="puddle",
                       group=PUDDLE_GROUP, contype=0, conaffinity=0)

    # Ego: a mocap body carrying the camera. The sun and the skylight ride on their own mocap
    # body "sun_rig", kept SHADOW_CENTER_AHEAD_M ahead of the ego along its heading but never
    # turned (gen/sim.py), so that the shadow map covers the view, on curves too, while the
    # light keeps its world direction.
    ego = world.add_body(name="ego", mocap=True, pos=[layout.ego.start_xy[0],
                                                      layout.ego.start_xy[1], 0.0],
                         quat=parts.unit_yaw_quat(layout.ego.heading).tolist())
    ego.add_camera(name=EGO_CAMERA, pos=[0.6, 0.0, layout.camera_height],
                   quat=_camera_quat(math.radians(layout.camera_pitch_deg)),
                   fovy=horizontal_to_vertical_fov(hfov_deg, width, height))
    rig = world.add_body(name="sun_rig", mocap=True,
                         pos=sun_rig_position(*layout.ego.start_xy, layout.ego.heading))
    sun = np.asarray(layout.sun_direction)
    rig.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                  pos=(-60.0 * sun).tolist(), dir=sun.tolist(),
                  castshadow=lighting.sun_castshadow, diffuse=list(lighting.sun_diffuse),
                  specular=[lighting.sun_specular] * 3, ambient=[0.0, 0.0, 0.0])
    rig.add_light(name="skylight", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                  pos=[0.0, 0.0, 60.0], dir=[0.0, 0.0, -1.0], castshadow=False,
                  diffuse=[lighting.skylight_diffuse] * 3, specular=[0.0, 0.0, 0.0],
                  ambient=[0.0, 0.0, 0.0])

    for unit_index, unit in enumerate(layout.units):
        body = world.add_body(name=unit.name, mocap=True,
                              pos=[unit.start_xy[0], unit.start_xy[1], 0.0],
                              quat=parts.unit_yaw_quat(unit.heading).tolist())
        for actor in layout.actors:
            if actor.unit != unit_index:
                continue
            prefix = ACTOR_PREFIX.format(actor.instance_id)
            if actor.role == "car":
                _add_vehicle(spec, body, prefix, unit, layout.seed, actor.instance_id)
            elif actor.role == "pedestrian":
                parts.add_person(body, prefix, unit.colours, build=unit.build,
                                 umbrella=unit.colours.get("umbrella"))
            elif actor.role == "bicycle":
                parts.add_bicycle(body, prefix, unit.colours["frame"], ride_style(unit), rider=unit.build)
            elif actor.role == "motorcycle":
                parts.add_motorcycle(body, prefix, unit.colours["frame"], ride_style(unit))
            elif actor.role == "rider":
                parts.add_rider(body, prefix, unit.colours, ride_style(unit), build=unit.build,
                                helmet=unit.colours["helmet"])
            else:
                raise ValueError(f"actor role: unknown {actor.role!r}")
    # dusk and night: beams on the ego and the moving vehicles, spot lights under the street
    # lamps; by day the moving vehicles' lamps get dark materials, lit in dark rain
    # (rainbench.gen.weather). Parked vehicles (speed 0) keep their lamps off.
    vehicles = [unit for unit in layout.units if unit.kind in ("car", "motorcycle")]
    moving = [unit.name for unit in vehicles if unit.speed > 0]
    parked = [unit.name for unit in vehicles if unit.speed <= 0]
    if layout.time_of_day == "day":
        lights.add_dark_vehicle_lamps(spec, parked_bodies=parked)
    lights.add_time_of_day_lights(
        spec, layout.time_of_day, sky=layout.sky, street_lamps=lights.lamp_heads(spec, scenery),
        vehicle_bodies=moving, parked_bodies=parked, scenery_geoms=scenery)
    return spec


_PROP_SHAPES = {"box": GEOM.mjGEOM_BOX, "cylinder": GEOM.mjGEOM_CYLINDER,
                "ellipsoid": GEOM.mjGEOM_ELLIPSOID, "sphere": GEOM.mjGEOM_SPHERE}



def _add_prop(world, prop: L.Prop):
    """One static scenery geom ``scenery/{prop.name}``; returns it (an ``MjsGeom``)."""
    if prop.shape not in _PROP_SHAPES:
        raise ValueError(f"prop {prop.name}: expected a shape in {', '.join(_PROP_SHAPES)}, "
                         f"got {prop.shape!r}")
    kwargs = {"material": prop.material} if prop.material else {}
    if prop.rgba is not None or not prop.material:
        kwargs["rgba"] = list(prop.rgba or PLAIN_GREY)
    return world.add_geom(name=f"scenery/{prop.name}", type=_PROP_SHAPES[prop.shape],
                          size=list(prop.size), pos=list(prop.pos), quat=list(prop.quat),
                          contype=0, conaffinity=0, **kwargs)


def ride_style(unit: L.Unit) -> str:
    """The bicycle or motorcycle style of a ridden ``unit`` (the first style when unset)."""
    if unit.style:
        return unit.style
    return parts.BICYCLE_STYLES[0] if unit.kind == "bicycle" else parts.MOTORCYCLE_STYLES[0]


def _add_vehicle(spec: mujoco.MjSpec, body, prefix: str, unit: L.Unit, seed: int,
                 instance_id: int) -> None:
    """The mesh vehicle of ``unit`` (style, size, paint) under ``body``, geoms named
    ``{prefix}...`` (:func:`rainbench.mjcf.vehicles.add_vehicle`). Its proportions (roofline,
    windows, wheels) are drawn from a generator of (``seed``, ``instance_id``), its size is the
    layout's ``unit.size`` (the planning size), or the style's planning size when unset."""
    if unit.style not in L.VEHICLE_DIMENSIONS:
        raise ValueError(f"vehicle style: expected one of {', '.join(L.VEHICLE_STYLES)}, "
                         f"got {unit.style!r}")
    size = tuple(unit.size) if unit.size else L.VEHICLE_DIMENSIONS[unit.style]
    shape = vehicles.sample_vehicle(unit.style, np.random.default_rng([seed, 11, instance_id]),
                                    size=size)
    vehicles.add_vehicle(spec, body, prefix, shape, unit.colours["paint"])


def weather_sky_endpoints(weather) -> tuple[list[float], list[float]]:
    """(zenith, horizon) RGB of ``weather``'s sky, for the builtin gradient of an exported scene."""
    zenith, horizon = sky_colours(weather, np.array([1.0, 0.0]))
    return zenith.tolist(), horizon.tolist()


def geom_instance_table(model: mujoco.MjModel) -> np.ndarray:
    """(ngeom,) int32: the actor instance id of every geom (the digits of its ``actor<id>/``
    prefix, :data:`ACTOR_PREFIX`: three or more), -1 for static scenery."""
    table = np.full(model.ngeom, -1, dtype=np.int32)
    for geom_id in range(model.ngeom):
        match = _ACTOR_NAME.match(model.geom(geom_id).name)
        if match:
            table[geom_id] = int(match.group(1))
    return table


_ACTOR_NAME = re.compile(r"actor(\d+)/")
"""An actor geom's name: ``actor<id>/...``. The id has three digits up to 999 and more beyond: a
long residential clip has over a thousand actors (its parked cars grow with the road), and
reading three digits gave ``actor1043/`` the id 104, a parked car's (its people, bicycles and
motorcycle labelled as that car, merged with it)."""


def export_scene(spec: mujoco.MjSpec, out_dir: str | Path) -> Path:
    """Write ``out_dir/scene.xml`` and its PNG textures; returns the XML path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    xml = spec.to_xml()
    for filename, data in spec.assets.items():
        (out / filename).write_bytes(data)
    path = out / "scene.xml"
    path.write_text(xml)
    return path
