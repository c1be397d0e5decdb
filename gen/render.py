"""Offscreen rendering of the ego camera: RGB, depth, instance segmentation, actor-alone passes.

:class:`FrameRenderer` owns one GL context and one ``MjrContext`` (use it with ``with``). It
follows ``mujoco.Renderer`` but reads RGB and depth from the same rasterisation, decodes
segmentation straight to actor instance ids, and renders chosen actors alone on a padded canvas
(same focal length, larger field of view) to measure occlusion and truncation.
"""

from __future__ import annotations

import ctypes
import math
import os
import threading
import warnings
from collections.abc import Callable

import cv2
from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np

from rainbench.mjcf.scene import CLOUD_DECK_GEOM, CLOUD_DECK_GROUP, EGO_CAMERA, PUDDLE_GROUP, padded_size  # noqa: F401 -- padded_size re-exported
from rainbench.rain.weather import (CLIPPED_GAIN, PUDDLE_MIRROR_REFLECTANCE, Weather, add_glow,
                                     film_streak_sigma_px, light_glow, mirrored_light_pixels,
                                     plane_pixels,
                                     puddle_coverage_at, puddle_pixels, puddle_ripple_slope,
                                     puddle_water,
                                     road_mirror_weight, streak_reflection)

from rainbench.gl import GLBackendError, check_pyopengl_platform, context_failure_message
from rainbench.gl import state as _gl_state
from .weather import WeatherRig

HIDDEN_GROUP = 5
MIRROR_SCALE = 0.5
"""The wet road's mirror image is rendered at half the width and height and resized: rain-
roughened water mirrors a blurred world (a sharp mirror looked like glass), and the pass costs
a quarter of the pixels."""
COVERED_DROP_M = 1.0
"""How far the road's other slabs are lowered in the mirror render, under the one stretched
mirror geom (level with it they would draw over its reflection)."""
MIRROR_SKY_REACH_M = 60_000.0
"""How far the wet road's mirror pass sees: its far clip plane and the half size of the cloud deck,
centred under the camera in that pass. The main pass draws the road out to zfar (1 000 m); a
camera 1 m above it sees that point's mirror ray rise 1 / 1 000 rad, which meets the deck (60 m
up) 60 km away. With the model's own zfar and deck, rays under 3.4 degrees (the road beyond
about 25 m) met nothing and mirrored black: the far wet road went dark where it should mirror
the sky (bench/RESULTS.md)."""
CULL_MARGIN_M = 0.5
"""Slack beyond a geom's bounding sphere before :meth:`FrameRenderer.hidden_geoms` leaves it out
of a pass (rounding in the GL pipeline never reaches it)."""


class PendingImage:
    """An image whose GL passes are done and whose array work is not: :meth:`result` does that
    work once, in whichever thread calls it first, and returns the (H, W, 3) uint8 image.

    :meth:`FrameRenderer.start_weather` and :meth:`FrameRenderer.start_glow` make them, so the
    thread that holds the GL context can simulate and render the next frame while pool threads
    finish this one's weather images (the wet road's mirror blend, puddles, lamp glow). The work
    reads only what was captured when the passes ran, so the image is the same whichever thread
    finishes it, and whenever."""

    def __init__(self, finish: Callable[[], np.ndarray]) -> None:
        self._finish: Callable[[], np.ndarray] | None = finish
        self._image: np.ndarray | None = None
        self._lock = threading.Lock()

    @classmethod
    def done(cls, image: np.ndarray) -> "PendingImage":
        """An image with no work left."""
        pending = cls(lambda: image)
        pending._image, pending._finish = image, None
        return pending

    def result(self) -> np.ndarray:
        """The finished (H, W, 3) uint8 image (computed on the first call)."""
        with self._lock:
            if self._image is None:
                self._image = self._finish()
                self._finish = None
            return self._image


class _FrameCache:
    """What one frame's weathers share (it depends only on the frame's geometry: the road's
    pixels, the lamps' mirror images, the puddles' pixels), built once; thread-safe."""

    def __init__(self) -> None:
        self._entries: dict[str, tuple[bytes, object]] = {}
        self._lock = threading.Lock()

    def get(self, name: str, key: bytes, build: Callable[[], object]):
        """``build()``, kept while ``key`` stays the same for ``name``."""
        with self._lock:
            entry = self._entries.get(name)
            if entry is None or entry[0] != key:
                entry = self._entries[name] = (key, build())
            return entry[1]


def camera_intrinsics(model: mujoco.MjModel, camera: str, width: int, height: int) -> np.ndarray:
    """(3, 3) float64 pinhole K of ``camera`` at W x H (square pixels, centred principal point)."""
    fovy = math.radians(float(model.camera(camera).fovy[0]))
    focal = (height / 2) / math.tan(fovy / 2)
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def camera_pose(model: mujoco.MjModel, data: mujoco.MjData, camera: str) -> np.ndarray:
    """(4, 4) float64 T_world_cam in OpenCV axes (x right, y down, z forward)."""
    cam = data.camera(camera)
    rotation = cam.xmat.reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = cam.xpos
    return pose


SCENE_GEOM_RECORD = np.dtype({"names": ["objtype", "objid", "segid"], "formats": ["<i4"] * 3,
                              "offsets": [8, 12, 36], "itemsize": 256})
"""Where MuJoCo's ``mjvGeom`` (``mujoco/mjvisualize.h``, mujoco 4.0) holds the fields the
segmentation decode reads: ``int type, dataid, objtype, objid, category, matid, texid,
texuniform, texcoord, segid`` lead the struct, then ``float size[3]`` at byte 40; 256 bytes a
geom."""
_SIZE_OFFSET = 40


