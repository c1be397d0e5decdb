"""Scene -> render -> labels -> rain -> shard: the generator's main loop.

:func:`generate_shard` is the one entry point; the CLI (`rainbench generate`) and the tests
call it. Its result depends only on the :class:`~rainbench.gen.config.GenerateConfig` (and the
GL backend).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import json
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import h5py
import numpy as np

from rainbench import __version__
from rainbench.mjcf import layout as L
from rainbench.mjcf.scene import build_spec, geom_instance_table
from rainbench.rain.weather import Weather, weather_at
from rainbench.store.manifest import is_int
from rainbench.store.shard import ShardWriter, shard_name

from . import labels as lb
from . import sim
from .config import GenerateConfig
from .render import FrameRenderer, PendingImage, camera_pose
from .weather import render_key


@dataclass(frozen=True)
class SceneSetup:
    layout: L.Layout
    model: mujoco.MjModel
    geom_instance: np.ndarray  # (ngeom,) int32
    class_of_instance: np.ndarray  # (K,) int32

    @property
    def base_weather(self) -> Weather:
        return weather_at(self.layout.sky, 0.0, time_of_day=self.layout.time_of_day)


def build_scene(config: GenerateConfig) -> SceneSetup:
    """Sample the layout of ``config.seed`` and compile its model."""
    layout = L.sample_layout(config.seed, config.scenario_config(),
                             np.random.default_rng(config.seed))
    model = build_spec(layout, config.width, config.height, config.hfov_deg).compile()
    classes = np.array([actor.class_id for actor in layout.actors], dtype=np.int32)
    table = geom_instance_table(model)
    # labels index the classes by instance id: every actor's geoms must carry its own id
    drawn = np.unique(table[table >= 0])
    if any(actor.instance_id != index for index, actor in enumerate(layout.actors)) \
            or not np.array_equal(drawn, np.arange(len(classes))):
        raise RuntimeError(f"seed {config.seed}: the scene's actor geoms carry {drawn.size} distinct ids for "
                           f"{len(classes)} actors 0..{len(classes) - 1}; the labels would be wrong")
    return SceneSetup(layout, model, table, classes)


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
    rgb: np.ndarray  # (H, W, 3) uint8 clean, base weather
    depth: np.ndarray | None  # (H, W) float32 metres, +inf sky; None when not rendered
    instance: np.ndarray  # (H, W) int32
    labels: lb.FrameLabels
    T_world_cam: np.ndarray  # (4, 4)
    # the re-render of the same state under each other weather asked for, its GL passes done
    # and its array work left to whichever thread asks first (PendingImage.result)
    pending_by_weather: dict[Weather, PendingImage] = field(default_factory=dict)
    time_s: float = 0.0  # clip time of the frame

    def weather_rgb(self, weather: Weather) -> np.ndarray:
        """(H, W, 3) uint8: the frame under ``weather`` (``rgb`` for the base weather)."""
        pending = self.pending_by_weather.get(weather)
        return self.rgb if pending is None else pending.result()

    @property
    def rgb_by_weather(self) -> dict[Weather, np.ndarray]:
        """(H, W, 3) uint8 re-render of the same state under each other weather asked for."""
        return {weather: pending.result() for weather, pending in self.pending_by_weather.items()}


def render_frame(renderer: FrameRenderer, data: mujoco.MjData, setup: SceneSetup,
                 label_filter: lb.LabelFilter, weathers=(), depth: bool = True) -> FrameResult:
    """Every pass of one frame at the state in ``data``: RGB, segmentation (+ depth when
    ``depth``, else ``FrameResult.depth`` is None), labels, then one RGB re-render per weather
    in ``weathers`` other than the base weather. The re-renders' GL passes run here; their array
    work (wet road, puddles, glow) is left to :meth:`FrameResult.weather_rgb`, so a pool
    thread can do it while this thread renders the next frame."""
    renderer.update(data)
    rgb = renderer.render_rgb()
    rerender = any(weather != renderer.base_weather for weather in weathers)
    if depth or rerender:  # the re-renders lay puddles where the depth shows the road
        visible, _, depth_map = renderer.render_instances_depth()
    else:  # the same segmentation without reading the depth buffer back
        visible, _ = renderer.render_instances()
        depth_map = None
    labels = frame_labels(renderer, data, visible, setup.class_of_instance, label_filter)
    rendered: dict[tuple, PendingImage] = {render_key(renderer.base_weather): PendingImage.done(rgb)}
    others = {}
    for weather in weathers:
        if weather == renderer.base_weather:
            continue
        key = render_key(weather)
        if key not in rendered:  # weathers that differ only in light level share a render
            rendered[key] = renderer.start_weather(data, weather, depth_map)
        # the glow follows the rate, so weathers that share a render each get their own
        others[weather] = renderer.start_glow(rendered[key], data, weather, depth_map)
    return FrameResult(rgb, depth_map if depth else None, visible, labels,
                       camera_pose(setup.model, data, "ego"),
                       others, float(data.time))


def render_clip(config: GenerateConfig, setup: SceneSetup | None = None, weathers=(),
                depth: bool = True):
    """Yield (frame index within the shard, FrameResult, the renderer) for every frame.

    ``weathers``: the weathers each frame is also rendered in (see :func:`sweep_weathers`).
    ``depth``: whether frames carry a depth map (:attr:`GenerateConfig.needs_depth` says
    whether the generator uses one).
    """
    setup = setup or build_scene(config)
    model = setup.model
    data = mujoco.MjData(model)
    driver = sim.ActorDriver(model, setup.layout)
    with FrameRenderer(model, config.width, config.height, setup.geom_instance,
                       base_weather=setup.base_weather) as renderer:
        # A piece of a clip starts at its first frame: the state at a time is its kinematic
        # targets (sim.advance), so stepping there from 0 s would render the same frame after
        # steps that cost 3.7 ms a frame (22 s before frame 5990 of a 10-minute clip).
        t_prev = config.frame_offset / config.fps
        for index in range(config.frames):
            t = (config.frame_offset + index) / config.fps
            sim.advance(model, data, driver, t_prev, t)
            t_prev = t
            yield index, render_frame(renderer, data, setup, config.label_filter,
                                      weathers, depth), renderer


def sweep_weathers(config: GenerateConfig, layout: L.Layout) -> list[Weather]:
    """The weather of each rate of ``config`` in the scene ``layout`` (the base weather at every
    rate when the weather does not follow the rate)."""
    return [weather_at(layout.sky, rate, config.follows_rate, time_of_day=layout.time_of_day)
            for rate in config.rates]


def shard_attrs(config: GenerateConfig, layout: L.Layout) -> dict:
    """The attributes of ``config``'s shard (docs/format.md), in the order they are written."""
    return {
        "sky": layout.sky, "weather_follows_rate": config.follows_rate,
        "layout": layout.name, "time_of_day": layout.time_of_day,
        "scene_seed": config.seed, "rain_seed": config.rain_seed,
        "frame_offset": config.frame_offset, "fps": config.fps,
        "class_names": json.dumps(list(L.CLASS_NAMES)), "rain_model": config.rain_model,
        # as MuJoCo reads it (case and spaces ignored): "EGL" renders what "egl" does
        "gl_backend": os.environ.get("MUJOCO_GL", "").strip().lower(), "generator_version": __version__,
        "config": config.to_json(),
    }


