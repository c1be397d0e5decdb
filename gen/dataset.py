"""Writing datasets: many scenes as many shards, the manifest, resume, parallel workers.

A dataset directory holds shards (docs/format.md) and ``manifest.json``
(:mod:`rainbench.store.manifest`); reading it is :mod:`rainbench.store`'s job, and the dataset
config (:class:`~rainbench.gen.config.DatasetConfig`) is checked when it is built. Here:

- scene k of a dataset uses seed ``seed + k``; a clip longer than ``frames_per_shard`` is split
  into shards of at most that many frames (the layout is planned for the whole clip);
- the manifest lists every finished shard (relative path, scene seed, frame range, rates,
  sha256, byte size) and the full dataset config. It is rewritten atomically (temporary file +
  rename) after each shard is complete, with ``"complete": true`` once every shard is in;
- the manifest is written before the first shard is rendered, so an interrupted run always
  leaves one; re-running the same command skips shards whose file matches its manifest entry
  and adopts a complete shard under a final name that the manifest does not list yet (a run
  killed between the rename and the manifest update) after checking it (format, labels, the
  same config), so a killed run (even ``kill -9``) is finished by running it again; temporary
  files of a killed run are removed. A different config into a non-empty directory is refused
  unless ``overwrite``;
- worker processes die with the process that started them, whatever kills it (Linux
  ``PR_SET_PDEATHSIG``, and a watchdog thread polling the parent elsewhere); Ctrl-C stops the
  workers at once instead of letting them finish their shards;
- one ``generate`` at a time per directory: a second one is refused while the first holds the
  lock (``fcntl.flock`` on ``OUT/.rainbench.lock``).
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import json
import multiprocessing
import os
import queue
import shutil
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from rainbench import __version__
from rainbench.store.locks import LOCK_NAME, directory_lock
from rainbench.store.manifest import (MANIFEST, SHARD_GLOB, DatasetError, is_int, read_manifest,
                                      sha256_of, shard_entry, write_manifest)
from rainbench.store.shard import ShardFormatError, open_checked, read_rgb, shard_name
from rainbench.store.signals import STOP_SIGNALS, TERMINATING_SIGNALS, signals_held

from .config import DatasetConfig, GenerateConfig
from .generate import ShardAssembler, generate_shard, piece_configs

EXECUTORS = ("local", "ray")
LOCK = LOCK_NAME

_progress_queue = None


def _die_with_parent(parent_pid: int) -> None:
    """Make this worker die with ``parent_pid``, the process that started it, however that one
    dies (``kill -9`` included): Linux ``PR_SET_PDEATHSIG`` (SIGKILL at once), and a watchdog
    thread that polls the parent's process id (every platform; the guard where prctl is not)."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1: PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="rainbench-parent-watch", daemon=True).start()


PARENT_SIGNALS = STOP_SIGNALS
"""Signals a local worker ignores: sent to the whole process group (Ctrl-C, a scheduler stopping
the job), the parent gets them, stops the workers and cleans up (:func:`signals_held`: a second
one cannot cut that short)."""


def _init_worker(progress_queue, render_threads: int | None, threads: int,
                 parent_pid: int | None = None) -> None:
    global _progress_queue
    if parent_pid is not None:
        _die_with_parent(parent_pid)
    # Ctrl-C (and a SIGTERM or SIGHUP sent to the whole process group) goes to every process:
    # the parent handles it and stops the workers.
    for signum in PARENT_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    _progress_queue = progress_queue
    if render_threads is not None:
        os.environ["LP_NUM_THREADS"] = str(render_threads)
    import cv2  # noqa: PLC0415 -- this process is ours: OpenCV's own pool takes its share too

    cv2.setNumThreads(threads)


def _generate_task(task: GenerateConfig, out: str, threads: int | None = None) -> str:
    """Worker body: render one shard; progress goes to the queue set by :func:`_init_worker`."""
    report = (lambda n: _progress_queue.put(n)) if _progress_queue is not None else None
    return str(generate_shard(task, out, progress=report, threads=threads))


def _locked(root: Path):
    """Hold ``root/.rainbench.lock`` for one generate run
    (:func:`rainbench.store.locks.directory_lock`); a second run on the same directory gets a
    one-line :class:`DatasetError` naming the holder's pid."""
    return directory_lock(root, "generate", option="OUT", error=DatasetError)


