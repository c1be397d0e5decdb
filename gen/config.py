"""The generator's configs: the dataset a user asks for and the shard each worker renders.

The fields are defined once, in :class:`ClipConfig`: the scene, the camera and the rain of a
clip. :class:`DatasetConfig` (the user-facing dataset: the CLI, recipes, ``make paper``) adds
how many scenes and how they are split into shards; :class:`GenerateConfig` (one shard, built by
:meth:`DatasetConfig.tasks`) adds where the shard lies in its clip. Every field is checked when a
config is built, before anything renders: a bad value is a one-line ``ValueError``
(:class:`~rainbench.store.manifest.DatasetError` for most) naming the field.

Importing this module imports no MuJoCo and chooses no GL backend, so the CLI checks a whole
config before it honours ``--gl`` and before anything renders; its flags take their limits and
defaults from here.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rainbench.devices import parse_device
from rainbench.mjcf.layout import ScenarioConfig, check_layout
from rainbench.rain.config import RAIN_MODELS, RAIN_OPTIONS, RainConfig
from rainbench.rain.weather import check_sky, check_time_of_day
from rainbench.store.manifest import DatasetError, is_int
from rainbench.store.rates import check_rate_list
from rainbench.store.shard import STORABLE

from .labels import LabelFilter

MAX_SEED = 2**31 - 1
"""Largest scene or rain seed (``--seed``, ``--rain-seed``; scene k of a dataset uses seed + k)."""
MAX_FRAMES = 100_000
"""Most frames of one clip (``--frames``), at the highest frame rates: the clip's length in
seconds is bounded by :data:`MAX_CLIP_SECONDS` too."""
MAX_CLIP_SECONDS = 3600.0
"""Longest clip in seconds (clip frames / fps: 36 000 frames at 10 frames/s). A scene is laid out
for its whole clip, and MuJoCo's spec takes time growing with the square of its geoms to build
(each ``add_geom``); a frame then costs what it costs in a short clip (far scenery is left out
of the passes). Measured on 2 cores, the highway (the most road per second): 10 minutes 11.5 s
and 0.4 GB, 30 minutes 50 s and 0.6 GB, an hour 227 s and 1.7 GB, in every worker that renders
a piece of it; for more data, render more scenes."""
MAX_SCENES = 100_000
"""Most scenes of one dataset (``--scenes``)."""
MAX_SHARDS = 100_000
"""Most shards of one dataset (scenes x shards per scene)."""
MAX_FRAME_OFFSET = 10_000_000
"""Largest index of a shard's first frame within its clip."""
SIDE_PX = (16, 8192)
"""Smallest and largest image width or height in pixels (``--width``, ``--height``)."""
MAX_PIXELS = 4096 * 4096
"""Most pixels of one image: its framebuffer (the image plus the truncation margins, 2.25 times
the pixels) is what Mesa's llvmpipe still allocates (measured: 4096 x 4096 and 8192 x 2048
render; 8192 x 4096 and 5461 x 5461 do not)."""
MAX_FPS = 1000.0
"""Largest frame rate in frames per second (``--fps``: (0, 1000])."""
HFOV_DEG = (10.0, 170.0)
"""Range of the camera's horizontal field of view in degrees (``--hfov``)."""
STATS_DEVICE = re.compile(r"cpu|cuda(:[0-9]+)?")
"""The devices the per-rate statistics run on (``--device``, :attr:`ClipConfig.stats_device`)."""
PAPER_CLIP = {"seed": 0, "sky": "cloudy", "layout": "street", "time_of_day": "day"}
"""The seed paper's clip (its CARLA clip was a straight drive under cloud, by day): what the CLI
renders when none of --seed, --sky, --layout, --time is given, and ``make paper``'s scene."""


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True, kw_only=True)
class ClipConfig:
    """The fields every clip of a dataset and every shard of a clip share, defined once.

    Defaults are the paper's clip (seed paper, Sec. III) except sky, layout and time of day,
    which each seed decides. ``frames`` counts the frames of a :class:`DatasetConfig`'s clips
    and of a :class:`GenerateConfig`'s shard; ``seed`` is a dataset's first scene seed and a
    shard's scene seed.
    """

    seed: int = 0
    frames: int = 200
    fps: float = 10.0
    width: int = 800  # pixels
    height: int = 600  # pixels
    hfov_deg: float = 90.0  # horizontal field of view of the ego camera
    rates: tuple[float, ...] = (0.0,)  # rain rates in mm/h, strictly ascending
    rain_model: str = "jeon2022"  # one of rainbench.rain.RAIN_MODELS
    rain_seed: int = 0
    rain_options: dict = field(default_factory=dict)  # RainConfig fields other than model
    store: tuple[str, ...] = ()  # extra per-frame arrays: some of depth, instance
    label_filter: LabelFilter = field(default_factory=LabelFilter)
    scenario: ScenarioConfig | None = None  # None: the paper's actor mix over the clip's length
    sky: str | None = None  # base weather (clear, cloudy, overcast); None: each seed decides
    layout: str | None = None  # road layout (mjcf.layout.LAYOUTS); None: each seed decides
    time_of_day: str | None = None  # day, dusk, night; None: each seed decides
    # Whether sky, light, wet road, spray and camera follow the rain rate; None: the rain
    # model's default (on for physical, off for jeon2022: the seed paper's method).
    weather_follows_rate: bool | None = None
    # Where each rate's statistics (SSIM, PSNR, per-box rain labels) are computed: "cpu"
    # (NumPy/OpenCV) or a CUDA device ("cuda", "cuda:N") through torch, all of a frame's rates
    # in one batch. The figures agree to float32 rounding, not byte for byte.
    stats_device: str = "cpu"

    def __post_init__(self) -> None:
        """Check every shared field (one-line errors naming it); ``rates`` and ``store`` become
        tuples and ``rain_options`` a copy, so that a config never changes after its check."""
        for name, low, high in (("seed", 0, MAX_SEED), ("rain_seed", 0, MAX_SEED),
                                ("width", *SIDE_PX), ("height", *SIDE_PX)):
            value = getattr(self, name)
            if not (is_int(value) and low <= value <= high):
                raise DatasetError(f"{name}: expected an integer in {low}..{high}, got {value!r}")
        if not (is_int(self.frames) and 1 <= self.frames <= MAX_FRAMES):
            raise DatasetError(f"FRAMES: expected an integer in 1..{MAX_FRAMES}, got {self.frames!r}")
        if self.width * self.height > MAX_PIXELS:
            raise DatasetError(f"WIDTH x HEIGHT: {self.width}x{self.height} = "
                               f"{self.width * self.height} pixels; at most {MAX_PIXELS} "
                               "(4096x4096): larger framebuffers do not render")
        if not (_is_number(self.fps) and 0 < self.fps <= MAX_FPS):
            raise DatasetError(f"fps: expected 0 < fps <= {MAX_FPS:g}, got {self.fps!r}")
        if not (_is_number(self.hfov_deg) and HFOV_DEG[0] <= self.hfov_deg <= HFOV_DEG[1]):
            raise DatasetError(f"hfov_deg: expected {HFOV_DEG[0]:g}..{HFOV_DEG[1]:g} degrees, "
                               f"got {self.hfov_deg!r}")
        check_rate_list(self.rates, "rates")
        object.__setattr__(self, "rates", tuple(self.rates))
        if isinstance(self.store, str) or not all(isinstance(item, str) for item in self.store):
            raise DatasetError(f"store: expected a sequence of names ({','.join(STORABLE)}), "
                               f"got {self.store!r}")
        unknown = sorted(set(self.store) - set(STORABLE))
        if unknown:
            raise DatasetError(f"store: expected a subset of {','.join(STORABLE)}, got "
                               f"{','.join(unknown)}")
        object.__setattr__(self, "store", tuple(self.store))
        self._check_rain()
        if not isinstance(self.label_filter, LabelFilter):
            raise DatasetError(f"label_filter: expected a LabelFilter, got "
                               f"{type(self.label_filter).__name__}")
        if self.scenario is not None and not isinstance(self.scenario, ScenarioConfig):
            raise DatasetError(f"scenario: expected a ScenarioConfig or None, got "
                               f"{type(self.scenario).__name__}")
        if self.sky is not None:
            check_sky(self.sky)
        if self.layout is not None:
            check_layout(self.layout)
        if self.time_of_day is not None:
            check_time_of_day(self.time_of_day)
        for name in ("sky", "layout", "time_of_day"):  # one value each, not a silent override
            mine, scenario = getattr(self, name), getattr(self.scenario, name, None)
            if mine is not None and scenario is not None and mine != scenario:
                raise DatasetError(f"{name}: {mine!r} disagrees with scenario.{name} {scenario!r}; "
                                   "give it once")
        if self.weather_follows_rate is not None and not isinstance(self.weather_follows_rate, bool):
            # 1 == True: an int passed the old "in (None, True, False)" and was stored as an int
            raise DatasetError(f"weather_follows_rate: expected True, False or None, got "
                               f"{self.weather_follows_rate!r}")
        if not (isinstance(self.stats_device, str) and STATS_DEVICE.fullmatch(self.stats_device)):
            raise DatasetError(f"stats_device: expected cpu, cuda or cuda:N, got "
                               f"{self.stats_device!r}")

    def _check_rain(self) -> None:
        """``rain_model`` and ``rain_options``: the rain of every rate > 0, built once here so
        that a bad option fails now rather than at the first rainy frame."""
        if self.rain_model not in RAIN_MODELS:
            raise DatasetError(f"RAIN_MODEL: expected one of {', '.join(RAIN_MODELS)}, "
                               f"got {self.rain_model!r}")
        if not isinstance(self.rain_options, dict):
            raise DatasetError(f"rain_options: expected a mapping of rain options, got "
                               f"{type(self.rain_options).__name__}")
        unknown = sorted(str(name) for name in self.rain_options if name not in RAIN_OPTIONS)
        if unknown:
            raise DatasetError(f"rain_options: unknown option {unknown[0]!r}; expected some of "
                               f"{', '.join(RAIN_OPTIONS)}")
        object.__setattr__(self, "rain_options", dict(self.rain_options))
        try:
            self.rain_config()
        except ValueError as error:  # RainConfig's messages name the option
            raise DatasetError(f"rain_options: {error}") from None

    def rain_config(self) -> RainConfig:
        """The rain drawn at every rate > 0: ``rain_model`` with ``rain_options``."""
        return RainConfig(model=self.rain_model, **self.rain_options)


