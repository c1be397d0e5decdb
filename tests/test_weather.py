"""The world under the rain: base weather, weather that follows the rate, wet road, spray, camera."""

import argparse
import dataclasses
import math

import cv2
import h5py
from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np
import pytest

from rainbench import rain
from rainbench.cli import _seed_and_sky
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene, generate_shard
from rainbench.gen.render import FrameRenderer, camera_pose
from rainbench.mjcf.scene import (CLOUD_DECK_GEOM, CLOUD_DECK_GROUP, CLOUD_DECK_HEIGHT_M, _camera_quat,
                                  geom_instance_table, horizontal_to_vertical_fov)
from rainbench.rain import weather as wx

# the paper's street by day: these tests are about the daytime weather laws
SMALL = dict(frames=2, frame_offset=100, clip_frames=200, width=160, height=120,
             store=("depth",), layout="street", time_of_day="day")


def _saturation(rgb, mask):
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    return float(hsv[..., 1][mask].mean()) / 255.0


def _luma(rgb):
    return float(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).mean())


# -- laws ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("sky", wx.SKIES)
def test_weather_is_monotonic_in_the_rate_and_base_at_zero(sky):
    rates = [0, 0.5, 2, 5, 10, 25, 50, 75, 100]
    series = [wx.weather_at(sky, rate) for rate in rates]
    for name in ("cloud_cover", "wetness", "puddle_fraction", "road_reflectance", "spray",
                 "gain", "exposure_s"):
        values = [getattr(w, name) for w in series]
        assert values == sorted(values), name
    for name in ("sun", "illuminance_lux", "image_level"):
        values = [getattr(w, name) for w in series]
        assert values == sorted(values, reverse=True), name
    base = series[0]
    assert base.gain == 1.0 and base.image_level == 1.0 and base.wetness == 0.0
    assert base.puddle_fraction == 0.0 and base.spray == 0.0
    assert series[-1].sun < 1e-6 and series[-1].illuminance_lux == pytest.approx(100.0)
    assert 1 / 100 <= series[-1].exposure_s <= 1 / 60  # rain light: 1/60-1/100 s


def test_weather_not_following_the_rate_is_the_base_weather():
    assert wx.weather_at("clear", 80.0, follows_rate=False) == wx.weather_at("clear", 0.0)
    with pytest.raises(ValueError, match="SKY: expected one of clear, cloudy, overcast, got 'foggy'"):
        wx.weather_at("foggy", 0.0)


def test_cloud_sky_is_grey_and_cie_graded():
    def saturation(colours):
        return (colours.max(axis=1) - colours.min(axis=1)) / colours.max(axis=1)

    cloudy = wx.sky_colours(wx.weather_at("cloudy", 0.0), np.array([0.0, 0.5, 1.0]))
    assert (saturation(cloudy) < 0.15).all()  # 80 % cloud cover: a trace of blue at most
    colours = wx.sky_colours(wx.weather_at("overcast", 0.0), np.array([0.0, 0.5, 1.0]))
    assert (saturation(colours) < 0.05).all()
    # CIE overcast: L(zenith) / L(horizon) = 3 in luminance, (3) ** (1 / 2.2) after the tone curve
    assert colours[2].mean() / colours[0].mean() == pytest.approx(3 ** (1 / 2.2), rel=1e-6)
    clear = wx.sky_colours(wx.weather_at("clear", 0.0), np.array([1.0]))[0]
    assert clear[2] - clear[0] > 0.3  # a blue sky


def test_camera_response_is_identity_at_base_and_darker_and_noisier_in_rain():
    rng = np.random.default_rng(0)
    image = rng.integers(40, 200, (60, 80, 3), dtype=np.uint8)
    noise = rng.standard_normal((60, 80, 3)).astype(np.float32)
    base = wx.weather_at("cloudy", 0.0)
    assert np.array_equal(wx.camera_response(image, base, noise), image)
    heavy = wx.weather_at("cloudy", 100.0)
    out = wx.camera_response(image, heavy, noise)
    assert out.mean() == pytest.approx(image.mean() * heavy.image_level, abs=1.0)
    residual = out.astype(np.float64) - image * heavy.image_level
    expected = wx.ISP_NOISE_REDUCTION * math.sqrt(
        wx.NOISE_SIGNAL_DN * (heavy.gain - 1) * image.mean() * heavy.image_level
        + wx.NOISE_FLOOR_DN2 * (heavy.gain ** 2 - 1))
    assert residual.std() == pytest.approx(expected, rel=0.1)


def test_noise_field_is_unit_variance_grain_mostly_shared_by_the_channels():
    field = wx.noise_field(np.random.default_rng(3), 240, 320)
    assert field.shape == (240, 320, 3) and field.dtype == np.float32
    noise = field.astype(np.float64)
    assert noise.var() == pytest.approx(1.0, rel=0.03)
    # smoothed by the ISP's noise reduction: neighbours correlate (white noise: 0), but the grain
    # is fine (4 px apart: nearly independent)
    assert np.corrcoef(noise[:, :-1, 1].ravel(), noise[:, 1:, 1].ravel())[0, 1] > 0.4
    assert abs(np.corrcoef(noise[:, :-4, 1].ravel(), noise[:, 4:, 1].ravel())[0, 1]) < 0.05
    # luma noise: 85 % of the variance shared by the channels
    assert np.corrcoef(noise[..., 0].ravel(), noise[..., 2].ravel())[0, 1] == pytest.approx(
        1 - wx.CHROMA_NOISE_SHARE, abs=0.03)


def test_spray_is_occluded_by_nearer_surfaces():
    K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    depth = np.full((120, 160), np.inf, np.float32)
    depth[:, :80] = 2.0  # a wall 2 m away on the left half
    points = np.array([[-0.5, 0.0, 5.0], [0.5, 0.0, 5.0]])  # 5 m away: left one behind the wall
    opacity = wx.spray_opacity(depth, K, points, np.array([0.5, 0.5]))
    assert opacity[:, 85:96].max() > 0.3 and opacity[:, :60].max() == 0.0
    assert wx.composite_spray(np.zeros((120, 160, 3), np.uint8), opacity, [200, 200, 200])[60, 90:110].mean() > 20


def test_streaks_are_brighter_than_a_dark_wall():
    height, width = 120, 160
    rgb = np.zeros((height, width, 3), np.uint8)
    rgb[:40] = (200, 205, 210)  # sky
    rgb[40:] = (25, 25, 25)  # a dark wall 6 m away
    depth = np.full((height, width), 6.0, np.float32)
    depth[:40] = np.inf
    K = np.array([[80.0, 0, 80], [0, 80.0, 60], [0, 0, 1]])
    frame = rain.render_rain(rgb, depth, 100.0, config=rain.RainConfig(model="physical", lens_drops=False),
                             K=K, seed_sequence=np.random.SeedSequence([1, 2, 3]))
    coverage, wall = frame.coverage[40:], frame.rgb[40:].astype(float)
    streaks, plain = coverage > 0.03, coverage < 1e-3
    assert streaks.sum() > 20 and plain.sum() > 1000
    # streaks take the sky's light: brighter than the wall (and its airlight) around them
    assert wall[streaks].mean() > wall[plain].mean() + 3 and wall[plain].mean() >= 25


