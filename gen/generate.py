"""Scene -> render -> labels -> rain -> shard: the generator's main loop.

:func:`generate_shard` is the one entry point; the CLI (`rainbench generate`) and the tests
call it. Its result depends only on the :class:`GenerateConfig` (and the GL backend).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import json
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from rainbench import __version__
from rainbench.mjcf import layout as L
from rainbench.mjcf.scene import build_spec, geom_instance_table

from . import labels as lb
from . import sim
from .render import FrameRenderer, camera_pose
from .shard import STORABLE, ShardWriter, shard_name

MAX_SEED = 2**31 - 1


@dataclass(frozen=True)
class GenerateConfig:
    """Everything one shard depends on. Defaults are the paper's clip (seed paper, Sec. III)."""

    seed: int = 0
    frames: int = 200
    frame_offset: int = 0
    clip_frames: int | None = None  # frames of the whole clip; None: frame_offset + frames
    fps: float = 10.0
    width: int = 800
    height: int = 600
    hfov_deg: float = 90.0
    rates: tuple[float, ...] = (0.0,)
    rain_model: str = "jeon2022"
    rain_seed: int = 0
    rain_options: dict = field(default_factory=dict)
    store: tuple[str, ...] = ()
    label_filter: lb.LabelFilter = field(default_factory=lb.LabelFilter)
    scenario: L.ScenarioConfig | None = None  # None: the paper's mix over frames / fps seconds

    def __post_init__(self) -> None:
        for name, low, high in (("seed", 0, MAX_SEED), ("rain_seed", 0, MAX_SEED),
                                ("frames", 1, 100_000), ("frame_offset", 0, 10_000_000),
                                ("width", 16, 8192), ("height", 16, 8192)):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and low <= value <= high):
                raise ValueError(f"{name}: expected an integer in {low}..{high}, got {value!r}")
        if not (0 < self.fps <= 1000):
            raise ValueError(f"fps: expected 0 < fps <= 1000, got {self.fps}")
        if not (10 <= self.hfov_deg <= 170):
            raise ValueError(f"hfov_deg: expected 10..170 degrees, got {self.hfov_deg}")
        unknown = sorted(set(self.store) - set(STORABLE))
        if unknown:
            raise ValueError(f"store: expected a subset of {','.join(STORABLE)}, got "
                             f"{','.join(unknown)}")
        if self.clip_frames is not None and self.clip_frames < self.frame_offset + self.frames:
            raise ValueError(f"clip_frames: expected >= frame_offset + frames = "
                             f"{self.frame_offset + self.frames}, got {self.clip_frames}")
        rates = tuple(float(r) for r in self.rates)
        if not rates or list(rates) != sorted(set(rates)) or rates[0] < 0:
            raise ValueError(f"rates: expected ascending distinct values >= 0, got {self.rates}")

    @property
    def duration_s(self) -> float:
        """Length of the whole clip the layout is planned for (all shards of a scene share it)."""
        clip = self.clip_frames if self.clip_frames is not None else self.frame_offset + self.frames
        return clip / self.fps

    def scenario_config(self) -> L.ScenarioConfig:
        if self.scenario is not None:
            return self.scenario
        return L.ScenarioConfig(duration_s=self.duration_s)

    def to_dict(self) -> dict:
        config = dataclasses.asdict(self)
        config["scenario"] = dataclasses.asdict(self.scenario_config())
        return config


@dataclass(frozen=True)
class SceneSetup:
    layout: L.Layout
    model: mujoco.MjModel
    geom_instance: np.ndarray  # (ngeom,) int32
    class_of_instance: np.ndarray  # (K,) int32


def build_scene(config: GenerateConfig) -> SceneSetup:
    """Sample the layout of ``config.seed`` and compile its model."""
    layout = L.sample_layout(config.seed, config.scenario_config(),
                             np.random.default_rng(config.seed))
    model = build_spec(layout, config.width, config.height, config.hfov_deg).compile()
    classes = np.array([actor.class_id for actor in layout.actors], dtype=np.int32)
    return SceneSetup(layout, model, geom_instance_table(model), classes)