def _entry(path: Path, task: GenerateConfig, root: Path) -> dict:
    """The manifest entry of ``task``'s finished shard ``path``."""
    return shard_entry(path, root, scene_seed=task.seed, frame_offset=task.frame_offset,
                       frames=task.frames, rates=task.rates)


def _remove_temporaries(root: Path) -> None:
    """Remove what a run leaves behind when it is killed: temporary shards (``.NAME.tmp-PID``)
    and folders of shard pieces (``.pieces.tmp-PID``)."""
    for stale in root.glob(".*.tmp-*"):
        if stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            stale.unlink(missing_ok=True)


def _prepare_directory(root: Path, config: DatasetConfig, overwrite: bool,
                       remedy: str | None = None) -> dict[str, dict]:
    """Clean temporaries, check the config, and return the reusable manifest entries by path.
    The caller holds the directory's lock. ``remedy``: what a refusal advises instead of
    ``--overwrite`` (for callers that have no such option)."""
    _remove_temporaries(root)
    try:
        manifest = read_manifest(root)
    except DatasetError as error:  # unreadable, or not a manifest of this version
        if not overwrite:
            raise DatasetError(f"OUT: {error}; " + (remedy or f"use --overwrite to replace the dataset in {root} "
                                                   "or choose another OUT")) from None
        _remove_dataset(root)
        return {}
    if manifest is None:
        # folders are left alone (a dataset is files at the top: shards and the manifest), so
        # `make scene`'s OUT/scene_*, `make paper`'s OUT/paper or preview's videos do not block it
        if any(p.name not in (MANIFEST, LOCK) and not p.is_dir() for p in root.iterdir()) and not overwrite:
            raise DatasetError(f"OUT: {root} is not empty and has no manifest; "
                               + (remedy or "use --overwrite or choose another OUT"))
        return {}
    if manifest["config"] == json.loads(json.dumps(config.to_dict())):
        return {entry["path"]: entry for entry in manifest["shards"]}
    if not overwrite:
        raise DatasetError(f"OUT: {root} holds a dataset of another config; "
                           + (remedy or "use --overwrite to replace it or choose another OUT"))
    _remove_dataset(root)
    return {}


def _remove_dataset(root: Path) -> None:
    """Delete the dataset in ``root`` that ``--overwrite`` replaces: its shards and manifest."""
    for path in list(root.glob(SHARD_GLOB)) + [root / MANIFEST]:
        path.unlink(missing_ok=True)


def _adoptable(path: Path, task: GenerateConfig) -> bool:
    """Whether ``path``, a file under a final shard name that the manifest does not list (a run
    killed between the rename and the manifest update), is a complete shard of ``task``: it
    opens, its labels check, its generator version and config are this task's, and every RGB
    chunk inflates (zlib checksums)."""
    expected = json.loads(task.to_json())
    try:
        with open_checked(path) as handle:
            if handle.attrs.get("generator_version") != __version__ \
                    or json.loads(handle.attrs["config"]) != expected \
                    or handle["rgb"].shape[:2] != (len(task.rates), task.frames):
                return False
            for rate_row in range(len(task.rates)):
                for frame in range(task.frames):
                    read_rgb(handle, rate_row, frame)
    except (ShardFormatError, OSError, KeyError, TypeError, ValueError, RecursionError):
        return False
    return True


def start_bar_at(bar) -> Callable[[int], None]:
    """:func:`run_dataset`'s ``kept`` callback for a ``tqdm`` bar: the kept frames become the
    bar's starting count, so its frames/s and time left count only what this run renders (they
    arrived all at once and read as thousands of frames a second)."""
    def start(frames: int) -> None:
        bar.reset(total=bar.total)  # the clock too: checking the kept shards took time, not frames
        bar.initial = bar.n = bar.last_print_n = frames
        bar.refresh()

    return start


