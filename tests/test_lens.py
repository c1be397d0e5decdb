"""Lens water (rainbench.rain.lens): persistence and sliding over a clip, nesting, exactness,
determinism, the defocused drawing, and the SSIM calibration on the paper's clip."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rainbench import rain
from rainbench.rain import LensClock, RainConfig, image_quality, render_rain, render_rain_sweep, sample_drops
from rainbench.rain import lens as lens_mod
from rainbench.rain import physical
from testframe import street_frame

RATES = tuple(float(rate) for rate in range(0, 101, 10))
CLIP = np.random.SeedSequence([3, 14])


def _clock(frame: int, fps: float = 10.0) -> LensClock:
    return LensClock(CLIP, frame, fps)


@pytest.fixture(scope="module")
def frame_320():
    """(rgb (240, 320, 3), depth, K) street scene."""
    return street_frame(np.random.default_rng(21), 240, 320)


def _assert_frames_equal(first, second) -> None:
    np.testing.assert_array_equal(first.rgb, second.rgb)
    np.testing.assert_array_equal(first.coverage, second.coverage)
    assert first.drop_count == second.drop_count


# --------------------------------------------------------------------------------------------
# persistence and motion


def test_drops_persist_and_move_at_most_the_documented_distance():
    config = RainConfig()
    height, width = 600, 800
    count = lens_mod.jeon2022_drop_count(100.0, height, width)
    limit = lens_mod.max_slide_px_per_frame(config, height, width, 10.0)
    assert limit == pytest.approx(3.0)  # 30 px/s at 10 frames/s
    moved_total, renewed_total, pairs = 0, 0, 0
    for frame in (0, 1, 57, 58, 199, 1000):
        now = lens_mod.sample_lens_drops(count, config=config, height=height, width=width, lens_clock=_clock(frame))
        then = lens_mod.sample_lens_drops(count, config=config, height=height, width=width, lens_clock=_clock(frame + 1))
        same = now.generation == then.generation
        # a drop present in frame i is present in frame i + 1 (same slot, same drop), the same
        # size and shape, moved by at most the documented distance
        step = np.hypot(then.x_px - now.x_px, then.y_px - now.y_px)[same]
        assert step.max() <= limit + 1e-9
        for name in ("radius_px", "aspect", "cos_angle", "sin_angle"):
            np.testing.assert_array_equal(getattr(now, name)[same], getattr(then, name)[same])
        # a replaced drop had faded out: its strength in frame i was small
        assert np.all(now.strength[~same] < 0.6)
        assert np.all(then.generation[~same] == now.generation[~same] + 1)
        moved_total += int(np.count_nonzero(step > 0))
        renewed_total += int(np.count_nonzero(~same))
        pairs += count
    # lives of 4-12 s: about 1.4 % of the drops are replaced per frame at 10 frames/s
    assert 0.005 < renewed_total / pairs < 0.03
    assert moved_total > 0.05 * pairs  # some drops slide, most do not
    assert moved_total < 0.6 * pairs


def test_rendered_water_persists_between_consecutive_frames(frame_320):
    rgb, _, _ = frame_320
    coverage = [render_rain(rgb, None, 50.0, config=RainConfig(), K=None, seed_sequence=np.random.SeedSequence([1, f]), lens_clock=_clock(f)).coverage for f in (40, 41, 140)]
    next_frame = np.corrcoef(coverage[0].ravel(), coverage[1].ravel())[0, 1]
    ten_seconds = np.corrcoef(coverage[0].ravel(), coverage[2].ravel())[0, 1]
    assert next_frame > 0.9 > ten_seconds + 0.3


def test_time_not_frame_index_places_the_drops():
    config = RainConfig()
    a = lens_mod.sample_lens_drops(700, config=config, height=300, width=400, lens_clock=_clock(30, 10.0))
    b = lens_mod.sample_lens_drops(700, config=config, height=300, width=400, lens_clock=_clock(90, 30.0))
    np.testing.assert_array_equal(a.as_array(), b.as_array())  # both at t = 3 s


def test_lens_clock_validation_and_default():
    with pytest.raises(ValueError, match="LensClock.frame must be an int >= 0"):
        LensClock(CLIP, -1)
    with pytest.raises(ValueError, match="LensClock.fps must be a finite number > 0"):
        LensClock(CLIP, 0, 0.0)
    with pytest.raises(TypeError, match="seed_sequence must be a numpy.random.SeedSequence"):
        LensClock(7, 0)
    assert LensClock(CLIP, np.int64(5)).frame == 5 and LensClock(CLIP, 5).time_s == 0.5
    rgb = np.full((48, 64, 3), 120, np.uint8)
    rgb[:, 32:] = 30
    seeds = np.random.SeedSequence([5, 6, 7])
    default = render_rain(rgb, None, 80.0, config=RainConfig(), K=None, seed_sequence=seeds)
    explicit = render_rain(rgb, None, 80.0, config=RainConfig(), K=None, seed_sequence=seeds, lens_clock=LensClock(seeds, 0, 10.0))
    _assert_frames_equal(default, explicit)  # no clock: frame 0 of a clip seeded by seed_sequence
    with pytest.raises(TypeError, match="lens_clock must be a LensClock or None, got int"):
        render_rain(rgb, None, 80.0, config=RainConfig(), K=None, seed_sequence=seeds, lens_clock=3)


# --------------------------------------------------------------------------------------------
# nesting, exactness, determinism


@pytest.mark.parametrize("model", rain.RAIN_MODELS)
def test_nesting_across_rates_at_any_frame(model, frame_320):
    rgb, _, K = frame_320
    config = RainConfig(model=model)
    for frame in (0, 73):
        drops = [sample_drops(rate, config=config, K=K, shape=rgb.shape, seed_sequence=np.random.SeedSequence([2, frame]), lens_clock=_clock(frame)).lens for rate in RATES]
        for lower, higher in zip(drops, drops[1:]):
            assert len(lower) <= len(higher)
            np.testing.assert_array_equal(lower.as_array(), higher.as_array()[: len(lower)])
        top_count = lens_mod.jeon2022_drop_count(100.0, 240, 320) if model == "jeon2022" else physical.lens_drop_count(100.0, config=config, K=K, height=240, width=320)
        assert len(drops[-1]) == top_count > 0


@pytest.mark.parametrize(
    "config",
    [RainConfig(), RainConfig(model="physical"), RainConfig(lens_life_min_s=0.5, lens_life_max_s=1.0, lens_slide_fraction=1.0, lens_slide_max_px_s=200.0)],
    ids=["jeon2022", "physical-lens", "jeon2022-fast-lens"],
)
def test_sweep_equals_single_rate_byte_for_byte(config, frame_320):
    rgb, depth, K = frame_320
    seeds = np.random.SeedSequence([9, 9, 46])
    clock = _clock(46)
    full = render_rain_sweep(rgb, depth, RATES, config=config, K=K, seed_sequence=seeds, lens_clock=clock)
    for rate, frame in zip(RATES, full):
        _assert_frames_equal(render_rain(rgb, depth, rate, config=config, K=K, seed_sequence=seeds, lens_clock=clock), frame)
    subset = render_rain_sweep(rgb, depth, [90.0, 10.0, 55.0], config=config, K=K, seed_sequence=seeds, lens_clock=clock)
    _assert_frames_equal(subset[0], full[RATES.index(90.0)])
    _assert_frames_equal(subset[1], full[RATES.index(10.0)])
    # water only grows with the rate: every pixel wet at a lower rate is at least as wet higher up
    for lower, higher in zip(full[1:], full[2:]):
        assert np.all(higher.coverage >= lower.coverage - 1e-6) or config.model == "physical"


def test_lens_water_is_deterministic_and_leaves_inputs_alone(frame_320):
    rgb, _, _ = frame_320
    before = rgb.copy()
    seeds = np.random.SeedSequence([4, 4])
    first = render_rain(rgb, None, 60.0, config=RainConfig(), K=None, seed_sequence=seeds, lens_clock=_clock(12))
    second = render_rain(rgb, None, 60.0, config=RainConfig(), K=None, seed_sequence=np.random.SeedSequence([4, 4]), lens_clock=LensClock(np.random.SeedSequence([3, 14]), 12, 10.0))
    _assert_frames_equal(first, second)
    np.testing.assert_array_equal(rgb, before)
    assert CLIP.n_children_spawned == 0 and seeds.n_children_spawned == 0
    # jeon2022 lens water depends on the clip and the time, not on the frame's seed sequence
    other_seed = render_rain(rgb, None, 60.0, config=RainConfig(), K=None, seed_sequence=np.random.SeedSequence([8]), lens_clock=_clock(12))
    _assert_frames_equal(first, other_seed)
    other_clip = render_rain(rgb, None, 60.0, config=RainConfig(), K=None, seed_sequence=seeds, lens_clock=LensClock(np.random.SeedSequence([3, 15]), 12))
    assert not np.array_equal(first.rgb, other_clip.rgb)


def test_hash_uniforms_are_uniform_and_independent():
    key = _clock(0).key()
    slots = np.arange(20000, dtype=np.uint64)
    u = lens_mod.hash_uniforms(key, slots, np.zeros(20000, dtype=np.uint64), 3)
    assert u.min() >= 0.0 and u.max() < 1.0
    assert np.allclose(u.mean(axis=0), 0.5, atol=0.01)
    assert abs(np.corrcoef(u[:, 0], u[:, 1])[0, 1]) < 0.03
    later = lens_mod.hash_uniforms(key, slots, np.ones(20000, dtype=np.uint64), 3)
    assert abs(np.corrcoef(u[:, 0], later[:, 0])[0, 1]) < 0.03


# --------------------------------------------------------------------------------------------
# drawing


def _draw(image: np.ndarray, drop: lens_mod.LensDrops, config: RainConfig):
    height, width = image.shape[:2]
    raster = lens_mod.rasterize_lens_drops(drop, config=config, height=height, width=width)
    sums = lens_mod.LensSums.zeros(raster.view_height, raster.view_width, raster.factor)
    sums.add(raster, lens_mod.planar_view(lens_mod.lens_view(image, config)))
    return lens_mod.apply_lens(image, sums)


def test_a_large_drop_shows_a_flipped_view_with_a_soft_darker_edge():
    height, width = 120, 160
    scale = lens_mod.image_scale(height, width)
    config = RainConfig(lens_view_blur_px=1.0 / scale, lens_defocus_px=2.0 / scale, lens_view_field_px=24.0 / scale, lens_rim_darkening=0.4)
    assert lens_mod.lens_grid_factor(config, height, width) == 1
    # top half white (sky), bottom half black (road); a drop on the horizon sees it upside down
    image = np.zeros((height, width, 3), dtype=np.uint8)
    image[: height // 2] = 255
    out, coverage = _draw(image, lens_mod.single_lens_drop(80.0, 60.0, 16.0), config)
    assert out[52, 80].mean() < 60  # above the centre, inside the drop: the dark road
    assert out[68, 80].mean() > 190  # below the centre: the bright sky
    assert coverage[60, 80] == 1.0 and coverage[60, 10] == 0.0
    np.testing.assert_array_equal(out[:, :40], image[:, :40])  # away from water: exact
    # a defocused edge: coverage falls from 1 to 0 over about 2 b = 4 px, not in one step
    profile = coverage[60, 80:110]
    ramp = np.flatnonzero((profile > 0.02) & (profile < 0.98))
    assert 3 <= ramp.shape[0] <= 6
    # uniform grey: the centre keeps the grey, the edge is darker
    grey = np.full((height, width, 3), 200, dtype=np.uint8)
    out_grey, _ = _draw(grey, lens_mod.single_lens_drop(80.0, 60.0, 16.0), config)
    assert int(out_grey[60, 80, 0]) == 200
    assert int(out_grey[60, 95, 0]) < 190


def test_a_drop_smaller_than_the_defocus_blur_is_semi_transparent():
    height, width = 120, 160
    scale = lens_mod.image_scale(height, width)
    config = RainConfig(lens_defocus_px=8.0 / scale)
    image = np.full((height, width, 3), 100, dtype=np.uint8)
    image[:, ::2] = 200  # texture that an opaque drop would hide
    _, small = _draw(image, lens_mod.single_lens_drop(80.0, 60.0, 2.0), config)
    _, large = _draw(image, lens_mod.single_lens_drop(80.0, 60.0, 20.0), config)
    assert small.max() == pytest.approx((2.0 / 8.0) ** 2, abs=0.03)  # (r / b)^2 of the blur disc
    assert large.max() == 1.0
    # the footprint of the small drop reaches r + b, far beyond its own radius
    assert np.count_nonzero(small > 0) > 10 * np.pi * 2.0**2


def test_drop_sizes_and_fading_follow_the_config():
    config = RainConfig()
    drops = lens_mod.sample_lens_drops(3204, config=config, height=600, width=800, lens_clock=_clock(123))
    assert drops.radius_px.min() >= config.lens_radius_min_px and drops.radius_px.max() <= config.lens_radius_max_px
    assert np.all((drops.strength >= 0) & (drops.strength <= 1))
    assert np.mean(drops.strength == 1.0) > 0.9  # only drops landing or leaving are faded
    # half the drops are 3-4.3 px (p(r) ~ r^-3), the footprint with the 10 px blur is 13-35 px
    assert 3.8 < np.median(drops.radius_px) < 4.8
    no_fade = dataclasses.replace(config, lens_fade_s=0.0)
    assert np.all(lens_mod.sample_lens_drops(100, config=no_fade, height=600, width=800, lens_clock=_clock(5)).strength == 1.0)


def test_lens_config_validation():
    with pytest.raises(ValueError, match=r"RainConfig.lens_opacity must be a number in \[0, 1\]"):
        RainConfig(lens_opacity=1.5)
    with pytest.raises(ValueError, match="lens_life_max_s must be >= lens_life_min_s"):
        RainConfig(lens_life_min_s=5.0, lens_life_max_s=4.0)
    with pytest.raises(ValueError, match="lens_fade_s must be at most half of lens_life_min_s"):
        RainConfig(lens_fade_s=3.0)
    with pytest.raises(ValueError, match="lens_slide_max_px_s must be a finite number >= 0"):
        RainConfig(lens_slide_max_px_s=-1.0)
    assert RainConfig(model="physical").lens_drops  # lens water is on by default in physical
    assert RainConfig.from_dict(RainConfig().to_dict()) == RainConfig()


def test_physical_lens_drop_fraction_takes_the_first_slots(frame_320):
    rgb, _, K = frame_320
    full = sample_drops(100.0, config=RainConfig(model="physical"), K=K, shape=rgb.shape, seed_sequence=CLIP, lens_clock=_clock(8)).lens
    half = sample_drops(100.0, config=RainConfig(model="physical", lens_drop_fraction=0.5), K=K, shape=rgb.shape, seed_sequence=CLIP, lens_clock=_clock(8)).lens
    jeon = sample_drops(100.0, config=RainConfig(), K=K, shape=rgb.shape, seed_sequence=CLIP, lens_clock=_clock(8)).lens
    expected = physical.lens_drop_count(100.0, config=RainConfig(model="physical"), K=K, height=rgb.shape[0], width=rgb.shape[1])
    assert 0 < len(full) == expected < len(jeon)
    np.testing.assert_array_equal(full.as_array(), jeon.as_array()[: len(full)])  # jeon2022's first slots
    assert len(half) == int(np.floor(expected * 0.5 + 0.5))  # half up, as the count
    np.testing.assert_array_equal(half.as_array(), full.as_array()[: len(half)])
    none = sample_drops(100.0, config=RainConfig(model="physical", lens_drops=False), K=K, shape=rgb.shape, seed_sequence=CLIP, lens_clock=_clock(8)).lens
    assert len(none) == 0


def test_physical_lens_count_is_the_flux_onto_the_glass_over_a_drop_life():
    # 90 degrees across 800x600 (fx = fy = 400): the glass 3 cm ahead shows 6 x 4.5 cm
    K = np.array([[400.0, 0.0, 400.0], [0.0, 400.0, 300.0], [0.0, 0.0, 1.0]])
    config = RainConfig(model="physical")
    slope = 4.1 * 100.0**-0.21  # Marshall-Palmer Lambda at 100 mm/h, per mm
    per_m3 = 8000.0 / slope * np.exp(-slope * 0.5)  # drops of D >= 0.5 mm
    expected = per_m3 * 10.0 * (0.06 * 0.045) * 8.0  # x 10 m/s x glass area x mean life (4..12 s)
    assert physical.lens_drop_count(100.0, config=config, K=K, height=600, width=800) == round(expected) == 508
    counts = [physical.lens_drop_count(rate, config=config, K=K, height=600, width=800) for rate in (0.0, 1.0, 10.0, 50.0, 100.0)]
    assert counts[0] == 0 and counts == sorted(counts)
    assert counts[2] == 193  # about eq. 5's 204 in light rain, a sixth of its 3204 at 100 mm/h
    # the same field of view at half the resolution sees the same glass, so the same drops
    assert physical.lens_drop_count(100.0, config=config, K=K / np.array([[2.0], [2.0], [1.0]]), height=300, width=400) == 508
    faster = RainConfig(model="physical", lens_sweep_speed_m_s=20.0, lens_glass_distance_m=0.015)
    assert physical.lens_drop_count(100.0, config=faster, K=K, height=600, width=800) == round(expected * 2.0 / 4.0)
    with pytest.raises(ValueError, match=r"RainConfig.lens_sweep_speed_m_s must be a finite number > 0"):
        RainConfig(model="physical", lens_sweep_speed_m_s=0.0)


def test_physical_lens_water_leaves_the_downpour_seen_through_the_lens():
    """At 100 mm/h the glass's drops cover (opacity > 0.5) under 15 % of an 800x600 frame (6.6 %
    here); eq. 5's count, which the physical model took before, covers over 40 % (54 %)."""
    rgb, depth, K = street_frame(np.random.default_rng(21), 600, 800)
    covered = {}
    for model in ("physical", "jeon2022"):
        frame = render_rain(rgb, depth, 100.0, config=RainConfig(model=model), K=K, seed_sequence=CLIP, lens_clock=_clock(80))
        covered[model] = float((frame.coverage > 0.5).mean())
    assert 0.02 < covered["physical"] < 0.15 < 0.40 < covered["jeon2022"], covered


