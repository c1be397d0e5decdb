"""Time of day: the laws of dusk and night, the lights after dark, and what they do to a frame."""

import dataclasses
import math

import cv2
import h5py
from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np
import pytest

from rainbench.gen import sim
from rainbench.gen.render import FrameRenderer, camera_pose
from rainbench.mjcf import layout as L
from rainbench.mjcf import lights as tod
from rainbench.mjcf.scene import build_spec, geom_instance_table
from rainbench.mjcf.weather import scene_lighting
from rainbench.rain import weather as wx

SEED, SKY = 0, "cloudy"


def _luma(rgb):
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float64)


def _layout(time_of_day="day"):
    config = L.ScenarioConfig(sky=SKY, layout="street", time_of_day=time_of_day)
    return L.sample_layout(SEED, config, np.random.default_rng(SEED))


def _vehicles(layout):
    return [unit.name for unit in layout.units if unit.kind in ("car", "motorcycle")]


def _scene(time_of_day, width, height):
    """(layout, spec, model) of the seed's street at ``time_of_day`` (build_spec adds the
    time of day's lights)."""
    layout = _layout(time_of_day)
    spec = build_spec(layout, width, height)
    return layout, spec, spec.compile()


def _posed(model, layout, t):
    data = mujoco.MjData(model)
    sim.ActorDriver(model, layout).apply(data, t)
    mujoco.mj_forward(model, data)
    return data


def _render(model, data, time_of_day, width, height):
    base = wx.weather_at(SKY, 0.0, time_of_day=time_of_day)
    with FrameRenderer(model, width, height, geom_instance_table(model),
                       base_weather=base) as renderer:
        renderer.update(data)
        return renderer.render_rgb()


def _project(renderer, data, points):
    """(N, 2) int pixel (u, v) and (N,) camera depth of world ``points`` (N, 3)."""
    pose = camera_pose(renderer.model, data, "ego")
    cam = (np.asarray(points, dtype=np.float64) - pose[:3, 3]) @ pose[:3, :3]
    uv = (renderer.K @ cam.T).T
    return np.floor(uv[:, :2] / uv[:, 2:]).astype(int), cam[:, 2]


# -- laws -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("sky", wx.SKIES)
def test_dusk_and_night_are_darker_noisier_and_day_is_unchanged(sky):
    day, dusk, night = (wx.weather_at(sky, 0.0, time_of_day=t) for t in wx.TIMES_OF_DAY)
    assert day.illuminance_lux > dusk.illuminance_lux > night.illuminance_lux
    assert 1e2 <= dusk.illuminance_lux <= 1e3 and night.illuminance_lux < 20
    assert night.daylight_lux < 1 and night.street_light_lux == wx.STREET_LIGHT_LUX
    assert day.light_level == 1.0 > dusk.light_level > night.light_level > 0.2
    assert night.gain > dusk.gain > day.gain == 1.0
    assert night.noise_dn > dusk.noise_dn > day.noise_dn == 0.0
    assert night.exposure_s == pytest.approx(wx.LOW_LIGHT_MAX_EXPOSURE_S)
    # the night's gain is at the camera's limit (relative to the day base's own gain)
    assert night.gain * wx._exposure(wx.BASE_ILLUMINANCE_LUX[sky])[1] == pytest.approx(wx.MAX_GAIN)
    assert night.sun == 0.0 and night.image_level == 1.0
    # by day every value is the daytime law's, whatever the default
    for rate in (0.0, 5.0, 50.0):
        assert wx.weather_at(sky, rate) == wx.weather_at(sky, rate, time_of_day="day")
    assert wx.weather_at(sky, 50.0).image_level == (200.0 / wx.BASE_ILLUMINANCE_LUX[sky]) ** 0.1
    record = night.as_record()
    assert "time_of_day" not in record and "sky" not in record
    assert set(record) == set(wx.RECORD_FIELDS)
    assert all(isinstance(value, float) for value in record.values())


@pytest.mark.parametrize("time_of_day", ["dusk", "night"])
def test_weather_after_dark_is_monotonic_in_the_rate(time_of_day):
    rates = [0, 0.5, 2, 5, 10, 25, 50, 75, 100]
    for sky in wx.SKIES:
        series = [wx.weather_at(sky, rate, time_of_day=time_of_day) for rate in rates]
        for name in ("cloud_cover", "wetness", "road_reflectance", "gain", "exposure_s",
                     "noise_dn"):
            values = [getattr(w, name) for w in series]
            assert values == sorted(values), name
        for name in ("sun", "illuminance_lux", "daylight_lux", "image_level"):
            values = [getattr(w, name) for w in series]
            assert values == sorted(values, reverse=True), name
        assert {w.light_level for w in series} == {series[0].light_level}  # the base's