def run_dataset(config: DatasetConfig, out: str | Path, *, workers: int = 1,
                executor: str = "local", ray_address: str | None = None,
                render_threads: int | None = None, threads: int | None = None,
                overwrite: bool = False, remedy: str | None = None,
                progress: Callable[[int], None] | None = None,
                kept: Callable[[int], None] | None = None) -> Path:
    """Generate (or finish) the dataset ``config`` in ``out``; returns the manifest path.

    ``workers`` processes (local) or Ray tasks render one shard each; the bytes do not depend on
    the worker count. With more local workers than shards to make, each shard is rendered in
    up to ``ceil(workers / shards)`` pieces of consecutive frames (at least
    :data:`~rainbench.gen.generate.MIN_PIECE_FRAMES` each) by separate workers and joined in
    frame order into the same file (:class:`~rainbench.gen.generate.ShardAssembler`), so one
    long clip keeps every worker busy. ``render_threads`` sets ``LP_NUM_THREADS`` (Mesa's software renderer
    threads) in local workers; None keeps Mesa's default (all cores). ``threads``: rain,
    statistics and compression threads per worker (see :func:`generate_shard`; 1 = one core
    per worker); None gives each local worker cores / workers and each Ray task its node's
    cores. ``progress(n)`` receives finished frames; the frames of shards kept from an earlier
    run go, all at once before anything renders, to ``kept(n)`` when given (a progress bar
    started there counts this run's rate only: :func:`start_bar_at`), else to ``progress``. ``remedy``: what
    the refusal of an ``out`` holding something else advises instead of ``--overwrite`` (the
    commands that generate as a step and have no such option: train, paper).

    The run holds ``out``'s lock throughout, writes the manifest before the first shard, and
    after a failure or an interrupt stops its workers, lists the shards that were finished,
    removes its temporary files and re-raises: running it again resumes.
    """
    if executor not in EXECUTORS:
        raise DatasetError(f"executor: expected one of {', '.join(EXECUTORS)}, got {executor!r}")
    if executor == "ray":
        check_ray_address(ray_address)
        if "ray" not in sys.modules and importlib.util.find_spec("ray") is None:  # before OUT is made
            raise DatasetError("executor ray: Ray is not installed; pip install 'rainbench[ray]'")
    if not (is_int(workers) and workers >= 1):
        raise DatasetError(f"WORKERS: expected an integer >= 1, got {workers!r}")
    if threads is not None and not (is_int(threads) and threads >= 1):
        raise DatasetError(f"THREADS: expected an integer >= 1, got {threads!r}")
    local_threads = threads or max(1, (os.cpu_count() or 1) // workers)
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    with _locked(root):
        reusable = _prepare_directory(root, config, overwrite, remedy)
        fresh = not (root / MANIFEST).exists()
        tasks = config.tasks()
        entries: dict[int, dict] = {}
        pending: list[int] = []
        kept_frames = 0
        for index, task in enumerate(tasks):
            name = shard_name(task.seed, task.frame_offset)
            entry = reusable.get(name)
            path = root / name
            if entry and path.is_file() and path.stat().st_size == entry["bytes"] \
                    and sha256_of(path) == entry["sha256"]:
                entries[index] = entry
            elif entry is None and path.is_file() and _adoptable(path, task):
                entries[index] = _entry(path, task, root)
            else:
                pending.append(index)
                continue
            kept_frames += task.frames
        if kept is not None:
            kept(kept_frames)
        elif progress and kept_frames:
            progress(kept_frames)

        def save() -> Path:
            return write_manifest(root, config.to_dict(), [entries[i] for i in sorted(entries)],
                                  complete=len(entries) == len(tasks))

        def record(index: int, path: Path) -> None:
            entries[index] = _entry(path, tasks[index], root)
            save()

        save()  # before the first shard: an interrupted run always leaves a manifest to resume
        if not pending:
            return root / MANIFEST
        try:
            if executor == "ray":
                _run_ray(tasks, pending, root, ray_address, threads, record, progress, render_threads)
            elif workers == 1:
                with _render_threads_set(render_threads):
                    for index in pending:
                        record(index, generate_shard(tasks[index], root, progress=progress,
                                                     threads=local_threads))
            else:
                _run_local_pool(tasks, pending, root, workers, render_threads, local_threads,
                                record, progress)
        except BaseException:
            # The workers are stopped: list what they finished, remove their temporary files.
            with signals_held():
                try:
                    for index in pending:
                        path = root / shard_name(tasks[index].seed, tasks[index].frame_offset)
                        if index not in entries and path.is_file() and _adoptable(path, tasks[index]):
                            entries[index] = _entry(path, tasks[index], root)
                    if executor == "local":
                        _remove_temporaries(root)
                    if fresh and not entries:
                        (root / MANIFEST).unlink(missing_ok=True)  # leave the directory as it was
                    else:
                        save()
                except (OSError, DatasetError):
                    pass  # e.g. the disk is still full: the next run does the same
            raise
    return root / MANIFEST


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Kill the pool's worker processes now (they may be in the middle of a shard: its temporary
    file is removed by the caller) and shut the pool down."""
    known = getattr(pool, "_processes", None)  # CPython's pid -> Process of the pool
    processes = list(known.values()) if known is not None else multiprocessing.active_children()
    for process in processes:
        process.kill()
    for process in processes:
        process.join(10)
    pool.shutdown(wait=True, cancel_futures=True)


def _run_local_pool(tasks, pending, root, workers, render_threads, threads, record,
                    progress) -> None:
    # More workers than shards: each shard in pieces of consecutive frames, joined in order.
    pieces_per_shard = -(-workers // len(pending))
    jobs = []  # (task index, piece number, config, folder)
    piece_count: dict[int, int] = {}
    pieces_dir = root / f".pieces.tmp-{os.getpid()}"
    for index in pending:
        pieces = piece_configs(tasks[index], pieces_per_shard)
        piece_count[index] = len(pieces)
        for number, piece in enumerate(pieces):
            jobs.append((index, number, piece, root if len(pieces) == 1 else pieces_dir))
    context = multiprocessing.get_context("spawn")  # a fresh GL context in every worker
    progress_queue = context.Queue()
    pool = ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=context,
                               initializer=_init_worker,
                               initargs=(progress_queue, render_threads, threads, os.getpid()))
    futures = {}
    finished: dict[int, dict[int, Path]] = {index: {} for index in pending}  # pieces not yet joined
    joined = dict.fromkeys(pending, 0)  # pieces of each shard joined so far
    done_shards: set[int] = set()  # shards finished and recorded
    with contextlib.ExitStack() as assemblers:
        joining: dict[int, ShardAssembler] = {}

        def piece_done(index: int, number: int, path: Path) -> None:
            if piece_count[index] == 1:
                record(index, path)
                done_shards.add(index)
                return
            if index not in joining:
                joining[index] = assemblers.enter_context(ShardAssembler(tasks[index], root))
            finished[index][number] = path
            while joined[index] in finished[index]:
                piece = finished[index].pop(joined[index])
                joining[index].add(piece)
                piece.unlink()
                joined[index] += 1
            if joined[index] == piece_count[index]:
                record(index, joining[index].commit())
                done_shards.add(index)

        try:
            # Workers are started with SIGINT blocked (the mask is inherited through fork and exec)
            # so that a Ctrl-C while they start cannot kill one with a traceback; the parent gets
            # it as soon as its mask is restored, and stops them.
            mask = signal.pthread_sigmask(signal.SIG_BLOCK, set(PARENT_SIGNALS))
            try:
                for index, number, piece, folder in jobs:
                    futures[pool.submit(_generate_task, piece, str(folder), threads)] = (index, number)
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            remaining = set(futures)
            while remaining:
                done, remaining = wait(remaining, timeout=0.2, return_when=FIRST_COMPLETED)
                _drain(progress_queue, progress)
                for future in done:
                    try:
                        result = future.result()
                    except BrokenProcessPool:  # every pending piece fails with it: which one died is unknown
                        rendering = sorted({shard_name(tasks[index].seed, tasks[index].frame_offset)
                                            for index, _ in futures.values() if index not in done_shards})
                        shown = ", ".join(rendering[:3]) + (f" and {len(rendering) - 3} more" if len(rendering) > 3 else "")
                        raise DatasetError(
                            f"OUT: a worker process died while rendering {shown} (killed: out of memory? fewer "
                            f"--workers, or a smaller image, need less); the finished shards are kept") from None
                    piece_done(*futures[future], Path(result))
        except BaseException:
            with signals_held():
                _stop_workers(pool)
            raise
    pool.shutdown(wait=True)
    _drain(progress_queue, progress)
    shutil.rmtree(pieces_dir, ignore_errors=True)


def _drain(progress_queue, progress) -> None:
    while True:
        try:
            frames = progress_queue.get_nowait()
        except queue.Empty:
            return
        if progress:
            progress(frames)


RAY_AUTH_HINT = ("a cluster with token authentication needs RAY_AUTH_MODE=token and the "
                 "cluster's token in RAY_AUTH_TOKEN, in the file named by RAY_AUTH_TOKEN_PATH, "
                 "or in ~/.ray/auth_token (docs/datasets.md)")


def _has_ray_token() -> bool:
    """Whether Ray would find an authentication token here (its own search order)."""
    if os.environ.get("RAY_AUTH_TOKEN", "").strip():
        return True
    token_path = os.environ.get("RAY_AUTH_TOKEN_PATH")
    return Path(token_path).is_file() if token_path else (Path.home() / ".ray" / "auth_token").is_file()


def _is_local_cluster(address: str) -> bool:
    """Whether ``address`` (host:port) is the address of a Ray head running on this machine: a
    loopback address, or this machine's address and the port of a Ray head running here."""
    host, _, port = address.rpartition(":")
    host = host.strip("[]")
    if host in ("localhost", "::1") or host.startswith("127."):
        return True
    try:
        from ray._private import services  # noqa: PLC0415 -- how ``ray.init("auto")`` finds it

        running = services.find_gcs_addresses()
    except (ImportError, AttributeError, OSError):
        return False
    for gcs in running:
        gcs_host, _, gcs_port = gcs.rpartition(":")
        if gcs_port == port and host == gcs_host.strip("[]"):
            return True
    return False