# -- a tiny inline scene with the weather rig ------------------------------------------------
def _rig_spec(width: int, height: int, road: str = "asphalt") -> mujoco.MjSpec:
    """The weather rig's needs (a skybox ``sky``; lights are the caller's) and a grey road
    material named ``road``, for an offscreen image of ``width`` x ``height``."""
    spec = mujoco.MjSpec()
    spec.stat.extent = 100.0
    spec.visual.map.znear = 0.001
    spec.visual.map.zfar = 10.0
    spec.visual.global_.offwidth = width * 2
    spec.visual.global_.offheight = height * 2
    spec.visual.quality.shadowsize = 2048
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT, rgb1=[1, 1, 1], rgb2=[1, 1, 1],
                     width=32, height=32)
    # the rig re-colours "asphalt" only (its rgba: the wet factor); a dark texture makes it a
    # road (scene asphalt is about 90 of 255 dry), not a white floor
    spec.add_texture(name="road_grey", type=mujoco.mjtTexture.mjTEXTURE_2D,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_FLAT, rgb1=[0.35, 0.35, 0.35],
                     rgb2=[0.35, 0.35, 0.35], width=8, height=8)
    road_material = spec.add_material(name=road, rgba=[0.4, 0.4, 0.4, 1])
    road_material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "road_grey"
    return spec


def _rig_scene(*, camera_pos, camera_quat, fovy, width=120, height=90, red_box=True,
               road="asphalt", puddle=None, split_at=None, planes=False):
    """A 40 m road plane (top at z = 0) with a 1 m box at the origin; ``puddle``: (x, y, half
    length, half width) of a ``scenery/puddle0`` outline geom on the road; ``split_at``: the
    road is two slabs meeting at this x (MuJoCo mirrors one geom a render); ``planes``: the slabs
    are plane geoms (the night scenes' lit grid) instead of boxes, one unbounded plane when not
    split."""
    spec = _rig_spec(width, height, road)
    world = spec.worldbody
    if split_at is None and planes:  # one unbounded plane (size 0)
        world.add_geom(name="scenery/road", type=mujoco.mjtGeom.mjGEOM_PLANE,
                       size=[0, 0, 0.25], pos=[0, 0, 0], material=road)
    elif split_at is None:
        world.add_geom(name="scenery/road", type=mujoco.mjtGeom.mjGEOM_BOX,
                       size=[20, 20, 0.05], pos=[0, 0, -0.05], material=road)
    else:
        for index, (start, end) in enumerate(((-20.0, split_at), (split_at, 20.0))):
            if planes:
                world.add_geom(name=f"scenery/road{index}", type=mujoco.mjtGeom.mjGEOM_PLANE,
                               size=[(end - start) / 2, 20, 0.25],
                               pos=[(start + end) / 2, 0, 0], material=road)
            else:
                world.add_geom(name=f"scenery/road{index}", type=mujoco.mjtGeom.mjGEOM_BOX,
                               size=[(end - start) / 2, 20, 0.05],
                               pos=[(start + end) / 2, 0, -0.05], material=road)
    world.add_geom(name="actor000/box", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5, 0.5, 0.5],
                   pos=[0, 0, 0.5], rgba=[0.9, 0.05, 0.05, 1] if red_box else [0.5, 0.5, 0.5, 1])
    if puddle is not None:
        x, y, half_length, half_width = puddle
        world.add_geom(name="scenery/puddle0", type=mujoco.mjtGeom.mjGEOM_ELLIPSOID,
                       size=[half_length, half_width, 0.001], pos=[x, y, 0.004], group=3,
                       contype=0, conaffinity=0)
    ego = world.add_body(name="ego", mocap=True)
    ego.add_camera(name="ego", pos=list(camera_pos), quat=list(camera_quat), fovy=fovy)
    direction = np.array([-1.0, 0.0, -1.0]) / math.sqrt(2)  # sun at 45 degrees from +x
    ego.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                  pos=(-20 * direction).tolist(), dir=direction.tolist(), castshadow=True)
    ego.add_light(name="skylight", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, pos=[0, 0, 20],
                  dir=[0, 0, -1], castshadow=False)
    model = spec.compile()
    table = np.array([0 if model.geom(i).name.startswith("actor") else -1
                      for i in range(model.ngeom)], np.int32)
    return model, table


def _render(model, table, weather, base, width=120, height=90):
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with FrameRenderer(model, width, height, table, base_weather=base) as renderer:
        renderer.update(data)
        rgb, _ = renderer.render_rgb_depth()
        _, _, depth = renderer.render_instances_depth()
        return rgb if weather == base else renderer.render_weather(data, weather, depth)


def test_cloudy_light_casts_no_hard_shadow_and_clear_sun_does():
    """Top-down view of a 1 m box: the sun at 45 degrees from +x shades x in [-1.5, -0.5] m."""
    down = [1.0, 0.0, 0.0, 0.0]  # camera looking along -z, image x along +x, up along +y
    model, table = _rig_scene(camera_pos=[0, 0, 10], camera_quat=down, fovy=60.0, road="grey")
    steps = {}
    for sky in ("clear", "cloudy"):
        base = wx.weather_at(sky, 0.0)
        luma = cv2.cvtColor(_render(model, table, base, base), cv2.COLOR_RGB2GRAY).astype(float)
        metres_per_px = 2 * 10 * math.tan(math.radians(30)) / 90  # vertical fov 60 deg over 90 px

        def patch(x, y):
            col = int(60 + x / metres_per_px)
            row = int(45 - y / metres_per_px)
            return luma[row - 2:row + 3, col - 2:col + 3].mean()

        shadow, lit = patch(-1.0, 0.0), patch(-1.0, 1.6)
        steps[sky] = (lit - shadow) / lit
    # documented threshold (docs/rain.md): a shadow edge under 5 % is no hard shadow
    assert steps["cloudy"] < 0.05 < 0.15 < steps["clear"]


@pytest.mark.parametrize("split_at, planes",
                         [(None, False), (-1.0, False), (-1.0, True), (None, True)])
def test_wet_road_mirrors_a_red_box_only_when_wet(split_at, planes):
    """Split at x = -1, the box's reflection lies mostly on the near slab, though MuJoCo's
    mirror is the far one (under the point 15 m ahead): every slab of the road mirrors, boxes
    and planes alike."""
    model, table = _rig_scene(camera_pos=[-6, 0, 1.0], camera_quat=_camera_quat(),
                              fovy=horizontal_to_vertical_fov(60, 120, 90), split_at=split_at,
                              planes=planes)
    base = wx.weather_at("overcast", 0.0)
    images = {rate: _render(model, table, wx.weather_at("overcast", rate), base).astype(int)
              for rate in (0.0, 50.0)}
    dry = images[0.0]
    box = (dry[..., 0] > dry[..., 1] + 60) & (dry[..., 0] > dry[..., 2] + 60)
    rows, cols = np.flatnonzero(box.any(axis=1)), np.flatnonzero(box.any(axis=0))
    ground_line = rows.max()  # the box's lowest row in the dry render
    below = (slice(ground_line + 2, ground_line + 12), slice(cols.min() + 2, cols.max() - 1))

    def red_excess(image):
        return image[..., 0] - (image[..., 1] + image[..., 2]) / 2

    assert np.abs(red_excess(dry[below])).max() <= 8  # dry: grey road under the box
    assert (red_excess(images[50.0][below]) > 15).mean() > 0.5  # wet: the box mirrored
    # the reflection meets the box's base: the mirror is the road's top (a plane's pos, a
    # box's pos + half height), not a plane lowered by its grid spacing
    touching = (slice(ground_line + 1, ground_line + 4), below[1])
    assert red_excess(images[50.0][touching]).mean() > 20


