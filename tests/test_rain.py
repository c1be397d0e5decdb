"""Tests of rainbench.rain: rate specs, both rain models, nesting, determinism and statistics."""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import numpy as np
import pytest

from rainbench.rain import (
    RAIN_MODELS,
    BoxRainReference,
    RainConfig,
    box_rain_labels,
    image_quality,
    render_rain,
    render_rain_sweep,
    sample_drops,
)
from rainbench.rain import lens as lens_mod
from rainbench.rain import physical as phys
from rainbench.rain.metrics import box_pixel_ranges, luma, psnr
from rainbench.store.rates import RatesError, parse_rates
from testframe import intrinsics, street_frame

RAIN_DIR = pathlib.Path(__file__).resolve().parents[1] / "rain"
SWEEP_RATES = tuple(float(rate) for rate in range(0, 101, 10))


@pytest.fixture(scope="module")
def small_frame():
    """(rgb (96, 128, 3) uint8, depth (96, 128) float32, K) street scene."""
    return street_frame(np.random.default_rng(7), 96, 128)


def _seed(frame: int = 0) -> np.random.SeedSequence:
    return np.random.SeedSequence([11, 22, frame])


def _config(model: str, **overrides) -> RainConfig:
    return RainConfig(model=model, **overrides)


def _assert_frames_equal(first, second) -> None:
    assert first.rgb.dtype == np.uint8 and second.rgb.dtype == np.uint8
    np.testing.assert_array_equal(first.rgb, second.rgb)
    np.testing.assert_array_equal(first.coverage, second.coverage)
    assert first.drop_count == second.drop_count


# --------------------------------------------------------------------------------------------
# RATES specs


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("0:100:10", SWEEP_RATES),
        ("0:1:0.1", (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)),
        ("10:30:10", (10.0, 20.0, 30.0)),
        ("0:25:10", (0.0, 10.0, 20.0)),
        ("5:5:1", (5.0,)),
        ("0,25,50", (0.0, 25.0, 50.0)),
        ("50, 0 ,25", (0.0, 25.0, 50.0)),
        ("50", (50.0,)),
        (" 7.5 ", (7.5,)),
        ("1000", (1000.0,)),
    ],
)
def test_parse_rates_accepts(spec, expected):
    assert parse_rates(spec) == expected


def test_a_rate_list_refuses_rates_that_float32_storage_would_merge():
    from rainbench.store.rates import check_rate_list

    assert check_rate_list([0.0, 12.3]) == (0.0, 12.3)  # kept as given; stored as float32 12.3
    with pytest.raises(ValueError, match=r"^rates: rates 0\.1 and 0\.10000000001 are the same once stored as float32"):
        check_rate_list([0.1, 0.10000000001])
    with pytest.raises(ValueError, match=r"^rates: rate 1e-50 is stored as 0 "):
        check_rate_list([1e-50])


@pytest.mark.parametrize(
    ("spec", "reason"),
    [
        ("100:0:10", "stop 0 is below start 100"),
        ("abc", 'rate "abc" is not a number'),
        ("-5", "rate -5 is negative"),
        ("0,-1", "item 2 -1 is negative"),
        ("0:100:0", "step 0 must be > 0"),
        ("0:100:-10", "step -10 must be > 0"),
        ("1001", "rate 1001 exceeds 1000 mm/h"),
        ("0:2000:10", "stop 2000 exceeds 1000 mm/h"),
        ("", "empty spec"),
        ("   ", "empty spec"),
        ("nan", 'rate "nan" is not finite'),
        ("inf", 'rate "inf" is not finite'),
        ("0:inf:1", 'stop "inf" is not finite'),
        ("10,10", "rate 10 is listed twice"),
        ("10,,20", "empty item 2"),
        ("0:100", "exactly start:stop:step"),
        ("0:1000:0.5", "expands to 2001 rates"),
        ("line\nbreak", 'rate "line\\nbreak" is not a number'),
        # shards store rates as float32: what it cannot tell apart, or stores as 0, is refused
        ("0.1,0.10000000001", "rates 0.1 and 0.10000000001 are the same once stored as float32"),
        ("0,1e-50", "rate 1e-50 is stored as 0 (shards hold rates as float32)"),
        ("1e-50", "rate 1e-50 is stored as 0"),
    ],
)
def test_parse_rates_refuses_with_one_line(spec, reason):
    with pytest.raises(RatesError, match="^RATES ") as caught:
        parse_rates(spec)
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"RATES {json.dumps(spec)}: ")
    assert reason in message
    assert isinstance(caught.value, ValueError)


# --------------------------------------------------------------------------------------------
# jeon2022: eq. 5 counts


def test_eq5_counts_at_800x600():
    expected = [0, 204, 537, 871, 1204, 1537, 1871, 2204, 2537, 2871, 3204]
    assert [lens_mod.jeon2022_drop_count(rate, 600, 800) for rate in SWEEP_RATES] == expected
    assert lens_mod.jeon2022_drop_count(3.88) == 0
    assert lens_mod.jeon2022_drop_count(3.9) == 1  # (3.9 - 3.88) / 0.03 = 0.67 -> 1