@pytest.mark.parametrize("sky", wx.SKIES)
def test_at_dusk_under_rain_the_lamps_gain_on_the_fading_daylight(sky):
    """The camera exposes for the light it meters: at dusk rain takes daylight away, so the lamps'
    level rises against the daylight's (a rainy dusk is lit by its street lights); by day and at
    night every level is the base weather's at any rate."""
    rates = [0.0, 5.0, 10.0, 25.0, 50.0, 100.0]
    dusk = [wx.weather_at(sky, rate, time_of_day="dusk") for rate in rates]
    base = dusk[0]
    base_lux = base.illuminance_lux
    # rate 0: the base weather's law, light_level x (lux / E0)^(1 / 2.2); daylight at its level
    assert wx.display_light(base, 30.0) == pytest.approx(
        base.light_level * (30.0 / base_lux) ** (1 / 2.2))
    assert wx.daylight_level(base) == base.light_level and wx.sky_key(base)[-1] == 1.0
    daylight = [wx.daylight_level(w) for w in dusk]
    lamps = [scene_lighting(w).lamp_diffuse[0] for w in dusk]
    assert daylight == sorted(daylight, reverse=True) and daylight[-1] < 0.7 * daylight[0]
    assert lamps == sorted(lamps) and lamps[-1] > 2 * lamps[0]
    # what the image shows (after the camera's image_level): the lamps brighter, the day dimmer
    assert lamps[-1] * dusk[-1].image_level > 1.5 * lamps[0]
    assert daylight[-1] * dusk[-1].image_level < 0.6 * daylight[0]
    # the dusk sky dims with the daylight: darker at 100 mm/h than the base's rain-free deck
    up = np.array([0.25])
    assert (wx.sky_colours(dusk[-1], up) < wx.sky_colours(
        dataclasses.replace(dusk[-1], daylight_lux=base.daylight_lux,
                            illuminance_lux=base_lux), up)).all()
    for time_of_day in ("day", "night"):
        series = [wx.weather_at(sky, rate, time_of_day=time_of_day) for rate in rates]
        assert {wx.daylight_level(w) for w in series} == {series[0].light_level}
        assert {wx.sky_key(w)[-1] for w in series} == {1.0}
    night = [wx.weather_at(sky, rate, time_of_day="night") for rate in rates]  # lamps as at rate 0
    assert {wx.display_light(w, 30.0) for w in night} == {wx.display_light(night[0], 30.0)}


def test_a_rainy_dusk_is_as_light_under_every_base_sky():
    """Under rain the deck is closed whatever the base sky: the dusk daylight is the overcast
    dusk's share (150 / 2 000) of the rainy day's light, capped by the base sky's own dusk light,
    so from 5 mm/h every base sky has the same dusk daylight (30 lux at 25 mm/h)."""
    share = wx.DUSK_DAYLIGHT_LUX["overcast"] / wx.BASE_ILLUMINANCE_LUX["overcast"]
    for rate in (5.0, 10.0, 25.0, 50.0, 100.0):
        lux = {sky: wx.weather_at(sky, rate, time_of_day="dusk").daylight_lux for sky in wx.SKIES}
        day = wx.weather_at("overcast", rate).illuminance_lux
        assert lux == pytest.approx({sky: min(wx.DUSK_DAYLIGHT_LUX[sky], day * share)
                                     for sky in wx.SKIES})
        assert len(set(lux.values())) == 1, rate
    assert wx.weather_at("clear", 25.0, time_of_day="dusk").daylight_lux == pytest.approx(30.0)
    for sky in wx.SKIES:  # rate 0 keeps the base sky's own dusk light
        assert wx.weather_at(sky, 0.0, time_of_day="dusk").daylight_lux == wx.DUSK_DAYLIGHT_LUX[sky]


def test_rain_at_night_keeps_the_street_lights_and_rain_at_dusk_darkens():
    night = [wx.weather_at("cloudy", rate, time_of_day="night") for rate in (0.0, 10.0, 100.0)]
    assert [w.illuminance_lux for w in night] == [night[0].illuminance_lux] * 3
    assert night[2].wetness > night[1].wetness > 0 and night[2].road_reflectance > 0
    dusk = [wx.weather_at("cloudy", rate, time_of_day="dusk") for rate in (0.0, 10.0, 100.0)]
    levels = [w.image_level for w in dusk]
    assert levels == sorted(levels, reverse=True) and levels[0] == 1.0 > levels[2]


