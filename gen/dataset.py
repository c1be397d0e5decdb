"""Datasets: many scenes as many shards, a manifest, resume, verification, parallel workers.

A dataset directory holds shards (format v1, docs/format.md) and ``manifest.json``:

- scene k of a dataset uses seed ``seed + k``; a clip longer than ``frames_per_shard`` is split
  into shards of at most that many frames (the layout is planned for the whole clip);
- the manifest lists every finished shard (relative path, scene seed, frame range, rates,
  sha256, byte size) and the full dataset config. It is rewritten atomically (temporary file +
  rename) after each shard is complete, with ``"complete": true`` once every shard is in;
- re-running the same command skips shards whose file matches its manifest entry, so a killed
  run (even ``kill -9``) is finished by running it again; temporary files of a killed run are
  removed. A different config into a non-empty directory is refused unless ``overwrite``.

Image ids are 1-based, counting frames in manifest shard order, then frame order: the same
numbering everywhere in rainbench (exports, evaluation).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import multiprocessing
import os
import queue
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

from rainbench.mjcf.layout import ScenarioConfig

from . import labels as lb
from .generate import GenerateConfig, generate_shard
from .shard import ShardFormatError, open_shard, shard_name

MANIFEST = "manifest.json"
MANIFEST_FORMAT = "rainbench.manifest"
MANIFEST_VERSION = 1
EXECUTORS = ("local", "ray")


class DatasetError(ValueError):
    """A dataset request or directory that cannot be honoured; the message is one line."""


@dataclass(frozen=True)
class DatasetConfig:
    """A dataset: ``scenes`` clips of ``frames`` frames, seeds ``seed .. seed + scenes - 1``."""

    seed: int = 0
    scenes: int = 1
    frames: int = 200
    frames_per_shard: int = 200
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
    scenario: ScenarioConfig | None = None  # None: the paper's actor mix over frames / fps seconds

    def __post_init__(self) -> None:
        if self.scenario is not None and abs(self.scenario.duration_s - self.frames / self.fps) > 1e-9:
            raise DatasetError(f"scenario.duration_s: expected frames / fps = {self.frames / self.fps:g} s "
                               f"(the clip's length), got {self.scenario.duration_s:g}")
        if not (isinstance(self.scenes, int) and 1 <= self.scenes <= 100_000):
            raise DatasetError(f"SCENES: expected an integer in 1..100000, got {self.scenes!r}")
        if not (isinstance(self.frames_per_shard, int) and self.frames_per_shard >= 1):
            raise DatasetError(
                f"frames-per-shard: expected an integer >= 1, got {self.frames_per_shard!r}")
        if self.seed + self.scenes - 1 > 2**31 - 1:
            raise DatasetError(f"SEED: seed + scenes - 1 must be <= 2147483647, got "
                               f"{self.seed + self.scenes - 1}")
        self.tasks()  # validates every shard's GenerateConfig

    def tasks(self) -> list[GenerateConfig]:
        """One GenerateConfig per shard, in manifest order (scene, then frame offset)."""
        tasks = []
        for scene in range(self.scenes):
            for offset in range(0, self.frames, self.frames_per_shard):
                tasks.append(GenerateConfig(
                    seed=self.seed + scene, frames=min(self.frames_per_shard, self.frames - offset),
                    frame_offset=offset, clip_frames=self.frames, fps=self.fps, width=self.width,
                    height=self.height, hfov_deg=self.hfov_deg, rates=tuple(self.rates),
                    rain_model=self.rain_model, rain_seed=self.rain_seed,
                    rain_options=dict(self.rain_options), store=tuple(self.store),
                    label_filter=self.label_filter, scenario=self.scenario))
        return tasks

    def to_dict(self) -> dict:
        config = dataclasses.asdict(self)
        config["rates"] = [float(rate) for rate in self.rates]
        config["store"] = list(self.store)
        return config


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def shard_entry(path: Path, task: GenerateConfig, root: Path) -> dict:
    return {
        "path": path.relative_to(root).as_posix(),
        "scene_seed": task.seed,
        "frame_offset": task.frame_offset,
        "frames": task.frames,
        "rates": [float(rate) for rate in task.rates],
        "sha256": sha256_of(path),
        "bytes": path.stat().st_size,
    }


def _atomic_write_json(path: Path, payload: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "w") as handle:
        json.dump(payload, handle, indent=1, sort_keys=True)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def write_manifest(root: Path, config: DatasetConfig, entries: list[dict], complete: bool) -> Path:
    path = root / MANIFEST
    _atomic_write_json(path, {
        "format": MANIFEST_FORMAT, "format_version": MANIFEST_VERSION,
        "config": config.to_dict(), "complete": complete, "shards": entries,
    })
    return path


def read_manifest(root: str | Path) -> dict | None:
    """The manifest of dataset ``root`` (None if it has none); errors name the file."""
    path = Path(root) / MANIFEST
    if not path.exists():
        return None
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise DatasetError(f"{path}: not a readable manifest ({error})") from error
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise DatasetError(f"{path}: not a rainbench manifest")
    if manifest.get("format_version") != MANIFEST_VERSION:
        raise DatasetError(f"{path}: unknown manifest format_version "
                           f"{manifest.get('format_version')!r}")
    return manifest


def list_shards(data: str | Path | Sequence[str | Path]) -> list[Path]:
    """Shard paths of a dataset directory (manifest order; sorted names without a manifest),
    of one shard file, or of a list of shard files (kept in the given order)."""
    if isinstance(data, (list, tuple)):
        paths = [Path(p) for p in data]
    else:
        root = Path(data)
        if root.is_file():
            paths = [root]
        elif root.is_dir():
            manifest = read_manifest(root)
            if manifest is not None:
                paths = [root / entry["path"] for entry in manifest["shards"]]
            else:
                paths = sorted(root.glob("scene*_f*.h5"))
        else:
            raise DatasetError(f"{root}: no such dataset directory or shard")
    if not paths:
        raise DatasetError(f"{data}: no shards (scene*_f*.h5) found")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise DatasetError(f"{missing[0]}: shard listed but missing")
    return paths


def image_index(shards: Sequence[Path]) -> list[tuple[int, Path, int]]:
    """(image id, shard path, frame) for every frame; ids 1-based, shard order then frames."""
    index, next_id = [], 1
    for path in shards:
        with open_shard(path) as handle:
            frames = int(handle["labels/offsets"].shape[0]) - 1
        for frame in range(frames):
            index.append((next_id, Path(path), frame))
            next_id += 1
    return index


def open_in_turn(index: Sequence[tuple[int, Path, int]]):
    """Yield ``(image_id, shard_path, frame, handle)`` for the entries of :func:`image_index` (or a
    slice of it), in order: each shard is opened once while its frames follow each other, and
    closed when the walk moves on or ends. ``handle`` is an open :func:`open_shard` file."""
    handle, current = None, None
    try:
        for image_id, path, frame in index:
            if path != current:
                if handle is not None:
                    handle.close()
                handle, current = open_shard(path), path
            yield image_id, path, frame, handle
    finally:
        if handle is not None:
            handle.close()


def verify_dataset(root: str | Path) -> list[str]:
    """Problems of dataset ``root``, one line each, naming the file (empty list: all good)."""
    root = Path(root)
    manifest = read_manifest(root)
    if manifest is None:
        return [f"{root / MANIFEST}: missing"]
    problems = []
    if not manifest.get("complete"):
        problems.append(f"{root / MANIFEST}: the dataset is incomplete (run the same command "
                        "again to finish it)")
    for entry in manifest["shards"]:
        path = root / entry["path"]
        if not path.is_file():
            problems.append(f"{path}: missing")
            continue
        if path.stat().st_size != entry["bytes"]:
            problems.append(f"{path}: {path.stat().st_size} bytes, manifest says {entry['bytes']}")
            continue
        if sha256_of(path) != entry["sha256"]:
            problems.append(f"{path}: sha256 differs from the manifest")
            continue
        try:
            with open_shard(path) as handle:
                rgb = handle["rgb"].shape
                offsets = handle["labels/offsets"].shape[0]
                if rgb[:2] != (len(entry["rates"]), entry["frames"]) or offsets != rgb[1] + 1:
                    problems.append(f"{path}: shapes disagree with the manifest (rgb {rgb})")
        except ShardFormatError as error:
            problems.append(str(error))
    return problems


# -- generation --------------------------------------------------------------------------------

_progress_queue = None


def _init_worker(progress_queue, render_threads: int | None, threads: int) -> None:
    global _progress_queue
    _progress_queue = progress_queue
    if render_threads is not None:
        os.environ["LP_NUM_THREADS"] = str(render_threads)
    import cv2  # noqa: PLC0415 -- this process is ours: OpenCV's own pool takes its share too

    cv2.setNumThreads(threads)


def _generate_task(task: GenerateConfig, out: str, threads: int | None = None) -> str:
    """Worker body: render one shard; progress goes to the queue set by :func:`_init_worker`."""
    report = (lambda n: _progress_queue.put(n)) if _progress_queue is not None else None
    return str(generate_shard(task, out, progress=report, threads=threads))


def _prepare_directory(root: Path, config: DatasetConfig, overwrite: bool) -> dict[str, dict]:
    """Clean temporaries, check the config, and return the reusable manifest entries by path."""
    root.mkdir(parents=True, exist_ok=True)
    for stale in root.glob(".*.tmp-*"):
        stale.unlink(missing_ok=True)
    manifest = read_manifest(root)
    if manifest is None:
        if any(p.name != MANIFEST for p in root.iterdir()) and not overwrite:
            raise DatasetError(f"OUT: {root} is not empty and has no manifest; use --overwrite "
                               "or choose another OUT")
        return {}
    if manifest["config"] == json.loads(json.dumps(config.to_dict())):
        return {entry["path"]: entry for entry in manifest["shards"]}
    if not overwrite:
        raise DatasetError(f"OUT: {root} holds a dataset of another config; use --overwrite to "
                           "replace it or choose another OUT")
    for path in list(root.glob("scene*_f*.h5")) + [root / MANIFEST]:
        path.unlink(missing_ok=True)
    return {}


def run_dataset(config: DatasetConfig, out: str | Path, *, workers: int = 1,
                executor: str = "local", ray_address: str | None = None,
                render_threads: int | None = None, threads: int | None = None,
                overwrite: bool = False,
                progress: Callable[[int], None] | None = None) -> Path:
    """Generate (or finish) the dataset ``config`` in ``out``; returns the manifest path.

    ``workers`` processes (local) or Ray tasks render one shard each; the bytes do not depend on
    the worker count. ``render_threads`` sets ``LP_NUM_THREADS`` (Mesa's software renderer
    threads) in local workers; None keeps Mesa's default (all cores). ``threads``: rain,
    statistics and compression threads per worker (see :func:`generate_shard`; 1 = one core
    per worker); None gives each local worker cores / workers and each Ray task its node's
    cores. ``progress(n)`` receives
    finished frames, skipped shards included.
    """
    if executor not in EXECUTORS:
        raise DatasetError(f"executor: expected one of {', '.join(EXECUTORS)}, got {executor!r}")
    if not (isinstance(workers, int) and workers >= 1):
        raise DatasetError(f"WORKERS: expected an integer >= 1, got {workers!r}")
    if threads is not None and not (isinstance(threads, int) and threads >= 1):
        raise DatasetError(f"THREADS: expected an integer >= 1, got {threads!r}")
    local_threads = threads or max(1, (os.cpu_count() or 1) // workers)
    root = Path(out)
    reusable = _prepare_directory(root, config, overwrite)
    tasks = config.tasks()
    entries: dict[int, dict] = {}
    pending: list[int] = []
    for index, task in enumerate(tasks):
        name = shard_name(task.seed, task.frame_offset)
        entry = reusable.get(name)
        path = root / name
        if entry and path.is_file() and path.stat().st_size == entry["bytes"] \
                and sha256_of(path) == entry["sha256"]:
            entries[index] = entry
            if progress:
                progress(task.frames)
        else:
            pending.append(index)

    def record(index: int, path: Path) -> None:
        entries[index] = shard_entry(path, tasks[index], root)
        ordered = [entries[i] for i in sorted(entries)]
        write_manifest(root, config, ordered, complete=len(entries) == len(tasks))

    if not pending:
        return write_manifest(root, config, [entries[i] for i in sorted(entries)], complete=True)
    if executor == "ray":
        _run_ray(tasks, pending, root, ray_address, threads, record, progress)
    elif workers == 1:
        for index in pending:
            record(index, generate_shard(tasks[index], root, progress=progress,
                                         threads=local_threads))
    else:
        _run_local_pool(tasks, pending, root, workers, render_threads, local_threads, record,
                        progress)
    return root / MANIFEST


def _run_local_pool(tasks, pending, root, workers, render_threads, threads, record,
                    progress) -> None:
    context = multiprocessing.get_context("spawn")  # a fresh GL context in every worker
    progress_queue = context.Queue()
    with ProcessPoolExecutor(max_workers=min(workers, len(pending)), mp_context=context,
                             initializer=_init_worker,
                             initargs=(progress_queue, render_threads, threads)) as pool:
        futures = {pool.submit(_generate_task, tasks[i], str(root), threads): i for i in pending}
        remaining = set(futures)
        try:
            while remaining:
                done, remaining = wait(remaining, timeout=0.2, return_when=FIRST_COMPLETED)
                _drain(progress_queue, progress)
                for future in done:
                    record(futures[future], Path(future.result()))
        except BaseException:
            for future in remaining:
                future.cancel()
            raise
        finally:
            _drain(progress_queue, progress)


def _drain(progress_queue, progress) -> None:
    while True:
        try:
            frames = progress_queue.get_nowait()
        except queue.Empty:
            return
        if progress:
            progress(frames)


def _run_ray(tasks, pending, root, ray_address, threads, record, progress) -> None:
    try:
        import ray  # noqa: PLC0415 -- optional extra rainbench[ray]
    except ImportError as error:
        raise DatasetError("executor ray: Ray is not installed; pip install 'rainbench[ray]'") \
            from error
    if not ray.is_initialized():
        ray.init(address=ray_address, log_to_driver=False)
    # GPU-aware: where the cluster has GPUs, each task asks for a share of one (EGL renders
    # on it); otherwise one CPU.
    gpus = ray.cluster_resources().get("GPU", 0)
    options = {"num_cpus": 1, "num_gpus": 0.25 if gpus else 0}
    remote = ray.remote(_generate_task).options(**options)
    refs = {remote.remote(tasks[i], str(root), threads): i for i in pending}
    remaining = list(refs)
    while remaining:
        done, remaining = ray.wait(remaining, num_returns=1)
        for ref in done:
            index = refs[ref]
            record(index, Path(ray.get(ref)))
            if progress:
                progress(tasks[index].frames)