def scene_geom_records(scene: mujoco.MjvScene) -> np.ndarray | None:
    """The geoms of ``scene`` as a (maxgeom,) :data:`SCENE_GEOM_RECORD` array viewing the scene's
    own memory (valid while ``scene`` lives, and current after each ``mjv_updateScene``), or
    None where the bindings' geoms are not laid out ``itemsize`` bytes apart (another MuJoCo)."""
    geoms = scene.geoms
    if len(geoms) < 2:
        return None
    first = geoms[0].size.ctypes.data
    if geoms[1].size.ctypes.data - first != SCENE_GEOM_RECORD.itemsize:
        return None
    memory = (ctypes.c_char * (SCENE_GEOM_RECORD.itemsize * len(geoms))).from_address(first - _SIZE_OFFSET)
    return np.frombuffer(memory, dtype=SCENE_GEOM_RECORD)


def _shown_geoms(records: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(segid, model geom id) int64 of the model geoms among ``records`` that are shown."""
    shown = (records["objtype"] == int(mujoco.mjtObj.mjOBJ_GEOM)) & (records["segid"] >= 0)
    return records["segid"][shown].astype(np.int64), records["objid"][shown].astype(np.int64)


def _shown_geoms_one_by_one(scene: mujoco.MjvScene) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_shown_geoms` of ``scene`` through the bindings' attributes, geom by geom."""
    geom_type = mujoco.mjtObj.mjOBJ_GEOM
    segids, objids = [], []
    for geom in scene.geoms[: scene.ngeom]:
        if geom.objtype == geom_type and geom.segid >= 0:
            segids.append(geom.segid)
            objids.append(geom.objid)
    return np.asarray(segids, dtype=np.int64), np.asarray(objids, dtype=np.int64)


def _same_geoms(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b))