def frame_labels(renderer: FrameRenderer, data: mujoco.MjData, visible: np.ndarray,
                 class_of_instance: np.ndarray, label_filter: lb.LabelFilter) -> lb.FrameLabels:
    """Labels of the current frame from its visible instance map plus actor-alone passes.

    Only actors with visible pixels are rendered alone, grouped so that actors whose projected
    boxes are disjoint share one pass (each pass shows its actors unoccluded).
    """
    num = class_of_instance.shape[0]
    visible_counts, visible_boxes = lb.tight_boxes(visible, num)
    projected = renderer.actor_boxes_padded(data)
    present = {i: projected[i] for i in np.flatnonzero(visible_counts) if i in projected}
    alone_in = np.zeros(num, np.int64)
    alone_total = np.zeros(num, np.int64)
    amodal = np.full((num, 4), np.nan, np.float32)
    for group in lb.group_disjoint(present):
        window = lb.union_window([present[i] for i in group],
                                 (renderer.padded_width, renderer.padded_height))
        alone = renderer.render_alone(data, group, window)
        inside, total, boxes = lb.alone_statistics(
            alone, window[:2], renderer.margins, (renderer.width, renderer.height), num)
        alone_in[group], alone_total[group], amodal[group] = inside[group], total[group], boxes[group]
    return lb.make_labels(visible_counts, visible_boxes, alone_in, alone_total, amodal,
                          class_of_instance, label_filter)


@dataclass
class FrameResult:
    rgb: np.ndarray  # (H, W, 3) uint8 clean
    depth: np.ndarray  # (H, W) float32 metres, +inf sky
    instance: np.ndarray  # (H, W) int32
    labels: lb.FrameLabels
    T_world_cam: np.ndarray  # (4, 4)


def render_frame(renderer: FrameRenderer, data: mujoco.MjData, setup: SceneSetup,
                 label_filter: lb.LabelFilter) -> FrameResult:
    """Every pass of one frame at the state in ``data``: RGB + depth, segmentation, labels."""
    renderer.update(data)
    rgb, depth = renderer.render_rgb_depth()
    visible, geometry = renderer.render_instances()
    depth[~geometry] = np.inf
    labels = frame_labels(renderer, data, visible, setup.class_of_instance, label_filter)
    return FrameResult(rgb, depth, visible, labels, camera_pose(setup.model, data, "ego"))


def render_clip(config: GenerateConfig, setup: SceneSetup | None = None):
    """Yield (frame index within the shard, FrameResult, the renderer) for every frame."""
    setup = setup or build_scene(config)
    model = setup.model
    data = mujoco.MjData(model)
    driver = sim.ActorDriver(model, setup.layout)
    with FrameRenderer(model, config.width, config.height, setup.geom_instance) as renderer:
        t_prev = 0.0
        for index in range(config.frames):
            t = (config.frame_offset + index) / config.fps
            sim.advance(model, data, driver, t_prev, t)
            t_prev = t
            yield index, render_frame(renderer, data, setup, config.label_filter), renderer


