"""Every numeric RainConfig field has an upper bound (rain.config.RAIN_OPTION_MAX and the older
unit-interval, aspect, slant and airlight bounds), so that no rain option that passes the check
crashes, hangs or warns in the renderer: an audit found `--rain-option exposure_s=1e9` asking for
a 22.9 PiB array, `lens_sweep_speed_m_s=1e300` hanging in `lens_block` and
`sky_distance_m=1e300` overflowing into RuntimeWarnings."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

from cli_errors import cli_status, one_line_error
from rainbench.gen.config import DatasetConfig
from rainbench.rain import physical
from rainbench.rain.config import MAX_LENS_DROPS_AT_REFERENCE, RAIN_OPTION_MAX, RainConfig

GENERATE = ["generate", "--frames", "2", "--width", "160", "--height", "120", "--quiet",
            "--rates", "0,50", "--rain-model", "physical", "--overwrite"]

BOUNDS = [
    # field, largest value accepted, fields it needs beside it, message above the bound
    ("exposure_s", 0.1, {}, "must be a finite number in (0, 0.1]"),
    ("focus_distance_m", 10000.0, {}, "must be a finite number in (0, 10000]"),
    ("f_number", 64.0, {}, "must be a finite number in (0, 64]"),
    ("pixel_pitch_um", 1000.0, {}, "must be a finite number in (0, 1000]"),
    ("wind_slant_deg", 60.0, {}, "must be in [-60, 60] degrees"),
    ("streak_z_near_m", 100.0, {"streak_z_far_m": 1000.0}, "must be a finite number in (0, 100]"),
    ("streak_z_far_m", 1000.0, {}, "must be a finite number in (0, 1000]"),
    ("streak_min_diameter_mm", 10.0, {}, "must be a finite number in (0, 10]"),
    ("max_streak_candidates", 1_000_000, {}, "must be an int in [1, 1000000]"),
    ("sky_distance_m", 10000.0, {}, "must be a finite number in (0, 10000]"),
    ("streak_sky_weight", 1.0, {}, "must be a number in [0, 1]"),
    ("lens_drop_fraction", 1.0, {}, "must be a number in [0, 1]"),
    ("lens_glass_distance_m", 0.5, {}, "must be a finite number in (0, 0.5]"),
    ("lens_sweep_speed_m_s", 100.0, {}, "must be a finite number in (0, 100]"),
    ("lens_min_diameter_mm", 10.0, {}, "must be a finite number in (0, 10]"),
    ("lens_radius_min_px", 100.0, {"lens_radius_max_px": 100.0}, "must be a finite number in (0, 100]"),
    ("lens_radius_max_px", 100.0, {}, "must be a finite number in (0, 100]"),
    ("lens_radius_exponent", 10.0, {}, "must be a finite number in [-10, 10]"),
    ("lens_aspect_min", 1.0, {}, "must be in (0, 1]"),
    ("lens_view_field_px", 8192.0, {}, "must be a finite number in (0, 8192]"),
    ("lens_view_blur_px", 8192.0, {}, "must be a finite number in (0, 8192]"),
    ("lens_rim_darkening", 1.0, {}, "must be a number in [0, 1]"),
    ("lens_defocus_px", 8192.0, {}, "must be a finite number in (0, 8192]"),
    ("lens_opacity", 1.0, {}, "must be a number in [0, 1]"),
    ("lens_life_min_s", 3600.0, {"lens_life_max_s": 3600.0}, "must be a finite number in (0, 3600]"),
    ("lens_life_max_s", 3600.0, {}, "must be a finite number in (0, 3600]"),
    ("lens_fade_s", 1800.0, {"lens_life_min_s": 3600.0, "lens_life_max_s": 3600.0},
     "must be at most half of lens_life_min_s (3600.0 s)"),
    ("lens_slide_fraction", 1.0, {}, "must be a number in [0, 1]"),
    ("lens_slide_max_px_s", 8192.0, {}, "must be a finite number in [0, 8192]"),
]

LOWER_BOUNDS = [  # the fields whose range is also bounded below by something other than 0
    ("wind_slant_deg", -60.0, "must be in [-60, 60] degrees"),
    ("lens_radius_exponent", -10.0, "must be a finite number in [-10, 10]"),
]


def _above(value):
    """The next representable value above ``value`` (the next int for an int)."""
    return value + 1 if isinstance(value, int) else math.nextafter(value, math.inf)


def test_every_numeric_field_has_an_upper_bound():
    numeric = {f.name for f in dataclasses.fields(RainConfig)
               if f.name != "lens_drops" and isinstance(f.default, (int, float))}
    assert {name for name, *_ in BOUNDS} == numeric
    assert set(RAIN_OPTION_MAX) < numeric
    for name, bound, _, _ in BOUNDS:
        if name in RAIN_OPTION_MAX:
            assert RAIN_OPTION_MAX[name] == bound, name
    # the defaults are unchanged and inside their bounds, for both models
    for model in ("jeon2022", "physical"):
        config = RainConfig(model=model)
        for name, bound, _, _ in BOUNDS:
            assert getattr(config, name) <= bound, name


@pytest.mark.parametrize("model", ["jeon2022", "physical"])
@pytest.mark.parametrize("name, bound, beside, message", BOUNDS, ids=[row[0] for row in BOUNDS])
def test_a_value_just_above_its_bound_is_refused_and_the_bound_is_accepted(model, name, bound, beside, message):
    config = RainConfig(model=model, **beside, **{name: bound})
    assert getattr(config, name) == bound
    above = _above(bound)
    with pytest.raises(ValueError, match=r"^RainConfig\." + re.escape(f"{name} {message}") + r".*, got "
                       + re.escape(repr(above)) + "$"):
        RainConfig(model=model, **beside, **{name: above})


@pytest.mark.parametrize("name, bound, message", LOWER_BOUNDS, ids=[row[0] for row in LOWER_BOUNDS])
def test_a_value_just_below_a_negative_bound_is_refused_and_the_bound_is_accepted(name, bound, message):
    assert getattr(RainConfig(**{name: bound}), name) == bound
    below = math.nextafter(bound, -math.inf)
    with pytest.raises(ValueError, match=r"^RainConfig\." + re.escape(f"{name} {message}, got {below!r}") + "$"):
        RainConfig(**{name: below})


def test_the_existing_lower_bound_messages_are_kept():
    with pytest.raises(ValueError, match=r"^RainConfig\.exposure_s must be a finite number > 0, got -1\.0$"):
        RainConfig(exposure_s=-1.0)
    with pytest.raises(ValueError, match=r"^RainConfig\.lens_slide_max_px_s must be a finite number >= 0, got -1\.0$"):
        RainConfig(lens_slide_max_px_s=-1.0)
    with pytest.raises(ValueError, match=r"^RainConfig\.max_streak_candidates must be an int >= 1, got 0$"):
        RainConfig(max_streak_candidates=0)
    with pytest.raises(ValueError, match=r"^RainConfig\.lens_radius_exponent must be a finite number, got inf$"):
        RainConfig(lens_radius_exponent=math.inf)


def test_the_lens_drops_of_the_physical_model_are_bounded_together():
    """Each lens field at its bound alone stays under the cap (the test above); together they
    would put billions of drops on the glass, so the product is capped too."""
    heavy = dict(lens_life_min_s=3600.0, lens_life_max_s=3600.0, lens_sweep_speed_m_s=20.0)
    with pytest.raises(ValueError, match=r"^RainConfig\.lens_sweep_speed_m_s, lens_glass_distance_m, "
                       r"lens_life_min_s, lens_life_max_s, lens_drop_fraction and lens_min_diameter_mm "
                       r"must keep the drops on the glass at 1000 mm/h \(800x600, 90 degrees\) at most "
                       r"1000000, got [0-9]+ \(or set lens_drops=false\)$"):
        RainConfig(model="physical", **heavy)
    # the cap counts what the renderer draws; without physical lens water nothing is drawn
    RainConfig(model="physical", lens_drops=False, **heavy)
    RainConfig(model="jeon2022", **heavy)
    K = np.array([[400.0, 0.0, 400.0], [0.0, 400.0, 300.0], [0.0, 0.0, 1.0]])
    under = RainConfig(model="physical", lens_life_min_s=3600.0, lens_life_max_s=3600.0, lens_sweep_speed_m_s=19.9)
    held = physical.lens_drop_count(1000.0, config=under, K=K, height=600, width=800)
    assert 0.99 * MAX_LENS_DROPS_AT_REFERENCE < held <= MAX_LENS_DROPS_AT_REFERENCE


AUDIT = ["exposure_s=1e9", "streak_z_far_m=1e300", "lens_glass_distance_m=1e300",
         "lens_radius_exponent=1e300", "lens_view_blur_px=1e300", "exposure_s=1e300",
         "lens_defocus_px=1e300", "lens_sweep_speed_m_s=1e300", "lens_life_max_s=1e300",
         "sky_distance_m=1e300", "lens_view_field_px=1e300"]


@pytest.mark.parametrize("option", AUDIT)
def test_an_option_above_its_bound_is_one_line_naming_it_and_no_shard_is_written(tmp_path, capsys, option):
    name, value = option.split("=")
    out = tmp_path / "out"
    code = cli_status([*GENERATE, "--out", out, "--rain-option", option])
    line = one_line_error(capsys, code, r"rain_options: RainConfig\." + name + r" must be a finite number in "
                          r"[(\[][-0-9.]+, [0-9.]+\], got " + re.escape(repr(float(value))))
    assert line.startswith("rainbench: error: ") and name in line
    assert not out.exists() or not any(out.iterdir())
    with pytest.raises(ValueError, match=r"^rain_options: RainConfig\." + name):
        DatasetConfig(rain_model="physical", rain_options={name: float(value)})