SENSOR_NOISE_STREAM = 0x5E45
"""The camera's sensor noise of scene ``seed`` at clip frame ``f`` draws from
``default_rng([seed, SENSOR_NOISE_STREAM, f])``: a property of the camera, so the rain seed does
not change it (after dark the clean frame carries it). Scene streams use other ids
(``mjcf.scene``, ``mjcf.layout``)."""


def sensor_noise_generator(seed: int, frame: int) -> np.random.Generator:
    """The generator of the sensor-noise field of scene ``seed``'s clip frame ``frame``."""
    return np.random.default_rng([seed, SENSOR_NOISE_STREAM, frame])


def _rain_for_frame(config: GenerateConfig, frame: FrameResult, K: np.ndarray, global_frame: int,
                    pool: ThreadPoolExecutor | None, weathers: list[Weather],
                    layout: L.Layout, base_weather: Weather, statistics=None):
    """The R images of one frame (a list of (H, W, 3) uint8, in the order of the rates; rows at
    rate 0 are the clean image itself) and its per-rate statistics.

    The clean image is the render of the base weather through its camera: after dark the
    auto-exposure's gain adds sensor noise to it (by day the render itself). Without weather
    following the rate, one rain sweep over the clean image shares the rate-independent work.
    With it, each rate starts from its own weather's render, gets tyre spray, rain drawn in its
    light (exposure time, airlight) and the camera's response (exposure level, sensor noise).
    The per-rate statistics run in ``pool`` threads (OpenCV and numpy release the GIL), or in
    this thread when ``pool`` is None; with ``statistics`` (a
    :class:`~rainbench.rain.metrics_torch.TorchRateStatistics`, the config's ``stats_device``)
    they run there instead, all rates of the frame in one batch.
    """
    from rainbench.rain import weather as wx  # noqa: PLC0415

    rates = config.rates
    num_rates, num_boxes = len(rates), len(frame.labels)
    images: list[np.ndarray | None] = [None] * num_rates
    drop_count = np.zeros(num_rates, np.int32)
    ssim = np.ones(num_rates, np.float32)
    psnr = np.full(num_rates, np.inf, np.float32)
    coverage = np.zeros((num_rates, num_boxes), np.float32)
    contrast = np.zeros((num_rates, num_boxes), np.float32)
    seeds = np.random.SeedSequence([config.rain_seed, config.seed, global_frame])
    clean = frame.rgb
    noise = None  # one sensor-noise field per frame, shared by every row that needs it
    if base_weather.gain > 1.0 or any(weather.gain > 1.0 for weather in weathers):
        noise = wx.noise_field(sensor_noise_generator(config.seed, global_frame), *clean.shape[:2])
    if base_weather.gain > 1.0:
        clean = wx.camera_response(clean, base_weather, noise)
        frame = dataclasses.replace(frame, rgb=clean)
    rainy_rows = [r for r, rate in enumerate(rates) if rate > 0]
    for row, rate in enumerate(rates):
        if rate == 0:
            images[row] = clean
    if not rainy_rows:
        return images, drop_count, ssim, psnr, coverage, contrast
    from rainbench import rain  # noqa: PLC0415 -- only needed when it rains

    # the clean image's half of the statistics, in a pool thread while the rain is drawn here
    references = None if statistics is not None else (pool.submit if pool is not None else _call_now)(
        lambda: (rain.SsimReference(frame.rgb), rain.BoxRainReference(frame.rgb, frame.labels.bbox)))
    rain_config = config.rain_config()
    # lens water persists over the clip: seeded by the clip, placed by the frame's time
    clock = rain.LensClock(np.random.SeedSequence([config.rain_seed, config.seed]), global_frame,
                           config.fps)
    if not any(weathers[r].rain_mm_h > 0 for r in rainy_rows):  # the base weather throughout
        frames = rain.render_rain_sweep(frame.rgb, frame.depth, [rates[r] for r in rainy_rows],
                                        config=rain_config, K=K, seed_sequence=seeds,
                                        lens_clock=clock)
        coverages = [rainy.coverage for rainy in frames]
    else:
        # the weather re-renders' array work (wet road, puddles, glow), over the pool's threads
        list((pool.map if pool is not None else map)(PendingImage.result,
                                                      frame.pending_by_weather.values()))
        frames, coverages = _weather_rain(config, frame, K, seeds, clock, rain_config,
                                          [weathers[r] for r in rainy_rows],
                                          [rates[r] for r in rainy_rows], layout, noise, pool)
    for row, rainy in zip(rainy_rows, frames):
        images[row] = rainy.rgb
        drop_count[row] = rainy.drop_count
    if statistics is not None:
        ssim[rainy_rows], psnr[rainy_rows], coverage[rainy_rows], contrast[rainy_rows] = \
            statistics.frame(frame.rgb, [rainy.rgb for rainy in frames], coverages,
                             frame.labels.bbox)
        return images, drop_count, ssim, psnr, coverage, contrast
    ssim_reference, box_reference = references.result()

    def row_statistics(row_frame_coverage):
        row, rainy, rain_coverage = row_frame_coverage
        ssim[row], psnr[row] = ssim_reference.quality(rainy.rgb)
        coverage[row], contrast[row] = box_reference.labels(rainy.rgb, rain_coverage)

    list((pool.map if pool is not None else map)(row_statistics, zip(rainy_rows, frames, coverages)))
    return images, drop_count, ssim, psnr, coverage, contrast