def test_the_wet_road_mirror_changes_road_pixels_only():
    """The mirror render is drawn at half size: blended anywhere but on the road it would blur
    the box, its edges and the sky. Off the road the wet render equals the same weather's plain
    render (no mirror, no puddles) byte for byte."""
    model, table = _rig_scene(camera_pos=[-6, 0, 1.0], camera_quat=_camera_quat(),
                              fovy=horizontal_to_vertical_fov(60, 120, 90))
    base = wx.weather_at("overcast", 0.0)
    wet = wx.weather_at("overcast", 50.0)
    plain_weather = dataclasses.replace(wet, road_reflectance=0.0, puddle_fraction=0.0)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with FrameRenderer(model, 120, 90, table, base_weather=base) as renderer:
        renderer.update(data)
        ids, geometry, depth = renderer.render_instances_depth()
        mirrored = renderer.render_weather(data, wet, depth).astype(int)
        plain = renderer.render_weather(data, plain_weather).astype(int)
        pose = camera_pose(model, data, "ego")
        road = wx.plane_pixels(renderer.K, pose, depth, np.array([0, 0, 0, 20, 20, 0.0]))
    changed = np.abs(mirrored - plain).max(axis=-1) > 0
    assert (ids >= 0).sum() > 200 and (~geometry).sum() > 200  # the box and the sky are seen
    assert road.sum() > 2000 and not (road & (ids >= 0)).any() and not (road & ~geometry).any()
    assert changed[road].sum() > 400  # the road mirrors (weakly near the camera)
    assert not changed[~road].any()  # nothing else changes: the box and the sky stay sharp


@pytest.mark.parametrize("sky, rate, least_gain", [("overcast", 50.0, 100), ("clear", 1.0, 20)])
def test_the_far_wet_road_mirrors_the_cloud_deck_down_to_the_horizon(sky, rate, least_gain):
    """A camera 1 m above a 2 km road sees its mirror ray from the road d metres ahead rise at
    1/d rad: under 3.4 degrees (beyond 17 m) it met nothing within the model's 1 000 m far plane
    and mirrored black, so the far wet road went dark where it should mirror the sky (a visual
    audit: a dark block over the car ahead at a street's vanishing point). The mirror pass now
    reaches the deck (here only 100 m across in the model) to the horizon: the far road mirrors
    it, out to a few hundred metres, far brighter than in the same weather without its mirror.

    In light rain with the sun out (clear, 1 mm/h) there was no deck at all (it would have shaded
    the mirrored scene): the wet road mirrored black. The deck is drawn in any rain now, and the
    sun casts no shadow in the mirror pass (here it casts one in the camera's own)."""
    spec = _rig_spec(320, 240)
    spec.add_material(name="cloud_deck", rgba=[0.5, 0.5, 0.5, 1.0], emission=1.0, specular=0.0)
    world = spec.worldbody
    world.add_geom(name="scenery/road", type=mujoco.mjtGeom.mjGEOM_BOX, size=[1000, 200, 0.05],
                   pos=[990, 0, -0.05], material="asphalt")
    world.add_geom(name=CLOUD_DECK_GEOM, type=mujoco.mjtGeom.mjGEOM_BOX, size=[50, 50, 1.0],
                   pos=[0, 0, CLOUD_DECK_HEIGHT_M], material="cloud_deck", group=CLOUD_DECK_GROUP,
                   contype=0, conaffinity=0)
    ego = world.add_body(name="ego", mocap=True)
    ego.add_camera(name="ego", pos=[-10, 0, 1.0], quat=list(_camera_quat()),
                   fovy=horizontal_to_vertical_fov(20, 320, 240))
    ego.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, pos=[0, 0, 20],
                  dir=[0.5, 0, -0.87], castshadow=True)
    ego.add_light(name="skylight", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, pos=[0, 0, 20],
                  dir=[0, 0, -1], castshadow=False)
    model = spec.compile()
    table = np.full(model.ngeom, -1, np.int32)
    wet = wx.weather_at(sky, rate)
    assert wet.road_reflectance > 0 and (wet.sun > 0.02) == (sky == "clear")  # sun out or not
    plain_weather = dataclasses.replace(wet, road_reflectance=0.0, puddle_fraction=0.0)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with FrameRenderer(model, 320, 240, table, base_weather=wx.weather_at(sky, 0.0)) as renderer:
        renderer.update(data)
        _, _, depth = renderer.render_instances_depth()
        mirrored = cv2.cvtColor(renderer.render_weather(data, wet, depth), cv2.COLOR_RGB2GRAY)
        plain = cv2.cvtColor(renderer.render_weather(data, plain_weather), cv2.COLOR_RGB2GRAY)
        focal = renderer.K[1, 1]
        horizon = renderer.K[1, 2]
    for near_m, far_m in ((25.0, 60.0), (60.0, 150.0), (150.0, 400.0)):
        rows = slice(int(math.ceil(horizon + focal * 1.0 / far_m)),
                     int(horizon + focal * 1.0 / near_m) + 1)
        assert np.isfinite(depth[rows]).all()  # the road, out to 400 m
        gained = mirrored[rows].astype(float).mean() - plain[rows].astype(float).mean()
        # the deck's light at water's grazing reflectance (about 150 levels here, 40-55 in the
        # light rain's weak wetness); with the model's far plane 25-45, what the mirror pass
        # draws where nothing is mirrored; without the deck in sunny rain, none
        assert gained > least_gain, (near_m, far_m, gained)


def test_the_deck_casts_no_sun_shadow_on_the_mirrored_scene():
    """In light rain with the sun out the mirror pass draws the deck (above); casting the sun's
    shadow it darkened the mirrored sunlit scene. The sun casts no shadow in that pass: the
    wet road is as bright or brighter everywhere (the highway of seed 18, clear, 1 mm/h)."""
    scene = build_scene(GenerateConfig(seed=18, layout="highway", sky="clear", time_of_day="day",
                                       frames=1, width=200, height=150))
    model = scene.model
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    weather = wx.weather_at("clear", 1.0)
    assert weather.sun > 0.02 and weather.road_reflectance > 0
    with FrameRenderer(model, 200, 150, geom_instance_table(model),
                       base_weather=wx.weather_at("clear", 0.0)) as renderer:
        renderer.update(data)
        _, _, depth = renderer.render_instances_depth()
        unshaded = renderer.render_weather(data, weather, depth).astype(float)
        renderer._sun_light = -1  # the deck with the sun's shadows in the mirror pass too
        shaded = renderer.render_weather(data, weather, depth).astype(float)
    assert (unshaded - shaded).min() >= 0 and (unshaded - shaded).mean() > 0.1