def test_night_camera_adds_sensor_noise_to_the_base_image():
    rng = np.random.default_rng(0)
    image = np.full((60, 80, 3), 118, np.uint8)
    noise = wx.noise_field(rng, 60, 80)
    day, night = wx.weather_at("clear", 0.0), wx.weather_at("clear", 0.0, time_of_day="night")
    assert np.array_equal(wx.camera_response(image, day, noise), image)
    residual = wx.camera_response(image, night, noise).astype(np.float64) - image
    assert abs(residual.mean()) < 1.0
    assert residual.std() == pytest.approx(night.noise_dn, rel=0.1)


def test_night_sky_is_dark_with_a_warm_glow_at_the_horizon():
    s = np.array([0.0, 1.0])  # horizon, zenith
    means = {}
    for time_of_day in wx.TIMES_OF_DAY:
        for sky in ("clear", "overcast"):
            colours = wx.sky_colours(wx.weather_at(sky, 0.0, time_of_day=time_of_day), s)
            means[time_of_day, sky] = colours.mean()
            if time_of_day == "night":
                horizon, zenith = colours
                assert horizon.sum() > zenith.sum() and horizon[0] > horizon[2]  # brown-grey
                assert colours.max() < 0.2
            if time_of_day == "dusk" and sky == "clear":
                horizon, zenith = colours
                assert horizon[0] > horizon[2] + 0.3 and zenith[2] > zenith[0]  # warm band, blue
    for sky in ("clear", "overcast"):
        assert means["day", sky] > means["dusk", sky] > means["night", sky]


def test_night_lighting_has_no_sun_and_lit_lamps():
    day = scene_lighting(wx.weather_at("clear", 0.0))
    night = scene_lighting(wx.weather_at("clear", 0.0, time_of_day="night"))
    dusk = scene_lighting(wx.weather_at("clear", 0.0, time_of_day="dusk"))
    assert day.lamp_diffuse == day.beam_diffuse == (0.0, 0.0, 0.0) and day.sun_active
    assert not night.sun_active and not night.skylight_active and max(night.sun_diffuse) == 0.0
    assert min(night.lamp_diffuse) > 0 and min(night.beam_diffuse) > 0
    assert max(night.headlight_ambient) < 0.3 * min(day.headlight_ambient)
    assert dusk.sun_active and dusk.sun_diffuse[0] > 2 * dusk.sun_diffuse[2]  # orange low sun


def test_bad_time_of_day_is_a_one_line_error():
    message = r"time_of_day: expected one of day, dusk, night, got 'noon'"
    with pytest.raises(ValueError, match=message):
        wx.weather_at("clear", 0.0, time_of_day="noon")
    with pytest.raises(ValueError, match=message):
        tod.add_time_of_day_lights(mujoco.MjSpec(), "noon")


# -- scenes --------------------------------------------------------------------------------------
def test_day_adds_nothing_and_renders_byte_identical():
    width, height = 160, 120
    layout, plain_spec, plain = _scene("day", width, height)
    assert not [plain.light(i).name for i in range(plain.nlight)
                if plain.light(i).name.startswith("tod/")]
    lit_spec = build_spec(layout, width, height)
    tod.add_time_of_day_lights(lit_spec, "day", vehicle_bodies=_vehicles(layout),
                               street_lamps=tod.lamp_heads(lit_spec), sky=SKY)
    assert lit_spec.to_xml() == plain_spec.to_xml()
    lit = lit_spec.compile()
    images = []
    for model in (plain, lit):
        data = _posed(model, layout, 8.0)
        with FrameRenderer(model, width, height, geom_instance_table(model),
                           base_weather=wx.weather_at(SKY, 0.0)) as renderer:
            renderer.update(data)
            rgb = renderer.render_rgb()
            _, _, depth = renderer.render_instances_depth()
            images.append((rgb, renderer.render_weather(data, wx.weather_at(SKY, 50.0), depth)))
    assert np.array_equal(images[0][0], images[1][0])
    assert np.array_equal(images[0][1], images[1][1])


