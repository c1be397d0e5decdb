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


@dataclasses.dataclass(frozen=True)
class RainConfig:
    """All parameters of rain rendering. Frozen; build a new one with ``dataclasses.replace``.

    Attributes (units in the names; defaults in docs/rain.md, section "Parameters"):
        model: one of :data:`RAIN_MODELS`.

        exposure_s: camera exposure time T in seconds (physical model: streak length).
        focus_distance_m: focus distance of the thin-lens camera in metres (defocus of drops).
        f_number: aperture f-number N (defocus of drops).
        pixel_pitch_um: sensor pixel pitch in micrometres; with fx it fixes the focal length in
            metres ``f = fx * pitch`` used by the defocus formula.
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
        lens_view_blur_px: blur of the view through a lens drop, px @800x600 (the scene is
            box-averaged over this many pixels); also the cell size on which lens water is drawn.
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
    pixel_pitch_um: float = 3.0
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
        unit_interval = ("lens_rim_darkening", "lens_drop_fraction", "lens_opacity", "lens_slide_fraction", "streak_sky_weight")
        for name in unit_interval:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise ValueError(f"RainConfig.{name} must be a number in [0, 1], got {value!r}")
        for name in ("lens_fade_s", "lens_slide_max_px_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"RainConfig.{name} must be a finite number >= 0, got {value!r}")
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
