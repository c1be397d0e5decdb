"""Compose the road scene as a ``mujoco.MjSpec`` from a :class:`~rainbench.mjcf.layout.Layout`.

:func:`build_spec` is the one pure builder: the same layout and image size give the same spec
(and the same MJCF text). :func:`export_scene` writes it as a standalone ``scene.xml`` with its
PNG textures beside it, loadable with ``mujoco.MjModel.from_xml_path`` and MuJoCo's viewer.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np

from rainbench.rain.weather import sky_colours, weather_at

from . import layout as L
from . import parts, textures
from .weather import scene_lighting

GEOM = mujoco.mjtGeom
EGO_CAMERA = "ego"
ACTOR_PREFIX = "actor{:03d}/"
# Render margin (fraction of width/height added on every side) of the unoccluded
# "actor alone" pass that measures truncation; the framebuffer is sized for it.
TRUNCATION_MARGIN = 0.25
STATIC_SURFACE_Z = 0.002  # markings float this high above the asphalt (no z-fighting)
PUDDLE_GROUP = 3  # puddles are drawn only when the road is wet (not in segmentation passes)
CLOUD_DECK_GROUP = 4  # the rain-cloud deck: drawn only in renders of a sunless rainy weather
CLOUD_DECK_HEIGHT_M = 60.0  # low enough that the deck is inside zfar (1000 m) down to 3.4 deg
SKY_TEXTURE_SIZE = 128  # skybox face size: re-uploaded whenever the weather changes the sky


def padded_size(width: int, height: int) -> tuple[int, int, int, int]:
    """(padded width, padded height, margin x, margin y) of the actor-alone canvas: the one
    definition of the framebuffer size (``build_spec``) and of the canvas (``FrameRenderer``)."""
    margin_x = math.ceil(width * TRUNCATION_MARGIN)
    margin_y = math.ceil(height * TRUNCATION_MARGIN)
    return width + 2 * margin_x, height + 2 * margin_y, margin_x, margin_y


def horizontal_to_vertical_fov(hfov_deg: float, width: int, height: int) -> float:
    """Vertical FOV (degrees) of square pixels with horizontal FOV ``hfov_deg`` at W x H."""
    return math.degrees(2 * math.atan(math.tan(math.radians(hfov_deg) / 2) * height / width))


def _camera_quat() -> list[float]:
    """MuJoCo camera looking along +x of its body (camera x = -y world, y = +z world)."""
    xaxis, yaxis = np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0])
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
    spec.visual.quality.shadowsize = 2048
    # Tessellation of spheres, capsules and cylinders: 16 x 8 instead of MuJoCo's 28 x 16 halves
    # the software-rendered frame time (measured 183 -> 94 ms at 800x600) with no visible facets
    # at road distances.
    spec.visual.quality.numslices = 16
    spec.visual.quality.numstacks = 8
    spec.stat.extent = 100.0
    spec.stat.center = [0.0, 0.0, 0.0]
    spec.visual.map.znear = 0.001  # 0.1 m
    spec.visual.map.zfar = 10.0  # 1000 m
    spec.visual.map.shadowclip = 0.8
    base = weather_at(layout.sky, 0.0)
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
    spec.add_material(name="puddle", rgba=list(lighting.puddle_rgba), specular=0.6, shininess=0.9)
    for index, wall in enumerate(L.FACADES):
        # One tile = 4 floors x 4 windows, 12.8 m square.
        _add_texture_material(spec, f"facade{index}", textures.facade(tex_rng, wall), 1 / 12.8)

    world = spec.worldbody
    x_min, x_max = layout.road_x_range
    x_mid, x_half = (x_min + x_max) / 2, (x_max - x_min) / 2
    _static_box(world, "scenery/ground", [x_half + 200, 200, 0.05], [x_mid, 0, -0.07],
                material="grass")
    _static_box(world, "scenery/road", [x_half, L.ROAD_HALF_WIDTH, 0.05], [x_mid, 0, -0.05],
                material="asphalt")
    for side in (-1, 1):
        tag = "lr"[side > 0]
        y_mid = side * (L.ROAD_HALF_WIDTH + L.SIDEWALK_OUTER) / 2
        _static_box(world, f"scenery/sidewalk_{tag}",
                    [x_half, L.SIDEWALK_WIDTH / 2, L.CURB_HEIGHT / 2],
                    [x_mid, y_mid, L.CURB_HEIGHT / 2], material="concrete")
        _static_box(world, f"scenery/curb_{tag}", [x_half, 0.1, L.CURB_HEIGHT / 2 + 0.005],
                    [x_mid, side * (L.ROAD_HALF_WIDTH + 0.1), L.CURB_HEIGHT / 2],
                    rgba=(0.62, 0.62, 0.60, 1))
        # Solid edge lines between the outer lanes and the bicycle lanes.
        _static_box(world, f"scenery/edge_line_{tag}", [x_half, 0.075, STATIC_SURFACE_Z],
                    [x_mid, side * (L.NUM_LANES * L.LANE_WIDTH / 2), 0],
                    rgba=(0.92, 0.92, 0.90, 1))
    # Double yellow centre line.
    for offset in (-0.12, 0.12):
        _static_box(world, f"scenery/centre_line_{offset:+.2f}", [x_half, 0.06, STATIC_SURFACE_Z],
                    [x_mid, offset, 0], rgba=(0.95, 0.75, 0.10, 1))
    # Dashed lines between same-direction lanes: 3 m dashes every 9 m.
    dash_x = np.arange(math.floor(x_min / 9) * 9, x_max, 9.0)
    for side in (-1, 1):
        for x in dash_x:
            if abs(x - layout.crosswalk_x) < 4.0:
                continue
            _static_box(world, f"scenery/dash_{'lr'[side > 0]}_{x:.0f}",
                        [1.5, 0.075, STATIC_SURFACE_Z], [x, side * L.LANE_WIDTH, 0],
                        rgba=(0.92, 0.92, 0.90, 1))
    # Zebra crosswalk.
    stripe_ys = np.arange(-L.ROAD_HALF_WIDTH + 0.5, L.ROAD_HALF_WIDTH - 0.2, 1.0)
    for y in stripe_ys:
        _static_box(world, f"scenery/zebra_{y:+.1f}", [1.5, 0.25, STATIC_SURFACE_Z * 1.5],
                    [layout.crosswalk_x, y, 0], rgba=(0.93, 0.93, 0.91, 1))
    # The rain-cloud deck: an emissive ceiling that stands for the sky in rainy renders, so that
    # the wet road mirrors the sky (MuJoCo's mirror pass does not draw the skybox).
    spec.add_material(name="cloud_deck", rgba=[0.5, 0.5, 0.5, 1.0], emission=1.0, specular=0.0)
    world.add_geom(name="scenery/cloud_deck", type=GEOM.mjGEOM_BOX,
                   size=[x_half + 2000.0, 2000.0, 1.0], pos=[x_mid, 0.0, CLOUD_DECK_HEIGHT_M],
                   material="cloud_deck", group=CLOUD_DECK_GROUP, contype=0, conaffinity=0)
    for index, (x, y, half_length, half_width, yaw) in enumerate(layout.puddles):
        # full-size puddles; the renderer scales them with the weather's puddle fraction
        world.add_geom(name=f"scenery/puddle{index}", type=GEOM.mjGEOM_ELLIPSOID,
                       size=[half_length, half_width, 0.001], pos=[x, y, STATIC_SURFACE_Z * 2],
                       quat=parts.unit_yaw_quat(yaw).tolist(), material="puddle",
                       group=PUDDLE_GROUP, contype=0, conaffinity=0)
    for index, building in enumerate(layout.buildings):
        facade = L.FACADES.index(building.facade)
        sx, sy, sz = building.size
        _static_box(world, f"scenery/building{index}", [sx / 2, sy / 2, sz / 2],
                    [building.centre[0], building.centre[1], sz / 2], material=f"facade{facade}")
    trunk, foliage = (0.35, 0.25, 0.16, 1), (0.18, 0.38, 0.15, 1)
    for index, (x, side) in enumerate(layout.tree_xs):
        y = side * L.TREE_Y
        world.add_geom(name=f"scenery/tree{index}_trunk", type=GEOM.mjGEOM_CYLINDER,
                       size=[0.15, 1.6, 0], pos=[x, y, 1.6], rgba=list(trunk),
                       contype=0, conaffinity=0)
        world.add_geom(name=f"scenery/tree{index}_crown", type=GEOM.mjGEOM_ELLIPSOID,
                       size=[1.9, 1.9, 2.3], pos=[x, y, 4.9], rgba=list(foliage),
                       contype=0, conaffinity=0)
        world.add_geom(name=f"scenery/tree{index}_crown_top", type=GEOM.mjGEOM_SPHERE,
                       size=[1.3, 0, 0], pos=[x + 0.3, y, 6.6],
                       rgba=[0.22, 0.44, 0.18, 1], contype=0, conaffinity=0)
    for index, (x, side) in enumerate(layout.pole_xs):
        y = side * L.POLE_Y
        world.add_geom(name=f"scenery/pole{index}", type=GEOM.mjGEOM_CYLINDER,
                       size=[0.08, 4.0, 0], pos=[x, y, 4.0], rgba=list(parts.METAL),
                       contype=0, conaffinity=0)
        world.add_geom(name=f"scenery/pole{index}_arm", type=GEOM.mjGEOM_CAPSULE,
                       size=[0.05, 0, 0], fromto=[x, y, 7.8, x, y - side * 1.8, 8.0],
                       rgba=list(parts.METAL), contype=0, conaffinity=0)
        _static_box(world, f"scenery/pole{index}_lamp", [0.3, 0.15, 0.06],
                    [x, y - side * 1.9, 7.95], rgba=(0.9, 0.9, 0.8, 1))

    # Ego: a mocap body carrying the camera and the sun (so the shadow map follows the view).
    ego = world.add_body(name="ego", mocap=True, pos=[layout.ego.start_xy[0],
                                                      layout.ego.start_xy[1], 0.0])
    ego.add_camera(name=EGO_CAMERA, pos=[0.6, 0.0, layout.camera_height], quat=_camera_quat(),
                   fovy=horizontal_to_vertical_fov(hfov_deg, width, height))
    sun = np.asarray(layout.sun_direction)
    ego.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                  pos=(np.array([35.0, 0.0, 0.0]) - 60.0 * sun).tolist(), dir=sun.tolist(),
                  castshadow=lighting.sun_castshadow, diffuse=list(lighting.sun_diffuse),
                  specular=[lighting.sun_specular] * 3, ambient=[0.0, 0.0, 0.0])
    ego.add_light(name="skylight", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
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
                parts.add_car(body, prefix, unit.style, unit.colours["paint"])
            elif actor.role == "pedestrian":
                parts.add_person(body, prefix, unit.colours)
            elif actor.role == "bicycle":
                saddle = parts.add_bicycle(body, prefix, unit.colours["frame"])
            elif actor.role == "motorcycle":
                saddle = parts.add_motorcycle(body, prefix, unit.colours["frame"])
            elif actor.role == "rider":
                helmet = unit.colours["helmet"]
                back = -0.20 if unit.kind == "bicycle" else -0.30
                parts.add_person(body, prefix, unit.colours, pos=(back, 0.0, saddle - 0.93),
                                 helmet=helmet)
            else:
                raise ValueError(f"actor role: unknown {actor.role!r}")
    return spec


def weather_sky_endpoints(weather) -> tuple[list[float], list[float]]:
    """(zenith, horizon) RGB of ``weather``'s sky, for the builtin gradient of an exported scene."""
    zenith, horizon = sky_colours(weather, np.array([1.0, 0.0]))
    return zenith.tolist(), horizon.tolist()


def geom_instance_table(model: mujoco.MjModel) -> np.ndarray:
    """(ngeom,) int32: the actor instance id of every geom, -1 for static scenery."""
    table = np.full(model.ngeom, -1, dtype=np.int32)
    for geom_id in range(model.ngeom):
        name = model.geom(geom_id).name
        if name.startswith("actor"):
            table[geom_id] = int(name[5:8])
    return table


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