def test_film_streaks_smear_along_the_vertical_over_the_road_only():
    """A lit pixel on an all-road mirror becomes a vertical Gaussian of the given sigma, with
    nothing spread across; a car (not road) next to the road is not smeared into it."""
    mirror = np.zeros((61, 9, 3), np.float32)
    mirror[30, 4] = 200.0
    road = np.ones((61, 9), np.float32)
    streak = wx.streak_reflection(mirror, road, 4.0)
    column = streak[:, 4, 0]
    rows = np.arange(61) - 30.0
    expected = np.where(np.abs(rows) <= 12, np.exp(-0.5 * (rows / 4.0) ** 2), 0.0)  # 3 sigma
    np.testing.assert_allclose(column, 200.0 * expected / expected.sum(), rtol=1e-4, atol=1e-3)
    assert not streak[:, [0, 1, 2, 3, 5, 6, 7, 8]].any()  # no horizontal spread
    assert np.array_equal(wx.streak_reflection(mirror, road, 0.0), mirror)

    car = np.full((61, 9, 3), 50.0, np.float32)
    car[:20] = 250.0  # a bright car body above the road, in rows 0..19
    road = np.ones((61, 9), np.float32)
    road[:20] = 0.0
    smeared = wx.streak_reflection(car, road, 6.0)
    np.testing.assert_allclose(smeared[20:], 50.0, atol=1e-3)  # the car is not smeared in
    assert np.array_equal(smeared[:2], car[:2])  # over 3 sigma from the road: kept

    light = np.full((61, 9, 3), 20.0, np.float32)
    light[30, 4] = 255.0  # a clipped lamp
    road = np.ones((61, 9), np.float32)
    plain = wx.streak_reflection(light, road, 4.0)
    boosted = wx.streak_reflection(light, road, 4.0, clipped_gain=wx.CLIPPED_GAIN)
    assert plain[30, 4, 0] < 100 < boosted[30, 4, 0]  # a glow, or a bright streak at night
    np.testing.assert_allclose(boosted[:, [0, 8]], plain[:, [0, 8]])  # only the light's column


def test_only_the_lamps_mirror_images_streak_brightly():
    """Two clipped spots: the one among ``lights`` (a lamp) streaks with the night gain, the
    other (a light car body lit past the sensor's range) smears as without it."""
    scene = np.full((120, 40, 3), 20.0, np.float32)
    scene[50:53, 5:8] = 255.0  # a lamp's mirror image
    scene[50:70, 25:35] = (90.0, 250.0, 255.0)  # a cyan body, clipped
    lights = np.zeros((120, 40), bool)
    lights[48:55, 3:10] = True
    road = np.ones((120, 40), np.float32)
    plain = wx.streak_reflection(scene, road, 4.0)
    boosted = wx.streak_reflection(scene, road, 4.0, wx.CLIPPED_GAIN, lights)
    assert boosted[51, 6, 0] > plain[51, 6, 0] + 100  # the lamp's streak
    np.testing.assert_array_equal(boosted[:, 20:], plain[:, 20:])  # the body: no gain
    every_clip = wx.streak_reflection(scene, road, 4.0, wx.CLIPPED_GAIN)
    assert every_clip[60, 30, 1] > boosted[60, 30, 1] + 100  # what lights=None would do
    with pytest.raises(ValueError, match=r"lights: expected shape \(120, 40\), got \(4, 4\)"):
        wx.streak_reflection(scene, road, 4.0, wx.CLIPPED_GAIN, np.zeros((4, 4), bool))


def test_mirrored_light_pixels_project_the_lamps_reflection():
    """A lamp 1 m up and 10 m ahead of a camera 1.5 m over the water: its mirror image, 1 m
    under the water, is seen 2.5 m below the camera at 10 m: row cy + f x 0.25, a disc of
    f x r / 10 + 1 pixels. Lamps behind the camera or out of view draw nothing."""
    K = np.array([[100.0, 0.0, 80.0], [0.0, 100.0, 60.0], [0.0, 0.0, 1.0]])
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # looks along +y
    pose[:3, 3] = (0.0, 0.0, 1.5)
    lamp = [0.0, 10.0, 1.0, 0.1]
    mask = wx.mirrored_light_pixels(K, pose, np.array([lamp]), 0.0, 120, 160)
    expected = np.zeros((120, 160), np.uint8)
    cv2.circle(expected, (80, 85), 2, 1, -1)  # 100 x 0.1 / 10 + 1 = 2 pixels
    np.testing.assert_array_equal(mask, expected.astype(bool))
    raised = wx.mirrored_light_pixels(K, pose, np.array([lamp]), 0.5, 120, 160)  # water 0.5 m up
    assert raised[75, 80] and not raised[85, 80]  # mirrored to z = 0: 1.5 m below the camera
    away = np.array([[0.0, -10.0, 1.0, 0.1], [500.0, 10.0, 1.0, 0.1]])  # behind; far aside
    assert not wx.mirrored_light_pixels(K, pose, away, 0.0, 120, 160).any()
    assert not wx.mirrored_light_pixels(K, pose, np.zeros((0, 4)), 0.0, 120, 160).any()
    assert wx.film_streak_sigma_px(400.0) == pytest.approx(16.0)


def test_a_box_lamps_mirror_image_is_its_footprint_not_its_bounding_disc():
    """A tail lamp is a flat box (0.2 x 0.02 x 0.06 m): its bounding sphere's disc covered
    several times the lamp, and the clipped car body around it streaked 8x brighter than the car
    (a visual audit: a pink car at night, seed 14 at the junction). As a box it covers the
    projection of its 8 mirrored corners: the lamp 0.5 m up and 10 m ahead is mirrored 2.0 m
    below the camera, row cy + f x 0.2 = 100, 0.2 m across (4 px about column 80) and 0.06 m tall
    (1.2 px)."""
    K = np.array([[200.0, 0.0, 80.0], [0.0, 200.0, 60.0], [0.0, 0.0, 1.0]])
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # looks along +y
    pose[:3, 3] = (0.0, 0.0, 1.5)
    half = np.array([0.1, 0.01, 0.03])  # across (x), along the view (y), up (z)
    sphere = np.array([[0.0, 10.0, 0.5, float(np.linalg.norm(half))]])
    box = np.concatenate([[0.0, 10.0, 0.5], np.eye(3).ravel(), half])[None]
    disc = wx.mirrored_light_pixels(K, pose, sphere, 0.0, 120, 160)
    footprint = wx.mirrored_light_pixels(K, pose, sphere, 0.0, 120, 160, boxes=box)
    rows, cols = np.nonzero(footprint)
    assert footprint.any() and footprint.sum() * 3 < disc.sum()
    assert not (footprint & ~disc).any()  # inside the lamp's disc
    assert cols.min() >= 77 and cols.max() <= 82  # 4 px across, not the disc's 2 x 4 + 1
    assert rows.min() >= 98 and rows.max() <= 101  # about row 100, 1.2 px tall
    np.testing.assert_array_equal(  # NaN rows (not boxes) fall back to the disc
        wx.mirrored_light_pixels(K, pose, sphere, 0.0, 120, 160, boxes=np.full((1, 15), np.nan)), disc)
    with pytest.raises(ValueError, match=r"boxes: expected one row per sphere \(1\), got 2"):
        wx.mirrored_light_pixels(K, pose, sphere, 0.0, 120, 160, boxes=np.repeat(box, 2, axis=0))