def _check_clip_seconds(clip_frames: int, fps: float, what: str) -> None:
    """Refuse a clip longer than :data:`MAX_CLIP_SECONDS` (one line naming ``what`` gave its
    length in frames, and FPS: either may be the one to change)."""
    what = f"({what}) / FPS" if "+" in what else f"{what} / FPS"
    seconds = clip_frames / fps
    if seconds > MAX_CLIP_SECONDS:
        most = int(MAX_CLIP_SECONDS * fps)
        at_this_rate = (f"{most} frames at {fps:g} frames/s" if most >= 1
                        else f"not one frame at {fps:g} frames/s: raise the frame rate")
        raise DatasetError(f"{what}: a clip of {clip_frames} frames at {fps:g} frames/s is {seconds:.6g} s; "
                           f"expected at most {MAX_CLIP_SECONDS:g} s ({at_this_rate}): a scene is laid out "
                           "for its whole clip; for more data, render more scenes (--scenes)")


@dataclass(frozen=True, kw_only=True)
class DatasetConfig(ClipConfig):
    """A dataset: ``scenes`` clips of ``frames`` frames, seeds ``seed .. seed + scenes - 1``,
    each split into shards of at most ``frames_per_shard`` frames.

    A scene is planned for its clip's length (its actors meet the ego car within it, and the
    sky and time of day are drawn after them), so a seed's world depends on that length. The
    clip is ``clip_frames`` frames long (default ``first_frame + frames``) and the dataset
    holds its frames ``first_frame .. first_frame + frames - 1``: ``frames=10,
    clip_frames=200`` are the first 10 frames of the seed's 200-frame clip, byte for byte."""

    scenes: int = 1
    frames_per_shard: int = 200
    first_frame: int = 0
    clip_frames: int | None = None

    def __post_init__(self) -> None:
        if not (is_int(self.scenes) and 1 <= self.scenes <= MAX_SCENES):
            raise DatasetError(f"SCENES: expected an integer in 1..{MAX_SCENES}, got {self.scenes!r}")
        if not (is_int(self.frames_per_shard) and self.frames_per_shard >= 1):
            raise DatasetError(
                f"frames-per-shard: expected an integer >= 1, got {self.frames_per_shard!r}")
        if not (is_int(self.first_frame) and 0 <= self.first_frame <= MAX_FRAME_OFFSET):
            raise DatasetError(f"first-frame: expected an integer in 0..{MAX_FRAME_OFFSET}, got "
                               f"{self.first_frame!r}")
        super().__post_init__()
        if self.clip_frames is not None and not (
                is_int(self.clip_frames) and self.clip_frames >= self.first_frame + self.frames):
            raise DatasetError(f"clip-frames: expected an integer >= first-frame + frames = "
                               f"{self.first_frame + self.frames}, got {self.clip_frames!r}")
        _check_clip_seconds(self.clip_length, self.fps, "CLIP_FRAMES" if self.clip_frames is not None
                            else "FIRST_FRAME + FRAMES" if self.first_frame else "FRAMES")
        if self.shard_count > MAX_SHARDS:
            raise DatasetError(f"SCENES x ceil(FRAMES / FRAMES_PER_SHARD) = {self.shard_count} "
                               f"shards; at most {MAX_SHARDS} (raise --frames-per-shard)")
        if self.seed + self.scenes - 1 > MAX_SEED:
            raise DatasetError(f"SEED: seed + scenes - 1 must be <= {MAX_SEED}, got "
                               f"{self.seed + self.scenes - 1}")
        if self.scenario is not None and abs(self.scenario.duration_s - self.duration_s) > 1e-9:
            raise DatasetError(f"scenario.duration_s: expected clip frames / fps = "
                               f"{self.duration_s:g} s (the clip's length), got "
                               f"{self.scenario.duration_s:g}")

    @property
    def clip_length(self) -> int:
        """Frames of every scene's clip: ``clip_frames``, default ``first_frame + frames``."""
        return self.clip_frames if self.clip_frames is not None else self.first_frame + self.frames

    @property
    def duration_s(self) -> float:
        """Length of every scene's clip in seconds (what its layout is planned for)."""
        return self.clip_length / self.fps

    @property
    def shard_count(self) -> int:
        """Shards of the dataset: ``len(self.tasks())``."""
        return self.scenes * math.ceil(self.frames / self.frames_per_shard)

    def tasks(self) -> list[GenerateConfig]:
        """One GenerateConfig per shard, in manifest order (scene, then frame offset): the shared
        fields as they are here, with the scene's seed and the shard's frames."""
        shared = {f.name: getattr(self, f.name) for f in dataclasses.fields(ClipConfig)}
        end, clip = self.first_frame + self.frames, self.clip_length
        return [GenerateConfig(**{**shared, "seed": self.seed + scene,
                                  "frames": min(self.frames_per_shard, end - offset)},
                               frame_offset=offset, clip_frames=clip)
                for scene in range(self.scenes)
                for offset in range(self.first_frame, end, self.frames_per_shard)]

    def to_dict(self) -> dict:
        """The config as the manifest's ``config`` object (rates as floats; ``first_frame`` and
        ``clip_frames`` only where they are not their defaults, and ``stats_device`` only where
        it is not ``"cpu"``, so that datasets written before they existed still match their
        config)."""
        config = _without_cpu_device(dataclasses.asdict(self))
        config["rates"] = [float(rate) for rate in self.rates]
        config["store"] = list(self.store)
        if self.first_frame == 0:
            del config["first_frame"]
        if self.clip_frames is None:
            del config["clip_frames"]
        return config


