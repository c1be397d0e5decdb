"""Clouds in the sky: the skybox's texel directions, the scene's cloud field, cover and shade."""

import cv2
from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np
import pytest

from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene
from rainbench.gen.render import FrameRenderer
from rainbench.gen.weather import (CLOUD_EDGE_TEXELS, cloud_field_ranks, skybox_cloud_ranks,
                                   skybox_directions, skybox_edge_ranks)
from rainbench.mjcf import layout as L
from rainbench.mjcf import textures
from rainbench.mjcf.layout import ScenarioConfig
from rainbench.mjcf.scene import CLOUD_TEXTURE, build_spec, geom_instance_table
from rainbench.rain import weather as wx


@pytest.fixture
def street():
    """The street by day at 96x96 (any scene with the skybox would do); a test may change it."""
    return build_scene(GenerateConfig(seed=0, frames=1, width=96, height=96, layout="street",
                                      time_of_day="day"))


def _look(model, data, camera_id, yaw_deg, pitch_deg):
    """Turn ``camera_id`` to look at (yaw, pitch) in the world; returns its world rotation."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    world = np.column_stack([right, np.cross(right, forward), -forward])
    body = data.xmat[model.cam_bodyid[camera_id]].reshape(3, 3)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, (body.T @ world).ravel())
    model.cam_quat[camera_id] = quat
    mujoco.mj_forward(model, data)
    return world


def test_skybox_texels_face_the_directions_a_render_shows(street):
    """Texels coded with their own direction (rgb = (d + 1) / 2) render, in any view, as the
    direction of the pixel's ray: the layout of skybox_directions is MuJoCo's."""
    model = street.model
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    sky = model.texture("sky")
    size = int(model.tex_width[sky.id])
    directions = skybox_directions(size)
    assert directions.shape == (6 * size * size, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0)
    start = int(model.tex_adr[sky.id])
    model.tex_data[start:start + directions.size] = np.rint(
        (directions + 1.0) / 2.0 * 255.0).astype(np.uint8).ravel()
    model.vis.map.fogstart, model.vis.map.fogend, model.vis.map.haze = 1e6, 1e7, 0.0
    option = mujoco.MjvOption()
    option.geomgroup[:] = 0  # the sky alone
    camera = model.camera("ego").id
    side = 96
    focal = side / 2 / np.tan(np.radians(model.cam_fovy[camera] / 2))
    u, v = np.meshgrid(np.arange(side) + 0.5 - side / 2, np.arange(side) + 0.5 - side / 2)
    errors = []
    with mujoco.Renderer(model, side, side) as renderer:
        for yaw, pitch in [(0, 0), (90, 10), (180, 35), (270, 60), (33, 85), (120, -40)]:
            world = _look(model, data, camera, yaw, pitch)
            renderer.update_scene(data, camera=camera, scene_option=option)
            coded = renderer.render().astype(np.float64) / 255.0 * 2.0 - 1.0
            coded /= np.linalg.norm(coded, axis=-1, keepdims=True)
            ray = np.stack([u / focal, -v / focal, -np.ones_like(u)], axis=-1) @ world.T
            ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
            errors.append(np.degrees(np.arccos(np.clip((coded * ray).sum(-1), -1.0, 1.0))))
    errors = np.stack(errors)
    assert errors.mean() < 0.5 and errors.max() < 2.0  # texels are 0.7 degrees wide


def test_cloud_field_is_seeded_tileable_and_read_as_uniform_ranks():
    field = textures.clouds(np.random.default_rng(3))
    assert field.shape == (256, 256, 3) and field.dtype == np.uint8
    np.testing.assert_array_equal(field, textures.clouds(np.random.default_rng(3)))
    assert not np.array_equal(field, textures.clouds(np.random.default_rng(4)))
    grey = field[:, :, 0].astype(np.float64)
    # tileable: the step across the tile's edge is like any step inside it
    inside = np.abs(np.diff(grey, axis=1)).mean()
    assert np.abs(grey[:, 0] - grey[:, -1]).mean() < 1.5 * inside
    assert np.abs(grey[0] - grey[-1]).mean() < 1.5 * inside
    # fractal, not white: neighbours are alike, far texels are not
    assert inside < 0.25 * np.abs(grey - np.roll(grey, 128, axis=1)).mean()
    ranks = cloud_field_ranks(field[:, :, 0])
    assert ranks.shape == (256, 256) and ranks.min() > 0.0 and ranks.max() < 1.0
    # uniform: every rank once
    np.testing.assert_allclose(np.sort(ranks, axis=None), (np.arange(256 * 256) + 0.5) / 256 ** 2)
    # in the field's order where it is smooth, smoother than the field from cell to cell
    raw = np.argsort(np.argsort(grey, axis=None, kind="stable")).reshape(grey.shape) / grey.size
    assert np.corrcoef(raw.ravel(), ranks.ravel())[0, 1] > 0.95
    step = np.abs(np.diff(ranks, axis=1)).mean()
    assert step < 0.6 * np.abs(np.diff(raw, axis=1)).mean()
    with pytest.raises(ValueError, match=r"cloud field: expected \(H, W\) levels, got shape \(4,\)"):
        cloud_field_ranks(np.zeros(4))


def test_cloud_edges_are_never_sharper_than_the_sky_texels_draw(street):
    """Where the layer's ranks step fast between texels (far away, at a slant), the edge widens
    so that no neighbouring texels jump from gap to cloud: the texture's bilinear filter then
    draws ramps, not the blocky squares of the field's cells (seen in light rain)."""
    size = 128
    directions = skybox_directions(size)
    ranks = skybox_cloud_ranks(street.model, directions)
    edges = skybox_edge_ranks(ranks)
    assert edges.shape == ranks.shape and edges.min() == pytest.approx(wx.CLOUD_EDGE_RANKS)
    assert edges.max() > 2 * wx.CLOUD_EDGE_RANKS  # some texels do step fast
    high = directions[:, 2] > wx.CLOUD_FADE_SIN_ELEVATION  # above the haze's fade
    for cover in (0.3, 0.5, 0.8):
        widened, _ = wx.cloud_cover_and_shade(cover, ranks, directions[:, 2], edges)
        fixed, _ = wx.cloud_cover_and_shade(cover, ranks, directions[:, 2])
        steps = []
        for share in (widened, fixed):
            grid = share.reshape(6, size, size)
            mask = high.reshape(6, size, size)
            step = np.maximum(np.abs(np.diff(grid, axis=1))[mask[:, 1:] & mask[:, :-1]].max(),
                              np.abs(np.diff(grid, axis=2))[mask[:, :, 1:] & mask[:, :, :-1]].max())
            steps.append(step)
        # a ramp over two texels or more (a step of 1/2; a little over where the widths differ)
        assert steps[0] < 0.8
        assert steps[1] >= 0.99  # a fixed edge jumps from gap to cloud in one texel
        # the widening keeps the cover
        assert abs(widened[high].mean() - fixed[high].mean()) < 0.03
    # the widths follow the texels' steps: a ramp of 0.1 a texel along the rows...
    ramp = np.tile(np.arange(8.0) * 0.1, (6, 8, 1)).reshape(-1)
    np.testing.assert_allclose(skybox_edge_ranks(ramp), CLOUD_EDGE_TEXELS * 0.1)
    # ... and a ridge one texel wide, whose own centred difference is 0: its larger step counts
    ridge = np.zeros((6, 8, 8))
    ridge[:, :, 3] = 0.1
    widths = skybox_edge_ranks(ridge.reshape(-1)).reshape(6, 8, 8)
    np.testing.assert_allclose(widths[:, :, 2:5], CLOUD_EDGE_TEXELS * 0.1)
    np.testing.assert_allclose(widths[:, :, [0, 1, 5, 6, 7]], wx.CLOUD_EDGE_RANKS)
    np.testing.assert_allclose(skybox_edge_ranks(np.full(6 * 16, 0.3)), wx.CLOUD_EDGE_RANKS)
    with pytest.raises(ValueError, match=r"skybox ranks: expected \(6 \* S \* S,\) with S >= 2, "
                                         r"got \(7,\)"):
        skybox_edge_ranks(np.zeros(7))