def test_ripple_impacts_integrate_marshall_palmer_and_the_slope_saturates():
    """The closed form against a numerical integral of N(D) v(D) over D >= 1 mm; the puddles'
    slope grows with the rate until the rings cover them (about 10 mm/h), then stays."""
    from rainbench.rain import physical

    for rate in (2.0, 10.0, 50.0, 100.0):
        diameters = np.linspace(wx.RIPPLE_MIN_DROP_MM, 40.0, 400_001)
        density = physical.MP_N0_PER_M3_MM * np.exp(
            -physical.marshall_palmer_slope(rate) * diameters)
        flux = np.trapezoid(density * physical.terminal_velocity(diameters), diameters)
        assert wx.ripple_impacts_per_m2_s(rate) == pytest.approx(flux, rel=1e-4)
    assert wx.ripple_impacts_per_m2_s(0.0) == 0.0 == wx.puddle_ripple_slope(0.0)
    slopes = [wx.puddle_ripple_slope(rate) for rate in (1, 2, 4, 6, 8)]
    assert all(a < b for a, b in zip(slopes, slopes[1:])) and slopes[-1] < wx.RIPPLE_SLOPE
    assert wx.puddle_ripple_slope(11.0) == wx.puddle_ripple_slope(100.0) == wx.RIPPLE_SLOPE


def test_plane_pixels_finds_the_rectangle_seen_from_above():
    """Top-down camera 10 m over a level plane z = 0: the pixels of a 4 x 2 m rectangle turned
    by 90 degrees, and none where something stands over it or where the depth says sky."""
    K = np.array([[50.0, 0, 50], [0, 50.0, 50], [0, 0, 1]])  # 100 x 100 px, 0.2 m per px
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])  # x right = +x, y down = -y, looking down
    pose[2, 3] = 10.0
    depth = np.full((100, 100), 10.0, np.float32)
    rectangle = np.array([1.0, 0.0, 0.0, 2.0, 1.0, math.pi / 2])  # 2 m along x, 4 m along y
    mask = wx.plane_pixels(K, pose, depth, rectangle)
    # every pixel whose centre is inside (columns 50..59, rows 40..59), none beyond one pixel of
    # the edges (the rectangles are filled as polygons: edges are exact to half a pixel)
    assert mask[40:60, 50:60].all() and mask.sum() <= 22 * 12
    assert not mask[:, :49].any() and not mask[:, 61:].any()
    assert not mask[:39].any() and not mask[61:].any()
    depth[45:50, 52:55] = 9.0  # a box standing on the rectangle
    depth[55:57] = np.inf  # a gap: no geometry
    hidden = wx.plane_pixels(K, pose, depth, rectangle)
    assert not hidden[45:50, 52:55].any() and not hidden[55:57].any()
    assert np.array_equal(hidden, mask & np.isfinite(depth) & (depth == 10.0))
    level = np.full((100, 100), 10.0, np.float32)
    assert wx.plane_pixels(K, pose, level, np.array([0, 0, 0, np.inf, np.inf, 0.0])).all()
    assert wx.plane_pixels(K, pose, level, np.array([0, 0, 0, np.inf, 1.0, 0.0])).all()
    with pytest.raises(ValueError, match=r"rectangles: expected one plane, got heights 0 to 1 m"):
        wx.plane_pixels(K, pose, level, np.array([[0, 0, 0, 1, 1, 0], [0, 0, 1, 1, 1, 0.0]]))


def test_a_puddle_mirrors_more_than_the_wet_road_and_only_where_it_lies():
    """The red box mirrored in a puddle 1.5-3.5 m in front of it: the reflection is redder than
    on the wet film (water's Fresnel reflectance, 0.19-0.26 at the 74-77 degrees seen here, in
    linear light, against the film's 0.42 F / F(80) of display values: a few grey levels more),
    pixels away from the puddle and the box itself are unchanged, and dry renders never show the
    outline geom."""
    view = dict(camera_pos=[-6, 0, 1.0], camera_quat=_camera_quat(),
                fovy=horizontal_to_vertical_fov(60, 120, 90))
    plain = _rig_scene(**view)
    puddled = _rig_scene(**view, puddle=(-2.5, 0.0, 1.0, 1.2))
    base = wx.weather_at("overcast", 0.0)
    wet = wx.weather_at("overcast", 50.0)
    assert wet.puddle_fraction == 1.0
    assert np.array_equal(_render(*plain, base, base), _render(*puddled, base, base))
    road, water = (_render(*scene, wet, base).astype(int) for scene in (plain, puddled))
    dry = _render(*plain, base, base).astype(int)
    box = (dry[..., 0] > dry[..., 1] + 60) & (dry[..., 0] > dry[..., 2] + 60)
    ground_line = np.flatnonzero(box.any(axis=1)).max()
    cols = np.flatnonzero(box.any(axis=0))
    below = (slice(ground_line + 2, ground_line + 10), slice(cols.min() + 2, cols.max() - 1))

    def red_excess(image):
        return image[..., 0] - (image[..., 1] + image[..., 2]) / 2

    assert red_excess(water[below]).mean() > red_excess(road[below]).mean() + 2
    assert np.array_equal(water[box], road[box])  # the box stands in front of nothing
    changed = np.abs(water - road).max(axis=-1) > 0
    rows = np.flatnonzero(changed.any(axis=1))
    assert not changed[:ground_line].any()  # the puddle is on the road, below the box's base
    assert rows.max() < 89 and not changed[:, :5].any()  # and it ends inside the image


def test_rain_ripples_smear_a_puddles_mirror_and_nothing_else():
    """The same puddle under still water (rate 0 in an otherwise equal weather) and under 50
    mm/h: the ripples smooth the mirrored box's edges inside the puddle, and every pixel outside
    it is the same."""
    scene = _rig_scene(camera_pos=[-6, 0, 1.0], camera_quat=_camera_quat(),
                       fovy=horizontal_to_vertical_fov(60, 120, 90), puddle=(-2.5, 0.0, 1.0, 1.2))
    base = wx.weather_at("overcast", 0.0)
    rippled = wx.weather_at("overcast", 50.0)
    still = dataclasses.replace(rippled, rain_mm_h=0.0)
    assert wx.puddle_ripple_slope(still.rain_mm_h) == 0.0 < wx.puddle_ripple_slope(50.0)
    calm, rained = (_render(*scene, weather, base).astype(float) for weather in (still, rippled))
    changed = np.abs(calm - rained).max(axis=-1) > 0
    rows, cols = np.nonzero(changed)
    assert changed.sum() > 100
    puddle = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))

    def vertical_detail(image):
        return np.abs(np.diff(image[puddle], axis=0)).sum()

    assert vertical_detail(rained) < 0.8 * vertical_detail(calm)
    assert rows.min() > 50  # the ripples are on the road in front of the box, not elsewhere