def test_eq5_rounds_exact_halves_up():
    """Float arithmetic put exact halves just under .5: 3.925 mm/h (1.5 drops) gave 1, 3.985 gave
    3; 186 of the 6000 half-way rates 3.88 + 0.03 (k + 1/2) below 184 mm/h rounded down."""
    assert lens_mod.jeon2022_drop_count(3.925) == 2 and lens_mod.jeon2022_drop_count(3.985) == 4
    halves = [round(3.88 + 0.03 * (k + 0.5), 3) for k in range(6000)]
    assert [lens_mod.jeon2022_drop_count(rate) for rate in halves] == [k + 1 for k in range(6000)]
    assert lens_mod.jeon2022_drop_count(3.925, 1080, 1920) == 9  # 2 x 4.32 = 8.64 -> 9
    # a rate read back from a shard (float32) is the decimal it stands for
    assert lens_mod.jeon2022_drop_count(np.float32(3.925)) == 2
    assert lens_mod.jeon2022_drop_count(float(np.float32(3.985))) == 4


def test_eq5_counts_scale_with_area():
    assert lens_mod.jeon2022_drop_count(100.0, 300, 400) == 801  # 3204 / 4
    assert lens_mod.jeon2022_drop_count(100.0, 1200, 1600) == 12816  # 3204 * 4
    assert lens_mod.jeon2022_drop_count(50.0, 600, 400) == 769  # 1537 / 2 = 768.5, rounded half up
    assert lens_mod.jeon2022_drop_count(10.0, 96, 128) == 5  # 204 * 0.0256 = 5.2


def test_jeon_render_draws_the_eq5_count(small_frame):
    rgb, depth, K = small_frame
    for rate in (10.0, 55.0, 100.0):
        frame = render_rain(rgb, depth, rate, config=RainConfig(), K=K, seed_sequence=_seed())
        assert frame.drop_count == lens_mod.jeon2022_drop_count(rate, 96, 128)
        drops = sample_drops(rate, config=RainConfig(), K=K, shape=rgb.shape, seed_sequence=_seed())
        assert len(drops.lens) == frame.drop_count and len(drops.air) == 0


def test_jeon_works_without_depth_and_K(small_frame):
    rgb, depth, K = small_frame
    with_depth = render_rain(rgb, depth, 40.0, config=RainConfig(), K=K, seed_sequence=_seed())
    without = render_rain(rgb, None, 40.0, config=RainConfig(), K=None, seed_sequence=_seed())
    _assert_frames_equal(with_depth, without)


# --------------------------------------------------------------------------------------------
# nesting


def test_lens_sequence_is_prefix_stable_across_blocks():
    config = RainConfig()
    clock = lens_mod.LensClock(_seed(), 37, 10.0)
    long = lens_mod.sample_lens_drops(1500, config=config, height=600, width=800, lens_clock=clock)
    for count in (1, 100, 511, 512, 513, 1024, 1499):
        short = lens_mod.sample_lens_drops(count, config=config, height=600, width=800, lens_clock=clock)
        np.testing.assert_array_equal(short.as_array(), long.as_array()[:count])


@pytest.mark.parametrize("model", RAIN_MODELS)
def test_every_drop_of_a_lower_rate_is_present_at_a_higher_rate(model, small_frame):
    rgb, _, K = small_frame
    config = _config(model, lens_drops=True) if model == "physical" else _config(model)
    drops = [sample_drops(rate, config=config, K=K, shape=rgb.shape, seed_sequence=_seed(3)) for rate in SWEEP_RATES]
    for lower, higher, lower_rate in zip(drops, drops[1:], SWEEP_RATES):
        assert len(lower) <= len(higher)
        # lens drops: the first slots of the clip's lens
        np.testing.assert_array_equal(lower.lens.as_array(), higher.lens.as_array()[: len(lower.lens)])
        # falling drops: the higher rate restricted to thresholds <= the lower rate, unchanged
        restricted = higher.air.select(higher.air.threshold_rate_mm_h <= lower_rate)
        np.testing.assert_array_equal(lower.air.as_array(), restricted.as_array())
    assert len(drops[-1]) > len(drops[1]) > 0
    if model == "physical":
        assert len(drops[1].air) > 0 and len(drops[1].lens) > 0


def test_physical_thinning_gives_marshall_palmer_at_each_rate():
    # a wide, deep streak volume so that there are many drops
    config = RainConfig(model="physical", streak_z_far_m=3.0, max_streak_candidates=200_000)
    K = intrinsics(600, 800, 90.0)
    candidates = phys.sample_air_candidates(config=config, K=K, height=600, width=800, seed_sequence=_seed(5))
    z_near, z_far = phys.streak_depth_range(config, K, 600, 800)
    assert (z_near, z_far) == (config.streak_z_near_m, config.streak_z_far_m)  # under the candidate bound
    volume = phys.frustum_volume_m3(K, 600, 800, z_near, z_far)
    assert np.all((candidates.z_m >= z_near) & (candidates.z_m <= z_far))
    for rate in (10.0, 50.0, 100.0):
        drops = candidates.at_rate(rate)
        expected = phys.marshall_palmer_density(rate, config.streak_min_diameter_mm) * volume
        assert abs(len(drops) - expected) < 5 * math.sqrt(expected)
        # D - D_min is exponential with mean 1 / Lambda(R)
        mean_excess = float(np.mean(drops.diameter_mm - config.streak_min_diameter_mm))
        expected_mean = 1.0 / phys.marshall_palmer_slope(rate)
        assert abs(mean_excess - expected_mean) < 5 * expected_mean / math.sqrt(len(drops))
        assert np.all(drops.threshold_rate_mm_h <= rate)


# --------------------------------------------------------------------------------------------
# determinism, rate 0, rate-set independence