def test_cover_is_the_share_of_the_sky_under_cloud():
    ranks = (np.arange(10_000) + 0.5) / 10_000
    high = np.full(ranks.shape, 0.8)  # well above the haze
    for cover in (0.0, 0.2, 0.5, 0.8, 1.0):
        share, shade = wx.cloud_cover_and_shade(cover, ranks, high)
        assert share.shape == (ranks.size, 1)
        assert abs(share.mean() - cover) < 0.03
        under = share[:, 0] == 1.0
        if 0 < cover < 1:  # clouds where the field is highest, gaps where it is lowest
            assert ranks[under].min() > ranks[share[:, 0] == 0.0].max()
    share, shade = wx.cloud_cover_and_shade(0.0, ranks, high)
    assert (share == 0).all()
    share, shade = wx.cloud_cover_and_shade(1.0, ranks, high)
    assert (share == 1).all()
    # wider edges: softer, but cover 0 and 1 still leave no cloud and no gap
    wide = np.full(ranks.shape, 0.3)
    soft, _ = wx.cloud_cover_and_shade(0.5, ranks, high, wide)
    sharp, _ = wx.cloud_cover_and_shade(0.5, ranks, high)
    assert ((soft > 0) & (soft < 1)).mean() > 2 * ((sharp > 0) & (sharp < 1)).mean()
    assert abs(soft.mean() - 0.5) < 1e-3
    assert (wx.cloud_cover_and_shade(0.0, ranks, high, wide)[0] == 0).all()
    assert (wx.cloud_cover_and_shade(1.0, ranks, high, wide)[0] == 1).all()
    with pytest.raises(ValueError, match=r"edge_ranks: expected shape \(10000,\) of positive "
                                         r"widths, got \(10000,\), least 0"):
        wx.cloud_cover_and_shade(0.5, ranks, high, np.zeros(ranks.shape))
    assert abs(shade.mean() - 1.0) < 1e-9 and shade.max() - shade.min() > 0.2
    # at the horizon the structure has faded into the mean
    share, shade = wx.cloud_cover_and_shade(0.8, ranks, np.zeros(ranks.shape))
    np.testing.assert_allclose(share, 0.8)
    np.testing.assert_allclose(shade, 1.0)
    # no field: the mean sky, the blend by cover
    share, shade = wx.cloud_cover_and_shade(0.8, None, high)
    np.testing.assert_allclose(share, 0.8)
    np.testing.assert_allclose(shade, 1.0)
    with pytest.raises(ValueError, match=r"cloud_ranks: expected shape \(3,\), got \(2,\)"):
        wx.cloud_cover_and_shade(0.8, np.zeros(2), np.zeros(3))