def rate_statistics(config: GenerateConfig):
    """Where a shard's per-rate statistics run: None for ``stats_device`` ``"cpu"`` (NumPy and
    OpenCV over the statistics threads), else a
    :class:`~rainbench.rain.metrics_torch.TorchRateStatistics` on that device. A CUDA device
    without CUDA raises ValueError naming ``stats_device``."""
    if config.stats_device == "cpu":
        return None
    from rainbench.rain.metrics_torch import TorchRateStatistics  # noqa: PLC0415 -- imports torch

    return TorchRateStatistics(config.stats_device, config.height, config.width)


def _in_thread(function: Callable[..., object], *args) -> concurrent.futures.Future:
    """``function(*args)`` started in a daemon thread of its own, as a future of its result
    (or of its exception)."""
    future: concurrent.futures.Future = concurrent.futures.Future()

    def run() -> None:
        try:
            future.set_result(function(*args))
        except BaseException as error:  # handed to whoever takes the result
            future.set_exception(error)

    threading.Thread(target=run, name="rainbench-stats-device", daemon=True).start()
    return future


def _call_now(function: Callable[[], object]) -> concurrent.futures.Future:
    """``function()`` run in this thread, as a finished future (the pool-less path)."""
    future: concurrent.futures.Future = concurrent.futures.Future()
    future.set_result(function())
    return future