def test_night_is_dark_dusk_between_and_the_scene_rejects_a_daytime_weather():
    width, height = 160, 120
    luma = {}
    for time_of_day in wx.TIMES_OF_DAY:  # mean over three frames of the clip
        layout, _, model = _scene(time_of_day, width, height)
        data = mujoco.MjData(model)
        driver = sim.ActorDriver(model, layout)
        base = wx.weather_at(SKY, 0.0, time_of_day=time_of_day)
        with FrameRenderer(model, width, height, geom_instance_table(model),
                           base_weather=base) as renderer:
            frames = []
            for t in (4.0, 8.0, 12.0):
                driver.apply(data, t)
                mujoco.mj_forward(model, data)
                renderer.update(data)
                frames.append(_luma(renderer.render_rgb()).mean())
        luma[time_of_day] = float(np.mean(frames))
    assert luma["night"] < 0.35 * luma["day"]
    assert luma["night"] < luma["dusk"] < luma["day"]
    with pytest.raises(ValueError, match="weather: expected time_of_day 'night' \\(the scene's "
                                         "lights\\), got 'day'"):
        FrameRenderer(model, width, height, geom_instance_table(model),
                      base_weather=wx.weather_at(SKY, 0.0))


@pytest.fixture(scope="module")
def night_scene():
    layout, _, model = _scene("night", 320, 240)
    return layout, model


def test_lights_after_dark_fit_the_renderer_and_the_road_is_a_grid(night_scene):
    layout, model = night_scene
    names = [model.light(i).name for i in range(model.nlight)]
    assert set(tod.EGO_BEAM_NAMES) <= set(names)
    assert sum(n.startswith("tod/lamp") for n in names) == len(
        [g for g in range(model.ngeom) if tod.STREET_LAMP_NAME.match(model.geom(g).name)]) > 4
    road = [g for g in range(model.ngeom) if model.geom(g).name.startswith("scenery/")
            and model.geom_matid[g] == model.material("asphalt").id]
    assert road and all(model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE for g in road)
    data = _posed(model, layout, 8.0)
    with FrameRenderer(model, 320, 240, geom_instance_table(model),
                       base_weather=wx.weather_at(SKY, 0.0, time_of_day="night")) as renderer:
        renderer.update(data)
        active = [names[i] for i in np.flatnonzero(model.light_active)]
        assert set(tod.EGO_BEAM_NAMES) <= set(active) and "sun" not in active
        assert len(active) + 1 == tod.GL_MAX_LIGHTS  # with the headlight: every OpenGL light
        assert sum(n.startswith("tod/lamp") for n in active) >= 2


def test_ego_low_beams_light_the_road_ahead(night_scene):
    layout, model = night_scene
    data = _posed(model, layout, 8.0)
    beams = [model.light(name).id for name in tod.EGO_BEAM_NAMES]
    with FrameRenderer(model, 320, 240, geom_instance_table(model),
                       base_weather=wx.weather_at(SKY, 0.0, time_of_day="night")) as renderer:
        renderer.update(data)
        lit = _luma(renderer.render_rgb())
        ids, geometry = renderer.render_instances()
        pose = camera_pose(model, data, "ego")
        forward = pose[:3, 2] * [1.0, 1.0, 0.0]
        forward /= np.linalg.norm(forward)
        points = [pose[:3, 3] * [1, 1, 0] + d * forward for d in np.arange(8.0, 26.0, 1.0)]
        uv, _ = _project(renderer, data, points)
        saved = model.light_diffuse[beams].copy()
        model.light_diffuse[beams] = 0.0  # the same frame without the ego's beams
        renderer.update(data)
        dark = _luma(renderer.render_rgb())
        model.light_diffuse[beams] = saved
    road = [(x, y) for x, y in uv if 0 <= x < 320 and 0 <= y < 240 and ids[y, x] < 0
            and geometry[y, x]]
    assert len(road) >= 8
    on = np.mean([lit[y, x] for x, y in road])
    off = np.mean([dark[y, x] for x, y in road])
    assert on > 1.4 * off and on > off + 10


def test_vehicle_headlights_glow_brighter_than_the_vehicle(night_scene):
    layout, model = night_scene
    material = model.material("tod_headlamp").id
    heads = np.flatnonzero(model.geom_matid == material)
    assert heads.size >= 2
    table = geom_instance_table(model)
    with FrameRenderer(model, 320, 240, table,
                       base_weather=wx.weather_at(SKY, 0.0, time_of_day="night")) as renderer:
        best = None  # the frame whose nearest headlight facing the camera is nearest
        for t in np.arange(1.0, 20.0, 1.0):
            data = _posed(model, layout, t)
            uv, depth = _project(renderer, data, data.geom_xpos[heads])
            facing = data.geom_xmat[heads].reshape(-1, 3, 3)[:, :, 0] @ camera_pose(
                model, data, "ego")[:3, 2] < -0.5
            inside = ((uv[:, 0] >= 0) & (uv[:, 0] < 320) & (uv[:, 1] >= 0) & (uv[:, 1] < 240)
                      & (depth > 2.0) & facing)
            if inside.any() and (best is None or depth[inside].min() < best[0]):
                best = (depth[inside].min(), t)
        assert best is not None
        data = _posed(model, layout, best[1])
        renderer.update(data)
        glowing = _luma(renderer.render_rgb())
        ids, _ = renderer.render_instances()
        model.mat_emission[material] = 0.0
        renderer.update(data)
        plain = _luma(renderer.render_rgb())
        model.mat_emission[material] = tod.HEADLAMP_EMISSION
    lamp = (glowing - plain) > 30  # the headlight geoms' pixels
    assert lamp.sum() >= 4
    owners = np.unique(ids[lamp])
    owners = owners[owners >= 0]
    body = np.isin(ids, owners) & ~lamp
    assert glowing[lamp].max() >= 230 and glowing[lamp].mean() > glowing[body].mean() + 80