class FrameRenderer:
    """Renders the ``ego`` camera of ``model`` at ``width`` x ``height``.

    ``geom_instance`` is the (ngeom,) int32 table geom id -> actor instance id (-1: not an actor).
    ``base_weather``: the scene's weather at rate 0 (a road scene of
    :func:`rainbench.mjcf.scene.build_spec`); :meth:`render_weather` renders other weathers.
    None for scenes without the weather lights (every pass renders the model as compiled).
    """

    def __init__(self, model: mujoco.MjModel, width: int, height: int,
                 geom_instance: np.ndarray, camera: str = EGO_CAMERA,
                 base_weather: Weather | None = None) -> None:
        self._gl_context = None
        self._mjr_context = None
        self._label_context = None
        self._rig: WeatherRig | None = None  # close() may run before they are set
        self._weather: Weather | None = None
        padded_w, padded_h, self._margin_x, self._margin_y = padded_size(width, height)
        if padded_w > model.vis.global_.offwidth or padded_h > model.vis.global_.offheight:
            raise ValueError(
                f"framebuffer: expected at least {padded_w}x{padded_h}, got "
                f"{model.vis.global_.offwidth}x{model.vis.global_.offheight}; set "
                "<visual><global offwidth=... offheight=...> in the MJCF"
            )
        if geom_instance.shape != (model.ngeom,):
            raise ValueError(
                f"geom_instance: expected shape ({model.ngeom},), got {geom_instance.shape}"
            )
        self.model = model
        self.width, self.height = width, height
        self.padded_width, self.padded_height = padded_w, padded_h
        self.camera_id = int(model.camera(camera).id)
        self.K = camera_intrinsics(model, camera, width, height)
        self._geom_instance = geom_instance.astype(np.int32)
        self._actor_geoms = np.flatnonzero(geom_instance >= 0)
        self._num_instances = int(geom_instance.max()) + 1 if geom_instance.size else 0
        self._scene = mujoco.MjvScene(model, maxgeom=max(1000, 2 * model.ngeom))
        # the segmentation pass's own scene: the frame's geoms less those behind the camera
        self._label_scene = mujoco.MjvScene(model, maxgeom=max(1000, 2 * model.ngeom))
        self._label_scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
        self._label_scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        # geoms that can be left out when wholly behind the camera: all but planes (unbounded)
        # and geoms without a bounding sphere
        self._cullable = (model.geom_type != mujoco.mjtGeom.mjGEOM_PLANE) & (model.geom_rbound > 0)
        # geoms that can be left out of a pass that draws shadows and mirrors (hidden_geoms):
        # those, less any that can be a mirror (MuJoCo mirrors the first reflective geom it is given)
        mirrors = np.append(np.flatnonzero(model.mat_reflectance > 0),
                            mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, "asphalt"))
        self._far_cullable = self._cullable & ~np.isin(model.geom_matid, mirrors[mirrors >= 0])
        self._cloud_deck_geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, CLOUD_DECK_GEOM)
        self._sun_light = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_LIGHT, "sun")
        self._label_scene_ready = False
        self._geom_records: dict[int, np.ndarray | None] = {}  # per scene, see _scene_geoms
        self._option = mujoco.MjvOption()
        self._alone_option = mujoco.MjvOption()
        self._alone_option.geomgroup[:] = 0
        self._alone_option.geomgroup[0] = 1
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._camera.fixedcamid = self.camera_id
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._rgb = np.empty((height, width, 3), np.uint8)
        self._depth = np.empty((height, width), np.float32)
        self._seg = np.empty((height, width, 3), np.uint8)
        extent = model.stat.extent
        self._near = np.float32(model.vis.map.znear * extent)
        self._far = np.float32(model.vis.map.zfar * extent)
        # the view frustum's vertical half-angle tangent; the horizontal one is this times the
        # aspect of the rectangle a pass renders (mjr_render's projection)
        self._tan_y = math.tan(math.radians(model.cam_fovy[self.camera_id]) / 2)
        self._shadow_clip = float(model.vis.map.shadowclip * extent)
        self.backend = os.environ.get("MUJOCO_GL", "")
        # a PyOpenGL platform of another backend makes no context, and MuJoCo's error blames a
        # missing package: say so first (MUJOCO_GL unset: nothing chose a backend to check)
        check_pyopengl_platform(os.environ, self.backend)
        try:
            with warnings.catch_warnings():  # GLFW reports its failures as warnings too: the error says it once
                warnings.simplefilter("ignore")
                self._gl_context = mujoco.GLContext(padded_w, padded_h)
                self._gl_context.make_current()
            self._mjr_context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
            self._label_context = self._mjr_context
            samples = int(model.vis.quality.offsamples)
            if samples > 0:
                # Segmentation, depth and actor-alone passes need no multisampling: a second
                # context without it in the same GL context makes them 1.6-2x cheaper.
                model.vis.quality.offsamples = 0
                try:
                    self._label_context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
                finally:
                    model.vis.quality.offsamples = samples
        except Exception as error:  # GL failures surface as several exception types
            with warnings.catch_warnings():  # freeing a failed GLFW context warns again
                warnings.simplefilter("ignore")
                self.close()
            if _gl_state.mujoco_imported_first and self.backend:
                raise GLBackendError(
                    f"mujoco was imported before rainbench set MUJOCO_GL={self.backend}: import "
                    "rainbench first, or set MUJOCO_GL in the environment"
                ) from error
            raise GLBackendError(context_failure_message(self.backend, error)) from error
        for context in (self._mjr_context, self._label_context):
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, context)
            context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._current_context = self._label_context
        self.base_weather = base_weather
        self._rig = WeatherRig(model) if base_weather is not None else None
        self._weather_option = mujoco.MjvOption()
        self._mirror_weights: dict[tuple, np.ndarray] = {}
        self._mirror_weights_lock = threading.Lock()
        self._frame_cache: tuple[np.ndarray | None, _FrameCache] = (None, _FrameCache())
        self._set_weather(base_weather)

    # -- context management ------------------------------------------------------------------
    def __enter__(self) -> "FrameRenderer":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Free the GL contexts, and put the model back in the base weather: the weathers are
        written into the model, and a later renderer of it starts from what it finds (a clip
        rendered again on the same ``SceneSetup`` gives the same bytes)."""
        if self._rig is not None and self._weather is not None and self._weather != self.base_weather:
            self._rig.apply(self.base_weather, None)
            self._weather = self.base_weather
        if self._gl_context is not None:
            self._gl_context.make_current()
        if self._label_context is not None and self._label_context is not self._mjr_context:
            self._label_context.free()
        self._label_context = None
        if self._mjr_context is not None:
            self._mjr_context.free()
            self._mjr_context = None
        if self._gl_context is not None:
            self._gl_context.free()
            self._gl_context = None

    def _context(self, labels: bool) -> mujoco.MjrContext:
        """The context for a pass (labels: segmentation, depth, actor-alone; else RGB), bound."""
        context = self._label_context if labels else self._mjr_context
        if context is not self._current_context:
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, context)
            self._current_context = context
        return context

    def _require_open(self) -> None:
        if self._mjr_context is None:
            raise RuntimeError("FrameRenderer: used after close()")
        self._gl_context.make_current()

    # -- passes ------------------------------------------------------------------------------
    def _set_weather(self, weather: Weather | None) -> None:
        if self._rig is not None and weather != self._weather:
            self._rig.apply(weather, self._mjr_context)
            self._weather = weather

    def update(self, data: mujoco.MjData) -> None:
        """Build the scene of ``data`` in the base weather, and the segmentation pass's own
        scene of it (call once per frame, before the passes)."""
        self._require_open()
        self._set_weather(self.base_weather)
        if self._rig is not None:
            self._rig.select_lights(data, self.camera_id)
        self._update_scene(data, self._option, self._scene)
        self._update_label_scene(data)

    def render_weather(self, data: mujoco.MjData, weather: Weather,
                       depth: np.ndarray | None = None) -> np.ndarray:
        """RGB (H, W, 3) uint8 of the state in ``data`` under ``weather`` (same geometry, same
        camera). Replaces the scene built by :meth:`update`; the next :meth:`update` restores
        the base weather.

        ``depth``: (H, W) float32 metres along the optical axis of the same state, +inf for sky
        (:meth:`render_instances_depth`), needed when the road is wet: the road's mirror is
        blended only over the pixels that show the road
        (:func:`rainbench.rain.weather.plane_pixels`), and puddles are laid over the image where
        the road is seen (:func:`rainbench.rain.weather.puddle_coverage`), not drawn by
        MuJoCo. The same as ``start_weather(data, weather, depth).result()``."""
        return self.start_weather(data, weather, depth).result()

    def start_weather(self, data: mujoco.MjData, weather: Weather,
                      depth: np.ndarray | None = None) -> PendingImage:
        """:meth:`render_weather` in two halves: its GL passes now, in this thread (the one
        holding the GL context), and its array work (the wet road's mirror blend and the
        puddles) in the returned image's :meth:`PendingImage.result`, which any thread may call
        later: it reads nothing of ``data`` or of this renderer's weather. ``depth`` must not
        change until then."""
        self._require_open()
        if self._rig is None:
            raise RuntimeError("render_weather: this renderer has no base_weather (the scene "
                               "has no 'sun' and 'skylight' lights)")
        self._set_weather(weather)
        puddle_scale = self._rig.puddle_scale
        reflectance = self._rig.road_reflectance
        puddles = puddle_scale > 0
        wet = reflectance > 0 or puddles
        if wet and (depth is None or np.shape(depth) != (self.height, self.width)):
            got = "None" if depth is None else str(np.shape(depth))
            raise ValueError(f"render_weather: this weather wets the road, so depth is needed: "
                             f"expected ({self.height}, {self.width}) from "
                             f"render_instances_depth(), got {got}")
        option = self._weather_option
        option.geomgroup[PUDDLE_GROUP] = 0  # the puddle geoms only mark where puddles are
        option.geomgroup[CLOUD_DECK_GROUP] = 0  # the camera sees the skybox's clouds
        self._set_segmentation(False)
        surface = self._render_rgb(data, option)
        if not wet:
            return PendingImage.done(surface)
        # MuJoCo's mirror is angle independent: render the road as a full mirror and blend it
        # over the plain render with water's Fresnel weight per pixel (rain/weather.py), on the
        # pixels that show the mirrored road only
        mirror_geom = self._rig.mirror_geom(data, self.camera_id)
        cover = slabs = others = None
        if mirror_geom >= 0:
            cover, slabs, others = self._rig.mirror_plane(data, mirror_geom)
        self._rig.set_mirror(True)
        # the mirror pass draws no skybox: the deck stands for the sky in the road's mirror
        option.geomgroup[CLOUD_DECK_GROUP] = self._rig.cloud_deck
        try:
            small = self._render_rgb(data, option, mirror_geom, scale=MIRROR_SCALE,
                                     mirror_cover=cover, covered=others, resize=False)
        finally:
            self._rig.set_mirror(False)
        pose = camera_pose(self.model, data, self.model.camera(self.camera_id).name)
        gain = CLIPPED_GAIN if self._rig.vehicle_lamps else 1.0  # lights are on
        # what the array work needs of the state and the weather, taken now
        spheres = boxes = None
        if slabs is not None and gain != 1.0:
            spheres, boxes = self._rig.lamp_spheres(data), self._rig.lamp_boxes(data)
        puddle_shapes = (self._rig.puddles, self._rig.puddle_phases)
        cache = self._frame_cache_of(depth)
        ripple_slope = puddle_ripple_slope(weather.rain_mm_h)

        def finish() -> np.ndarray:
            size = (self.width, self.height)
            rotation = pose[:3, :3]
            blended = surface.astype(np.float32)
            mirrored = small
            lights = road = road_small = None
            if slabs is not None:
                road, road_small = self._road_pixel_mask(cache, slabs, pose, depth, small.shape[:2])
                if spheres is not None:  # the lamps' mirror images: only they streak brightly
                    lights = self._mirrored_lights(cache, spheres, boxes, pose, float(slabs[0, 2]),
                                                   small.shape[:2])
            if slabs is not None and reflectance > 0:
                rows = np.flatnonzero(road.any(axis=1))
                if rows.size:
                    # the wet film smears its reflection along the vertical (puddles: their ripples)
                    sigma = film_streak_sigma_px(self.K[1, 1]) * small.shape[0] / self.height
                    film = cv2.resize(streak_reflection(small, road_small, sigma, gain, lights), size,
                                      interpolation=cv2.INTER_LINEAR)
                    band = slice(int(rows[0]), int(rows[-1]) + 1)  # only the rows the road reaches
                    weight = self._mirror_weight(rotation, reflectance)[band]
                    weight = np.where(road[band], weight, np.float32(0.0))[..., None]
                    blended[band] += weight * (film[band] - blended[band])
            if puddles:
                if slabs is not None:  # rain ripples the puddles: their mirror smears as well
                    sigma = 2.0 * ripple_slope * self.K[1, 1] * small.shape[0] / self.height
                    mirrored = streak_reflection(small, road_small, sigma, gain, lights)
                mirror = cv2.resize(mirrored, size, interpolation=cv2.INTER_LINEAR)
                self._lay_puddles(cache, blended, surface, mirror, pose, depth, puddle_shapes,
                                  puddle_scale)
            return np.clip(np.rint(blended), 0, 255).astype(np.uint8)

        return PendingImage(finish)

    def with_glow(self, image: np.ndarray, data: mujoco.MjData, weather: Weather,
                  depth: np.ndarray | None) -> np.ndarray:
        """``image`` ((H, W, 3) uint8, a render of the state in ``data``) with the glow rain lays
        around the lights when they are on (dusk, night) and it rains
        (:func:`~rainbench.rain.weather.light_glow`, which depends on the rate: weathers that
        share a render do not share their glow); else ``image`` itself."""
        return self.start_glow(PendingImage.done(image), data, weather, depth).result()

    def start_glow(self, pending: PendingImage, data: mujoco.MjData, weather: Weather,
                   depth: np.ndarray | None) -> PendingImage:
        """:meth:`with_glow` of a :class:`PendingImage`: the lamps' state is read now, the glow
        drawn in the returned image's :meth:`~PendingImage.result`; ``pending`` itself when
        there is no glow."""
        if (weather.time_of_day == "day" or weather.rain_mm_h <= 0 or depth is None
                or self._rig is None):
            return pending
        pose = camera_pose(self.model, data, self.model.camera(self.camera_id).name)
        centres, intensity, colours = self._rig.lamp_lights(data, pose[:3, 3])
        return PendingImage(lambda: add_glow(pending.result(), light_glow(
            self.K, pose, centres, intensity, colours, depth, weather)))

    def _frame_cache_of(self, depth: np.ndarray) -> _FrameCache:
        """The cache of the frame whose depth map is ``depth`` (the frame's weathers share it;
        a new depth array starts a new frame's cache, and frames still being finished keep
        theirs)."""
        if self._frame_cache[0] is not depth:
            self._frame_cache = (depth, _FrameCache())
        return self._frame_cache[1]

    def _road_pixel_mask(self, cache: _FrameCache, slabs: np.ndarray, pose: np.ndarray,
                         depth: np.ndarray, small: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) bool :func:`~rainbench.rain.weather.plane_pixels` of the road ``slabs``
        ((K, 6) top rectangles) and its area average (float32) at the mirror render's ``small``
        (h, w), kept in the frame's ``cache`` (its weathers share the depth map, the pose and
        the slabs)."""
        def build() -> tuple[np.ndarray, np.ndarray]:
            road = plane_pixels(self.K, pose, depth, slabs)
            return road, cv2.resize(road.astype(np.float32), (small[1], small[0]),
                                    interpolation=cv2.INTER_AREA)

        return cache.get("road", pose.tobytes() + slabs.tobytes() + bytes(str(small), "ascii"), build)

    def _mirrored_lights(self, cache: _FrameCache, spheres: np.ndarray, boxes: np.ndarray,
                         pose: np.ndarray, plane_z: float, small: tuple[int, int]) -> np.ndarray:
        """(h, w) bool :func:`~rainbench.rain.weather.mirrored_light_pixels` of the lamp geoms'
        ``spheres`` ((L, 4), :meth:`WeatherRig.lamp_spheres`) and ``boxes`` ((L, 15),
        :meth:`WeatherRig.lamp_boxes`) in the road plane at ``plane_z``, at the mirror render's
        ``small`` (h, w), kept in the frame's ``cache``."""
        def build() -> np.ndarray:
            # drawn on the full image, then any pixel a lamp touches counts at half size
            lights = mirrored_light_pixels(self.K, pose, spheres, plane_z, self.height,
                                           self.width, boxes)
            return cv2.resize(lights.astype(np.uint8), (small[1], small[0]),
                              interpolation=cv2.INTER_AREA) > 0

        return cache.get("lights", pose.tobytes() + spheres.tobytes() + boxes.tobytes()
                         + np.float64(plane_z).tobytes() + bytes(str(small), "ascii"), build)

    def _mirror_weight(self, rotation: np.ndarray, reflectance: float) -> np.ndarray:
        """(H, W) float32 :func:`road_mirror_weight`, cached (it depends on the camera's pitch and
        roll only, the rotation's last row: one per clip on a level road); thread-safe."""
        key = (np.round(rotation[2], 9).tobytes(), reflectance)
        with self._mirror_weights_lock:
            if key not in self._mirror_weights:
                self._mirror_weights[key] = road_mirror_weight(self.K, rotation, self.height,
                                                               self.width, reflectance)
            return self._mirror_weights[key]

    def _lay_puddles(self, cache: _FrameCache, blended: np.ndarray, surface: np.ndarray,
                     mirror: np.ndarray, pose: np.ndarray, depth: np.ndarray,
                     puddle_shapes: tuple[np.ndarray, np.ndarray], puddle_scale: float) -> None:
        """Blend the puddles (``puddle_shapes``: the rig's ``puddles`` and ``puddle_phases``), at
        ``puddle_scale``, into ``blended`` (H, W, 3) float32, in place: under each puddle the
        ``mirror`` at water's Fresnel reflectance over the plain ``surface`` seen through the
        water, in linear light (:func:`~rainbench.rain.weather.puddle_water`)."""
        puddles, phases = puddle_shapes  # the frame's weathers differ only in the puddles' size
        found = cache.get("puddles", pose.tobytes() + puddles.tobytes() + phases.tobytes(),
                          lambda: puddle_pixels(self.K, pose, depth, puddles, phases))
        coverage = puddle_coverage_at(found, puddle_scale)
        rows, cols = np.nonzero(coverage)  # the water is mixed where puddles lie only
        if not rows.size:
            return
        fresnel = self._mirror_weight(pose[:3, :3], PUDDLE_MIRROR_REFLECTANCE)[rows, cols]
        water = puddle_water(surface[rows, cols], mirror[rows, cols], fresnel[:, None])
        blended[rows, cols] += coverage[rows, cols, None] * (water - blended[rows, cols])

    def _render_rgb(self, data: mujoco.MjData, option: mujoco.MjvOption,
                    mirror_geom: int = -1, scale: float = 1.0,
                    mirror_cover: np.ndarray | None = None,
                    covered: np.ndarray | None = None, resize: bool = True) -> np.ndarray:
        """RGB (H, W, 3) of ``data`` in the weather set; ``mirror_geom`` >= 0: the only geom
        drawn as a mirror (MuJoCo mirrors the first reflective geom of the scene, which need not
        be the road under the camera), stretched in this render to ``mirror_cover`` ((6,) level
        rectangle ``(x, y, z, half_length, half_width, yaw)`` of its top, when given) so that it
        mirrors the whole road; the geoms ``covered`` (ids: the road's other slabs, level with
        it) are lowered out of its way. ``scale`` < 1: rendered at that fraction of the size
        (same field of view), then resized to H x W (a softer, cheaper image) unless not
        ``resize``."""
        self._rig.select_lights(data, self.camera_id)
        width, height = self.width, self.height
        if scale < 1.0:
            width, height = max(1, round(self.width * scale)), max(1, round(self.height * scale))
        mirror = self._mirror_plane(data, mirror_geom, mirror_cover) if mirror_geom >= 0 else None
        self._update_scene(data, option, self._scene, mirror, aspect=width / height)
        if mirror_geom >= 0:
            geom_type = mujoco.mjtObj.mjOBJ_GEOM
            camera = data.cam_xpos[self.camera_id]
            for gl_camera in self._scene.camera:  # the mirror sees the deck to the horizon
                gl_camera.frustum_far = MIRROR_SKY_REACH_M
            for index in range(self._scene.ngeom):
                geom = self._scene.geoms[index]
                if geom.objtype != geom_type:
                    continue
                if geom.objid == self._cloud_deck_geom:
                    geom.size[:2] = MIRROR_SKY_REACH_M
                    geom.pos[:2] = camera[:2]
                    continue
                if geom.objid == mirror_geom and mirror_cover is not None:
                    x, y, top, half_length, half_width, _ = mirror_cover
                    geom.size[:2] = (half_length, half_width)
                    box = geom.type == mujoco.mjtGeom.mjGEOM_BOX  # else a plane: pos is its top
                    geom.pos[:] = (x, y, top - geom.size[2] if box else top)
                elif geom.objid != mirror_geom:
                    geom.reflectance = 0.0
                    if covered is not None and geom.objid in covered:
                        geom.pos[2] -= COVERED_DROP_M
            if option.geomgroup[CLOUD_DECK_GROUP] and self._sun_light >= 0:
                # in light rain with the sun out the deck would shade the whole mirrored scene:
                # the sun casts no shadow in this pass (blurred and weak, the mirror shows none)
                for index in range(self._scene.nlight):
                    if self._scene.lights[index].id == self._sun_light:
                        self._scene.lights[index].castshadow = 0
        context = self._context(labels=False)
        if scale >= 1.0:
            mujoco.mjr_render(self._rect, self._scene, context)
            mujoco.mjr_readPixels(self._rgb, None, self._rect, context)
            return np.flipud(self._rgb).copy()
        rect = mujoco.MjrRect(0, 0, width, height)
        small = np.empty((height, width, 3), np.uint8)
        mujoco.mjr_render(rect, self._scene, context)
        mujoco.mjr_readPixels(small, None, rect, context)
        if not resize:
            return np.flipud(small).copy()
        return cv2.resize(np.flipud(small), (self.width, self.height),
                          interpolation=cv2.INTER_LINEAR)

    def _mirror_plane(self, data: mujoco.MjData, geom: int, cover: np.ndarray | None
                      ) -> tuple[np.ndarray, np.ndarray]:
        """(point, unit normal) of the plane MuJoCo mirrors in when road geom ``geom`` is the
        mirror, placed at ``cover`` (see :meth:`_render_rgb`) when given: a box's top face, a
        plane itself (``mjr_render``'s reflection)."""
        normal = data.geom_xmat[geom].reshape(3, 3)[:, 2].copy()
        box = self.model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_BOX
        size_z = float(self.model.geom_size[geom, 2]) if box else 0.0
        if cover is None:
            centre = data.geom_xpos[geom].astype(np.float64)
        else:
            centre = np.array([cover[0], cover[1], cover[2] - size_z])
        return centre + size_z * normal, normal

    def render_rgb(self) -> np.ndarray:
        """RGB (H, W, 3) uint8 of the scene built by :meth:`update` (multisampled)."""
        self._require_open()
        self._set_segmentation(False)
        context = self._context(labels=False)
        mujoco.mjr_render(self._rect, self._scene, context)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, context)
        return np.flipud(self._rgb).copy()

    def render_rgb_depth(self) -> tuple[np.ndarray, np.ndarray]:
        """RGB (H, W, 3) uint8 and depth (H, W) float32 metres along the optical axis (+inf: sky).

        Both are read from one rasterisation.
        """
        self._require_open()
        self._set_segmentation(False)
        context = self._context(labels=False)
        mujoco.mjr_render(self._rect, self._scene, context)
        mujoco.mjr_readPixels(self._rgb, self._depth, self._rect, context)
        rgb = np.flipud(self._rgb).copy()
        return rgb, self._metric_depth(np.flipud(self._depth))

    def render_instances(self) -> tuple[np.ndarray, np.ndarray]:
        """Visible actor instance ids (H, W) int32 (-1: no actor) and a (H, W) bool mask of
        pixels showing any geometry (False: sky), from one segmentation pass."""
        ids, geometry, _ = self._segmentation_pass(with_depth=False)
        return ids, geometry

    def render_instances_depth(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`render_instances` plus depth (H, W) float32 metres along the optical axis,
        +inf where no geometry is, read from the same (single-sample) rasterisation: the depth
        of exactly the surface each pixel's id belongs to."""
        ids, geometry, depth = self._segmentation_pass(with_depth=True)
        depth[~geometry] = np.inf
        return ids, geometry, depth

    def _segmentation_pass(self, with_depth: bool):
        self._require_open()
        if not self._label_scene_ready:
            raise RuntimeError("FrameRenderer: call update(data) before a segmentation pass")
        scene = self._label_scene
        context = self._context(labels=True)
        mujoco.mjr_render(self._rect, scene, context)
        mujoco.mjr_readPixels(self._seg, self._depth if with_depth else None, self._rect, context)
        seg = np.flipud(self._seg)
        depth = self._metric_depth(np.flipud(self._depth)) if with_depth else None
        # OR of the channels: 15x faster than seg.any(axis=-1) on an (H, W, 3) view
        return self._decode(seg, scene), (seg[..., 0] | seg[..., 1] | seg[..., 2]) != 0, depth

    def behind_camera(self, data: mujoco.MjData) -> np.ndarray:
        """(ngeom,) bool: geoms whose bounding sphere (``geom_rbound`` about ``geom_xpos``) lies
        wholly behind the plane through the camera's centre square to its view direction; such
        a geom cannot show in the image. Planes (unbounded) are never behind. ``data`` needs its
        kinematics (``mj_forward``): with none computed nothing is behind."""
        forward = -data.cam_xmat[self.camera_id].reshape(3, 3)[:, 2]  # cameras look along -z
        ahead = (data.geom_xpos - data.cam_xpos[self.camera_id]) @ forward
        return self._cullable & (ahead < -self.model.geom_rbound)

    def _outside_view(self, centres: np.ndarray, radius: np.ndarray, camera: np.ndarray,
                      axes: np.ndarray, aspect: float) -> np.ndarray:
        """(N,) bool: spheres (``centres`` (N, 3) world metres, ``radius`` (N,)) wholly outside
        the view frustum of a camera at ``camera`` (3,) with axes ``axes`` (3, 3) (columns x, y,
        z; it looks along -z) rendering a rectangle of width / height ``aspect``: behind its
        near plane, beyond its far plane, or beyond a side plane, by :data:`CULL_MARGIN_M` more
        than the radius."""
        local = (centres - camera) @ axes
        x, y, depth = local[:, 0], local[:, 1], -local[:, 2]
        reach = radius + CULL_MARGIN_M
        outside = (depth + reach < self._near) | (depth - reach > self._far)
        for tangent, across in ((self._tan_y * aspect, x), (self._tan_y, y)):
            scale = 1.0 / math.sqrt(1.0 + tangent * tangent)  # a side plane's distance per unit
            outside |= ((np.abs(across) - tangent * depth) * scale > reach)
        return outside

    def hidden_geoms(self, data: mujoco.MjData, mirror: tuple[np.ndarray, np.ndarray] | None = None,
                     aspect: float | None = None) -> np.ndarray:
        """(ngeom,) bool: geoms no pixel of a pass can come from in the state ``data``. A geom's
        bounding sphere (``geom_rbound`` about ``geom_xpos``) is outside the view frustum of a
        pass rendering a rectangle of width / height ``aspect`` (default the image's; a pass at
        a reduced scale rounds its size: :meth:`_outside_view`); its mirror image is too when
        the pass draws the road's ``mirror`` (a point and a unit normal of the mirror plane, (3,)
        each, as MuJoCo reflects); and it is outside the shadow-map box of every light that
        casts shadows (a directional light's: +-shadowclip across its axis, near..far along it,
        from its position). Planes, geoms without a bounding sphere and those that can be a
        mirror never are. Leaving them out of a pass changes no pixel (tested) and spares
        llvmpipe their vertices."""
        aspect = self.width / self.height if aspect is None else aspect
        camera = data.cam_xpos[self.camera_id]
        axes = data.cam_xmat[self.camera_id].reshape(3, 3)
        centres, radius = data.geom_xpos, self.model.geom_rbound
        hidden = self._far_cullable & self._outside_view(centres, radius, camera, axes, aspect)
        if mirror is not None:
            point, normal = mirror
            images = centres - 2.0 * ((centres - point) @ normal)[:, None] * normal
            hidden &= self._outside_view(images, radius, camera, axes, aspect)
        casting = np.flatnonzero((self.model.light_castshadow != 0) & (self.model.light_active != 0))
        for light in casting:
            if self.model.light_type[light] != mujoco.mjtLightType.mjLIGHT_DIRECTIONAL:
                return np.zeros(self.model.ngeom, bool)  # a spot light's map: not bounded here
            direction = data.light_xdir[light] / max(float(np.linalg.norm(data.light_xdir[light])), 1e-12)
            offset = centres - data.light_xpos[light]
            along = offset @ direction
            across = np.linalg.norm(offset - along[:, None] * direction, axis=1)
            reach = radius + CULL_MARGIN_M
            in_box = ((along + reach >= self._near) & (along - reach <= self._far)
                      & (across - reach <= math.sqrt(2.0) * self._shadow_clip))
            hidden &= ~in_box
        return hidden

    def _update_scene(self, data: mujoco.MjData, option: mujoco.MjvOption,
                      scene: mujoco.MjvScene, mirror: tuple[np.ndarray, np.ndarray] | None = None,
                      aspect: float | None = None) -> None:
        """``mjv_updateScene`` of ``data`` into ``scene`` less the geoms no pixel can come from
        (:meth:`hidden_geoms`, with the road's ``mirror`` when the pass draws it, for a pass
        rendering at ``aspect``)."""
        hidden = self.hidden_geoms(data, mirror, aspect)
        if not hidden.any():
            mujoco.mjv_updateScene(self.model, data, option, None, self._camera,
                                   mujoco.mjtCatBit.mjCAT_ALL, scene)
            return
        groups = self.model.geom_group.copy()
        groups[hidden] = HIDDEN_GROUP
        self._update_scene_in_groups(data, option, scene, groups)

    def _update_label_scene(self, data: mujoco.MjData) -> None:
        """Build the segmentation pass's scene of ``data`` (0.1 ms): the scene of
        :meth:`update` less the geoms behind the camera (:meth:`behind_camera`) or outside its
        view (:meth:`_outside_view`). They cannot change a pixel of that pass (it draws no
        shadows, reflections or sky) but cost llvmpipe their vertices: the paper clip's
        segmentation 10-20 % faster (bench/RESULTS.md)."""
        camera = data.cam_xpos[self.camera_id]
        axes = data.cam_xmat[self.camera_id].reshape(3, 3)
        outside = self._cullable & self._outside_view(data.geom_xpos, self.model.geom_rbound,
                                                      camera, axes, self.width / self.height)
        groups = self.model.geom_group.copy()
        groups[self.behind_camera(data) | outside] = HIDDEN_GROUP
        self._update_scene_in_groups(data, self._option, self._label_scene, groups)
        self._label_scene_ready = True

    def _update_scene_in_groups(self, data: mujoco.MjData, option: mujoco.MjvOption,
                                scene: mujoco.MjvScene, groups: np.ndarray) -> None:
        """``mjv_updateScene`` of ``data`` into ``scene`` with the geoms in ``groups`` ((ngeom,)
        int32; :data:`HIDDEN_GROUP` hides a geom) instead of the model's own, which are put
        back afterwards."""
        saved = self.model.geom_group.copy()
        try:
            self.model.geom_group[:] = groups
            mujoco.mjv_updateScene(self.model, data, option, None, self._camera,
                                   mujoco.mjtCatBit.mjCAT_ALL, scene)
        finally:
            self.model.geom_group[:] = saved

    def render_alone(self, data: mujoco.MjData, instance_ids,
                     window: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Render only the actors ``instance_ids`` on the padded canvas; (h, w) int32 ids.

        The canvas extends the image by :func:`padded_size` margins on every side with the same
        focal length, so canvas ``[my:my+H, mx:mx+W]`` is exactly the image. Only ``window`` =
        (x0, y0, x1, y1) canvas pixels (default: the whole canvas) is read back and returned.
        Callers pass actors whose projections do not overlap, so each pixel shows its actor
        unoccluded. This replaces the scene built by :meth:`update`.
        """
        self._require_open()
        x0, y0, x1, y1 = window or (0, 0, self.padded_width, self.padded_height)
        if not (0 <= x0 < x1 <= self.padded_width and 0 <= y0 < y1 <= self.padded_height):
            raise ValueError(f"window: expected inside (0, 0, {self.padded_width}, "
                             f"{self.padded_height}), got {(x0, y0, x1, y1)}")
        groups = np.full(self.model.ngeom, HIDDEN_GROUP, np.int32)
        groups[np.isin(self._geom_instance, np.asarray(instance_ids, dtype=np.int32))] = 0
        self._update_scene_in_groups(data, self._alone_option, self._scene, groups)
        # Only the window's rows are rasterised: the frustum is cut to canvas rows y0..y1 and
        # rendered into a viewport of that height and the canvas's width: 30 % faster on the
        # residential street. The pixels are the whole canvas's but for a rare edge pixel (1 in
        # 10 million measured, bench/RESULTS.md; equal on the tiny scene of the test). Columns
        # cannot be cut the same way: mjr_render does not honour an off-centre frustum_center.
        scale = self.padded_height / self.height
        for gl_camera in self._scene.camera:  # mjr_render averages both (stereo) cameras
            top, bottom = gl_camera.frustum_top * scale, gl_camera.frustum_bottom * scale
            gl_camera.frustum_top = top - (top - bottom) * y0 / self.padded_height
            gl_camera.frustum_bottom = top - (top - bottom) * y1 / self.padded_height
            gl_camera.frustum_width *= self.padded_width / self.width
        self._set_segmentation(True)
        context = self._context(labels=True)
        mujoco.mjr_render(mujoco.MjrRect(0, 0, self.padded_width, y1 - y0), self._scene, context)
        # GL rows count from the bottom: row 0 of the viewport is canvas row y1 - 1.
        read_rect = mujoco.MjrRect(x0, 0, x1 - x0, y1 - y0)
        seg = np.empty((y1 - y0, x1 - x0, 3), np.uint8)
        mujoco.mjr_readPixels(seg, None, read_rect, context)
        self._set_segmentation(False)
        return self._decode(np.flipud(seg), self._scene)

    # -- helpers -----------------------------------------------------------------------------
    def _set_segmentation(self, enabled: bool) -> None:
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = enabled
        self._scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = enabled

    def _decode(self, seg: np.ndarray, scene: mujoco.MjvScene) -> np.ndarray:
        """Segmentation colours (H, W, 3) uint8 -> instance ids (H, W) int32 via ``scene``, the
        scene the colours were rendered from."""
        lut = np.full(max(256, scene.ngeom + 2), -1, dtype=np.int32)
        segids, objids = self._scene_geoms(scene)
        lut[segids + 1] = self._geom_instance[objids]
        if lut.size == 256:  # fewer than 255 geoms: the red channel holds the whole id
            return np.take(lut, seg[..., 0])
        if lut.size <= 65536:  # red + 256 green: each pixel's first two bytes, little-endian
            pairs = seg[..., :2] if seg.strides[-1] == 1 else np.ascontiguousarray(seg[..., :2])
            return np.take(lut, pairs.view("<u2")[..., 0], mode="clip")
        code = seg[..., 0].astype(np.int32)
        code |= seg[..., 1].astype(np.int32) << 8
        code |= seg[..., 2].astype(np.int32) << 16
        return lut[np.minimum(code, lut.size - 1)]

    def _scene_geoms(self, scene: mujoco.MjvScene) -> tuple[np.ndarray, np.ndarray]:
        """(segid, model geom id) int64 arrays of the model geoms that ``scene`` shows.

        Read at once from the scene's geom records (:func:`scene_geom_records`) where their
        layout is the one expected: checked, the first time for each scene, against the
        bindings' own attributes, one geom at a time (about 8 ms for 1 750 geoms, which every
        segmentation pass would otherwise spend holding the GIL)."""
        records = self._geom_records.get(id(scene), ...)
        if records is ...:
            records = scene_geom_records(scene)
            if records is not None and not _same_geoms(_shown_geoms(records[: scene.ngeom]),
                                                        _shown_geoms_one_by_one(scene)):
                records = None
            if scene.ngeom:  # an empty scene checks nothing
                self._geom_records[id(scene)] = records
        if records is None:
            return _shown_geoms_one_by_one(scene)
        return _shown_geoms(records[: scene.ngeom])

    def _metric_depth(self, raw: np.ndarray) -> np.ndarray:
        """Reversed-Z depth buffer (0 = far) -> metres; as mujoco.Renderer, +inf for no geometry."""
        near, far = self._near, self._far
        c_coef = np.float32(-0.5) * (-(far + near) / (far - near)) - np.float32(0.5)
        d_coef = np.float32(-0.5) * (-(np.float32(2) * far * near) / (far - near))
        raw64 = raw.astype(np.float64)
        with np.errstate(divide="ignore"):
            metres = (d_coef / (raw64 + c_coef)).astype(np.float32)
        metres[raw <= 0.0] = np.inf
        return metres

    def actor_boxes_padded(self, data: mujoco.MjData) -> dict[int, tuple[float, float, float, float]]:
        """Conservative projected boxes of every actor on the padded canvas, from geom AABBs.

        Returns instance id -> (x1, y1, x2, y2) padded-canvas pixels; an actor with any corner
        behind the near plane gets the whole canvas. Actors entirely behind the camera are absent.
        """
        geoms = self._actor_geoms
        centre_local = self.model.geom_aabb[geoms, :3]
        half = self.model.geom_aabb[geoms, 3:]
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        corners_local = centre_local[:, None, :] + signs[None] * half[:, None, :]  # (G, 8, 3)
        rotation = data.geom_xmat[geoms].reshape(-1, 3, 3)
        corners = np.einsum("gij,gkj->gki", rotation, corners_local) + data.geom_xpos[geoms][:, None]
        pose = camera_pose(self.model, data, self.model.camera(self.camera_id).name)
        cam = (corners - pose[:3, 3]) @ pose[:3, :3]  # (G, 8, 3) OpenCV camera coordinates
        focal = self.K[0, 0]
        cx = self.padded_width / 2
        cy = self.padded_height / 2
        near = float(self._near)
        instances = self._geom_instance[geoms]
        boxes: dict[int, tuple[float, float, float, float]] = {}
        full = (0.0, 0.0, float(self.padded_width), float(self.padded_height))
        for instance in np.unique(instances):
            c = cam[instances == instance].reshape(-1, 3)
            z = c[:, 2]
            if np.all(z <= near):
                continue
            if np.any(z <= near):
                boxes[int(instance)] = full
                continue
            u = focal * c[:, 0] / z + cx
            v = focal * c[:, 1] / z + cy
            box = (max(0.0, float(u.min()) - 1), max(0.0, float(v.min()) - 1),
                   min(float(self.padded_width), float(u.max()) + 1),
                   min(float(self.padded_height), float(v.max()) + 1))
            if box[0] < box[2] and box[1] < box[3]:
                boxes[int(instance)] = box
        return boxes

    @property
    def margins(self) -> tuple[int, int]:
        return self._margin_x, self._margin_y