RAY_CONNECT_TIMEOUT_S = 10.0
"""How long ``--ray-address HOST:PORT`` may take to accept a TCP connection before rainbench
gives up (Ray itself retries an unreachable address for minutes)."""


def check_ray_address(ray_address: object) -> str | None:
    """``ray_address`` if it is a form Ray takes: None (a new local instance), ``auto``,
    ``local``, ``HOST:PORT`` or ``ray://HOST[:PORT]``; else a one-line :class:`DatasetError`
    (an empty address, ``:6379`` or ``http://...`` went to Ray, which answered with a traceback
    or hung)."""
    if ray_address is None or ray_address in ("auto", "local"):
        return ray_address
    expected = "expected auto, local, HOST:PORT or ray://HOST[:PORT]"
    if not isinstance(ray_address, str):
        raise DatasetError(f"--ray-address: {expected}, got {ray_address!r}")
    client = ray_address.startswith("ray://")
    rest = ray_address.removeprefix("ray://")
    host, colon, port = rest.rpartition(":") if ":" in rest else (rest, "", "")
    valid_port = (not colon and client) or (port.isdigit() and 1 <= int(port) <= 65535)
    if "://" in rest or not host.strip("[]") or any(c.isspace() or c == "/" for c in rest) or not valid_port:
        raise DatasetError(f"--ray-address: {expected}, got {ray_address!r}")
    return ray_address