@pytest.mark.parametrize("model", RAIN_MODELS)
def test_rate_zero_returns_a_copy_of_the_clean_frame(model, small_frame):
    rgb, depth, K = small_frame
    frame = render_rain(rgb, depth, 0.0, config=_config(model), K=K, seed_sequence=_seed())
    np.testing.assert_array_equal(frame.rgb, rgb)
    assert frame.rgb is not rgb and not np.shares_memory(frame.rgb, rgb)
    assert frame.coverage.dtype == np.float32 and frame.coverage.shape == rgb.shape[:2]
    assert not frame.coverage.any()
    assert frame.drop_count == 0


@pytest.mark.parametrize("model", RAIN_MODELS)
def test_render_is_deterministic_and_leaves_inputs_alone(model, small_frame):
    rgb, depth, K = small_frame
    rgb_before, depth_before = rgb.copy(), depth.copy()
    seed = _seed(1)
    first = render_rain(rgb, depth, 60.0, config=_config(model), K=K, seed_sequence=seed)
    second = render_rain(rgb, depth, 60.0, config=_config(model), K=K, seed_sequence=seed)
    _assert_frames_equal(first, second)
    assert seed.n_children_spawned == 0  # the caller's SeedSequence is not consumed
    np.testing.assert_array_equal(rgb, rgb_before)
    np.testing.assert_array_equal(depth, depth_before)
    other = render_rain(rgb, depth, 60.0, config=_config(model), K=K, seed_sequence=_seed(2))
    assert not np.array_equal(first.rgb, other.rgb)
    assert first.coverage.min() >= 0.0 and first.coverage.max() <= 1.0
    assert first.coverage.max() > 0.0


@pytest.mark.parametrize(
    "config",
    [
        RainConfig(),
        RainConfig(model="physical"),
        # lens drops on top, wind, and strong defocus so that blurred streak layers are used
        RainConfig(model="physical", lens_drops=True, wind_slant_deg=25.0, f_number=1.0, focus_distance_m=30.0, pixel_pitch_um=600.0),
    ],
    ids=["jeon2022", "physical", "physical-lens-defocus"],
)
def test_requested_rate_set_does_not_change_the_image(config, small_frame):
    rgb, depth, K = small_frame
    seed = _seed(4)
    full = render_rain_sweep(rgb, depth, SWEEP_RATES, config=config, K=K, seed_sequence=seed)
    subset = render_rain_sweep(rgb, depth, [100.0, 30.0, 70.0, 30.0], config=config, K=K, seed_sequence=seed)
    for rate, frame in zip([100.0, 30.0, 70.0, 30.0], subset):
        _assert_frames_equal(frame, full[SWEEP_RATES.index(rate)])
    assert not np.shares_memory(subset[1].rgb, subset[3].rgb)  # repeated rates are separate arrays
    for rate, frame in zip(SWEEP_RATES, full):
        _assert_frames_equal(render_rain(rgb, depth, rate, config=config, K=K, seed_sequence=seed), frame)
    if config.f_number == 1.0:
        air = sample_drops(100.0, config=config, K=K, shape=rgb.shape, seed_sequence=seed).air
        assert np.unique(phys.blur_layer(air.blur_sigma_px)).shape[0] > 2  # several blur layers exercised


@pytest.mark.parametrize("model", RAIN_MODELS)
def test_mean_ssim_decreases_with_rate(model):
    frames = [street_frame(np.random.default_rng(100 + index), 120, 160) for index in range(3)]
    ssim_by_rate = np.zeros(len(SWEEP_RATES))
    for index, (rgb, depth, K) in enumerate(frames):
        rendered = render_rain_sweep(rgb, depth, SWEEP_RATES, config=_config(model), K=K, seed_sequence=_seed(index))
        ssim_by_rate += [image_quality(rgb, frame.rgb)[0] for frame in rendered]
    ssim_by_rate /= len(frames)
    assert ssim_by_rate[0] == pytest.approx(1.0)
    assert np.all(np.diff(ssim_by_rate) < 0), ssim_by_rate


# --------------------------------------------------------------------------------------------
# physical model


def test_extinction_and_visibility_formulas():
    for rate in (1.0, 10.0, 50.0, 100.0):
        beta = phys.extinction_coefficient(rate)
        assert beta == pytest.approx(0.312 * rate**0.67, rel=1e-12)
        assert phys.visibility_km(rate) == pytest.approx(3.912 / beta, rel=1e-12)
    assert phys.visibility_km(10.0) == pytest.approx(2.68, abs=0.01)  # rain-physics.md: ~2.7 km
    assert phys.visibility_km(100.0) == pytest.approx(0.573, abs=0.001)  # ~0.57 km
    assert math.exp(-phys.extinction_coefficient(100.0) * 0.050) == pytest.approx(0.71, abs=0.005)
    assert phys.visibility_km(0.0) == math.inf
    assert phys.marshall_palmer_slope(10.0) == pytest.approx(4.1 * 10.0**-0.21)
    assert phys.marshall_palmer_density(10.0, 0.5) == pytest.approx(894, rel=1e-3)
    assert phys.marshall_palmer_density(100.0, 0.5) == pytest.approx(2354, rel=1e-3)
    assert phys.terminal_velocity(2.0) == pytest.approx(9.65 - 10.3 * math.exp(-1.2))
    assert phys.frustum_volume_m3(intrinsics(600, 800, 90.0), 600, 800, 0.0, 1.0) == pytest.approx(4 / 3 * 1.0 * 0.75)