@pytest.mark.parametrize("sky", ["cloudy", "overcast"])
def test_textured_sky_keeps_the_mean_sky(sky):
    """Over a uniform field high up, the clouded sky averages to the mean sky that the airlight
    and the statistics use (exactly under a closed deck; within the shading's tilt otherwise)."""
    weather = wx.weather_at(sky, 0.0)
    ranks = (np.arange(4000) + 0.5) / 4000
    sin_elevation = np.full(ranks.shape, 0.5)
    mean = wx.sky_colours(weather, sin_elevation[:1])[0]
    textured = wx.sky_colours(weather, sin_elevation, ranks).mean(axis=0)
    np.testing.assert_allclose(textured, mean, atol=0.03 if sky == "cloudy" else 1e-6)


def test_skybox_cloud_ranks_follow_the_layer_and_need_the_field(street):
    model = street.model
    directions = skybox_directions(32)
    ranks = skybox_cloud_ranks(model, directions)
    assert ranks.shape == (directions.shape[0],) and 0.0 <= ranks.min() and ranks.max() <= 1.0
    # straight up reads the field under the camera: the texel at the tile's origin
    index = model.texture(CLOUD_TEXTURE).id
    field = model.tex_data[int(model.tex_adr[index]):int(model.tex_adr[index]) + 256 * 256 * 3]
    origin_rank = cloud_field_ranks(field.reshape(256, 256, 3)[:, :, 0])[0, 0]
    zenith = skybox_cloud_ranks(model, np.array([[0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(zenith, [origin_rank])
    # a scene without the texture has no clouds
    spec = mujoco.MjSpec()
    spec.worldbody.add_geom(size=[1, 1, 1])
    assert skybox_cloud_ranks(spec.compile(), directions) is None


def _sky_renders(sky, rate_mm_h, without_field=False):
    """RGB (240, 320, 3) of the curved road of seed 7 under ``sky`` at ``rate_mm_h`` (0: the base
    render), and its depth; ``without_field``: the same scene without its cloud field."""
    layout = L.sample_layout(7, ScenarioConfig(sky=sky, layout="curved", time_of_day="day"),
                             np.random.default_rng(7))
    spec = build_spec(layout, 320, 240)
    if without_field:
        spec.delete(spec.texture(CLOUD_TEXTURE))
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    base = wx.weather_at(sky, 0.0)
    with FrameRenderer(model, 320, 240, geom_instance_table(model),
                       base_weather=base) as renderer:
        renderer.update(data)
        rgb = renderer.render_rgb()
        _, _, depth = renderer.render_instances_depth()
        if rate_mm_h:
            rgb = renderer.render_weather(data, wx.weather_at(sky, rate_mm_h), depth)
    return rgb, depth


def test_clouds_cover_a_cloudy_sky_stay_under_rain_and_leave_a_clear_sky_alone():
    """Against the same scene without its cloud field (the mean sky): a cloudy sky shows clouds
    and gaps; in light rain the camera still sees the skybox's closed, mottled deck (not the
    mirror's uniform one); a clear sky is untouched, byte for byte."""
    clear, _ = _sky_renders("clear", 0.0)
    np.testing.assert_array_equal(clear, _sky_renders("clear", 0.0, without_field=True)[0])
    for rate, least in ((0.0, 6.0), (5.0, 2.0)):
        clouded, depth = _sky_renders("cloudy", rate)
        mean_sky, _ = _sky_renders("cloudy", rate, without_field=True)
        sky = ~np.isfinite(depth)
        assert sky.sum() > 5000
        difference = clouded.astype(np.float64) - mean_sky
        luma = difference.mean(axis=-1)[sky]
        assert np.abs(luma).mean() > least
        assert (luma > least).mean() > 0.05 and (luma < -least).mean() > 0.05  # both ways
        # the clouds are in the sky only (its anti-aliased edges aside; a stray pixel of sky
        # between two geoms may change by a level)
        near_sky = cv2.dilate(sky.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        changed = np.abs(difference[~near_sky]).max(axis=-1)
        assert changed.max() <= 1 and (changed > 0).sum() <= 5