@dataclass(frozen=True, kw_only=True)
class GenerateConfig(ClipConfig):
    """Everything one shard depends on: frames ``frame_offset .. frame_offset + frames - 1``
    of the clip of scene ``seed``, which has ``clip_frames`` frames."""

    frame_offset: int = 0
    clip_frames: int | None = None  # frames of the whole clip; None: frame_offset + frames

    def __post_init__(self) -> None:
        if not (is_int(self.frame_offset) and 0 <= self.frame_offset <= MAX_FRAME_OFFSET):
            raise DatasetError(f"frame_offset: expected an integer in 0..{MAX_FRAME_OFFSET}, got "
                               f"{self.frame_offset!r}")
        super().__post_init__()
        if self.clip_frames is not None and not (
                is_int(self.clip_frames) and self.clip_frames >= self.frame_offset + self.frames):
            raise DatasetError(f"clip_frames: expected >= frame_offset + frames = "
                               f"{self.frame_offset + self.frames}, got {self.clip_frames!r}")
        _check_clip_seconds(self.clip_length, self.fps, "CLIP_FRAMES" if self.clip_frames is not None
                            else "FIRST_FRAME + FRAMES" if self.frame_offset else "FRAMES")

    @property
    def follows_rate(self) -> bool:
        """Whether the weather follows the rate (resolving None by the rain model)."""
        if self.weather_follows_rate is not None:
            return self.weather_follows_rate
        return self.rain_model == "physical"

    @property
    def needs_depth(self) -> bool:
        """Whether each frame's depth map is used: by the physical model (streaks, extinction),
        by tyre spray (weather following the rate) or to be stored (``store`` has ``depth``).
        The jeon2022 model under a fixed weather draws lens water only, which needs none."""
        return self.rain_model == "physical" or self.follows_rate or "depth" in self.store

    @property
    def clip_length(self) -> int:
        """Frames of the whole clip: ``clip_frames``, default ``frame_offset + frames``."""
        return self.clip_frames if self.clip_frames is not None else self.frame_offset + self.frames

    @property
    def duration_s(self) -> float:
        """Length of the whole clip the layout is planned for (all shards of a scene share it)."""
        return self.clip_length / self.fps

    def scenario_config(self) -> ScenarioConfig:
        """The scenario the layout is sampled from: ``scenario`` (default the paper's mix over
        the clip's length) with the chosen sky, layout and time of day."""
        scenario = self.scenario if self.scenario is not None else ScenarioConfig(
            duration_s=self.duration_s)
        chosen = {name: getattr(self, name) for name in ("sky", "layout", "time_of_day")
                  if getattr(self, name) is not None}
        return dataclasses.replace(scenario, **chosen) if chosen else scenario

    def to_dict(self) -> dict:
        """The config with the scenario resolved (:meth:`scenario_config`); ``stats_device``
        only where it is not ``"cpu"`` (a CPU shard's bytes are those of shards written before
        the field existed)."""
        config = _without_cpu_device(dataclasses.asdict(self))
        config["scenario"] = dataclasses.asdict(self.scenario_config())
        return config

    def to_json(self) -> str:
        """The shard's ``config`` attribute: :meth:`to_dict` as JSON with sorted keys (an
        infinite float as ``"inf"``, numpy scalars as numbers)."""
        return json.dumps(self.to_dict(), sort_keys=True, default=_json_default)


