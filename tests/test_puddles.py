"""Puddles: the coverage law (rainbench.rain.weather.puddle_coverage) on exact geometry, and the
renderer laying them over a wet road."""

import math

import numpy as np
import pytest

from rainbench.rain import weather as wx

REACH = 1.0 + sum(amplitude for _, amplitude in wx.PUDDLE_OUTLINE)  # the outline's largest radius
CORE = (1.0 - sum(amplitude for _, amplitude in wx.PUDDLE_OUTLINE)) * (1.0 - wx.PUDDLE_EDGE)


def _top_down(height=10.0, size=201, focal=100.0):
    """A camera ``height`` m above the origin looking straight down (image x = world +x, image y
    = world -y): pixel (r, c) sees ground point ((c + 0.5 - cx) / f * h, -(r + 0.5 - cy) / f * h)."""
    K = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = [0.0, 0.0, height]
    depth = np.full((size, size), height, np.float32)
    centres = (np.arange(size) + 0.5 - size / 2) / focal * height
    ground_x, ground_y = np.meshgrid(centres, -centres)
    return K, pose, depth, ground_x, ground_y


def test_coverage_is_one_inside_zero_outside_and_soft_between():
    K, pose, depth, gx, gy = _top_down()
    puddle = np.array([[1.0, -2.0, 0.0, 3.0, 2.0, math.radians(30)]])
    phases = wx.puddle_outline_phases(1)
    coverage = wx.puddle_coverage(K, pose, depth, puddle, 1.0, phases)
    yaw = math.radians(30)
    dx, dy = gx - 1.0, gy + 2.0
    along = (math.cos(yaw) * dx + math.sin(yaw) * dy) / 3.0
    across = (-math.sin(yaw) * dx + math.cos(yaw) * dy) / 2.0
    radius = np.hypot(along, across)
    assert coverage.dtype == np.float32 and coverage.shape == depth.shape
    assert (coverage[radius <= CORE - 0.01] == 1.0).all()
    assert (coverage[radius >= REACH] == 0.0).all()
    soft = (coverage > 0.05) & (coverage < 0.95)
    assert soft.sum() > 100  # a soft rim, not a drawn edge
    # not an ellipse: along the ellipse's own radius 0.9 the coverage varies with the angle
    ring = np.abs(radius - 0.95) < 0.02
    assert coverage[ring].max() - coverage[ring].min() > 0.5


def test_coverage_scales_with_the_weather_and_vanishes_at_zero():
    K, pose, depth, gx, gy = _top_down()
    puddle = np.array([[0.0, 0.0, 0.0, 4.0, 4.0, 0.0]])
    phases = wx.puddle_outline_phases(1)
    radius = np.hypot(gx, gy) / 4.0
    half = wx.puddle_coverage(K, pose, depth, puddle, 0.5, phases)
    assert (half[radius >= 0.5 * REACH] == 0.0).all() and half[radius <= 0.5 * CORE - 0.01].min() == 1
    assert not wx.puddle_coverage(K, pose, depth, puddle, 0.0, phases).any()
    assert not wx.puddle_coverage(K, pose, depth, np.zeros((0, 6)), 1.0, phases[:0]).any()
    with pytest.raises(ValueError, match=r"scale: expected 0\.\.1 \(full size\), got 1\.5"):
        wx.puddle_coverage(K, pose, depth, puddle, 1.5, phases)


def test_whatever_stands_in_front_or_the_sky_hides_the_puddle():
    K, pose, depth, _, _ = _top_down()
    puddle = np.array([[0.0, 0.0, 0.0, 4.0, 4.0, 0.0]])
    phases = wx.puddle_outline_phases(1)
    depth[90:110, 90:110] = 9.0  # a 1 m tall object on the puddle
    depth[:, :95] = np.inf  # no geometry (sky)
    coverage = wx.puddle_coverage(K, pose, depth, puddle, 1.0, phases)
    assert not coverage[90:110, 90:110].any() and not coverage[:, :95].any()
    assert (coverage[80:90, 100:110] == 1.0).all()  # still water beside the object
    depth[80:90, 100:110] += 0.05  # within 1 % + 2 cm: the plane itself (depth precision)
    assert (wx.puddle_coverage(K, pose, depth, puddle, 1.0, phases)[80:90, 100:110] == 1).all()


def test_the_window_search_misses_no_puddle_pixel(monkeypatch):
    """A road camera 1.5 m up looking ahead, pitched 5 degrees down; puddles ahead, beside,
    under and behind it: the per-puddle windows give the coverage of a whole-image evaluation."""
    height, width = 120, 160
    K = np.array([[80.0, 0, 80], [0, 80.0, 60], [0, 0, 1]])
    pitch = math.radians(5)
    forward = np.array([math.cos(pitch), 0.0, -math.sin(pitch)])
    down = np.array([-math.sin(pitch), 0.0, -math.cos(pitch)])
    right = np.cross(down, forward)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, down, forward])
    pose[:3, 3] = [0.0, 0.0, 1.5]
    u = (np.arange(width) + 0.5 - 80) / 80
    v = (np.arange(height) + 0.5 - 60) / 80
    rays = u[None, :, None] * right + v[:, None, None] * down + forward
    with np.errstate(divide="ignore"):
        depth = np.where(rays[..., 2] < 0, -1.5 / rays[..., 2], np.inf).astype(np.float32)
    puddles = np.array([[8.0, 0.5, 0.0, 2.0, 1.0, 0.3], [30.0, -3.0, 0.0, 4.0, 1.5, -0.2],
                        [1.0, 0.0, 0.0, 3.0, 2.0, 0.0],  # under the camera, reaching ahead
                        [-10.0, 0.0, 0.0, 3.0, 1.0, 0.0],  # behind it
                        [6.0, 9.0, 0.0, 2.0, 1.0, 1.0]])  # at the image's edge
    phases = wx.puddle_outline_phases(len(puddles))
    windowed = wx.puddle_coverage(K, pose, depth, puddles, 1.0, phases)
    monkeypatch.setattr(wx, "_ground_window", lambda *args: (0, height, 0, width))
    whole = wx.puddle_coverage(K, pose, depth, puddles, 1.0, phases)
    assert whole.any() and np.array_equal(windowed, whole)