def _rain_for_frame(config: GenerateConfig, frame: FrameResult, K: np.ndarray, global_frame: int,
                    pool: ThreadPoolExecutor | None):
    """(R, H, W, 3) images and per-rate statistics of one frame.

    The sweep shares rate-independent work; the per-rate statistics run in ``pool`` threads
    (OpenCV and numpy release the GIL), or in this thread when ``pool`` is None.
    """
    rates = config.rates
    num_rates, num_boxes = len(rates), len(frame.labels)
    images = np.empty((num_rates,) + frame.rgb.shape, np.uint8)
    drop_count = np.zeros(num_rates, np.int32)
    ssim = np.ones(num_rates, np.float32)
    psnr = np.full(num_rates, np.inf, np.float32)
    coverage = np.zeros((num_rates, num_boxes), np.float32)
    contrast = np.zeros((num_rates, num_boxes), np.float32)
    rainy_rows = [r for r, rate in enumerate(rates) if rate > 0]
    images[[r for r, rate in enumerate(rates) if rate == 0]] = frame.rgb
    if not rainy_rows:
        return images, drop_count, ssim, psnr, coverage, contrast
    from rainbench import rain  # noqa: PLC0415 -- only needed when it rains

    rain_config = rain.RainConfig(model=config.rain_model, **config.rain_options)
    seeds = np.random.SeedSequence([config.rain_seed, config.seed, global_frame])
    frames = rain.render_rain_sweep(frame.rgb, frame.depth, [rates[r] for r in rainy_rows],
                                    config=rain_config, K=K, seed_sequence=seeds)
    reference = rain.SsimReference(frame.rgb)

    def statistics(row_and_frame):
        row, rainy = row_and_frame
        images[row] = rainy.rgb
        drop_count[row] = rainy.drop_count
        ssim[row], psnr[row] = reference.quality(rainy.rgb)
        coverage[row], contrast[row] = rain.box_rain_labels(frame.rgb, rainy.rgb, rainy.coverage,
                                                            frame.labels.bbox)

    list((pool.map if pool is not None else map)(statistics, zip(rainy_rows, frames)))
    return images, drop_count, ssim, psnr, coverage, contrast


def generate_shard(config: GenerateConfig, out_dir: str | Path,
                   progress: Callable[[int], None] | None = None,
                   threads: int | None = None) -> Path:
    """Render ``config`` into ``out_dir/<shard name>``; returns the shard path.

    Rain, statistics and compression of frame i run in background threads (``threads`` of
    them, default one per core) while frame i + 1 renders; ``threads=1`` runs everything in
    this thread, one frame after the other (one core per worker). ``progress(n)`` is called
    with the number of frames finished since the last call. The bytes do not depend on
    ``threads``.
    """
    threads = threads or os.cpu_count() or 1
    if not (isinstance(threads, int) and threads >= 1):
        raise ValueError(f"threads: expected an integer >= 1, got {threads!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    setup = build_scene(config)
    path = out_dir / shard_name(config.seed, config.frame_offset)
    attrs = {
        "scene_seed": config.seed, "rain_seed": config.rain_seed,
        "frame_offset": config.frame_offset, "fps": config.fps,
        "class_names": json.dumps(list(L.CLASS_NAMES)), "rain_model": config.rain_model,
        "gl_backend": os.environ.get("MUJOCO_GL", ""), "generator_version": __version__,
        "config": json.dumps(config.to_dict(), sort_keys=True, default=_json_default),
    }
    writer = None
    pending = None

    def finish(index: int, frame: FrameResult, K: np.ndarray) -> None:
        images, drops, ssim, psnr, coverage, contrast = _rain_for_frame(
            config, frame, K, config.frame_offset + index, stats_pool)
        writer.write_frame(index, images, frame.labels, frame.T_world_cam, depth=frame.depth,
                           instance=frame.instance, drop_count=drops, ssim=ssim, psnr=psnr,
                           rain_coverage=coverage, contrast_loss=contrast)
        if progress is not None:
            progress(1)

    with contextlib.ExitStack() as pools:
        frame_pool = stats_pool = None
        if threads > 1:
            frame_pool = pools.enter_context(
                ThreadPoolExecutor(1, thread_name_prefix="rainbench-frame"))
            stats_pool = pools.enter_context(
                ThreadPoolExecutor(threads, thread_name_prefix="rainbench-rate"))
        try:
            for index, frame, renderer in render_clip(config, setup):
                if writer is None:
                    writer = ShardWriter(path, attrs=attrs, rates=np.asarray(config.rates),
                                         num_frames=config.frames, width=config.width,
                                         height=config.height, K=renderer.K, store=config.store,
                                         threads=threads)
                if frame_pool is None:
                    finish(index, frame, renderer.K)
                    continue
                if pending is not None:
                    pending.result()  # at most one frame in flight: bounded memory
                pending = frame_pool.submit(finish, index, frame, renderer.K)
            if pending is not None:
                pending.result()
            return writer.commit()
        finally:
            if pending is not None and not pending.done():
                pending.cancel()
                concurrent.futures.wait([pending])
            if writer is not None and not writer.committed:
                writer.abort()


def _json_default(value):
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
