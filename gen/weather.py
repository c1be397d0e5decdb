"""Weather between renders: writes a :class:`~rainbench.rain.weather.Weather` into a compiled
model (lights, materials, sky texels) without rebuilding it.

:class:`WeatherRig` changes only model fields that MuJoCo's renderer reads at every render
(``light_*``, ``vis.headlight``, ``mat_rgba``, ``mat_reflectance``) plus the sky texture, which it
re-uploads to the GL context when the sky changes. Puddles are not drawn by MuJoCo: the rig keeps
their outlines (:attr:`WeatherRig.puddles`, from the scene's ``scenery/puddle*`` geoms) and the
weather's :attr:`WeatherRig.puddle_scale`, and the renderer lays them over the image
(:func:`rainbench.rain.weather.puddle_coverage`).
Actors, poses and the camera are never touched, so labels of the clean geometry hold at every rate.

At dusk and night (scenes with the lights of :mod:`rainbench.mjcf.lights`) it also writes the
street light and headlight levels, and :meth:`WeatherRig.select_lights` switches on, before each
render, the lights that matter most to the camera: OpenGL lights only the first 8 active lights.
"""

from __future__ import annotations

import math

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np

from rainbench.mjcf import lights as tod
from rainbench.mjcf.scene import CLOUD_TEXTURE
from rainbench.mjcf.weather import scene_lighting
from rainbench.rain.weather import (CLOUD_BASE_M, CLOUD_EDGE_RANKS, CLOUD_TILE_M, Weather,
                                     puddle_outline_phases, puddle_ripple_slope, sky_colours,
                                     sky_key)

ROAD_LEVEL_TOLERANCE_M = 0.005
"""Road slabs whose tops lie within this of the mirrored one's are level with it (one mirror
plane): every other box of a curved road stands 1 mm higher
(:data:`rainbench.mjcf.layout.ARC_OVERLAP_LIFT_M`); an overpass deck is metres up."""
MIRROR_AHEAD_M = 15.0
"""Where the wet road's mirror matters most: Fresnel's weight grows with distance, the road's
image shrinks; the road geom under this point ahead of the camera is the one mirrored."""


def skybox_directions(size: int) -> np.ndarray:
    """(6 * size * size, 3) float64: the world direction (unit vector, +z up) of every skybox
    texel's centre, as MuJoCo lays them out.

    Faces in order: +x, -x, +z, -z, -y, +y; within a face, columns and rows as measured on
    mujoco 4.0.0 by rendering texels that encode their direction (tested against a render:
    within 1 degree). The z component is the sine of the texel's elevation.
    """
    centre = 2.0 * (np.arange(size) + 0.5) / size - 1.0
    a, b = np.meshgrid(centre, -centre)  # a: along the row (columns); b: up the face (rows)
    one = np.ones_like(a)
    faces = [(one, a, b), (-one, -a, b), (a, b, one), (a, -b, -one), (a, -one, b), (-a, one, b)]
    directions = np.concatenate([np.stack(face, axis=-1).reshape(-1, 3) for face in faces])
    return directions / np.linalg.norm(directions, axis=1, keepdims=True)


_CLOUD_MIN_SIN_ELEVATION = 0.01  # texels below it read the field at 150 km (they fade anyway)
CLOUD_SMOOTH_CELLS = 1.5
"""Standard deviation, in the cloud field's cells, of the Gaussian the field is smoothed with
before the sky reads it: bilinear between cells, a field rough from cell to cell draws its cloud
edges as the cells' squares (blocky clouds in light rain)."""
CLOUD_EDGE_TEXELS = 2.0
"""A cloud edge spans at least this many sky texels (:func:`skybox_edge_ranks`)."""