def _weather_rain(config: GenerateConfig, frame: FrameResult, K: np.ndarray,
                  seeds: np.random.SeedSequence, clock, rain_config, weathers: list[Weather],
                  rates: list[float], layout: L.Layout, noise: np.ndarray | None,
                  pool: ThreadPoolExecutor | None = None):
    """Rain over each rate's own weather: (list of RainFrame, list of (H, W) coverage incl. spray).

    Each rate's scene (its weather's render with tyre spray) gets rain drawn in its light, then
    the camera's response with the frame's sensor-noise field ``noise`` ((H, W, 3) float32, or
    None when no weather has gain). Rates whose exposure time is the same share one rain sweep
    (the falling drops and their streaks drawn once), each blended towards its own airlight.
    Each rate's spray and camera response run in ``pool``'s threads (each rate's on its own, so
    the result does not depend on the threads), the sweeps in this thread.
    """
    from rainbench import rain  # noqa: PLC0415
    from rainbench.rain import weather as wx  # noqa: PLC0415
    from rainbench.rain._seeding import STREAM_SPRAY, child_generator  # noqa: PLC0415

    from .spray import spray_particles  # noqa: PLC0415

    height, width = frame.rgb.shape[:2]
    spray_points = spray_weights = None
    if any(weather.spray > 0 for weather in weathers):
        world, spray_weights = spray_particles(layout, frame.time_s,
                                               child_generator(seeds, STREAM_SPRAY))
        pose = frame.T_world_cam
        spray_points = (world - pose[:3, 3]) @ pose[:3, :3]
    each = pool.map if pool is not None else map

    def sprayed(weather: Weather) -> tuple[np.ndarray, np.ndarray]:
        """(the weather's scene with its tyre spray, the spray's (H, W) opacity)."""
        scene = frame.weather_rgb(weather)
        spray = np.zeros((height, width), np.float32)
        if spray_points is not None and weather.spray > 0:
            spray = wx.spray_opacity(frame.depth, K, spray_points,
                                     spray_weights * (wx.SPRAY_OPACITY * weather.spray))
            scene = wx.composite_spray(scene, spray, wx.mean_sky_rgb(weather) * wx.SPRAY_BRIGHTNESS)
        return scene, spray

    scenes, sprays = (list(column) for column in zip(*each(sprayed, weathers)))
    airlights, groups = [], {}
    for index, weather in enumerate(weathers):
        light, airlight = {}, None
        if rain_config.model == "physical":
            # the rain is drawn in this weather's light, unless the user fixed these values
            if "exposure_s" not in config.rain_options:
                light["exposure_s"] = weather.exposure_s
            if "airlight_rgb" not in config.rain_options:
                airlight = tuple(round(float(c), 1) for c in wx.airlight_rgb(weather))
        airlights.append(airlight)
        groups.setdefault(tuple(sorted(light.items())), []).append(index)
    rainy: list = [None] * len(weathers)
    for light, members in groups.items():
        own = [airlights[i] for i in members]
        drawn = rain.render_rain_sweep(frame.rgb, frame.depth, [rates[i] for i in members],
                                       config=dataclasses.replace(rain_config, **dict(light)),
                                       K=K, seed_sequence=seeds, lens_clock=clock,
                                       scenes=[scenes[i] for i in members],
                                       airlights=None if own[0] is None else own)
        for index, result in zip(members, drawn):
            rainy[index] = result

    def seen(weather_result_spray) -> tuple:
        """(the rate's RainFrame through the camera, its coverage with the spray's)."""
        weather, result, spray = weather_result_spray
        image = wx.camera_response(result.rgb, weather, noise)
        return (rain.RainFrame(image, result.coverage, result.drop_count),
                (1.0 - (1.0 - result.coverage) * (1.0 - spray)).astype(np.float32))

    out_frames, out_coverage = (list(column) for column in zip(*each(seen, zip(weathers, rainy, sprays))))
    return out_frames, out_coverage