# --------------------------------------------------------------------------------------------
# calibration on the paper's clip (docs/rain.md, "Calibration")


PAPER_FRAMES = (20, 70, 120, 170)


@pytest.fixture(scope="module")
def paper_frames():
    """Four clean 800x600 frames of the paper's default clip (seed 0, 200 frames), with K."""
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import build_scene, render_clip

    setup = build_scene(GenerateConfig(frames=1, clip_frames=200))
    frames = {}
    for index in PAPER_FRAMES:
        for _, frame, renderer in render_clip(GenerateConfig(frames=1, frame_offset=index, clip_frames=200), setup):
            frames[index] = (frame.rgb, renderer.K)
    return frames


def test_jeon2022_ssim_at_20_mm_h_on_the_paper_clip(paper_frames):
    ssim, psnr = [], []
    for index, (rgb, K) in paper_frames.items():
        # seeded as the generator seeds frame `index` of scene 0 with rain seed 0
        rainy = render_rain(rgb, None, 20.0, config=RainConfig(), K=K, seed_sequence=np.random.SeedSequence([0, 0, index]),
                            lens_clock=LensClock(np.random.SeedSequence([0, 0]), index, 10.0))
        s, p = image_quality(rgb, rainy.rgb)
        ssim.append(s)
        psnr.append(p)
    assert 0.950 <= float(np.mean(ssim)) <= 0.975, ssim
    assert 24.0 < float(np.mean(psnr)) < 35.0, psnr