def cloud_field_ranks(levels: np.ndarray) -> np.ndarray:
    """(H, W) float64 ranks in 0..1 of a tileable cloud field ``levels`` (H, W) (any numbers:
    only their order counts), after a periodic Gaussian smoothing of ``CLOUD_SMOOTH_CELLS``
    cells; uniform over the field (each cell's rank is its place in the sorted field, ``(i +
    1/2) / (H W)``), so a cover c puts a share c of it under cloud."""
    levels = np.asarray(levels, dtype=np.float64)
    if levels.ndim != 2 or min(levels.shape) < 1:
        raise ValueError(f"cloud field: expected (H, W) levels, got shape {levels.shape}")
    height, width = levels.shape
    frequency_y = np.fft.fftfreq(height)[:, None]
    frequency_x = np.fft.fftfreq(width)[None, :]
    smoothing = np.exp(-2.0 * np.pi ** 2 * CLOUD_SMOOTH_CELLS ** 2
                       * (frequency_x ** 2 + frequency_y ** 2))
    smooth = np.fft.ifft2(np.fft.fft2(levels) * smoothing).real
    order = np.argsort(smooth, axis=None, kind="stable")
    ranks = np.empty(levels.size, np.float64)
    ranks[order] = (np.arange(levels.size) + 0.5) / levels.size
    return ranks.reshape(height, width)


def skybox_edge_ranks(ranks: np.ndarray) -> np.ndarray:
    """(6 * S * S,) float64: the cloud edge width (ranks) for each skybox texel whose cloud rank
    is ``ranks`` (6 * S * S,) (:func:`skybox_cloud_ranks` of :func:`skybox_directions` (S)):
    ``CLOUD_EDGE_RANKS``, or wider where the ranks step so fast between neighbouring texels that
    an edge would be sharper than ``CLOUD_EDGE_TEXELS`` texels (the far layer, seen at a slant).
    The texture's bilinear filter then draws the edge as a ramp, not as steps of texels."""
    ranks = np.asarray(ranks, dtype=np.float64)
    size = int(round(math.sqrt(ranks.size / 6)))
    if ranks.ndim != 1 or 6 * size * size != ranks.size or size < 2:
        raise ValueError(f"skybox ranks: expected (6 * S * S,) with S >= 2, got {ranks.shape}")
    faces = ranks.reshape(6, size, size)
    steps = []
    for axis in (1, 2):  # the larger step to either neighbour (a ridge's are both ways)
        step = np.abs(np.diff(faces, axis=axis))
        before = np.concatenate([np.take(step, [0], axis=axis), step], axis=axis)
        after = np.concatenate([step, np.take(step, [-1], axis=axis)], axis=axis)
        steps.append(np.maximum(before, after))
    return np.maximum(CLOUD_EDGE_RANKS, CLOUD_EDGE_TEXELS * np.hypot(*steps)).reshape(-1)


def skybox_cloud_ranks(model: mujoco.MjModel, directions: np.ndarray) -> np.ndarray | None:
    """(N,) float64 in 0..1: where each of ``directions`` (N, 3) (unit vectors, +z up; a skybox's
    texels: :func:`skybox_directions`) meets the scene's cloud layer, the rank of the cloud field
    there (:func:`cloud_field_ranks`), bilinear. The field is the scene's texture ``clouds``
    (:func:`rainbench.mjcf.scene.build_spec`), tiled over ``CLOUD_TILE_M`` on a layer
    ``CLOUD_BASE_M`` above the camera. Ranks are uniform over the field, so a cloud cover c
    covers a share c of it. None when the scene has no cloud field.
    """
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, CLOUD_TEXTURE)
    if index < 0:
        return None
    width, height = int(model.tex_width[index]), int(model.tex_height[index])
    channels, start = int(model.tex_nchannel[index]), int(model.tex_adr[index])
    ranks = cloud_field_ranks(model.tex_data[start:start + width * height * channels].reshape(
        height, width, channels)[:, :, 0])
    reach = CLOUD_BASE_M / np.maximum(directions[:, 2], _CLOUD_MIN_SIN_ELEVATION)
    x = directions[:, 0] * reach / CLOUD_TILE_M * width
    y = directions[:, 1] * reach / CLOUD_TILE_M * height
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.astype(np.int64) % width, y0.astype(np.int64) % height
    x1, y1 = (x0 + 1) % width, (y0 + 1) % height
    return ((ranks[y0, x0] * (1.0 - fx) + ranks[y0, x1] * fx) * (1.0 - fy)
            + (ranks[y1, x0] * (1.0 - fx) + ranks[y1, x1] * fx) * fy)