def _check_reachable(ray_address: str | None) -> None:
    """A one-line :class:`DatasetError` unless something accepts TCP connections at the
    ``HOST:PORT`` (or ``ray://HOST:PORT``) of ``ray_address``; other forms (None, ``auto``,
    ``local``, an address without a port) are left to Ray."""
    if not ray_address or ray_address in ("auto", "local"):
        return
    host, _, port = ray_address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        return
    try:
        with socket.create_connection((host.strip("[]"), int(port)), RAY_CONNECT_TIMEOUT_S):
            pass
    except (OSError, ValueError) as error:  # gaierror, refused, timed out; port out of range
        raise DatasetError(f"--ray-address {ray_address}: nothing answers at {host}:{port} "
                           f"({' '.join(str(error).split()) or type(error).__name__})") from None


def _ray_connect(ray, ray_address: str | None) -> None:
    """``ray.init`` for rainbench. Ray 2.60 turns token authentication on for a head started by
    ``ray start`` once a token exists (``~/.ray/auth_token``), but a driver given an explicit
    address sends no token unless ``RAY_AUTH_MODE=token``; ``--ray-address auto`` does. So, as
    ``auto`` does, a head on this machine named by its address gets token mode when a token is
    at hand and RAY_AUTH_MODE is unset. A remote cluster needs RAY_AUTH_MODE=token set by the
    user (Ray does not send a local token to another host on its own, nor does rainbench)."""
    if ray.is_initialized():
        return
    _check_reachable(ray_address)
    named = ray_address not in (None, "", "auto", "local") and not ray_address.startswith("ray://")
    if named and not os.environ.get("RAY_AUTH_MODE") and _has_ray_token() \
            and _is_local_cluster(ray_address):
        os.environ["RAY_AUTH_MODE"] = "token"
        try:
            from ray._raylet import Config  # noqa: PLC0415 -- refresh a config read at import

            Config.initialize("")
        except (ImportError, AttributeError):
            pass
    # Ray's driver installs its own SIGTERM handler (sys.exit): keep the caller's, so that a
    # terminated run stops and cleans up as Ctrl-C does
    handlers = {signum: signal.getsignal(signum) for signum in TERMINATING_SIGNALS} \
        if threading.current_thread() is threading.main_thread() else {}
    try:
        # no address: a new local instance ("local"), never a cluster found by Ray's discovery
        ray.init(address=ray_address if ray_address is not None else "local", log_to_driver=False)
    except (ConnectionError, RuntimeError, ValueError, ray.exceptions.RayError) as error:
        where = f"--ray-address {ray_address}" if ray_address else "executor ray"
        reason = " ".join(str(error).split())[:300]
        hint = f"; {RAY_AUTH_HINT}" if ray_address else ""
        raise DatasetError(f"{where}: cannot connect to the Ray cluster ({reason}){hint}") from None
    finally:
        for signum, handler in handlers.items():
            if handler is not None:
                signal.signal(signum, handler)