# -- the generator ---------------------------------------------------------------------------
def test_paper_default_clip_is_cloudy_with_a_grey_sky(tmp_path):
    assert _seed_and_sky(argparse.Namespace(seed=None, sky=None)) == (0, "cloudy")
    assert _seed_and_sky(argparse.Namespace(seed=7, sky=None)) == (7, None)
    assert _seed_and_sky(argparse.Namespace(seed=None, sky="clear")) == (0, "clear")
    shard = generate_shard(GenerateConfig(seed=0, sky="cloudy", **SMALL), tmp_path)
    with h5py.File(shard) as f:
        assert f.attrs["sky"] == "cloudy"
        rgb, depth = f["rgb"][0, 0], f["depth"][0]
    sky = ~np.isfinite(depth)
    assert sky.sum() > 500
    assert _saturation(rgb, sky) <= 0.15


@pytest.fixture(scope="module")
def clear_physical(tmp_path_factory):
    out = tmp_path_factory.mktemp("weather")
    # seed 10's street shows four labelled actors in each of these two small frames
    config = GenerateConfig(seed=10, sky="clear", rates=(0.0, 50.0, 100.0), rain_model="physical",
                            **SMALL)
    return config, generate_shard(config, out)


def test_physical_weather_darkens_greys_and_wets_a_clear_scene(clear_physical):
    config, shard = clear_physical
    with h5py.File(shard) as f:
        assert f.attrs["weather_follows_rate"] and f.attrs["sky"] == "clear"
        rgb = f["rgb"][()]
        depth = f["depth"][()]
        weather = {key: f[f"weather/{key}"][()] for key in f["weather"]}
    sky = ~np.isfinite(depth[0])
    assert _luma(rgb[2, 0]) <= 0.8 * _luma(rgb[0, 0])
    assert _saturation(rgb[0, 0], sky) > 0.2 and _saturation(rgb[2, 0], sky) < 0.10
    assert list(weather["rain_mm_h"]) == [0.0, 50.0, 100.0]
    assert np.all(np.diff(weather["wetness"]) >= 0) and weather["wetness"][0] == 0
    assert np.all(np.diff(weather["sun"]) <= 0) and weather["sun"][0] == 1.0
    assert set(wx.RECORD_FIELDS) == set(weather)


def test_weather_sweep_nests_is_deterministic_and_rate_set_independent(tmp_path, clear_physical):
    config, shard = clear_physical
    import dataclasses

    again = generate_shard(config, tmp_path / "again")
    subset = generate_shard(dataclasses.replace(config, rates=(0.0, 100.0)), tmp_path / "subset")
    clean = generate_shard(dataclasses.replace(config, rates=(0.0,)), tmp_path / "clean")
    with h5py.File(shard) as f, h5py.File(again) as g, h5py.File(subset) as h, h5py.File(clean) as c:
        assert np.array_equal(f["rgb"][()], g["rgb"][()])
        assert np.array_equal(f["rgb"][2], h["rgb"][1])  # 100 mm/h, whatever else is asked
        assert np.array_equal(f["rgb"][0], c["rgb"][0])  # rate 0 is the clean base render


def test_stored_statistics_match_the_stored_images(clear_physical):
    _, shard = clear_physical
    with h5py.File(shard) as f:
        rgb = f["rgb"][()]
        ssim, psnr = f["rain/ssim"][()], f["rain/psnr"][()]
        offsets = f["labels/offsets"][()]
        boxes = f["labels/bbox"][()]
        coverage, contrast = f["labels/rain_coverage"][()], f["labels/contrast_loss"][()]
    for row in (1, 2):
        for frame in range(rgb.shape[1]):
            s, p = rain.image_quality(rgb[0, frame], rgb[row, frame])
            assert ssim[row, frame] == pytest.approx(s, abs=1e-5)
            assert psnr[row, frame] == pytest.approx(p, abs=1e-3)
            lo, hi = offsets[frame], offsets[frame + 1]
            _, expected = rain.box_rain_labels(rgb[0, frame], rgb[row, frame],
                                               np.zeros(rgb.shape[2:4], np.float32), boxes[lo:hi])
            np.testing.assert_allclose(contrast[row, lo:hi], expected, atol=1e-5)
    assert (contrast[2] >= 0).all() and coverage[2].max() > 0


def test_scene_renders_rainy_weather_without_changing_labels():
    config = GenerateConfig(seed=1, sky="clear", **SMALL)
    setup = build_scene(config)
    data = mujoco.MjData(setup.model)
    mujoco.mj_forward(setup.model, data)
    with FrameRenderer(setup.model, 160, 120, setup.geom_instance,
                       base_weather=setup.base_weather) as renderer:
        renderer.update(data)
        before, _ = renderer.render_rgb_depth()
        ids_before, _, depth = renderer.render_instances_depth()
        with pytest.raises(ValueError, match=r"wets the road, so depth is needed: expected "
                                             r"\(120, 160\) .* got None"):
            renderer.render_weather(data, wx.weather_at("clear", 100.0))
        wet = renderer.render_weather(data, wx.weather_at("clear", 100.0), depth)
        renderer.update(data)
        after, _ = renderer.render_rgb_depth()
        ids_after, _ = renderer.render_instances()
    assert np.array_equal(before, after) and np.array_equal(ids_before, ids_after)
    assert not np.array_equal(before, wet)


@pytest.mark.parametrize("model", ["physical", "jeon2022"])
def test_sweep_over_per_rate_scenes_equals_single_rates(model):
    rng = np.random.default_rng(3)
    height, width = 90, 120
    depth = np.full((height, width), 8.0, np.float32)
    depth[:30] = np.inf
    K = np.array([[60.0, 0, 60], [0, 60.0, 45], [0, 0, 1]])
    rates = [0.0, 30.0, 100.0]
    scenes = [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in rates]
    config = rain.RainConfig(model=model)
    seeds = np.random.SeedSequence([4, 5, 6])
    swept = rain.render_rain_sweep(scenes[0], depth, rates, config=config, K=K,
                                   seed_sequence=seeds, scenes=scenes)
    for rate, scene, frame in zip(rates, scenes, swept):
        single = rain.render_rain(scene, depth, rate, config=config, K=K, seed_sequence=seeds)
        assert np.array_equal(single.rgb, frame.rgb) and frame.drop_count == single.drop_count
        assert np.array_equal(single.coverage, frame.coverage)
    assert np.array_equal(swept[0].rgb, scenes[0])
    with pytest.raises(ValueError, match=r"scenes: expected one image per rate \(3\), got 2"):
        rain.render_rain_sweep(scenes[0], depth, rates, config=config, K=K, seed_sequence=seeds,
                               scenes=scenes[:2])