def test_road_under_a_street_light_is_brighter_than_between_two(night_scene):
    layout, model = night_scene
    names = [model.light(i).name for i in range(model.nlight)]
    lamps = [i for i, n in enumerate(names) if n.startswith("tod/lamp")]
    beams = [i for i, n in enumerate(names) if n.endswith("_beam")]
    with FrameRenderer(model, 320, 240, geom_instance_table(model),
                       base_weather=wx.weather_at(SKY, 0.0, time_of_day="night")) as renderer:
        model.light_diffuse[beams] = 0.0  # street lights alone (the weather is not re-applied)
        found = None
        for t in np.arange(2.0, 20.0, 1.0):
            data = _posed(model, layout, t)
            renderer.update(data)
            ids, geometry, depth = renderer.render_instances_depth()
            on = [i for i in lamps if model.light_active[i]]
            for a in on:
                for b in on:
                    pa, pb = data.light_xpos[a], data.light_xpos[b]
                    if not (abs(pa[1] - pb[1]) < 0.5 and 25.0 < pb[0] - pa[0] < 35.0):
                        continue  # consecutive lamps on one side of the road
                    points = [[pa[0], pa[1], 0.0], [(pa[0] + pb[0]) / 2, pa[1], 0.0]]
                    uv, z = _project(renderer, data, points)
                    ok = all(2 <= x < 318 and 2 <= y < 238 and zz > 2.0
                             and (ids[y - 2:y + 3, x - 2:x + 3] < 0).all()
                             and abs(depth[y, x] - zz) < 0.05 * zz for (x, y), zz in zip(uv, z))
                    if ok:
                        found = uv
                        break
                if found is not None:
                    break
            if found is not None:
                break
        assert found is not None, "no frame shows the road under two lit lamps"
        luma = _luma(renderer.render_rgb())
    (xa, ya), (xm, ym) = found
    under = luma[ya - 1:ya + 2, xa - 1:xa + 2].mean()
    between = luma[ym - 1:ym + 2, xm - 1:xm + 2].mean()
    assert under > 1.3 * between and under > between + 8


def test_the_weather_rig_knows_the_lamps_whose_reflections_streak(night_scene):
    """The rig's lamp geoms are exactly the head and tail lights and street lamp heads (their
    emissive materials); their spheres follow the state."""
    from rainbench.gen.weather import WeatherRig

    layout, model = night_scene
    rig = WeatherRig(model)
    names = [model.geom(int(g)).name for g in rig.lamp_geoms]
    lamps = {model.material(name).id for name in tod.LAMP_MATERIALS}
    assert set(rig.lamp_geoms) == {g for g in range(model.ngeom) if model.geom_matid[g] in lamps}
    assert any("/headlight" in n for n in names) and any("/taillight" in n for n in names)
    assert any(tod.STREET_LAMP_NAME.match(n) for n in names)
    data = _posed(model, layout, 8.0)
    spheres = rig.lamp_spheres(data)
    np.testing.assert_array_equal(spheres[:, :3], data.geom_xpos[rig.lamp_geoms])
    assert spheres.shape == (len(names), 4) and (spheres[:, 3] > 0).all()
    boxes = rig.lamp_boxes(data)  # the boxes' footprints are what streak (not their discs)
    is_box = model.geom_type[rig.lamp_geoms] == mujoco.mjtGeom.mjGEOM_BOX
    assert boxes.shape == (len(names), 15) and is_box.any()
    np.testing.assert_array_equal(boxes[is_box, :3], data.geom_xpos[rig.lamp_geoms[is_box]])
    np.testing.assert_array_equal(boxes[is_box, 3:12], data.geom_xmat[rig.lamp_geoms[is_box]])
    np.testing.assert_array_equal(boxes[is_box, 12:], model.geom_size[rig.lamp_geoms[is_box]])
    assert np.isnan(boxes[~is_box]).all()