def _ids(model: mujoco.MjModel, kind: mujoco.mjtObj, names) -> dict[str, int]:
    """Ids of the named objects that ``model`` has (a custom scene may lack some)."""
    found = {name: mujoco.mj_name2id(model, kind, name) for name in names}
    return {name: index for name, index in found.items() if index >= 0}


def scene_time_of_day(model: mujoco.MjModel) -> str:
    """The time of day a scene was built for: its custom text ``rainbench/time_of_day``
    (:func:`rainbench.mjcf.lights.add_time_of_day_lights`), ``day`` when it has none."""
    index = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, tod.TIME_OF_DAY_TEXT)
    if index < 0:
        return "day"
    start = int(model.text_adr[index])
    return bytes(model.text_data[start:start + int(model.text_size[index]) - 1]).decode()


def render_key(weather: Weather) -> tuple:
    """Everything a weather changes in a render: two weathers with one key render the same
    image (heavy rates differ only in light level and camera, applied after the render; the
    puddles' ripples stop changing from about 10 mm/h)."""
    ripples = round(puddle_ripple_slope(weather.rain_mm_h), 6) if weather.puddle_fraction else 0.0
    return scene_lighting(weather), sky_key(weather), ripples


class WeatherRig:
    """Applies weathers to ``model``: a scene of :func:`rainbench.mjcf.scene.build_spec`, or any
    scene with a skybox texture ``sky`` and lights ``sun`` and ``skylight``; the materials
    ``asphalt`` (the mirroring road), ``concrete``, ``grass`` and ``cloud_deck`` are used when
    present.

    :attr:`puddles` is (N, 6) float64, each ``(x, y, z, half_length, half_width, yaw)`` of a
    ``scenery/puddle*`` ellipsoid geom at full size (yaw about +z in radians), and
    :attr:`puddle_phases` their outline phases; :attr:`puddle_scale` is the applied weather's
    linear puddle size (0: none)."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        lights = _ids(model, mujoco.mjtObj.mjOBJ_LIGHT, ("sun", "skylight"))
        if len(lights) != 2 or mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, "sky") < 0:
            raise ValueError("weather: expected lights 'sun' and 'skylight' and a skybox texture "
                             "'sky' in the scene (see rainbench.mjcf.scene.build_spec)")
        self._sun, self._skylight = lights["sun"], lights["skylight"]
        self._materials = _ids(model, mujoco.mjtObj.mjOBJ_MATERIAL,
                               ("asphalt", "concrete", "grass", "cloud_deck"))
        geoms = np.array([g for g in range(model.ngeom)
                          if model.geom(g).name.startswith("scenery/puddle")], np.int64)
        quat = model.geom_quat[geoms]
        yaw = 2.0 * np.arctan2(quat[:, 3], quat[:, 0])  # the geoms turn about +z only
        self.puddles = np.column_stack([model.geom_pos[geoms], model.geom_size[geoms, :2], yaw]
                                       ).astype(np.float64).reshape(-1, 6)
        self.puddle_phases = puddle_outline_phases(len(geoms))
        self.puddle_scale = 0.0
        sky = model.texture("sky")
        self._sky_id = int(sky.id)
        size = int(model.tex_width[self._sky_id])
        self._sky_slice = slice(int(model.tex_adr[self._sky_id]),
                                int(model.tex_adr[self._sky_id]) + 6 * size * size * 3)
        directions = skybox_directions(size)
        self._sky_sin = directions[:, 2]
        self._sky_cloud_ranks = skybox_cloud_ranks(model, directions)
        self._sky_edge_ranks = (None if self._sky_cloud_ranks is None
                                else skybox_edge_ranks(self._sky_cloud_ranks))
        self._sky_key: tuple | None = None
        self._sky_texels: dict[tuple, np.ndarray] = {}
        self.cloud_deck = False
        self.road_reflectance = 0.0
        self.time_of_day = scene_time_of_day(model)
        names = [model.light(i).name for i in range(model.nlight)]
        self._ego_beams = np.array([i for i, n in enumerate(names) if n in tod.EGO_BEAM_NAMES],
                                   np.int64)
        self._lamps = np.array([i for i, n in enumerate(names)
                                if n.startswith(tod.LIGHT_PREFIX + "lamp")], np.int64)
        self._vehicle_beams = np.array([i for i, n in enumerate(names)
                                        if n.startswith(tod.LIGHT_PREFIX) and n.endswith("_beam")
                                        and i not in self._ego_beams], np.int64)
        self._candidates = np.concatenate([self._lamps, self._vehicle_beams])
        lamp_materials = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, name)
                          for name in tod.LAMP_MATERIALS]
        self.lamp_geoms = np.flatnonzero(np.isin(model.geom_matid,
                                                 [m for m in lamp_materials if m >= 0]))
        """(L,) int64: the geoms drawn as lights (head and tail lights, street lamp heads)."""
        material_names = {m: name for m, name in zip(lamp_materials, tod.LAMP_MATERIALS) if m >= 0}
        self.lamp_kinds = tuple(tod.LAMP_KINDS[material_names[int(m)]]
                                for m in model.geom_matid[self.lamp_geoms])
        """(L,) each lamp geom's kind: ``"head"``, ``"tail"`` or ``"street"``."""
        self._lamp_not_box = model.geom_type[self.lamp_geoms] != mujoco.mjtGeom.mjGEOM_BOX
        self._lamp_colours = np.array([tod.lamp_colour(kind) for kind in self.lamp_kinds],
                                      np.float64).reshape(-1, 3)
        # by day the vehicle lamps are built dark (tod.add_dark_vehicle_lamps), lit in dark rain
        headlamp, taillamp, _ = lamp_materials
        self._day_lamp_materials = (headlamp, taillamp) if min(headlamp, taillamp) >= 0 else None
        self._tail_geoms = (np.flatnonzero(model.geom_matid == taillamp)
                            if self._day_lamp_materials else np.zeros(0, np.int64))
        self._tail_rgba = model.geom_rgba[self._tail_geoms].copy()
        self.vehicle_lamps = self.time_of_day != "day"
        """Whether the vehicles' lamps glow in the applied weather (set by :meth:`apply`)."""
        asphalt = self._materials.get("asphalt", -2)
        self._mirror_candidates = np.flatnonzero(model.geom_matid == asphalt)
        # road geoms of the world body never move: their tops are measured once
        self._tops_are_static = bool(np.all(model.geom_bodyid[self._mirror_candidates] == 0))
        self._static_tops: np.ndarray | None = None
        self.light_budget = 0  # candidate lights OpenGL can still light (set by apply)

    def select_lights(self, data: mujoco.MjData, camera_id: int) -> None:
        """Switch on the street lights and vehicle beams that matter most to camera
        ``camera_id`` in the state ``data`` (call before each ``mjv_updateScene``), at most
        :attr:`light_budget` of them; the others are switched off.

        A street light's pool is a disc of :data:`~rainbench.mjcf.lights.POOL_RADIUS_M` under its
        lamp; a vehicle beam's is centred :data:`~rainbench.mjcf.lights.VEHICLE_BEAM_REACH_M`
        ahead of it. Pools with some part in front of the camera are ranked by how far their edge
        is from the road the camera sees best (:data:`~rainbench.mjcf.lights.FOCUS_AHEAD_M`
        ahead); ties go to the lower light id. Deterministic: the same state lights the same
        lamps.
        """
        if not self._candidates.size:
            return
        camera = data.cam_xpos[camera_id][:2]
        forward = -data.cam_xmat[camera_id].reshape(3, 3)[:2, 2]
        forward = forward / max(float(np.linalg.norm(forward)), 1e-9)
        position = data.light_xpos[self._candidates][:, :2].copy()
        direction = data.light_xdir[self._candidates][:, :2]
        radius = np.full(len(self._candidates), tod.POOL_RADIUS_M)
        beams = np.arange(len(self._candidates)) >= len(self._lamps)
        position[beams] += tod.VEHICLE_BEAM_REACH_M * direction[beams] / np.maximum(
            np.linalg.norm(direction[beams], axis=1, keepdims=True), 1e-9)
        radius[beams] = tod.VEHICLE_BEAM_REACH_M
        offset = position - camera
        ahead = offset @ forward > -radius  # some of the pool is in front of the camera
        focus = camera + tod.FOCUS_AHEAD_M * forward
        edge = np.maximum(np.linalg.norm(position - focus, axis=1) - radius, 0.0)
        order = np.lexsort((np.arange(len(edge)), edge, ~ahead))
        chosen = order[:self.light_budget]
        chosen = chosen[ahead[chosen]]
        active = np.zeros(len(self._candidates), np.uint8)
        active[chosen] = 1
        self.model.light_active[self._candidates] = active

    def mirror_geom(self, data: mujoco.MjData, camera_id: int) -> int:
        """The road geom (material ``asphalt``) to draw as the mirror for camera ``camera_id``:
        the one under the point :data:`MIRROR_AHEAD_M` ahead of the camera, else the one under
        the camera, else the nearest; -1 when the scene has none.

        MuJoCo mirrors only the first reflective geom of a scene; a road built of several boxes
        or planes (straights, arcs, gaps at crosswalks) must choose the one the camera sees.
        """
        if not self._mirror_candidates.size:
            return -1
        if self._mirror_candidates.size == 1:
            return int(self._mirror_candidates[0])
        ids = self._mirror_candidates
        camera = data.cam_xpos[camera_id]
        forward = -data.cam_xmat[camera_id].reshape(3, 3)[:, 2].copy()
        forward[2] = 0.0
        forward /= max(float(np.linalg.norm(forward)), 1e-9)
        half = self.model.geom_size[ids, :2]
        rotation = data.geom_xmat[ids].reshape(-1, 3, 3)
        for point in (camera + MIRROR_AHEAD_M * forward, camera):
            local = np.einsum("gji,gj->gi", rotation, point - data.geom_xpos[ids])[:, :2]
            inside = np.all(np.abs(local) <= half, axis=1)
            if inside.any():
                return int(ids[np.flatnonzero(inside)[0]])
        distance = np.linalg.norm(data.geom_xpos[ids, :2] - camera[:2], axis=1)
        return int(ids[int(np.argmin(distance))])

    def top_rectangle(self, data: mujoco.MjData, geom: int) -> np.ndarray:
        """(6,) float64 ``(x, y, z, half_length, half_width, yaw)`` of road geom ``geom``'s top
        face in the state ``data`` (the plane MuJoCo mirrors): a box's top, or a plane
        (half sides inf where its size is 0). Road geoms are level (they turn about +z only)."""
        size = self.model.geom_size[geom]
        rotation = data.geom_xmat[geom].reshape(3, 3)
        x, y, z = data.geom_xpos[geom]
        yaw = math.atan2(rotation[1, 0], rotation[0, 0])
        if self.model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_PLANE:
            half = [float(s) if s > 0 else math.inf for s in size[:2]]
            return np.array([x, y, z, half[0], half[1], yaw], np.float64)
        return np.array([x, y, z + size[2], size[0], size[1], yaw], np.float64)

    def mirror_plane(self, data: mujoco.MjData, geom: int
                     ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """The road's mirror plane through road geom ``geom``'s top: ``(cover, slabs, others)``.

        ``slabs``: (K, 6) :meth:`top_rectangle` of every road geom whose top is level with
        ``geom``'s (within :data:`ROAD_LEVEL_TOLERANCE_M`; a road of several slabs: straights,
        arcs, the crossing street), ``geom``'s first, all at ``geom``'s height; ``others``: (K - 1,) int64 ids of those other than ``geom``. ``cover``: (6,) the
        smallest rectangle at ``geom``'s yaw holding them all: drawn as the one mirror (the
        others out of its way), it mirrors every slab in one pass (MuJoCo mirrors one geom a
        render); None when a slab is an unbounded plane (it mirrors everywhere already).
        """
        ids = self._mirror_candidates
        tops = self._static_tops
        if tops is None:
            tops = np.array([self.top_rectangle(data, int(g)) for g in ids])
            if self._tops_are_static:
                self._static_tops = tops
        mine = ids == geom
        own = tops[int(np.flatnonzero(mine)[0])]
        level = (np.abs(tops[:, 2] - own[2]) <= ROAD_LEVEL_TOLERANCE_M) & ~mine
        slabs = np.concatenate([own[None], tops[level]])
        slabs[:, 2] = own[2]  # one plane: an arc's boxes stand 0 or 1 mm up, alternately
        others = ids[level].astype(np.int64)
        if np.isinf(slabs[:, 3:5]).any():  # an unbounded plane: nothing to stretch
            return None, slabs, others
        corners = []
        for x, y, _, half_length, half_width, yaw in slabs:
            axes = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])
            for sign_l, sign_w in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                corners.append(np.array([x, y]) + sign_l * half_length * axes[0]
                               + sign_w * half_width * axes[1])
        yaw = own[5]
        frame = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])
        local = (np.array(corners) - own[:2]) @ frame.T
        low, high = local.min(axis=0), local.max(axis=0)
        centre = own[:2] + ((low + high) / 2) @ frame
        half = (high - low) / 2
        return np.array([centre[0], centre[1], own[2], half[0], half[1], yaw]), slabs, others

    def lamp_spheres(self, data: mujoco.MjData) -> np.ndarray:
        """(L, 4) float64 ``(x, y, z, radius)``: each of :attr:`lamp_geoms`' centre in the state
        ``data`` and its bounding radius, metres."""
        return np.column_stack([data.geom_xpos[self.lamp_geoms],
                                self.model.geom_rbound[self.lamp_geoms]])

    def lamp_boxes(self, data: mujoco.MjData) -> np.ndarray:
        """(L, 15) float64: each of :attr:`lamp_geoms` as a box in the state ``data``: centre (3),
        rotation (9, row-major, world from the geom's axes) and half sizes (3), metres; NaN rows
        for lamps that are not boxes (:func:`rainbench.rain.weather.mirrored_light_pixels`)."""
        geoms = self.lamp_geoms
        boxes = np.column_stack([data.geom_xpos[geoms], data.geom_xmat[geoms],
                                 self.model.geom_size[geoms]]).astype(np.float64).reshape(-1, 15)
        boxes[self._lamp_not_box] = np.nan
        return boxes

    def lamp_lights(self, data: mujoco.MjData, viewer: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The scene's lights as seen from ``viewer`` ((3,) world metres) in the state ``data``:
        ``(centres (L, 3) m, intensity towards the viewer (L,) cd, colours (L, 3) in 0..1)``
        (:func:`rainbench.mjcf.lights.lamp_intensity_cd`; a vehicle's forward axis is its
        body's x axis)."""
        centres = data.geom_xpos[self.lamp_geoms].astype(np.float64)
        forwards = data.xmat[self.model.geom_bodyid[self.lamp_geoms]].reshape(-1, 9)[:, [0, 3, 6]]
        intensity = tod.lamp_intensity_cd(self.lamp_kinds, centres, forwards, viewer)
        return centres, intensity, self._lamp_colours

    def set_mirror(self, on: bool) -> None:
        """Full mirror reflectance on the road (``on``), or none."""
        if "asphalt" in self._materials:
            self.model.mat_reflectance[self._materials["asphalt"]] = 1.0 if on else 0.0

    def apply(self, weather: Weather, context: mujoco.MjrContext | None) -> None:
        """Write ``weather`` into the model; upload the sky to ``context`` if it changed."""
        if weather.time_of_day != self.time_of_day:
            raise ValueError(f"weather: expected time_of_day {self.time_of_day!r} (the scene's "
                             f"lights), got {weather.time_of_day!r}")
        model, lighting = self.model, scene_lighting(weather)
        model.light_diffuse[self._sun] = lighting.sun_diffuse
        model.light_specular[self._sun] = lighting.sun_specular
        model.light_castshadow[self._sun] = lighting.sun_castshadow
        model.light_diffuse[self._skylight] = lighting.skylight_diffuse
        model.vis.headlight.ambient = lighting.headlight_ambient
        model.vis.headlight.diffuse = [lighting.headlight_diffuse] * 3
        if self.time_of_day != "day":  # by day the model's lights are left exactly as built
            model.light_active[self._sun] = lighting.sun_active
            model.light_active[self._skylight] = lighting.skylight_active
            model.light_diffuse[self._ego_beams] = np.multiply(lighting.beam_diffuse, tod.BEAM_GAIN)
            model.light_diffuse[self._vehicle_beams] = np.multiply(lighting.beam_diffuse,
                                                                   tod.BEAM_GAIN)
            model.light_diffuse[self._lamps] = np.multiply(lighting.lamp_diffuse, tod.LAMP_GAIN)
            used = (int(bool(model.vis.headlight.active)) + int(lighting.sun_active)
                    + int(lighting.skylight_active) + len(self._ego_beams))
            self.light_budget = max(tod.GL_MAX_LIGHTS - used, 0)
        elif self._day_lamp_materials is not None:
            lit = lighting.vehicle_lamps
            headlamp, taillamp = self._day_lamp_materials
            model.mat_emission[headlamp] = tod.HEADLAMP_EMISSION if lit else 0.0
            model.mat_emission[taillamp] = tod.TAILLAMP_EMISSION if lit else 0.0
            model.geom_rgba[self._tail_geoms] = tod.TAILLAMP_RGBA if lit else self._tail_rgba
        self.vehicle_lamps = lighting.vehicle_lamps and len(self.lamp_geoms) > 0
        materials = self._materials
        for name, factor in (("asphalt", lighting.road_factor),
                             ("concrete", lighting.pavement_factor),
                             ("grass", lighting.grass_factor)):
            if name in materials:
                model.mat_rgba[materials[name]] = [factor, factor, factor, 1.0]
        self.road_reflectance = lighting.road_reflectance if "asphalt" in materials else 0.0
        if "asphalt" in materials:  # the renderer draws the mirror itself (FrameRenderer)
            model.mat_reflectance[materials["asphalt"]] = 0.0
        self.puddle_scale = lighting.puddle_scale if len(self.puddles) else 0.0
        if "cloud_deck" in materials:
            model.mat_rgba[materials["cloud_deck"]] = lighting.cloud_deck_rgba
        self.cloud_deck = "cloud_deck" in materials and lighting.cloud_deck
        key = sky_key(weather)
        if key != self._sky_key:
            if key not in self._sky_texels:  # a clip's sweep has a handful of skies
                self._sky_texels[key] = np.rint(sky_colours(
                    weather, self._sky_sin, self._sky_cloud_ranks, self._sky_edge_ranks) * 255.0
                ).astype(np.uint8).reshape(-1)
            model.tex_data[self._sky_slice] = self._sky_texels[key]
            if context is not None:
                mujoco.mjr_uploadTexture(model, context, self._sky_id)
            self._sky_key = key