def default_frames_in_flight(threads: int) -> int:
    """How many rendered frames get their rain, statistics and compression at once when
    :func:`generate_shard` has ``threads`` threads: one per 4 threads, at least 2 and at most 8
    (1 for one thread, which runs everything in turn).

    A frame's rain sweep runs its rates one after the other in one thread (a heavier rate adds
    drops to the lighter rate's), while its statistics and compression spread over every
    thread; about 4 threads keep one sweep busy, so a machine with many cores feeds several
    frames at once. Even on 2 cores a second frame in flight fills the gaps of the first's
    sweep (the paper clip 3-4 % faster, bench/RESULTS.md). Each frame in flight holds its R
    images (R x 1.4 MB at 800x600)."""
    return 1 if threads == 1 else max(2, min(8, threads // 4))


def generate_shard(config: GenerateConfig, out_dir: str | Path,
                   progress: Callable[[int], None] | None = None,
                   threads: int | None = None, frames_in_flight: int | None = None) -> Path:
    """Render ``config`` into ``out_dir/<shard name>``; returns the shard path.

    Rain, statistics and compression of frame i run in background threads (``threads`` of
    them, default one per core) while frame i + 1 renders; up to ``frames_in_flight``
    rendered frames are in that stage at once (default :func:`default_frames_in_flight`), and
    they are written in frame order. ``threads=1`` runs everything in this thread, one frame
    after the other (one core per worker). ``progress(n)`` is called with the number of frames
    finished since the last call. The bytes do not depend on ``threads`` or
    ``frames_in_flight``.
    """
    if threads is not None and not (is_int(threads) and threads >= 1):
        raise ValueError(f"threads: expected an integer >= 1 or None, got {threads!r}")  # 0 was cpu_count
    threads = threads or os.cpu_count() or 1
    if frames_in_flight is None:
        frames_in_flight = default_frames_in_flight(threads)
    if not (is_int(frames_in_flight) and frames_in_flight >= 1):
        raise ValueError(f"frames_in_flight: expected an integer >= 1, got {frames_in_flight!r}")
    # a GPU's statistics cost torch's import and a CUDA context (seconds): started in a thread
    # of their own while the scene builds, taken by the first frame's rain step
    statistics = None if config.stats_device == "cpu" else _in_thread(rate_statistics, config)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    setup = build_scene(config)
    weathers = sweep_weathers(config, setup.layout)
    base_weather = setup.base_weather
    path = out_dir / shard_name(config.seed, config.frame_offset)
    attrs = shard_attrs(config, setup.layout)
    writer = None
    in_flight: collections.deque[concurrent.futures.Future] = collections.deque()

    def rain_of(index: int, frame: FrameResult, K: np.ndarray) -> tuple:
        return _rain_for_frame(config, frame, K, config.frame_offset + index, stats_pool,
                               weathers, setup.layout, base_weather,
                               statistics.result() if statistics is not None else None)

    def write(index: int, frame: FrameResult, rained) -> None:
        """Store frame ``index``; ``rained`` is its rain (a tuple, or a future of one)."""
        if isinstance(rained, concurrent.futures.Future):
            rained = rained.result()
        images, drops, ssim, psnr, coverage, contrast = rained
        writer.write_frame(index, images, frame.labels, frame.T_world_cam, depth=frame.depth,
                           instance=frame.instance, drop_count=drops, ssim=ssim, psnr=psnr,
                           rain_coverage=coverage, contrast_loss=contrast)
        if progress is not None:
            progress(1)

    with contextlib.ExitStack() as pools:
        rain_pool = write_pool = stats_pool = None
        if threads > 1:
            rain_pool = pools.enter_context(
                ThreadPoolExecutor(frames_in_flight, thread_name_prefix="rainbench-frame"))
            # one writer thread takes the frames in the order they were submitted: the file's
            # chunk order, hence its bytes, is that of a serial run
            write_pool = pools.enter_context(
                ThreadPoolExecutor(1, thread_name_prefix="rainbench-write"))
            stats_pool = pools.enter_context(
                ThreadPoolExecutor(threads, thread_name_prefix="rainbench-rate"))
        try:
            for index, frame, renderer in render_clip(config, setup, weathers,
                                                      depth=config.needs_depth):
                if writer is None:
                    writer = ShardWriter(path, attrs=attrs, rates=np.asarray(config.rates),
                                         num_frames=config.frames, width=config.width,
                                         height=config.height, K=renderer.K, store=config.store,
                                         threads=threads,
                                         weather=[w.as_record() for w in weathers])
                if rain_pool is None:
                    write(index, frame, rain_of(index, frame, renderer.K))
                    continue
                while len(in_flight) >= frames_in_flight:  # bounded memory
                    in_flight.popleft().result()
                rained = rain_pool.submit(rain_of, index, frame, renderer.K)
                in_flight.append(write_pool.submit(write, index, frame, rained))
            while in_flight:
                in_flight.popleft().result()
            return writer.commit()
        finally:
            for written in in_flight:
                written.cancel()
            concurrent.futures.wait(in_flight)
            if writer is not None and not writer.committed:
                writer.abort()


MIN_PIECE_FRAMES = 8
"""The fewest frames a piece of a shard gets (:func:`piece_configs`): each piece builds the scene,
opens a GL context and simulates from the clip's start, about a second of setup, so shorter
pieces would cost more than they save."""


def piece_configs(config: GenerateConfig, pieces: int) -> list[GenerateConfig]:
    """``config``'s frames as at most ``pieces`` runs of consecutive frames of the same clip, in
    frame order, each at least :data:`MIN_PIECE_FRAMES` long, their lengths differing by at
    most one; ``[config]`` itself when it makes one piece. Each run is a shard config of its own
    (its ``frame_offset``, ``frames``, and the clip length made explicit), whose frames equal
    those frames of ``config``'s shard byte for byte; :class:`ShardAssembler` joins their
    shards."""
    if not (is_int(pieces) and pieces >= 1):
        raise ValueError(f"pieces: expected an integer >= 1, got {pieces!r}")
    count = max(1, min(pieces, config.frames // MIN_PIECE_FRAMES))
    if count == 1:
        return [config]
    size, extra = divmod(config.frames, count)
    configs, offset = [], config.frame_offset
    for piece in range(count):
        frames = size + (piece < extra)
        configs.append(dataclasses.replace(config, frame_offset=offset, frames=frames,
                                           clip_frames=config.clip_length))
        offset += frames
    return configs


class ShardAssembler:
    """``config``'s shard built from the shards of its pieces (:func:`piece_configs`, each made
    by :func:`generate_shard`), added in frame order as they are ready: their stored images
    (compressed chunks as they are, not re-encoded), labels, poses and rain statistics are
    copied into one shard under ``config``'s name and attributes, byte for byte the file that
    ``generate_shard(config)`` writes. Use as a context manager; :meth:`commit` when every piece
    is in (leaving the block without it removes the temporary file). A piece that is not the
    next run of frames of ``config``'s clip (its frames, or any other field of its config) is
    refused (ValueError)."""

    def __init__(self, config: GenerateConfig, out_dir: str | Path) -> None:
        self.config = config
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        self.path = Path(out_dir) / shard_name(config.seed, config.frame_offset)
        self._layout = L.sample_layout(config.seed, config.scenario_config(),
                                       np.random.default_rng(config.seed))
        self._writer: ShardWriter | None = None
        self._next_frame = 0

    def __enter__(self) -> "ShardAssembler":
        return self

    def __exit__(self, *exc_info) -> None:
        if self._writer is not None and not self._writer.committed:
            self._writer.abort()

    def add(self, piece: str | Path) -> None:
        """Copy the next piece's shard (frames from the first not yet copied)."""
        config = self.config
        with h5py.File(piece, "r") as source:
            offset, frames = int(source.attrs["frame_offset"]), int(source["rgb"].shape[1])
            expected = config.frame_offset + self._next_frame
            same_clip = json.loads(source.attrs["config"]) == json.loads(dataclasses.replace(
                config, frame_offset=offset, frames=frames, clip_frames=config.clip_length).to_json())
            if offset != expected or self._next_frame + frames > config.frames or not same_clip \
                    or not np.array_equal(source["rates"][()], np.asarray(config.rates, np.float32)) \
                    or source["rgb"].shape[2:4] != (config.height, config.width):
                raise ValueError(f"{piece}: expected a piece of {self.path.name} from clip frame "
                                 f"{expected} (at most {config.frames - self._next_frame} frames of "
                                 f"its config, rates {list(config.rates)}, {config.width}x{config.height}); got "
                                 f"{frames} frames from {offset}, rates {source['rates'][()].tolist()}, "
                                 f"{source['rgb'].shape[3]}x{source['rgb'].shape[2]}")
            if self._writer is None:
                self._writer = ShardWriter(
                    self.path, attrs=shard_attrs(config, self._layout), rates=np.asarray(config.rates),
                    num_frames=config.frames, width=config.width, height=config.height,
                    K=source["camera/K"][()], store=config.store, threads=1,
                    weather=[w.as_record() for w in sweep_weathers(config, self._layout)])
            self._writer.copy_frames(source, self._next_frame)
        self._next_frame += frames

    def commit(self) -> Path:
        """Finish the shard (every frame must be in) and move it to its final name."""
        if self._writer is None or self._next_frame != self.config.frames:
            raise RuntimeError(f"shard {self.path.name}: {self._next_frame} of {self.config.frames} "
                               "frames were added")
        return self._writer.commit()