def test_wet_night_road_mirrors_the_strip_the_camera_sees(night_scene):
    layout, model = night_scene
    data = _posed(model, layout, 8.0)
    table = geom_instance_table(model)
    with FrameRenderer(model, 320, 240, table,
                       base_weather=wx.weather_at(SKY, 0.0, time_of_day="night")) as renderer:
        renderer.update(data)
        base = renderer.render_rgb()
        _, _, depth = renderer.render_instances_depth()
        wet = renderer.render_weather(data, wx.weather_at(SKY, 50.0, time_of_day="night"), depth)
        strip = renderer._rig.mirror_geom(data, renderer.camera_id)
    pose = camera_pose(model, data, "ego")
    ahead = pose[:3, 3] + 15.0 * pose[:3, 2] * [1, 1, 0] / np.linalg.norm(pose[:3, 2][:2])
    local = model.geom_size[strip, :2] - np.abs(
        (data.geom_xmat[strip].reshape(3, 3).T @ (ahead - data.geom_xpos[strip]))[:2])
    assert model.geom_matid[strip] == model.material("asphalt").id and (local >= 0).all()
    assert _luma(wet).mean() < _luma(base).mean() and not math.isclose(
        float(np.abs(wet.astype(int) - base).mean()), 0.0)


def test_a_night_clip_stores_its_clean_image_with_the_cameras_noise(tmp_path):
    """Rate 0 of a night shard is the render through the night camera (gain ~30: noise); the
    same render by day is stored as rendered."""
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import generate_shard, render_clip

    for time_of_day in ("night", "day"):
        config = GenerateConfig(seed=SEED, frames=1, frame_offset=80, clip_frames=200, width=160,
                                height=120, rates=(0.0, 30.0), sky=SKY, layout="street",
                                time_of_day=time_of_day)
        path = generate_shard(config, tmp_path / time_of_day, threads=1)
        with h5py.File(path) as handle:
            stored = handle["rgb"][0, 0]
        rendered = next(render_clip(config))[1].rgb
        difference = np.abs(stored.astype(np.int16) - rendered).mean()
        if time_of_day == "day":
            assert difference == 0
        else:
            assert difference > 2.0, difference
            again = generate_shard(config, tmp_path / "again", threads=1)
            with h5py.File(again) as handle:
                assert np.array_equal(handle["rgb"][0, 0], stored)  # seeded: the same bytes
            # the noise is the camera's: another rain seed draws other rain over the same clean frame
            other_rain = generate_shard(dataclasses.replace(config, rain_seed=7), tmp_path / "rain7", threads=1)
            with h5py.File(other_rain) as handle:
                assert np.array_equal(handle["rgb"][0, 0], stored)
                with h5py.File(path) as first:
                    assert not np.array_equal(handle["rgb"][1, 0], first["rgb"][1, 0])


def test_lights_send_their_intensity_towards_a_viewer_as_documented():
    viewer = np.zeros(3)
    kinds = ["street", "street", "street", "head", "head", "tail", "tail"]
    lamps = np.array([[0, 0, 6.4], [6.4 * math.tan(math.radians(60)), 0, 6.4], [40, 0, 6.4],
                      [20, 0, 0.7], [20, 0, 0.7], [20, 0, 0.7], [20, 0, 0.7]], float)
    forwards = np.array([[1, 0, 0]] * 3 + [[-1, 0, 0], [1, 0, 0], [1, 0, 0], [-1, 0, 0]], float)
    candela = tod.lamp_intensity_cd(kinds, lamps, forwards, viewer)
    np.testing.assert_allclose(candela, [tod.STREET_LAMP_NADIR_CD, tod.STREET_LAMP_NADIR_CD * 0.5, 0.0,
                                         tod.HEADLAMP_ONCOMING_CD, 0.0, tod.TAILLAMP_CD, 0.0])
    assert tod.STREET_LAMP_NADIR_CD == pytest.approx(30.0 * 7.9**2)  # 30 lux under a head 7.9 m up


