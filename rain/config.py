"""Rain configuration: which model, and every parameter of the drawing with its default.

Every default is explained in docs/rain.md. Lengths marked "px @800x600" are given for an
800x600 image and scale with ``sqrt(H * W / (800 * 600))`` for other sizes.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

RAIN_MODELS = ("jeon2022", "physical")
"""Available rain models; ``jeon2022`` (the seed paper's eq. 5 with lens water) is the default."""

RAIN_OPTION_MAX: dict[str, float] = {
    # physical model: camera
    "exposure_s": 0.1,  # 3x the longest auto-exposure (1/30 s at night), the frame time at 10 fps
    "focus_distance_m": 10_000.0,  # 10 km: far past the hyperfocal distance, i.e. infinity
    "f_number": 64.0,  # the smallest apertures made (large-format lenses)
    "pixel_pitch_um": 1000.0,  # 1 mm: far past any sensor (1-25 um); tests use 600 um for blur
    # physical model: drops drawn as streaks
    "streak_z_near_m": 100.0,  # a 5 mm drop at 100 m is ~1 px even at the narrowest view
    "streak_z_far_m": 1000.0,  # a drop at 1 km is sub-pixel at any view; extinction does the rest
    "streak_min_diameter_mm": 10.0,  # rain drops break up above ~8 mm
    "max_streak_candidates": 1_000_000,  # 120 MB of candidates; 1.0 GB peak at 800x600
    # physical model: extinction
    "sky_distance_m": 10_000.0,  # 10 km: above any rain cloud's base
    # physical model: lens water
    "lens_glass_distance_m": 0.5,  # a windscreen or housing window, not a glass metres away
    "lens_sweep_speed_m_s": 100.0,  # 360 km/h, faster than any road vehicle
    "lens_min_diameter_mm": 10.0,  # rain drops break up above ~8 mm
    # lens water (px @800x600, seconds)
    "lens_radius_min_px": 100.0,  # D = 15 mm at 3 cm: twice the largest adherent drops (8 mm)
    "lens_radius_max_px": 100.0,
    "lens_radius_exponent": 10.0,  # and >= -10: p(r) ~ r^-10 is already all r_min
    "lens_view_field_px": 8192.0,  # the largest image side
    "lens_view_blur_px": 8192.0,
    "lens_defocus_px": 8192.0,
    "lens_life_min_s": 3600.0,  # an hour
    "lens_life_max_s": 3600.0,
    "lens_slide_max_px_s": 8192.0,  # the largest image side in a second
}
"""Upper bound of every numeric :class:`RainConfig` field that has no other (the unit-interval
fields, ``lens_aspect_min``, ``wind_slant_deg`` and ``airlight_rgb`` keep theirs;
``lens_fade_s`` is at most half of ``lens_life_min_s``, so at most 1800 s). Far beyond any
sensible value, they keep the renderer's arrays and loops bounded (docs/rain.md, "Parameters")."""

MAX_LENS_DROPS_AT_REFERENCE = 1_000_000
"""Most drops the physical model's cover glass may hold at 1000 mm/h in the reference view
(800x600, fx = fy = 400 px, i.e. 90 degrees): ``physical.lens_drop_count`` grows with the product
of lens_drop_fraction, lens_sweep_speed_m_s, lens_glass_distance_m^2 and the mean lens life, which
the per-field bounds alone leave at up to ~2 billion drops (measured at 800x600: 1 000 000
default-size drops draw in 9 s with a 3.1 GB peak; larger drops cost more per drop)."""


def _bound(value: float) -> str:
    """A bound as the message shows it: ``10000``, ``0.1``, ``-10``."""
    return str(int(value)) if float(value).is_integer() else repr(value)


@dataclasses.dataclass(frozen=True)
class RainConfig:
    """All parameters of rain rendering. Frozen; build a new one with ``dataclasses.replace``.

    Attributes (units in the names; defaults in docs/rain.md, section "Parameters"):
        model: one of :data:`RAIN_MODELS`.

        exposure_s: camera exposure time T in seconds (physical model: streak length).
        focus_distance_m: focus distance of the thin-lens camera in metres (defocus of drops).
        f_number: aperture f-number N (defocus of drops).
        pixel_pitch_um: pixel pitch of the image resized to 800 px wide, in micrometres (at W
            px it is ``pixel_pitch_um * 800 / W``); with fx it fixes the focal length in metres
            ``f = fx * pitch`` used by the defocus formula, the same at every image size. The
            default 7.2 um is the lens-water camera's (docs/rain.md): 1920 sensor pixels of 3 um
            resized to 800 px, so f = 400 px x 7.2 um = 2.9 mm at 90 degrees (at 1920 px: 3 um
            pixels, the sensor's own).
        wind_slant_deg: angle of the streaks from the image vertical, degrees, positive = the
            drop drifts towards +x (right) while falling.
        streak_z_near_m, streak_z_far_m: depth range (metres along the optical axis) in which
            falling drops are drawn as streaks; drops beyond are accounted by the extinction.
        streak_min_diameter_mm: smallest drop diameter drawn as a streak (Marshall-Palmer D_min).
        max_streak_candidates: bound on the expected number of candidate drops sampled at the
            maximum rate (1000 mm/h); if the frustum volume would exceed it, the far end of the
            streak range is pulled in (depends only on K and the image size, never on the rate).
        sky_distance_m: path length in metres assigned to sky pixels (depth +inf) for the
            extinction, i.e. a cloud base; sky fades continuously towards the airlight.
        airlight_rgb: airlight colour A (R, G, B in 0..255); None estimates it from the frame
            (mean sky colour, else mean colour of the farthest 1 % of pixels).
        streak_sky_weight: a streak's radiance is this share of the sky's (airlight) colour plus
            the rest of the frame's mean colour: a falling drop refracts a ~165 degree view,
            mostly of the sky (Garg & Nayar), so streaks show bright over dark surfaces.
        lens_drops: physical model only: also draw water on the lens (the jeon2022 lens water,
            on top of the streaks and extinction). On by default.
        lens_drop_fraction: physical model with lens_drops: lens drop count = this fraction of the
            count of drops that land on the cover glass (``physical.lens_drop_count``); they take
            the first slots of the same lens, so they are a subset of jeon2022's drops.
        lens_glass_distance_m: physical model: distance u of the cover glass in front of the lens
            (the glass area the camera sees is u^2 (W / fx) (H / fy)).
        lens_sweep_speed_m_s: physical model: speed at which the forward-facing cover glass
            meets the rain (the car's speed; the hood keeps the vertical fall off the glass).
        lens_min_diameter_mm: physical model: smallest falling drop counted on the glass.

        lens_radius_min_px, lens_radius_max_px: lens-drop radius range on the glass, px @800x600.
        lens_radius_exponent: lens-drop radii follow a truncated power law p(r) ~ r^-exponent.
        lens_aspect_min: lens drops are ellipses with minor/major axis ratio in [aspect_min, 1].
        lens_view_field_px: a lens drop shows the scene within this radius of its centre
            (px @800x600), point-reflected (flipped) and minified into the drop.
        lens_view_blur_px: blur of the view through a lens drop, px @800x600: the Gaussian
            sigma applied to the frame area-averaged to the drawing grid (whose cells are
            ``lens_defocus_px / 2`` wide).
        lens_rim_darkening: fractional darkening at the rim of a lens drop (0 = none).
        lens_defocus_px: radius of the defocus blur of a drop on the glass, px @800x600.
        lens_opacity: opacity of a drop larger than the defocus blur, in (0, 1].
        lens_life_min_s, lens_life_max_s: range of the life of a drop on the glass, seconds
            (each lens slot has its own life; its drop is replaced when the life ends).
        lens_fade_s: a drop fades in after landing and out before it is replaced over this time.
        lens_slide_fraction: fraction of drops that depin during their life and slide.
        lens_slide_max_px_s: largest sliding speed, px per second @800x600.
    """

    model: str = "jeon2022"

    # physical model: camera
    exposure_s: float = 0.004
    focus_distance_m: float = 5.0
    f_number: float = 2.0
    pixel_pitch_um: float = 7.2
    wind_slant_deg: float = 0.0
    # physical model: drops drawn as streaks
    streak_z_near_m: float = 0.5
    streak_z_far_m: float = 2.0
    streak_min_diameter_mm: float = 0.5
    max_streak_candidates: int = 60000
    # physical model: extinction and airlight
    sky_distance_m: float = 1000.0
    airlight_rgb: tuple[float, float, float] | None = None
    streak_sky_weight: float = 0.6
    # physical model: lens water (on by default)
    lens_drops: bool = True
    lens_drop_fraction: float = 1.0
    lens_glass_distance_m: float = 0.03
    lens_sweep_speed_m_s: float = 10.0
    lens_min_diameter_mm: float = 0.5

    # lens water (jeon2022, and physical with lens_drops); docs/rain.md, "Lens water"
    lens_radius_min_px: float = 3.0
    lens_radius_max_px: float = 25.0
    lens_radius_exponent: float = 3.0
    lens_aspect_min: float = 0.7
    lens_view_field_px: float = 120.0
    lens_view_blur_px: float = 30.0
    lens_rim_darkening: float = 0.2
    lens_defocus_px: float = 10.0
    lens_opacity: float = 1.0
    lens_life_min_s: float = 4.0
    lens_life_max_s: float = 12.0
    lens_fade_s: float = 0.2
    lens_slide_fraction: float = 0.5
    lens_slide_max_px_s: float = 30.0

    def __post_init__(self) -> None:
        if self.model not in RAIN_MODELS:
            raise ValueError(f"RainConfig.model must be one of {RAIN_MODELS}, got {self.model!r}")
        positive = (
            "exposure_s",
            "focus_distance_m",
            "f_number",
            "pixel_pitch_um",
            "streak_z_near_m",
            "streak_z_far_m",
            "streak_min_diameter_mm",
            "sky_distance_m",
            "lens_radius_min_px",
            "lens_radius_max_px",
            "lens_view_field_px",
            "lens_view_blur_px",
            "lens_defocus_px",
            "lens_opacity",
            "lens_life_min_s",
            "lens_life_max_s",
            "lens_glass_distance_m",
            "lens_sweep_speed_m_s",
            "lens_min_diameter_mm",
        )
        for name in positive:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"RainConfig.{name} must be a finite number > 0, got {value!r}")
            if name in RAIN_OPTION_MAX and value > RAIN_OPTION_MAX[name]:
                raise ValueError(f"RainConfig.{name} must be a finite number in (0, {_bound(RAIN_OPTION_MAX[name])}], got {value!r}")
        unit_interval = ("lens_rim_darkening", "lens_drop_fraction", "lens_opacity", "lens_slide_fraction", "streak_sky_weight")
        for name in unit_interval:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise ValueError(f"RainConfig.{name} must be a number in [0, 1], got {value!r}")
        for name in ("lens_fade_s", "lens_slide_max_px_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"RainConfig.{name} must be a finite number >= 0, got {value!r}")
            if name in RAIN_OPTION_MAX and value > RAIN_OPTION_MAX[name]:
                raise ValueError(f"RainConfig.{name} must be a finite number in [0, {_bound(RAIN_OPTION_MAX[name])}], got {value!r}")
        if self.lens_life_max_s < self.lens_life_min_s:
            raise ValueError(
                f"RainConfig.lens_life_max_s must be >= lens_life_min_s, got min {self.lens_life_min_s!r} and max {self.lens_life_max_s!r}"
            )
        if 2.0 * self.lens_fade_s > self.lens_life_min_s:
            raise ValueError(f"RainConfig.lens_fade_s must be at most half of lens_life_min_s ({self.lens_life_min_s!r} s), got {self.lens_fade_s!r}")
        if not isinstance(self.lens_aspect_min, (int, float)) or not 0.0 < self.lens_aspect_min <= 1.0:
            raise ValueError(f"RainConfig.lens_aspect_min must be in (0, 1], got {self.lens_aspect_min!r}")
        if not isinstance(self.lens_radius_exponent, (int, float)) or not math.isfinite(self.lens_radius_exponent):
            raise ValueError(f"RainConfig.lens_radius_exponent must be a finite number, got {self.lens_radius_exponent!r}")
        exponent_max = RAIN_OPTION_MAX["lens_radius_exponent"]
        if not -exponent_max <= self.lens_radius_exponent <= exponent_max:
            raise ValueError(f"RainConfig.lens_radius_exponent must be a finite number in [{_bound(-exponent_max)}, {_bound(exponent_max)}], got {self.lens_radius_exponent!r}")
        if not isinstance(self.wind_slant_deg, (int, float)) or not -60.0 <= self.wind_slant_deg <= 60.0:
            raise ValueError(f"RainConfig.wind_slant_deg must be in [-60, 60] degrees, got {self.wind_slant_deg!r}")
        if self.streak_z_far_m <= self.streak_z_near_m:
            raise ValueError(
                f"RainConfig.streak_z_far_m must exceed streak_z_near_m, got near {self.streak_z_near_m!r} m and far {self.streak_z_far_m!r} m"
            )
        if self.lens_radius_max_px < self.lens_radius_min_px:
            raise ValueError(
                f"RainConfig.lens_radius_max_px must be >= lens_radius_min_px, got min {self.lens_radius_min_px!r} and max {self.lens_radius_max_px!r}"
            )
        if isinstance(self.max_streak_candidates, bool) or not isinstance(self.max_streak_candidates, int) or self.max_streak_candidates < 1:
            raise ValueError(f"RainConfig.max_streak_candidates must be an int >= 1, got {self.max_streak_candidates!r}")
        if self.max_streak_candidates > RAIN_OPTION_MAX["max_streak_candidates"]:
            raise ValueError(
                f"RainConfig.max_streak_candidates must be an int in [1, {_bound(RAIN_OPTION_MAX['max_streak_candidates'])}], got {self.max_streak_candidates!r}"
            )
        if not isinstance(self.lens_drops, bool):
            raise ValueError(f"RainConfig.lens_drops must be a bool, got {self.lens_drops!r}")
        if self.airlight_rgb is not None:
            try:
                airlight = tuple(self.airlight_rgb)
            except TypeError:  # not a sequence: refused below
                airlight = ()
            if len(airlight) != 3 or not all(isinstance(c, (int, float)) and 0.0 <= c <= 255.0 for c in airlight):
                raise ValueError(f"RainConfig.airlight_rgb must be None or three numbers in [0, 255], got {self.airlight_rgb!r}")
            object.__setattr__(self, "airlight_rgb", tuple(float(c) for c in airlight))
        if self.model == "physical" and self.lens_drops:
            import numpy as np

            from rainbench.rain import physical  # imports this module: imported here

            reference_K = np.array([[400.0, 0.0, 400.0], [0.0, 400.0, 300.0], [0.0, 0.0, 1.0]])
            held = physical.lens_drop_count(physical.MAX_RATE_MM_H, config=self, K=reference_K, height=600, width=800)
            if held > MAX_LENS_DROPS_AT_REFERENCE:
                raise ValueError(
                    f"RainConfig.lens_sweep_speed_m_s, lens_glass_distance_m, lens_life_min_s, lens_life_max_s, lens_drop_fraction "
                    f"and lens_min_diameter_mm must keep the drops on the glass at {physical.MAX_RATE_MM_H:g} mm/h "
                    f"(800x600, 90 degrees) at most {MAX_LENS_DROPS_AT_REFERENCE}, got {held} (or set lens_drops=false)"
                )

    def to_dict(self) -> dict[str, Any]:
        """All fields as a JSON-ready dict (tuples become lists)."""
        out = dataclasses.asdict(self)
        if out["airlight_rgb"] is not None:
            out["airlight_rgb"] = list(out["airlight_rgb"])
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RainConfig:
        """Inverse of :meth:`to_dict`. Unknown keys are refused (they would be silently ignored)."""
        known = {field.name for field in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"RainConfig.from_dict: unknown keys {unknown}; expected a subset of {sorted(known)}")
        values = dict(data)
        if values.get("airlight_rgb") is not None:
            values["airlight_rgb"] = tuple(values["airlight_rgb"])
        return cls(**values)


RAIN_OPTIONS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(RainConfig) if f.name != "model")
"""The rain parameters a dataset config's ``rain_options`` may set: every :class:`RainConfig` field
but ``model`` (the config's ``rain_model``), in declaration order."""