# --------------------------------------------------------------------------------------------
# bounded memory: lens drops rasterised in runs


def test_stencil_size_and_entry_bound_hold_for_every_drop():
    for half_size in (*range(0, 70), 150):
        assert lens_mod._stencil_size(half_size) == lens_mod._build_stencil(half_size)[0].shape[0]
    # drops of every size, some partly or wholly off the image: the bound is never exceeded
    config = RainConfig(lens_radius_min_px=0.5, lens_radius_max_px=60.0, lens_radius_exponent=1.0, lens_defocus_px=3.0)
    height, width = 90, 130
    drops = lens_mod.sample_lens_drops(400, config=config, height=height, width=width, lens_clock=_clock(5))
    rng = np.random.default_rng(4)
    drops = dataclasses.replace(drops, x_px=rng.uniform(-80.0, width + 80.0, 400), y_px=rng.uniform(-80.0, height + 80.0, 400))
    bound = lens_mod.lens_entry_bound(drops, config=config, height=height, width=width)
    raster = lens_mod.rasterize_lens_drops(drops, config=config, height=height, width=width)
    entries = np.bincount(raster.drop, minlength=400)
    assert np.all(entries <= bound)
    assert entries.max() > 0.5 * bound[entries.argmax()]  # tight enough to mean something
    assert lens_mod.lens_entry_bound(lens_mod.empty_lens_drops(), config=config, height=height, width=width).shape == (0,)