def test_rain_at_night_glows_around_the_lights_each_rate_its_own(night_scene):
    """The glow (rain.weather.light_glow) lifts a rainy night's image where lights are seen, and
    follows the rate even where two rates share one render (render_frame adds it per weather)."""
    from rainbench.gen.generate import SceneSetup, render_frame
    from rainbench.gen.labels import LabelFilter
    from rainbench.gen.weather import render_key

    layout, model = night_scene
    data = _posed(model, layout, 8.0)
    table = geom_instance_table(model)
    moderate, heavy = (wx.weather_at(SKY, rate, time_of_day="night") for rate in (50.0, 100.0))
    assert render_key(moderate) == render_key(heavy)  # one render serves both rates
    with FrameRenderer(model, 320, 240, table,
                       base_weather=wx.weather_at(SKY, 0.0, time_of_day="night")) as renderer:
        renderer.update(data)
        _, _, depth = renderer.render_instances_depth()
        centres, candela, colours = renderer._rig.lamp_lights(data, camera_pose(model, data, "ego")[:3, 3])
        plain = renderer.render_weather(data, moderate, depth)
        classes = np.array([actor.class_id for actor in layout.actors], dtype=np.int32)
        setup = SceneSetup(layout, model, table, classes)
        frame = render_frame(renderer, data, setup, LabelFilter(), weathers=(moderate, heavy))
    assert len(centres) == len(candela) == len(colours) == len(renderer._rig.lamp_kinds) > 0
    assert (candela > 0).any() and (candela == 0).any()  # cut-off lamps far along the street send none
    lift = frame.rgb_by_weather[moderate].astype(int) - plain
    assert lift.min() >= 0 and lift.mean() > 0.5
    more = frame.rgb_by_weather[heavy].astype(int) - frame.rgb_by_weather[moderate]
    assert more.min() >= 0 and more.mean() > 0.1  # denser rain scatters more of the lamps' light


def test_a_rainy_day_has_no_glow(monkeypatch):
    import rainbench.gen.render as render_module

    calls = []
    monkeypatch.setattr(render_module, "light_glow", lambda *args: calls.append(args))
    renderer = render_module.FrameRenderer.__new__(render_module.FrameRenderer)
    image = np.zeros((2, 2, 3), np.uint8)
    for weather in (wx.weather_at(SKY, 50.0), wx.weather_at(SKY, 0.0, time_of_day="night")):
        assert renderer.with_glow(image, None, weather, np.ones((2, 2), np.float32)) is image
    assert not calls


# -- vehicle lamps by day in dark rain --------------------------------------------------------------
@pytest.mark.parametrize("sky", wx.SKIES)
def test_vehicle_lamps_are_on_by_day_only_below_1000_lux(sky):
    """UN ECE R48's automatic headlamp switching: on below 1 000 lux, which the daytime rain law
    reaches above 10 mm/h under every sky; always on at dusk and night; off where the weather
    does not follow the rate."""
    lamps = {rate: scene_lighting(wx.weather_at(sky, rate)).vehicle_lamps
             for rate in (0.0, 5.0, 10.0, 10.5, 25.0, 100.0)}
    assert lamps == {0.0: False, 5.0: False, 10.0: False, 10.5: True, 25.0: True, 100.0: True}
    assert not scene_lighting(wx.weather_at(sky, 100.0, follows_rate=False)).vehicle_lamps
    for time_of_day in ("dusk", "night"):
        assert scene_lighting(wx.weather_at(sky, 0.0, time_of_day=time_of_day)).vehicle_lamps