def test_sweep_with_per_rate_airlights_equals_single_rates_in_their_own_light():
    """Weather that changes the airlight with the rate (dusk, night) draws the falling drops
    once for the whole sweep: each rate still equals a sweep of its own with that airlight."""
    rng = np.random.default_rng(5)
    height, width = 90, 120
    depth = np.full((height, width), 8.0, np.float32)
    depth[:30] = np.inf
    K = np.array([[60.0, 0, 60], [0, 60.0, 45], [0, 0, 1]])
    rates = [100.0, 0.0, 30.0, 60.0]
    scenes = [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in rates]
    airlights = [(40.0, 42.5, 45.0), (0.0, 0.0, 0.0), (200.0, 180.0, 160.0), (90.0, 90.0, 90.0)]
    config = rain.RainConfig(model="physical", exposure_s=1 / 30)
    seeds = np.random.SeedSequence([4, 5, 6])
    for given_scenes in (scenes, None):
        swept = rain.render_rain_sweep(scenes[0], depth, rates, config=config, K=K,
                                       seed_sequence=seeds, scenes=given_scenes,
                                       airlights=airlights)
        for index, (rate, airlight, frame) in enumerate(zip(rates, airlights, swept)):
            own = dataclasses.replace(config, airlight_rgb=airlight)
            scene = scenes[index] if given_scenes is not None else scenes[0]
            single = rain.render_rain(scene, depth, rate, config=own, K=K, seed_sequence=seeds)
            assert np.array_equal(single.rgb, frame.rgb) and frame.drop_count == single.drop_count
            assert np.array_equal(single.coverage, frame.coverage)
    # the airlights matter: the same rates in one light give other images
    one_light = rain.render_rain_sweep(scenes[0], depth, rates, config=config, K=K,
                                       seed_sequence=seeds, scenes=scenes)
    assert not np.array_equal(one_light[0].rgb, swept[0].rgb)
    with pytest.raises(ValueError, match=r"airlights: expected one \(R, G, B\) per rate \(4\), got 3"):
        rain.render_rain_sweep(scenes[0], depth, rates, config=config, K=K, seed_sequence=seeds,
                               airlights=airlights[:3])
    with pytest.raises(ValueError, match=r"airlights: rate 30 mm/h is given twice with different airlights"):
        rain.render_rain_sweep(scenes[0], depth, [30.0, 30.0], config=config, K=K,
                               seed_sequence=seeds, airlights=airlights[:2])
    with pytest.raises(ValueError, match=r"RainConfig.airlight_rgb must be None or three numbers in \[0, 255\]"):
        rain.render_rain_sweep(scenes[0], depth, [30.0], config=config, K=K, seed_sequence=seeds,
                               airlights=[(300.0, 0.0, 0.0)])
    with pytest.raises(ValueError, match=r"airlights: only the physical model .* got model 'jeon2022'"):
        rain.render_rain_sweep(scenes[0], depth, [30.0], config=rain.RainConfig(model="jeon2022"),
                               K=K, seed_sequence=seeds, airlights=[(9.0, 9.0, 9.0)])


def test_a_dusk_frame_draws_its_falling_drops_once_for_all_rates(tmp_path, monkeypatch):
    """At dusk the airlight changes with the rate and the exposure does not: one sweep per
    frame, not one per rate."""
    from rainbench.gen import generate

    calls = []
    sweep = rain.render_rain_sweep

    def counted(*args, **kwargs):
        calls.append((len(args[2]), kwargs.get("airlights") is not None))
        return sweep(*args, **kwargs)

    monkeypatch.setattr(rain, "render_rain_sweep", counted)
    config = GenerateConfig(seed=3, sky="cloudy", rain_model="physical",
                            rates=(0.0, 20.0, 60.0, 100.0), **{**SMALL, "time_of_day": "dusk"})
    weathers = generate.sweep_weathers(config, build_scene(config).layout)
    assert len({w.exposure_s for w in weathers[1:]}) == 1  # the case this covers
    assert len({wx.airlight_rgb(w).tobytes() for w in weathers[1:]}) == 3
    generate_shard(config, tmp_path, threads=1)
    assert calls == [(3, True)] * 2


def test_rgb_is_antialiased_and_segmentation_stays_exact():
    config = GenerateConfig(seed=3, **SMALL)
    setup = build_scene(config)
    assert setup.model.vis.quality.offsamples == 4
    data = mujoco.MjData(setup.model)
    mujoco.mj_forward(setup.model, data)
    results = {}
    for samples in (0, 4):
        setup.model.vis.quality.offsamples = samples
        with FrameRenderer(setup.model, 160, 120, setup.geom_instance,
                           base_weather=setup.base_weather) as renderer:
            renderer.update(data)
            rgb, _ = renderer.render_rgb_depth()
            ids, geometry = renderer.render_instances()
        results[samples] = rgb, ids, geometry
    assert np.array_equal(results[0][1], results[4][1])  # exact ids with multisampling
    assert np.array_equal(results[0][2], results[4][2])
    # edges: multisampling blends colours along silhouettes, so more distinct colours appear
    distinct = {s: len(np.unique(results[s][0].reshape(-1, 3), axis=0)) for s in (0, 4)}
    assert distinct[4] > distinct[0] * 1.05


def test_format_v1_shards_are_still_read(tmp_path, clear_physical):
    """A v1 shard (no /weather, no sky attributes) reads through the dataset reader."""
    import shutil

    from rainbench import ShardDataset

    _, shard = clear_physical
    old = tmp_path / "v1" / shard.name
    old.parent.mkdir()
    shutil.copy(shard, old)
    with h5py.File(old, "a") as f:
        del f["weather"]
        del f.attrs["sky"], f.attrs["weather_follows_rate"]
        f.attrs["format_version"] = 1
    dataset = ShardDataset(old.parent)
    image, target = dataset[len(dataset) - 1]
    fresh_image, fresh_target = ShardDataset(shard.parent)[len(dataset) - 1]
    assert np.array_equal(np.asarray(image), np.asarray(fresh_image))
    assert np.array_equal(np.asarray(target["boxes"]), np.asarray(fresh_target["boxes"]))


# --------------------------------------------------------------------------------------------
# the glow rain lays around lights (dusk and night)


def test_light_passing_once_through_a_drop_spreads_as_geometric_optics_says():
    deviation, density = wx.refraction_phase()
    solid_angle = 2.0 * np.pi * (np.cos(deviation - np.radians(0.25)) - np.cos(deviation + np.radians(0.25)))
    assert float((density * solid_angle).sum()) == pytest.approx(1.0, abs=1e-9)
    # the share of the disc's light that passes once, by its own sum over impact parameters
    impact = np.linspace(0.0, 1.0, 100_001)[:-1] + 0.5e-5
    passing = float(np.sum(2.0 * impact * (1.0 - wx.water_fresnel(np.cos(np.arcsin(impact)))) ** 2) * 1e-5)
    assert passing == pytest.approx(0.8814, abs=5e-4) and wx.GLOW_SHARE == pytest.approx(0.5 * passing, abs=2e-3)
    normal_reflectance = ((1.333 - 1.0) / (1.333 + 1.0)) ** 2
    forward = 4.0 / np.pi * (1.0 - normal_reflectance) ** 2 / passing  # deviation ~ 2 b (1 - 1/n)
    assert density[:4].mean() == pytest.approx(forward, rel=0.01)  # flat near the forward direction
    cumulative = np.cumsum(density * solid_angle)
    assert np.degrees(deviation[np.searchsorted(cumulative, 0.5)]) == pytest.approx(24.3, abs=0.5)
    assert (density[deviation > np.radians(83.0)] == 0).all()