@contextlib.contextmanager
def _render_threads_set(render_threads: int | None):
    """``LP_NUM_THREADS`` set to ``render_threads`` in this process for the block (the one-worker
    run renders here; Mesa reads it when this process's first GL context starts, as it does for
    the command line), then restored; nothing when None."""
    if render_threads is None:
        yield
        return
    before = os.environ.get("LP_NUM_THREADS")
    os.environ["LP_NUM_THREADS"] = str(render_threads)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("LP_NUM_THREADS", None)
        else:
            os.environ["LP_NUM_THREADS"] = before


def ray_task_options(gpus: float, render_threads: int | None) -> dict:
    """Ray options of a shard task: one CPU, a quarter of a GPU where the cluster has GPUs (EGL
    renders on it), and ``LP_NUM_THREADS`` in the task's environment for ``render_threads``."""
    options = {"num_cpus": 1, "num_gpus": 0.25 if gpus else 0}
    if render_threads is not None:
        options["runtime_env"] = {"env_vars": {"LP_NUM_THREADS": str(render_threads)}}
    return options


def _run_ray(tasks, pending, root, ray_address, threads, record, progress, render_threads=None) -> None:
    try:
        import ray  # noqa: PLC0415 -- optional extra rainbench[ray]
    except ImportError as error:
        raise DatasetError("executor ray: Ray is not installed; pip install 'rainbench[ray]'") \
            from error
    _ray_connect(ray, ray_address)
    # GPU-aware: where the cluster has GPUs, each task asks for a share of one (EGL renders
    # on it); otherwise one CPU.
    gpus = ray.cluster_resources().get("GPU", 0)
    devices = sorted({tasks[i].stats_device for i in pending} - {"cpu"})
    if devices and not gpus:  # the tasks could not see a GPU: fail now, not in every task
        raise DatasetError(f"--device {devices[0]}: the Ray cluster has no GPU for the statistics; "
                           "use --device cpu")
    remote = ray.remote(_generate_task).options(**ray_task_options(gpus, render_threads))
    refs = {remote.remote(tasks[i], str(root), threads): i for i in pending}
    remaining = list(refs)
    try:
        while remaining:
            done, remaining = ray.wait(remaining, num_returns=1)
            for ref in done:
                index = refs[ref]
                try:
                    path = ray.get(ref)
                except ray.exceptions.RayTaskError as error:
                    cause = getattr(error, "cause", None) or error
                    name = shard_name(tasks[index].seed, tasks[index].frame_offset)
                    raise DatasetError(f"ray task {name}: {type(cause).__name__}: "
                                       f"{' '.join(str(cause).split())[:300]}") from None
                except ray.exceptions.RayError as error:  # a worker or node died past Ray's retries, ...
                    name = shard_name(tasks[index].seed, tasks[index].frame_offset)
                    reason = " ".join(str(error).split())[:200]
                    raise DatasetError(f"ray task {name}: {type(error).__name__}: {reason} (a worker that keeps "
                                       f"dying may be out of memory: fewer tasks a node, or a smaller image, "
                                       f"need less)") from None
                record(index, Path(path))
                if progress:
                    progress(tasks[index].frames)
    except BaseException:
        for ref in remaining:
            try:
                ray.cancel(ref, force=True)
            except (ValueError, TypeError, ray.exceptions.RayError):
                pass
        raise