def test_tail_lamps_light_up_by_day_in_dark_rain_and_go_dark_again():
    """A daytime scene builds its vehicle lamps dark (the same render as without their
    materials); at 25 mm/h the tail lamps of the car ahead glow saturated red, brighter than the
    car around them; back at 5 mm/h the lamps' model values are exactly the built ones."""
    width, height = 320, 240
    layout, spec, model = _scene("day", width, height)
    tail = model.material("tod_taillamp").id
    tails = np.flatnonzero(model.geom_matid == tail)
    assert tails.size >= 2 and model.mat_emission[tail] == 0.0
    built_rgba = model.geom_rgba[tails].copy()
    stripped = build_spec(layout, width, height)
    for geom in stripped.geoms:
        if geom.material in ("tod_headlamp", "tod_taillamp"):
            geom.material = ""
    plain = stripped.compile()
    table = geom_instance_table(model)
    with FrameRenderer(model, width, height, table, base_weather=wx.weather_at(SKY, 0.0)) as renderer:
        best = None  # the frame whose nearest tail lamp facing the camera is nearest
        for t in np.arange(1.0, 20.0, 1.0):
            data = _posed(model, layout, t)
            uv, depth = _project(renderer, data, data.geom_xpos[tails])
            facing = data.geom_xmat[tails].reshape(-1, 3, 3)[:, :, 0] @ camera_pose(
                model, data, "ego")[:3, 2] > 0.5  # the camera behind the vehicle
            inside = ((uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
                      & (depth > 2.0) & facing)
            if inside.any() and (best is None or depth[inside].min() < best[0]):
                best = (depth[inside].min(), t)
        assert best is not None and best[0] < 40.0
        data = _posed(model, layout, best[1])
        renderer.update(data)
        clean = renderer.render_rgb()
        ids, _, depth = renderer.render_instances_depth()
        light_rain = renderer.render_weather(data, wx.weather_at(SKY, 5.0), depth)
        dark_rain = renderer.render_weather(data, wx.weather_at(SKY, 25.0), depth)
        assert model.mat_emission[tail] == tod.TAILLAMP_EMISSION
        assert np.array_equal(model.geom_rgba[tails], np.tile(np.float32(tod.TAILLAMP_RGBA), (tails.size, 1)))
        renderer.render_weather(data, wx.weather_at(SKY, 5.0), depth)
        assert model.mat_emission[tail] == 0.0 and np.array_equal(model.geom_rgba[tails], built_rgba)
    with FrameRenderer(plain, width, height, geom_instance_table(plain),
                       base_weather=wx.weather_at(SKY, 0.0)) as renderer:
        renderer.update(_posed(plain, layout, best[1]))
        assert np.array_equal(renderer.render_rgb(), clean)
    red = dark_rain[..., 0].astype(np.int64) - light_rain[..., 0]
    lamp = (red > 60) & (dark_rain[..., 0] >= 200) & (dark_rain[..., 1] < 80)
    assert lamp.sum() >= 4
    owners = np.unique(ids[lamp])
    assert owners.size and (owners >= 0).all()  # on vehicles, not on the road
    body = np.isin(ids, owners) & ~lamp
    assert dark_rain[lamp, 0].mean() > dark_rain[body, 0].mean() + 60


@pytest.mark.parametrize("time_of_day", ["day", "night"])
def test_parked_vehicles_keep_their_lamps_off(time_of_day):
    """On the residential street the parked cars (speed 0 all clip) get no lamp material and no
    beam, by day (never lit in rain) or at night; the moving vehicles' lamps get theirs."""
    config = L.ScenarioConfig(sky=SKY, layout="residential", time_of_day=time_of_day)
    layout = L.sample_layout(SEED, config, np.random.default_rng(SEED))
    vehicles = [unit for unit in layout.units if unit.kind in ("car", "motorcycle")]
    parked = {unit.name for unit in vehicles if unit.speed <= 0}
    moving = {unit.name for unit in vehicles if unit.speed > 0}
    assert len(parked) >= 2 and moving
    model = build_spec(layout, 160, 120).compile()
    lamp_materials = {model.material(name).id for name in ("tod_headlamp", "tod_taillamp")}
    lit_bodies = set()
    for geom in range(model.ngeom):
        name = model.geom(geom).name
        if name.startswith("actor") and ("/headlight" in name or "/taillight" in name):
            body = model.geom_bodyid[geom]
            while model.body_parentid[body] != 0:  # the vehicle's root body
                body = model.body_parentid[body]
            root = model.body(body).name
            assert root in parked | moving, root
            assert (model.geom_matid[geom] in lamp_materials) == (root in moving), (root, name)
            if model.geom_matid[geom] in lamp_materials:
                lit_bodies.add(root)
    assert lit_bodies and lit_bodies <= moving
    beams = {model.light(i).name for i in range(model.nlight) if model.light(i).name.endswith("_beam")}
    assert not {f"{tod.LIGHT_PREFIX}{name}_beam" for name in parked} & beams


def test_after_dark_the_road_becomes_planes_but_the_barrier_foot_stays_a_box():
    """The highway's jersey-barrier foot (0.64 m wide, 0.32 m high, concrete) was turned into a
    plane at its top after dark like the road, and floated: the far carriageway's markings showed
    under it (a scene audit, seed 3 at dusk)."""
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import build_scene

    model = build_scene(GenerateConfig(seed=3, layout="highway", time_of_day="dusk", frames=10, width=64,
                                       height=48)).model
    types = {model.geom(i).name: int(model.geom_type[i]) for i in range(model.ngeom)}
    feet = [name for name in types if name.startswith("scenery/barrier_foot")]
    assert feet and all(types[name] == mujoco.mjtGeom.mjGEOM_BOX for name in feet)
    assert sum(kind == mujoco.mjtGeom.mjGEOM_PLANE for kind in types.values()) >= 2  # the carriageways