def test_outline_phases_are_fixed_per_index_and_differ_between_puddles():
    phases = wx.puddle_outline_phases(4)
    assert phases.shape == (4, len(wx.PUDDLE_OUTLINE))
    assert np.array_equal(phases, wx.puddle_outline_phases(4))
    assert np.array_equal(phases[:2], wx.puddle_outline_phases(2))  # index i: the same shape
    assert len({tuple(row) for row in np.round(phases, 6)}) == 4
    assert (phases >= 0).all() and (phases < 2 * math.pi).all()


def test_a_rendered_street_lays_its_puddles_where_the_road_shows_and_is_deterministic():
    """Seed 6's street at 160x120: the same state renders the same bytes twice; the wet render
    differs from a puddle-free one exactly where the coverage is above 0, and never on an actor
    or on the sky."""
    from rainbench.gl import mujoco
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import build_scene
    from rainbench.gen.render import FrameRenderer, camera_pose

    setup = build_scene(GenerateConfig(seed=6, sky="clear", frames=2, width=160, height=120,
                                       layout="street", time_of_day="day"))
    data = mujoco.MjData(setup.model)
    mujoco.mj_forward(setup.model, data)
    wet = wx.weather_at("clear", 50.0)
    with FrameRenderer(setup.model, 160, 120, setup.geom_instance,
                       base_weather=setup.base_weather) as renderer:
        renderer.update(data)
        ids, _, depth = renderer.render_instances_depth()
        first = renderer.render_weather(data, wet, depth)
        assert np.array_equal(first, renderer.render_weather(data, wet, depth))
        rig = renderer._rig
        coverage = wx.puddle_coverage(renderer.K, camera_pose(setup.model, data, "ego"), depth,
                                      rig.puddles, rig.puddle_scale, rig.puddle_phases)
        rig.puddles, rig.puddle_phases = rig.puddles[:0], rig.puddle_phases[:0]
        dry_puddles = renderer.render_weather(data, wet, depth)
    changed = np.abs(first.astype(int) - dry_puddles).max(axis=-1) > 0
    assert (coverage > 0).sum() > 500
    assert not changed[coverage == 0].any()
    assert changed[coverage == 1].mean() > 0.9  # water differs from the wet film it covers
    assert not (coverage[ids >= 0] > 0).any() and not (coverage[np.isinf(depth)] > 0).any()


def test_puddle_water_mixes_the_mirror_at_water_fresnel_in_linear_light():
    """Standing water shows water's Fresnel reflectance F of the mirror plus (1 - F) of the road
    seen through it (0.8 of its display value), added in linear light: F = 0 is the dimmed road,
    F = 1 the mirror, F = 0.25 of a white mirror over black 255 x 0.25^(1/2.2); the weight the
    renderer uses is F itself (0.35 at 80 degrees, 0.58 at 85), not more."""
    surface = np.full((1, 3, 3), 100, np.uint8)
    mirror = np.full((1, 3, 3), 255.0, np.float32)
    fresnel = np.array([0.0, 1.0, 0.25], np.float32).reshape(1, 3, 1)
    water = wx.puddle_water(surface, mirror, fresnel)
    assert water.dtype == np.float32 and water.shape == (1, 3, 3)
    assert water[0, 0] == pytest.approx([80.0] * 3, rel=1e-5)
    assert water[0, 1] == pytest.approx([255.0] * 3, rel=1e-5)
    black = wx.puddle_water(np.zeros((1, 1, 3), np.uint8), mirror[:, :1], fresnel[:, 2:])
    assert black[0, 0] == pytest.approx([255.0 * 0.25 ** (1 / 2.2)] * 3, rel=1e-5)
    # a boosted lamp's mirror (above 255) stays above 255 until the renderer clips it
    assert wx.puddle_water(surface[:, :1], mirror[:, :1] * 8, fresnel[:, 1:2])[0, 0, 0] > 255
    # the renderer's weight: road_mirror_weight with PUDDLE_MIRROR_REFLECTANCE is F(theta)
    K = np.array([[100.0, 0, 100.5], [0, 100.0, 100.5], [0, 0, 1]])  # pixel 100's centre on axis
    down = math.radians(5.0)  # looking 5 degrees down: the central ray meets the road at 85
    right, below = [1.0, 0, 0], [0, -math.sin(down), -math.cos(down)]
    forward = [0, math.cos(down), -math.sin(down)]
    rotation = np.array([right, below, forward]).T  # columns: the camera's axes in the world
    weight = wx.road_mirror_weight(K, rotation, 200, 200, wx.PUDDLE_MIRROR_REFLECTANCE)
    assert weight[100, 100] == pytest.approx(
        float(wx.water_fresnel(math.cos(math.radians(85.0)))), rel=1e-3)
    assert weight[100, 100] == pytest.approx(0.58, abs=0.01)