def test_candidate_bound_pulls_in_the_far_end():
    K = intrinsics(600, 800, 90.0)
    config = RainConfig(model="physical", streak_z_far_m=10.0, max_streak_candidates=20000)
    z_near, z_far = phys.streak_depth_range(config, K, 600, 800)
    assert z_near == config.streak_z_near_m and z_near < z_far < 10.0
    expected = phys.marshall_palmer_density(1000.0, config.streak_min_diameter_mm) * phys.frustum_volume_m3(K, 600, 800, z_near, z_far)
    assert expected == pytest.approx(20000, rel=1e-9)
    candidates = phys.sample_air_candidates(config=config, K=K, height=600, width=800, seed_sequence=_seed())
    assert abs(len(candidates) - 20000) < 5 * math.sqrt(20000) and candidates.z_m.max() <= z_far


def test_sample_marshall_palmer_diameters_uses_the_given_generator():
    first = phys.sample_marshall_palmer_diameters(np.random.default_rng(3), 20000, 25.0, 0.5)
    second = phys.sample_marshall_palmer_diameters(np.random.default_rng(3), 20000, 25.0, 0.5)
    np.testing.assert_array_equal(first, second)
    assert first.min() >= 0.5
    assert np.mean(first - 0.5) == pytest.approx(1.0 / phys.marshall_palmer_slope(25.0), rel=0.03)