def test_a_lamp_glows_in_rain_as_its_scattered_light_says():
    K = np.array([[400.0, 0.0, 400.0], [0.0, 400.0, 300.0], [0.0, 0.0, 1.0]])  # 90 degrees, 800x600
    pose = np.eye(4)  # the camera at the origin looking down +z (OpenCV axes)
    depth = np.full((600, 800), np.inf, np.float32)
    night = wx.weather_at("overcast", 100.0, time_of_day="night")
    lamp, candela = np.array([[0.0, 0.0, 20.0]]), np.array([400.0])
    glow = wx.light_glow(K, pose, lamp, candela, [[1.0, 1.0, 1.0]], depth, night)
    beta = rain.physical.extinction_coefficient(100.0) / 1000.0
    scattered = 400.0 / 20.0**2 * wx.GLOW_SHARE * (1.0 - np.exp(-beta * 20.0))
    forward = 4.0 / np.pi * (1.0 - (0.333 / 2.333) ** 2) ** 2 / 0.8814  # per sr (test above)
    expected = scattered * forward * np.pi / night.illuminance_lux * night.light_level**2.2
    assert glow[300, 400, 0] == pytest.approx(expected, rel=0.01)  # the lamp's own direction
    assert glow[300, 799, 0] < glow[300, 600, 0] < glow[300, 400, 0]  # falls off with the angle
    assert glow.shape == (600, 800, 3) and glow.dtype == np.float32
    red = wx.light_glow(K, pose, lamp, candela, [[1.0, 0.1, 0.0]], depth, night)
    np.testing.assert_allclose(red[..., 1], 0.1 * red[..., 0], rtol=1e-5)  # the lamp's colour
    assert not wx.light_glow(K, pose, lamp, candela, [[1.0] * 3], depth, wx.weather_at("overcast", 0.0, time_of_day="night")).any()
    assert not wx.light_glow(K, pose, lamp, [0.0], [[1.0] * 3], depth, night).any()  # turned away
    behind = wx.light_glow(K, pose, -lamp, candela, [[1.0] * 3], depth, night)
    assert not behind.any()
    wall = np.full((600, 800), 10.0, np.float32)  # a wall 10 m away hides the lamp at 20 m
    assert not wx.light_glow(K, pose, lamp, candela, [[1.0] * 3], wall, night).any()
    lighter = wx.light_glow(K, pose, lamp, candela, [[1.0] * 3], depth, dataclasses.replace(night, rain_mm_h=20.0))
    assert 0 < lighter[300, 400, 0] < glow[300, 400, 0]


def test_glow_adds_in_linear_light():
    rgb = np.array([[[0, 100, 255]]], np.uint8)
    assert np.array_equal(wx.add_glow(rgb, np.zeros((1, 1, 3), np.float32)), rgb)
    lifted = wx.add_glow(rgb, np.full((1, 1, 3), 0.25, np.float32))
    expected = np.clip(np.rint(255.0 * ((rgb / 255.0) ** 2.2 + 0.25) ** (1 / 2.2)), 0, 255)
    np.testing.assert_allclose(lifted, expected, atol=1)
    assert lifted[0, 0, 0] == pytest.approx(255 * 0.25 ** (1 / 2.2), abs=1) and lifted[0, 0, 2] == 255


@pytest.mark.parametrize("time_of_day", ["day", "night"])
def test_wet_surfaces_reflect_the_documented_share_of_the_light(time_of_day):
    """Wet asphalt reflects 45 % less light (Lekner & Dorf); its material colour was scaled by
    0.55, which through the renderer's display values is 73 % less light."""
    from rainbench.mjcf.weather import scene_lighting

    for rate in (0.0, 5.0, 100.0):
        weather = wx.weather_at("clear", rate, time_of_day=time_of_day)
        lighting = scene_lighting(weather)
        for factor, darkening in ((lighting.road_factor, wx.ROAD_WET_DARKENING),
                                  (lighting.pavement_factor, wx.PAVEMENT_WET_DARKENING),
                                  (lighting.grass_factor, wx.GRASS_WET_DARKENING)):
            assert factor ** wx.DISPLAY_LIGHT_GAMMA == pytest.approx(1.0 - darkening * weather.wetness)
    wet = scene_lighting(wx.weather_at("clear", 100.0, time_of_day=time_of_day))
    assert wet.road_factor == pytest.approx(0.55 ** (1 / 2.2), abs=1e-3)  # 0.762 of the display value


def test_spray_mixes_light_not_display_values():
    """Spray of opacity 0.5 lit at 200 over black shows as 255 (0.5 x 0.78)^(1/2.2) = 146, not the
    100 of a display-value mix; opacity 0 leaves the image as it was, 1 is the spray's colour."""
    opacity = np.array([[0.0, 0.5, 1.0]], np.float32)
    image = np.array([[[0, 0, 0], [0, 0, 0], [0, 0, 0]]], np.uint8)
    out = wx.composite_spray(image, opacity, [200.0, 200.0, 200.0])
    assert out[0, 0].tolist() == [0, 0, 0] and out[0, 2].tolist() == [200, 200, 200]
    assert out[0, 1].tolist() == [round(255 * (0.5 * (200 / 255) ** 2.2) ** (1 / 2.2))] * 3 == [146] * 3


def test_the_tone_curve_round_trips_display_values():
    from rainbench.rain import tone

    values = np.arange(256, dtype=np.uint8).reshape(16, 16)
    light = tone.to_linear(values)
    assert light.dtype == np.float32 and light[0, 0] == 0.0 and light[-1, -1] == 1.0
    np.testing.assert_allclose(light, (values / 255.0) ** 2.2, rtol=1e-5, atol=1e-7)
    assert np.array_equal(tone.to_display(light), values)  # every display value comes back
    assert tone.to_display(np.array([-0.5, 2.0, np.inf], np.float32)).tolist() == [0, 255, 255]  # clipped
    assert tone.to_display(np.float32(1.0)).shape == () and int(tone.to_display(np.float32(1.0))) == 255
    assert tone.to_display(np.zeros((0, 5, 3), np.float32)).shape == (0, 5, 3)
    assert tone.to_linear(np.zeros((0, 5, 3), np.uint8)).shape == (0, 5, 3)
    grey = np.full((4, 5, 1), 128, np.uint8)  # one channel: OpenCV's lookup would drop it
    assert tone.to_linear(grey).shape == (4, 5, 1)
    assert tone.to_display(tone.to_linear(grey)).tolist() == grey.tolist()
    assert float(tone.linear_value(128.0)) == pytest.approx((128 / 255) ** 2.2)
    with pytest.raises(TypeError, match="^display: expected uint8 values, got float64$"):
        tone.to_linear(np.zeros(3))