def test_drop_chunks_are_consecutive_and_within_the_budget():
    bounds = np.array([5, 1, 9, 2, 2, 30, 1, 1, 0, 4], dtype=np.int64)
    chunks = lens_mod.lens_drop_chunks(bounds, 10)
    assert chunks == [(0, 2), (2, 3), (3, 5), (5, 6), (6, 10)]  # 30 > 10 is a run alone
    assert lens_mod.lens_drop_chunks(bounds, 1000) == [(0, 10)]
    assert lens_mod.lens_drop_chunks(np.zeros(0, dtype=np.int64), 10) == []
    with pytest.raises(ValueError, match="budget must be >= 1 entry, got 0"):
        lens_mod.lens_drop_chunks(bounds, 0)


@pytest.mark.parametrize("model", rain.RAIN_MODELS)
def test_drops_drawn_in_runs_give_the_same_bytes(model, frame_320, monkeypatch):
    from rainbench.rain import render as render_mod

    rgb, depth, K = frame_320
    config = RainConfig(model=model, lens_glass_distance_m=0.1)  # physical: a few hundred lens drops
    seeds = np.random.SeedSequence([9, 9, 46])
    scenes = [np.ascontiguousarray(np.roll(rgb, 7 * index, axis=1)) for index in range(len(RATES))]
    whole = render_rain_sweep(rgb, depth, RATES, config=config, K=K, seed_sequence=seeds, lens_clock=_clock(46))
    over_scenes = render_rain_sweep(rgb, depth, RATES, config=config, K=K, seed_sequence=seeds, lens_clock=_clock(46), scenes=scenes)
    drawn: list[int] = []
    rasterize = lens_mod.rasterize_lens_drops

    def counting(drops, **kwargs):
        drawn.append(int(lens_mod.lens_entry_bound(drops, **kwargs).sum()))
        return rasterize(drops, **kwargs)

    monkeypatch.setattr(lens_mod, "rasterize_lens_drops", counting)
    monkeypatch.setattr(render_mod, "LENS_RASTER_BUDGET", 3000)
    monkeypatch.setattr(render_mod, "LENS_RASTER_KEEP", 2000)  # keeps the first runs only
    for split, reference in ((render_rain_sweep(rgb, depth, RATES, config=config, K=K, seed_sequence=seeds, lens_clock=_clock(46)), whole),
                             (render_rain_sweep(rgb, depth, RATES, config=config, K=K, seed_sequence=seeds, lens_clock=_clock(46), scenes=scenes), over_scenes)):
        for first, second in zip(split, reference):
            _assert_frames_equal(first, second)
    assert len(drawn) > 10 and max(drawn) <= 3000


def test_lens_water_memory_is_bounded_whatever_the_drop_size():
    """Large lens drops on a 1024 x 1024 image at 100 mm/h: 7 000 drops of 148 px, 12 million
    raster entries; drawn at once they took 2.4 GB, in runs about 0.4 GB."""
    import tracemalloc

    config = RainConfig(lens_radius_min_px=100.0, lens_radius_max_px=100.0)
    rgb = np.random.default_rng(0).integers(0, 256, (1024, 1024, 3), dtype=np.uint8)
    tracemalloc.start()
    try:
        frames = render_rain_sweep(rgb, None, [50.0, 100.0], config=config, K=None, seed_sequence=np.random.SeedSequence(3), lens_clock=_clock(5))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert frames[1].drop_count == 6999 and frames[1].coverage.mean() > 0.9
    assert peak < 0.8e9, f"lens water took {peak / 1e9:.2f} GB"