def test_extinction_and_airlight_applied_with_the_depth_render():
    height, width = 40, 60
    K = intrinsics(height, width, 60.0)
    rgb = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    depth = np.full((height, width), 50.0, dtype=np.float32)
    airlight = (200.0, 180.0, 160.0)
    config = RainConfig(model="physical", airlight_rgb=airlight, lens_drops=False)  # extinction and streaks alone
    frame = render_rain(rgb, depth, 100.0, config=config, K=K, seed_sequence=_seed())
    path = phys.ray_length_m(depth, K, config.sky_distance_m).astype(np.float64)
    transmission = np.exp(-phys.extinction_coefficient(100.0) * 1e-3 * path)[..., None]
    streaks = frame.coverage.astype(np.float64)[..., None]
    # radiance mixes in linear light: display values through the 1/2.2 tone curve, and back
    def linear(display):
        return (np.asarray(display, np.float64) / 255.0) ** 2.2

    def display(light):
        return 255.0 * np.clip(light, 0.0, 1.0) ** (1 / 2.2)

    air, scene = linear(airlight), linear(rgb)
    # the sky's share (the airlight) plus the rest of the frame's mean radiance
    drop_radiance = config.streak_sky_weight * air + (1 - config.streak_sky_weight) * scene.reshape(-1, 3).mean(axis=0)
    expected = display(air + (scene - air) * transmission * (1 - streaks) + (drop_radiance - air) * streaks)
    assert np.abs(frame.rgb.astype(np.float64) - expected).max() <= 1.0
    assert frame.coverage.max() > 0.01
    # without streaks it is the pure extinction / airlight blend (Koschmieder, in light)
    no_streaks = render_rain(rgb, np.full_like(depth, 0.2), 100.0, config=config, K=K, seed_sequence=_seed())
    near_path = phys.ray_length_m(np.full_like(depth, 0.2), K, config.sky_distance_m).astype(np.float64)
    near_expected = display(air + (scene - air) * np.exp(-phys.extinction_coefficient(100.0) * 1e-3 * near_path)[..., None])
    assert not no_streaks.coverage.any()
    assert np.abs(no_streaks.rgb.astype(np.float64) - near_expected).max() <= 0.5 + 1e-3
    # the mix is of light, not of display values: a grey 50 at 50 m under a 200 airlight at
    # 100 mm/h (T = 0.71) shows as 120, not the 93 of a display-value mix
    grey = render_rain(np.full((height, width, 3), 50, np.uint8), depth, 100.0,
                       config=dataclasses.replace(config, airlight_rgb=(200.0, 200.0, 200.0)), K=K,
                       seed_sequence=_seed())
    assert transmission[height // 2, width // 2, 0] == pytest.approx(0.71, abs=0.01)
    opacity = grey.coverage.astype(np.float64)
    streak_light = config.streak_sky_weight * linear(200) + (1 - config.streak_sky_weight) * linear(50)
    want = display(linear(200) + (linear(50) - linear(200)) * transmission[..., 0] * (1 - opacity)
                   + (streak_light - linear(200)) * opacity)
    np.testing.assert_allclose(grey.rgb[..., 0].astype(float), want, atol=1.0)
    assert np.median(grey.rgb) >= 118  # a display-value mix gave about 93
    # the corner ray is longer than the central one (path = depth * ray norm)
    assert path[0, 0] > path[height // 2, width // 2] >= 50.0


def test_sky_fades_to_airlight_with_rate():
    height, width = 30, 40
    K = intrinsics(height, width, 60.0)
    rgb = np.full((height, width, 3), 60, dtype=np.uint8)
    depth = np.full((height, width), np.inf, dtype=np.float32)
    config = RainConfig(model="physical", airlight_rgb=(240.0, 240.0, 240.0), streak_z_far_m=0.6)
    medians = [float(np.median(render_rain(rgb, depth, rate, config=config, K=K, seed_sequence=_seed()).rgb)) for rate in (1.0, 10.0, 100.0)]
    transmission_10 = math.exp(-phys.extinction_coefficient(10.0) * config.sky_distance_m * 1e-3)
    light_60, light_240 = (60 / 255) ** 2.2, (240 / 255) ** 2.2  # Koschmieder in linear light
    assert medians[1] == pytest.approx(255 * (light_240 + (light_60 - light_240) * transmission_10) ** (1 / 2.2), abs=2.0)
    assert medians[0] < medians[1] < medians[2] == pytest.approx(240, abs=1.0)


def _one_air_drop(z_m: float, config: RainConfig, K: np.ndarray, x: float = 30.0, y: float = 20.0) -> phys.AirDrops:
    diameter_mm = 3.0
    velocity = phys.terminal_velocity(diameter_mm)
    fall = K[1, 1] * velocity * config.exposure_s / z_m
    values = dict(
        x_px=x, y_px=y, z_m=z_m, diameter_mm=diameter_mm, threshold_rate_mm_h=1.0,
        diameter_px=K[0, 0] * diameter_mm * 1e-3 / z_m, fall_px=fall, drift_px=0.0, streak_length_px=fall, blur_sigma_px=0.0,
    )
    return phys.AirDrops(**{name: np.array([value], dtype=np.float64) for name, value in values.items()})


def test_drop_behind_a_near_wall_is_not_drawn():
    height, width = 40, 60
    K = intrinsics(height, width, 60.0)
    config = RainConfig(model="physical", lens_drops=False)  # streaks alone
    drop = _one_air_drop(1.5, config, K)
    far_wall = np.full((height, width), 3.0, dtype=np.float32)
    near_wall = np.full((height, width), 1.0, dtype=np.float32)
    assert phys.rasterize_streaks(drop, far_wall).pixel.shape[0] > 0
    hidden = phys.rasterize_streaks(drop, near_wall)
    assert hidden.pixel.shape[0] == 0 and not hidden.visible.any()
    # half wall: only the part of the streak over the far background is drawn
    half = far_wall.copy()
    half[:, :30] = 1.0
    partial = phys.rasterize_streaks(drop, half)
    assert partial.pixel.shape[0] > 0 and np.all(partial.pixel % width >= 30)

    # whole render: a wall nearer than every streak hides all streaks
    rgb = np.full((height, width, 3), 90, dtype=np.uint8)
    hidden_frame = render_rain(rgb, np.full((height, width), 0.3, np.float32), 100.0, config=config, K=K, seed_sequence=_seed())
    assert hidden_frame.drop_count == 0 and not hidden_frame.coverage.any()
    open_frame = render_rain(rgb, np.full((height, width), 100.0, np.float32), 100.0, config=config, K=K, seed_sequence=_seed())
    assert open_frame.drop_count > 0 and open_frame.coverage.max() > 0


def test_streak_length_grows_with_exposure():
    K = intrinsics(96, 128, 90.0)
    lengths = []
    for exposure in (0.002, 0.004, 0.008):
        config = RainConfig(model="physical", exposure_s=exposure)
        air = sample_drops(50.0, config=config, K=K, shape=(96, 128), seed_sequence=_seed()).air
        lengths.append(air.streak_length_px)
    np.testing.assert_allclose(lengths[1], 2 * lengths[0], rtol=1e-12)
    np.testing.assert_allclose(lengths[2], 4 * lengths[0], rtol=1e-12)
    # drawn: the vertical extent of one near drop's streak grows with the exposure
    extents = []
    K_large = intrinsics(300, 400, 90.0)
    for exposure in (0.002, 0.008):
        config = RainConfig(model="physical", exposure_s=exposure)
        raster = phys.rasterize_streaks(_one_air_drop(1.0, config, K_large, x=200.0, y=150.0), np.full((300, 400), 50.0, np.float32))
        rows = raster.pixel // 400
        extents.append(rows.max() - rows.min() + 1)
    assert extents[1] >= 2.5 * extents[0] and extents[0] >= 3


def test_streak_opacity_is_the_drop_area():
    K = intrinsics(96, 128, 90.0)
    config = RainConfig(model="physical")
    drop = _one_air_drop(0.8, config, K, x=64.0, y=48.0)
    raster = phys.rasterize_streaks(drop, np.full((96, 128), 50.0, np.float32))
    total = raster.weight_units.sum() / phys.WEIGHT_UNITS
    assert total == pytest.approx(math.pi / 4 * drop.diameter_px[0] ** 2, rel=1e-4)


def test_streak_sample_counts_bound_the_raster_of_every_drop():
    K = intrinsics(96, 128, 90.0)
    config = RainConfig(model="physical", exposure_s=0.02, wind_slant_deg=25.0, pixel_pitch_um=120.0)
    air = sample_drops(1000.0, config=config, K=K, shape=(96, 128), seed_sequence=_seed()).air
    samples = phys.streak_sample_counts(air)
    raster = phys.rasterize_streaks(air, np.full((96, 128), np.inf, np.float32))
    entries = np.bincount(raster.drop, minlength=len(air))
    assert np.all(entries <= 4 * samples)  # each sample splats into 2 x 2 pixels at most
    assert entries.sum() > 3 * samples.sum() * np.mean(raster.visible)  # and nearly always four


@pytest.mark.parametrize("diameter_mm, z_m, y", [(0.5, 0.5, 20.3), (3.0, 0.8, 47.71), (1.2, 1.0, 33.05)])
def test_a_streak_is_even_along_its_length(diameter_mm, z_m, y):
    """Samples are under 1 px apart along a streak; put whole into one row each, a row in about
    three streaks got two samples (twice the opacity of its neighbours: 0.019 against 0.0095
    for a 0.6 px drop). Away from its ends a vertical streak's rows now carry equal opacity."""
    height, width = 400, 400
    K = intrinsics(height, width, 90.0)
    config = RainConfig(model="physical", exposure_s=1 / 30)
    velocity = phys.terminal_velocity(diameter_mm)
    fall = K[1, 1] * velocity * config.exposure_s / z_m
    values = dict(x_px=200.37, y_px=y + fall / 2, z_m=z_m, diameter_mm=diameter_mm, threshold_rate_mm_h=1.0,
                  diameter_px=K[0, 0] * diameter_mm * 1e-3 / z_m, fall_px=fall, drift_px=0.0,
                  streak_length_px=fall, blur_sigma_px=0.0)
    drop = phys.AirDrops(**{name: np.array([value], dtype=np.float64) for name, value in values.items()})
    raster = phys.rasterize_streaks(drop, np.full((height, width), 50.0, np.float32))
    rows = np.bincount(raster.pixel // width, weights=raster.weight_units, minlength=height) / phys.WEIGHT_UNITS
    drawn = np.flatnonzero(rows)
    interior = rows[drawn[0] + 3:drawn[-1] - 2]
    assert len(interior) > 10
    assert interior.max() / interior.min() < 1.05
    assert rows.sum() == pytest.approx(math.pi / 4 * drop.diameter_px[0] ** 2, rel=1e-3)


@pytest.mark.parametrize("overrides", [dict(exposure_s=0.03, wind_slant_deg=30.0), dict(pixel_pitch_um=120.0, exposure_s=0.02)],
                         ids=["slanted-sharp", "sharp-and-blurred-layers"])
def test_streaks_drawn_in_runs_give_the_same_bytes(overrides, monkeypatch):
    """Past STREAK_SAMPLE_BUDGET the streaks are rasterised rate by rate in runs into dense sums
    (bounded memory); forced on a small frame, every rate's image, coverage and count are those
    of the single raster."""
    from rainbench.rain import render as render_mod

    rgb, depth, K = street_frame(np.random.default_rng(21), 120, 160)
    config = RainConfig(model="physical", **overrides)
    rates = (*SWEEP_RATES, 400.0, 1000.0)
    whole = render_rain_sweep(rgb, depth, rates, config=config, K=K, seed_sequence=_seed(3))
    calls: list[int] = []
    rasterize = phys.rasterize_streaks

    def counting(drops, depth_map):
        calls.append(int(phys.streak_sample_counts(drops).sum()))
        return rasterize(drops, depth_map)

    monkeypatch.setattr(phys, "rasterize_streaks", counting)
    monkeypatch.setattr(render_mod, "STREAK_SAMPLE_BUDGET", 4000)
    runs = render_rain_sweep(rgb, depth, rates, config=config, K=K, seed_sequence=_seed(3))
    for first, second in zip(runs, whole):
        _assert_frames_equal(first, second)
    assert len(calls) > 2 * len(rates) and max(calls) <= 4000
    assert whole[-1].drop_count > whole[1].drop_count > 0


def test_long_exposure_streaks_take_bounded_memory():
    """1/10 s at 1000 mm/h on 800x600: 6.7 million streak samples; rasterised at once they took
    1.65 GB (and 34 GB at 4096x4096), in runs 1.05 GB."""
    import tracemalloc

    height, width = 600, 800
    config = RainConfig(model="physical", exposure_s=0.1, lens_drops=False)
    depth = np.full((height, width), np.inf, np.float32)
    tracemalloc.start()
    try:
        frame = render_rain(np.zeros((height, width, 3), np.uint8), depth, 1000.0, config=config, K=intrinsics(height, width, 90.0), seed_sequence=_seed())
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert frame.drop_count > 30_000 and frame.coverage.mean() > 0.01  # long, faint streaks everywhere
    assert peak < 1.3e9, f"streaks took {peak / 1e9:.2f} GB"


# --------------------------------------------------------------------------------------------
# statistics


def _skimage_ssim(first: np.ndarray, second: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(luma(first), luma(second), gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=255))


@pytest.mark.parametrize("shape", [(11, 11), (37, 53), (64, 96), (120, 80), (101, 257)])
def test_ssim_and_psnr_match_references(shape):
    rng = np.random.default_rng(shape[0] * 1000 + shape[1])
    clean = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    pairs = [
        (clean, np.clip(clean.astype(int) + rng.integers(-20, 21, clean.shape), 0, 255).astype(np.uint8)),
        (clean, clean[::-1].copy()),
        (clean, np.full_like(clean, 128)),
    ]
    for first, second in pairs:
        ssim, peak = image_quality(first, second)
        assert ssim == pytest.approx(_skimage_ssim(first, second), abs=1e-3)
        assert abs(ssim - _skimage_ssim(first, second)) < 1e-5  # float32 maps: far inside the 1e-3 contract
        mse = np.mean((first.astype(np.float64) - second.astype(np.float64)) ** 2)
        assert peak == pytest.approx(10 * math.log10(255**2 / mse), abs=1e-3)
    assert image_quality(clean, clean.copy()) == (pytest.approx(1.0), math.inf)


def test_ssim_matches_skimage_on_rainy_frames(small_frame):
    rgb, depth, K = small_frame
    for model in RAIN_MODELS:
        frame = render_rain(rgb, depth, 80.0, config=_config(model), K=K, seed_sequence=_seed())
        ssim, _ = image_quality(rgb, frame.rgb)
        assert ssim == pytest.approx(_skimage_ssim(rgb, frame.rgb), abs=1e-5)
        assert ssim < 1.0


def test_ssim_reference_equals_image_quality(small_frame):
    from rainbench.rain import SsimReference

    rgb, depth, K = small_frame
    reference = SsimReference(rgb)
    frames = render_rain_sweep(rgb, depth, [20.0, 90.0], config=_config("jeon2022"), K=K,
                               seed_sequence=_seed())
    for frame in frames:
        assert reference.quality(frame.rgb) == image_quality(rgb, frame.rgb)
        assert reference.ssim(frame.rgb) == pytest.approx(_skimage_ssim(rgb, frame.rgb), abs=1e-5)


def test_image_quality_refuses_bad_inputs():
    image = np.zeros((20, 20, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match=r"clean and rainy must have the same shape, got \(20, 20, 3\) and \(20, 21, 3\)"):
        image_quality(image, np.zeros((20, 21, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"rainy must be an \(H, W, 3\) uint8 array, got ndarray \(20, 20, 3\) float64"):
        image_quality(image, image.astype(np.float64))
    with pytest.raises(ValueError, match=r"SSIM needs images of at least 11x11 pixels"):
        image_quality(np.zeros((10, 30, 3), np.uint8), np.zeros((10, 30, 3), np.uint8))
    with pytest.raises(ValueError, match=r"clean must be an \(H, W, 3\) uint8 array, got ndarray \(20, 20\) uint8"):
        psnr(image[..., 0], image[..., 0])


def test_box_rain_labels_definitions():
    height, width = 20, 30
    clean = np.zeros((height, width, 3), dtype=np.uint8)
    clean[:, ::2] = 200  # vertical stripes: luma std 100 everywhere
    rainy = clean.copy()
    rainy[:, :10] = (clean[:, :10] // 2 + 50).astype(np.uint8)  # halve the contrast on the left
    coverage = np.zeros((height, width), dtype=np.float32)
    coverage[:10, :10] = 1.0
    boxes = np.array(
        [
            [0, 0, 10, 10],  # fully covered, contrast halved
            [0, 0, 10, 20],  # half covered
            [20, 0, 30, 20],  # untouched
            [0.4, 0.4, 10.4, 10.4],  # pixel centres inside: columns/rows 0..9, same as box 0
            [40, 40, 50, 50],  # outside the image
            [5, 5, 5.2, 9],  # no pixel centre inside
        ],
        dtype=np.float32,
    )
    rain_coverage, contrast_loss = box_rain_labels(clean, rainy, coverage, boxes)
    assert rain_coverage.dtype == np.float32 and contrast_loss.dtype == np.float32
    np.testing.assert_allclose(rain_coverage, [1.0, 0.5, 0.0, 1.0, 0.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(contrast_loss, [0.5, 0.5, 0.0, 0.5, 0.0, 0.0], atol=2e-3)
    # a flat clean box has no contrast to lose; a rainy box with more contrast is clipped to 0
    flat = np.full((height, width, 3), 90, dtype=np.uint8)
    _, loss_flat = box_rain_labels(flat, clean, coverage, boxes[:1])
    assert loss_flat[0] == 0.0
    _, loss_gain = box_rain_labels(rainy, clean, coverage, boxes[:1])
    assert loss_gain[0] == 0.0
    empty_coverage, empty_loss = box_rain_labels(clean, rainy, coverage, np.zeros((0, 4), np.float32))
    assert empty_coverage.shape == (0,) and empty_loss.shape == (0,)
    with pytest.raises(ValueError, match=r"boxes must be an \(M, 4\) array of x1, y1, x2, y2, got shape \(2, 3\)"):
        box_rain_labels(clean, rainy, coverage, np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError, match=r"coverage must be an \(20, 30\) array, got \(30, 20\)"):
        box_rain_labels(clean, rainy, coverage.T, boxes)


def test_box_rain_reference_gives_the_numbers_of_box_rain_labels():
    """The clean side computed once (BoxRainReference) and reused for several rainy images gives
    the numbers of the definition exactly: ordinary, flat, degenerate and outside boxes."""
    rng = np.random.default_rng(3)
    clean = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    clean[40:50, 10:30] = 7  # a flat patch
    boxes = np.array([[0, 0, 80, 60], [10.4, 5.6, 30.2, 22.9], [10, 40, 30, 50], [5, 5, 5, 9],
                      [90, 70, 99, 80], [70.5, 50.5, 71.4, 51.4]], np.float32)
    reference = BoxRainReference(clean, boxes)
    for _ in range(3):
        rainy = rng.integers(0, 256, clean.shape, dtype=np.uint8)
        coverage = rng.random(clean.shape[:2], dtype=np.float32)
        expected = np.zeros((2, len(boxes)), np.float32)
        for index, (col0, row0, col1, row1) in enumerate(box_pixel_ranges(boxes, 60, 80)):
            if col1 <= col0 or row1 <= row0:
                continue
            expected[0, index] = coverage[row0:row1, col0:col1].mean(dtype=np.float64)
            std_clean = luma(clean[row0:row1, col0:col1]).std()
            if std_clean >= 1e-6:
                std_rainy = luma(rainy[row0:row1, col0:col1]).std()
                expected[1, index] = min(max(1.0 - std_rainy / std_clean, 0.0), 1.0)
        got = reference.labels(rainy, coverage)
        for want, have in zip(expected, got):
            assert have.dtype == np.float32 and have.tobytes() == want.tobytes()
        assert all(a.tobytes() == b.tobytes() for a, b in zip(got, box_rain_labels(clean, rainy, coverage, boxes)))
    assert expected[0, 3] == expected[0, 4] == 0 and expected[1, 2] == 0  # degenerate, outside, flat
    empty = BoxRainReference(clean, np.zeros((0, 4), np.float32)).labels(rainy, coverage)
    assert [a.shape for a in empty] == [(0,), (0,)]
    with pytest.raises(ValueError, match="coverage must be an"):
        reference.labels(rainy, coverage.T)
    with pytest.raises(ValueError, match="boxes must be an"):
        BoxRainReference(clean, np.zeros((2, 3), np.float32))


# --------------------------------------------------------------------------------------------
# configuration and argument checks


def test_config_validation_and_round_trip():
    with pytest.raises(ValueError, match=r"RainConfig.model must be one of \('jeon2022', 'physical'\), got 'garg'"):
        RainConfig(model="garg")
    with pytest.raises(ValueError, match=r"RainConfig.exposure_s must be a finite number > 0, got -1"):
        RainConfig(exposure_s=-1)
    with pytest.raises(ValueError, match="streak_z_far_m must exceed streak_z_near_m"):
        RainConfig(streak_z_near_m=2.0, streak_z_far_m=1.0)
    with pytest.raises(ValueError, match=r"airlight_rgb must be None or three numbers in \[0, 255\]"):
        RainConfig(airlight_rgb=(1.0, 2.0))
    config = RainConfig(model="physical", lens_drops=True, airlight_rgb=(1, 2, 3))
    data = json.loads(json.dumps(config.to_dict()))
    assert data["model"] == "physical" and data["airlight_rgb"] == [1.0, 2.0, 3.0]
    assert RainConfig.from_dict(data) == config
    with pytest.raises(ValueError, match=r"unknown keys \['colour'\]"):
        RainConfig.from_dict({**data, "colour": 1})
    assert dataclasses.replace(config, exposure_s=0.01).exposure_s == 0.01


def test_render_refuses_bad_arguments(small_frame):
    rgb, depth, K = small_frame
    physical = RainConfig(model="physical")
    with pytest.raises(ValueError, match=r"rgb must be an \(H, W, 3\) uint8 array, got ndarray \(96, 128, 3\) float32"):
        render_rain(rgb.astype(np.float32), depth, 10.0, config=RainConfig(), K=K, seed_sequence=_seed())
    with pytest.raises(ValueError, match=r"depth must be an \(96, 128\) float array in metres for the physical model, got None"):
        render_rain(rgb, None, 10.0, config=physical, K=K, seed_sequence=_seed())
    with pytest.raises(ValueError, match=r"depth must be an \(96, 128\) float array in metres, got ndarray \(96, 127\) float32"):
        render_rain(rgb, depth[:, :-1], 10.0, config=physical, K=K, seed_sequence=_seed())
    with pytest.raises(ValueError, match="depth must be >= 0 metres"):
        render_rain(rgb, np.full_like(depth, np.nan), 10.0, config=physical, K=K, seed_sequence=_seed())
    with pytest.raises(ValueError, match=r"K must be a \(3, 3\) pinhole intrinsics array for the physical model, got None"):
        render_rain(rgb, depth, 10.0, config=physical, K=None, seed_sequence=_seed())
    with pytest.raises(ValueError, match=r"rate_mm_h must be in \[0, 1000\] mm/h, got -1"):
        render_rain(rgb, depth, -1.0, config=RainConfig(), K=K, seed_sequence=_seed())
    with pytest.raises(ValueError, match=r"rate_mm_h must be in \[0, 1000\] mm/h, got nan"):
        render_rain(rgb, depth, float("nan"), config=RainConfig(), K=K, seed_sequence=_seed())
    with pytest.raises(TypeError, match="seed_sequence must be a numpy.random.SeedSequence.*got int"):
        render_rain(rgb, depth, 10.0, config=RainConfig(), K=K, seed_sequence=5)
    with pytest.raises(TypeError, match="config must be a RainConfig, got dict"):
        render_rain(rgb, depth, 10.0, config={}, K=K, seed_sequence=_seed())
    with pytest.raises(TypeError, match="rates must be a sequence of numbers in mm/h, got str"):
        render_rain_sweep(rgb, depth, "0:100:10", config=RainConfig(), K=K, seed_sequence=_seed())


def test_rain_code_does_not_import_mujoco():
    for path in RAIN_DIR.glob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "import mujoco" not in text and "from mujoco" not in text, path.name


def test_one_camera_for_falling_drops_and_lens_water():
    """The defocus of falling drops used f = fx x 3 um = 1.2 mm, the lens water a 2.9 mm lens:
    one default camera now, whose lens at f/2 blurs a point on the glass 3 cm away by about the
    lens water's defocus radius."""
    config = RainConfig(model="physical")
    focal_length_m = 400 * config.pixel_pitch_um * 1e-6  # fx at 800x600, 90 degrees
    assert focal_length_m == pytest.approx(2.9e-3, rel=0.01)
    glass_m = 0.03
    blur_px = (focal_length_m / config.f_number) * 400 / (2 * glass_m)
    assert blur_px == pytest.approx(config.lens_defocus_px, rel=0.05)
    # the same lens at any image size: the pitch is that of the image at 800 px (a fixed pitch
    # made a 1920 px image a 6.9 mm lens, its near drops blurred 2.4x too much)
    near_sigmas = {}
    for width, height in ((320, 240), (800, 600), (1920, 1080), (3840, 2160)):
        K = intrinsics(height, width, 90.0)
        assert K[0, 0] * phys.pixel_pitch_m(config, width) == pytest.approx(focal_length_m)
        near_sigmas[width] = float(phys.defocus_diameter_px(
            np.array([0.5]), focus_distance_m=config.focus_distance_m, focal_length_m=focal_length_m,
            f_number=config.f_number, pixel_pitch_m=phys.pixel_pitch_m(config, width))[0]) / 4
    assert near_sigmas[800] == pytest.approx(0.26, abs=0.01)
    assert near_sigmas[1920] == pytest.approx(near_sigmas[800] * 2.4) and near_sigmas[1920] == pytest.approx(0.62, abs=0.01)