def stats_device_for(device: str | None) -> str:
    """The :attr:`ClipConfig.stats_device` of a ``--device`` value
    (:func:`rainbench.devices.parse_device`).

    ``None`` or ``"auto"``: ``"cuda"`` when torch sees a CUDA GPU, else ``"cpu"`` (torch is
    imported only on a machine with an NVIDIA device node, ``/dev/nvidiactl``, so a CPU machine
    does not pay its import); ``"cpu"``; ``"cuda"`` as given; ``"cuda:N"`` or CUDA indices
    (``"0"``, ``"0,1"``: the first) -> ``"cuda:N"``. Anything else raises :class:`DatasetError`
    naming it.
    """
    parsed = parse_device(device, DatasetError)
    if parsed is None:
        if not Path("/dev/nvidiactl").exists():
            return "cpu"
        import torch  # noqa: PLC0415 -- only where a GPU may be

        return "cuda" if torch.cuda.is_available() else "cpu"
    kind, indices = parsed
    return f"cuda:{indices[0]}" if indices else kind


def _without_cpu_device(config: dict) -> dict:
    """``config`` without its ``stats_device`` where that is the default ``"cpu"``."""
    if config.get("stats_device") == "cpu":
        del config["stats_device"]
    return config


def _json_default(value):
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
