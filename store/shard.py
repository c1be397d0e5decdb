"""HDF5 shards, formats v1 and v2 (the contract is docs/format.md).

:class:`ShardWriter` writes one shard under a temporary name in the destination folder and
renames it to its final name only in :meth:`ShardWriter.commit`, so a final name always holds
a complete shard. :func:`open_shard` checks the format before anything is read; :func:`open_checked`, how
every reader opens a shard, also checks its labels (:func:`check_labels`).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import deflate
import h5py
import numpy as np
from isal import isal_zlib

from .classes import CLASS_NAMES, LABELLED_CLASSES
from .images import file_error
from .labels import FrameLabels

FORMAT = "rainbench.shard"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)  # v2 adds /weather and the sky / weather_follows_rate attributes
# The RGB dataset's filter: gzip, in every HDF5 build, so plain h5py (and other HDF5 tools) read
# the shards without plugins (docs/format.md "Compression"). Level 1 is what HDF5 itself uses
# where it writes a chunk (copies through h5py); rainbench writes its own chunks (below).
RGB_COMPRESSION = {"compression": "gzip", "compression_opts": 1}
# rainbench deflates each RGB chunk itself with ISA-L's igzip at this level (the `isal`
# package): the zlib stream the gzip filter stores. On rainy 800x600 frames, one thread: 6.0 ms
# an image against 13.1 ms for libdeflate level 1 (the writer before) and about 25 ms for zlib
# level 1, 4 % larger than libdeflate's; its streams also inflate faster (3.8 against 4.7 ms
# with libdeflate, which the readers keep). Level 2 costs what level 1 does and is 3 % smaller.
RGB_DEFLATE_LEVEL = 2
STORABLE = ("depth", "instance")
# While a shard is written, a thread hands its pages to the disk every WRITEBACK_INTERVAL_S
# (fdatasync), so that commit's fsync, which makes the shard durable before it takes its final
# name, waits for the last seconds of data only: on the paper clip (1.7 GB) it took 1.25 s at
# the end of a 62 s run, in which no other work is left to overlap it.
WRITEBACK_INTERVAL_S = 2.0


class _Writeback:
    """A daemon thread that calls ``fdatasync`` on ``path`` every ``interval_s`` seconds until
    :meth:`stop`. Usable while another handle writes the file; its errors are left to the final
    fsync, which reports them."""

    def __init__(self, path: Path, interval_s: float) -> None:
        self._fd = os.open(path, os.O_RDONLY)
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(interval_s,),
                                        name="rainbench-shard-writeback", daemon=True)
        self._thread.start()

    def _run(self, interval_s: float) -> None:
        sync = getattr(os, "fdatasync", os.fsync)  # macOS has no fdatasync
        while not self._stopped.wait(interval_s):
            try:
                sync(self._fd)
            except OSError:
                return

    def stop(self) -> None:
        """End the thread (after its current fdatasync) and close its descriptor; once."""
        if self._fd is None:
            return
        self._stopped.set()
        self._thread.join()
        os.close(self._fd)
        self._fd = None


def _deflate(image: np.ndarray) -> bytes:
    """One RGB chunk as HDF5's gzip filter stores it (a zlib stream); drops the GIL."""
    return isal_zlib.compress(np.ascontiguousarray(image), RGB_DEFLATE_LEVEL)


def _one_gzip_chunk_per_image(rgb: h5py.Dataset) -> bool:
    """Whether ``/rgb`` stores each image as one plain zlib stream (rainbench's layout), which
    can be read, or identified, from the stored chunk itself."""
    return (rgb.chunks == (1, 1) + rgb.shape[2:] and rgb.compression == "gzip" and not rgb.shuffle
            and not rgb.fletcher32 and rgb.scaleoffset is None)


def rgb_checksum(handle: h5py.File, rate_row: int, frame: int, raw=None) -> bytes:
    """A short identity of image ``/rgb[rate_row, frame]`` read without decoding it: the stored
    chunk's size and the Adler-32 checksum of the pixels that ends its zlib stream (the last 4
    bytes of a gzip-filtered chunk), read from ``raw`` (the shard file opened in binary; opened
    here when None). Images stored any other way give the sha256 of their pixels. Equal images
    written by the same rainbench on one machine give equal checksums (igzip's bytes depend on
    the image and may depend on the CPU's instruction sets, docs/format.md; shards written with
    libdeflate before 2026-11-27 differ too); a changed image changes it but with a chance of
    about 2^-32. Unequal checksums of equal images cost a cache miss, never a wrong match."""
    rgb = handle["rgb"]
    if _one_gzip_chunk_per_image(rgb):
        info = rgb.id.get_chunk_info_by_coord((rate_row, frame, 0, 0, 0))
        if info.filter_mask == 0 and info.byte_offset is not None and info.size >= 4:
            with contextlib.nullcontext(raw) if raw is not None else open(handle.filename, "rb") as source:
                source.seek(info.byte_offset + info.size - 4)
                return info.size.to_bytes(8, "little") + source.read(4)
    return hashlib.sha256(np.ascontiguousarray(read_rgb(handle, rate_row, frame)).tobytes()).digest()


def read_rgb(handle: h5py.File, rate_row: int, frame: int) -> np.ndarray:
    """Image ``/rgb[rate_row, frame]`` (H, W, 3) uint8 of an open shard.

    Reads the stored chunk and inflates it with libdeflate (2.6x faster than HDF5's zlib
    filter); a chunk stored any other way is read through h5py. A chunk that does not inflate
    raises :class:`ShardFormatError` naming the file.
    """
    rgb = handle["rgb"]
    if not (0 <= rate_row < rgb.shape[0] and 0 <= frame < rgb.shape[1]):
        raise IndexError(f"{handle.filename}: /rgb[{rate_row}, {frame}] is outside its "
                         f"{rgb.shape[0]} rates x {rgb.shape[1]} frames")
    shape = rgb.shape[2:]
    if not _one_gzip_chunk_per_image(rgb):
        return rgb[rate_row, frame]
    try:
        filter_mask, chunk = rgb.id.read_direct_chunk((rate_row, frame, 0, 0, 0))
        if filter_mask != 0:  # the filter was skipped for this chunk: h5py knows what to do
            return rgb[rate_row, frame]
        raw = deflate.zlib_decompress(chunk, int(np.prod(shape)))
    except (OSError, RuntimeError, KeyError, ValueError, deflate.DeflateError) as error:
        raise ShardFormatError(f"{handle.filename}: /rgb chunk of rate row {rate_row}, frame "
                               f"{frame} is corrupt ({error})") from error
    return np.frombuffer(raw, np.uint8).reshape(shape)


class ShardFormatError(ValueError):
    """A file that is not a complete, readable rainbench shard of a known version."""


def shard_name(scene_seed: int, frame_offset: int) -> str:
    return f"scene{scene_seed:06d}_f{frame_offset:05d}.h5"


class ShardWriter:
    """Write one shard. Use as a context manager; call :meth:`commit` when every frame is in.

    Leaving the ``with`` block without ``commit()`` (an error, a kill) removes the temporary
    file, and no file under the final name is created.
    """

    def __init__(self, path: str | Path, *, attrs: dict, rates: np.ndarray, num_frames: int,
                 width: int, height: int, K: np.ndarray, store: tuple[str, ...] = (),
                 threads: int | None = None, weather: list[dict] | None = None) -> None:
        unknown = sorted(set(store) - set(STORABLE))
        if unknown:
            raise ValueError(f"store: expected a subset of {STORABLE}, got {unknown}")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
            raise ValueError(f"threads: expected an integer >= 1 or None, got {threads!r}")
        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.name}.tmp-{os.getpid()}")
        self._num_frames = num_frames
        self._rates = np.asarray(rates, dtype=np.float32)
        with _naming(self.path):
            self._file = h5py.File(self._tmp, "w", libver=("v110", "latest"))
        try:
            with _naming(self.path):
                self._create(attrs, num_frames, width, height, K, store, weather)
            self._writeback = _Writeback(self._tmp, WRITEBACK_INTERVAL_S)
        except BaseException:
            with contextlib.suppress(OSError, RuntimeError):
                self._file.close()
            self._tmp.unlink(missing_ok=True)
            raise
        # igzip drops the GIL: images of one frame are compressed on ``threads`` threads.
        threads = threads or os.cpu_count() or 1
        self._pool = (ThreadPoolExecutor(max_workers=threads, thread_name_prefix="rainbench-deflate")
                      if threads > 1 else None)
        self._poses = np.zeros((num_frames, 4, 4), dtype=np.float64)
        self._labels: list[FrameLabels | None] = [None] * num_frames
        self._rain_box: list[tuple[np.ndarray, np.ndarray] | None] = [None] * num_frames
        num_rates = self._rates.shape[0]
        self._drop_count = np.zeros((num_rates, num_frames), dtype=np.int32)
        self._ssim = np.ones((num_rates, num_frames), dtype=np.float32)
        self._psnr = np.full((num_rates, num_frames), np.inf, dtype=np.float32)
        self._committed = False

    def _create(self, attrs, num_frames, width, height, K, store, weather) -> None:
        """The file's attributes and fixed datasets (everything but the frames and labels)."""
        num_rates = self._rates.shape[0]
        f = self._file
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = FORMAT_VERSION
        for key, value in attrs.items():
            f.attrs[key] = value
        f.attrs["width"] = width
        f.attrs["height"] = height
        f.create_dataset("rates", data=self._rates)
        f.create_dataset("rgb", shape=(num_rates, num_frames, height, width, 3), dtype=np.uint8,
                         chunks=(1, 1, height, width, 3), **RGB_COMPRESSION)
        if "depth" in store:
            f.create_dataset("depth", shape=(num_frames, height, width), dtype=np.float32,
                             chunks=(1, height, width), compression="gzip", compression_opts=1,
                             shuffle=True, fillvalue=np.inf)  # the fill is the sky: no geometry
        if "instance" in store:
            f.create_dataset("instance", shape=(num_frames, height, width), dtype=np.int32,
                             chunks=(1, height, width), compression="gzip", compression_opts=1,
                             shuffle=True, fillvalue=-1)  # the fill is no actor (0 is an actor's id)
        f.create_dataset("camera/K", data=np.asarray(K, dtype=np.float64))
        if weather is not None:  # one record per rate: /weather/<field> (R,) float64
            if len(weather) != num_rates:
                raise ValueError(f"weather: expected {num_rates} records (one per rate), got "
                                 f"{len(weather)}")
            for key in weather[0]:
                f.create_dataset(f"weather/{key}",
                                 data=np.array([record[key] for record in weather], np.float64))

    @property
    def committed(self) -> bool:
        return self._committed

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, *exc_info) -> None:
        if not self._committed:
            self.abort()

    def write_frame(self, index: int, rgb_by_rate: np.ndarray | Sequence[np.ndarray],
                    labels: FrameLabels,
                    T_world_cam: np.ndarray, *, depth: np.ndarray | None = None,
                    instance: np.ndarray | None = None, drop_count=None, ssim=None, psnr=None,
                    rain_coverage: np.ndarray | None = None,
                    contrast_loss: np.ndarray | None = None) -> None:
        """Store frame ``index`` (0..N-1): ``rgb_by_rate``, its images in the order of ``rates``,
        an (R, H, W, 3) uint8 array or a sequence of R (H, W, 3) uint8 arrays; ``labels`` its M
        labels; ``T_world_cam`` (4, 4) float camera pose (OpenCV axes); ``depth`` (H, W) float32
        metres and ``instance`` (H, W) int32 where the shard stores them; per-rate statistics
        ``drop_count``, ``ssim``, ``psnr`` (R,); per-box rain labels ``rain_coverage`` and
        ``contrast_loss`` (R, M) float32 (None: zeros). A wrong shape is a one-line ValueError
        here, before anything of the frame is stored, not a shard its readers refuse."""
        f = self._file
        rgb = f["rgb"]
        num_rates, image_shape = self._rates.shape[0], rgb.shape[2:]
        if np.shape(T_world_cam) != (4, 4):
            raise ValueError(f"T_world_cam: expected a (4, 4) pose, got {np.shape(T_world_cam)}")
        for name, value in (("rain_coverage", rain_coverage), ("contrast_loss", contrast_loss)):
            if value is not None and np.shape(value) != (num_rates, len(labels)):
                raise ValueError(f"{name}: expected ({num_rates}, {len(labels)}) (rates, labels of frame "
                                 f"{index}), got {np.shape(value)}")
        if isinstance(rgb_by_rate, np.ndarray):
            if rgb_by_rate.shape != (num_rates,) + image_shape or rgb_by_rate.dtype != np.uint8:
                raise ValueError(f"rgb_by_rate: expected {(num_rates,) + image_shape} uint8, got "
                                 f"{rgb_by_rate.shape} {rgb_by_rate.dtype}")
        elif len(rgb_by_rate) != num_rates or not all(
                isinstance(image, np.ndarray) and image.shape == image_shape
                and image.dtype == np.uint8 for image in rgb_by_rate):
            raise ValueError(f"rgb_by_rate: expected {num_rates} images of {image_shape} uint8, "
                             f"got {len(rgb_by_rate)} images "
                             f"{[getattr(image, 'shape', None) for image in rgb_by_rate][:3]}")
        chunks = (self._pool.map if self._pool is not None else map)(
            _deflate, [rgb_by_rate[r] for r in range(num_rates)])
        with _naming(self.path):
            for rate_index, chunk in enumerate(chunks):
                # A pre-compressed chunk is exactly what the gzip filter stores (filter mask 0),
                # so plain h5py reads it.
                rgb.id.write_direct_chunk((rate_index, index, 0, 0, 0), chunk)
            if "depth" in f:
                f["depth"][index] = depth
            if "instance" in f:
                f["instance"][index] = instance
        self._poses[index] = T_world_cam
        self._labels[index] = labels
        if drop_count is not None:
            self._drop_count[:, index] = drop_count
            self._ssim[:, index] = ssim
            self._psnr[:, index] = psnr
        num_boxes = len(labels)
        zeros = np.zeros((num_rates, num_boxes), dtype=np.float32)
        self._rain_box[index] = (
            zeros if rain_coverage is None else np.asarray(rain_coverage, np.float32),
            zeros if contrast_loss is None else np.asarray(contrast_loss, np.float32),
        )

    def copy_frames(self, source: h5py.File, first: int) -> None:
        """Store every frame of ``source``, an open shard of the same rates, image size and stored
        arrays, as frames ``first``, ``first + 1``, ...: its compressed image, depth and instance
        chunks as they are (nothing inflated or deflated again), poses, labels, ignore regions
        and rain statistics, in the order :meth:`write_frame` stores them, so the file is the
        one writing those frames would give. Used to join a shard rendered in pieces."""
        f = self._file
        rgb, source_rgb = f["rgb"], source["rgb"]
        num_rates, frames = source_rgb.shape[:2]
        if num_rates != self._rates.shape[0] or source_rgb.shape[2:] != rgb.shape[2:] \
                or first + frames > self._num_frames:
            raise ValueError(f"{source.filename}: expected at most {self._num_frames - first} frames of "
                             f"{rgb.shape[2:]} at {self._rates.shape[0]} rates, got {source_rgb.shape}")
        stored = [key for key in STORABLE if key in f]
        if sorted(stored) != sorted(key for key in STORABLE if key in source):
            raise ValueError(f"{source.filename}: expected the stored arrays {stored}")
        offsets = source["labels/offsets"][()]
        labels = {key: source[f"labels/{key}"][()] for key, _, _ in _LABEL_ARRAYS}
        rain_box = [source[f"labels/{key}"][()] for key in ("rain_coverage", "contrast_loss")]
        ignore_offsets = source["ignore/offsets"][()]
        ignore = {key: source[f"ignore/{key}"][()] for key, _, _ in _IGNORE_ARRAYS}
        poses = source["camera/T_world_cam"][()]
        drop_count, ssim, psnr = (source[f"rain/{key}"][()] for key in ("drop_count", "ssim", "psnr"))
        for frame in range(frames):
            index = first + frame
            with _naming(self.path):  # every chunk as it is stored: nothing inflated or deflated again
                for rate_index in range(num_rates):
                    mask, chunk = source_rgb.id.read_direct_chunk((rate_index, frame, 0, 0, 0))
                    rgb.id.write_direct_chunk((rate_index, index, 0, 0, 0), chunk, mask)
                for key in stored:
                    mask, chunk = source[key].id.read_direct_chunk((frame, 0, 0))
                    f[key].id.write_direct_chunk((index, 0, 0), chunk, mask)
            start, stop = int(offsets[frame]), int(offsets[frame + 1])
            low, high = int(ignore_offsets[frame]), int(ignore_offsets[frame + 1])
            self._labels[index] = FrameLabels(
                **{key: values[start:stop] for key, values in labels.items()},
                **{f"ignore_{key}": values[low:high] for key, values in ignore.items()})
            self._rain_box[index] = tuple(values[:, start:stop] for values in rain_box)
            self._poses[index] = poses[frame]
            self._drop_count[:, index] = drop_count[:, frame]
            self._ssim[:, index] = ssim[:, frame]
            self._psnr[:, index] = psnr[:, frame]

    def commit(self) -> Path:
        """Write the labels, flush, and move the shard to its final name. A failed write (a
        full disk) raises a one-line OSError naming the shard (``PATH: <reason>``)."""
        missing = [i for i, labels in enumerate(self._labels) if labels is None]
        if missing:
            raise RuntimeError(f"shard {self.path.name}: frames {missing[:5]} were never written")
        self._writeback.stop()
        with _naming(self.path):
            self._write_tables()
        if self._pool is not None:
            self._pool.shutdown()
        self._committed = True
        return self.path

    def _write_tables(self) -> None:
        """Labels, poses and rain statistics; then flush, sync and rename into place."""
        f = self._file
        f.create_dataset("camera/T_world_cam", data=self._poses)
        counts = np.array([len(labels) for labels in self._labels], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        f.create_dataset("labels/offsets", data=offsets)
        for key, dtype, width in _LABEL_ARRAYS:
            parts = [getattr(labels, key) for labels in self._labels]
            shape = (0, width) if width else (0,)
            data = np.concatenate(parts).astype(dtype) if counts.sum() else np.zeros(shape, dtype)
            f.create_dataset(f"labels/{key}", data=data)
        ignore_counts = np.array([len(labels.ignore_instance_id) for labels in self._labels], np.int64)
        f.create_dataset("ignore/offsets", data=np.concatenate([[0], np.cumsum(ignore_counts)]).astype(np.int64))
        for key, dtype, width in _IGNORE_ARRAYS:
            parts = [getattr(labels, f"ignore_{key}") for labels in self._labels]
            data = (np.concatenate(parts).astype(dtype) if ignore_counts.sum()
                    else np.zeros((0, width) if width else (0,), dtype))
            f.create_dataset(f"ignore/{key}", data=data)
        num_rates = self._rates.shape[0]
        for position, key in ((0, "rain_coverage"), (1, "contrast_loss")):
            parts = [pair[position] for pair in self._rain_box]
            data = (np.concatenate(parts, axis=1) if counts.sum()
                    else np.zeros((num_rates, 0), np.float32))
            f.create_dataset(f"labels/{key}", data=data.astype(np.float32))
        f.create_dataset("rain/drop_count", data=self._drop_count)
        f.create_dataset("rain/ssim", data=self._ssim)
        f.create_dataset("rain/psnr", data=self._psnr)
        f.flush()
        f.close()
        with open(self._tmp, "rb") as handle:
            os.fsync(handle.fileno())
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        """Remove the temporary file. Closing it may fail again (the disk that failed a write
        is still full): that is not reported, the error that led here is."""
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
        self._writeback.stop()
        try:
            with contextlib.suppress(OSError, RuntimeError):
                self._file.close()
        finally:
            self._tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def _naming(path: Path):
    """Failures to write shard ``path`` as one-line OSErrors naming it: the file system's, and
    HDF5's report of a failed write (h5py raises that as a 300-character RuntimeError naming the
    temporary file); other RuntimeErrors pass unchanged."""
    try:
        yield
    except OSError as error:
        raise file_error(error, path) from error
    except RuntimeError as error:
        named = file_error(OSError(str(error)), path)
        if named.errno is None:
            raise
        raise named from error


_NOT_THE_FILES_FAULT = frozenset({errno.EMFILE, errno.ENFILE, errno.EACCES, errno.EPERM, errno.ENOMEM})
"""Errors opening a file that say nothing of its contents (too many open files, no permission,
no memory): :func:`open_shard` raises them as an OSError naming the file, not as a
:class:`ShardFormatError`."""


def open_shard(path: str | Path) -> h5py.File:
    """Open a shard read-only after checking its format; errors name the file. A file that
    cannot be opened for a reason outside it (:data:`_NOT_THE_FILES_FAULT`: ``PATH: Too many
    open files``) is an OSError; one that is not a readable rainbench shard, a
    :class:`ShardFormatError`."""
    path = Path(path)
    try:
        handle = h5py.File(path, "r")
    except OSError as error:
        if error.errno in _NOT_THE_FILES_FAULT:  # a healthy shard must not be called corrupt
            raise file_error(OSError(error.errno, os.strerror(error.errno)), path) from error
        raise ShardFormatError(f"{path}: not a readable HDF5 shard ({error})") from error
    except ValueError as error:
        raise ShardFormatError(f"{path}: not a readable HDF5 shard ({error})") from error
    try:
        if handle.attrs.get("format") != FORMAT:
            raise ShardFormatError(f"{path}: not a rainbench shard (format attribute "
                                   f"{handle.attrs.get('format')!r})")
        if "format_version" not in handle.attrs:
            raise ShardFormatError(f"{path}: no format_version attribute; this rainbench reads "
                                   f"versions {', '.join(map(str, READABLE_VERSIONS))}")
        version = _plain(handle.attrs["format_version"])
        if not _is_integer(version) or int(version) not in READABLE_VERSIONS:
            shown = version if _is_integer(version) else f"{version!r} (not an integer)"
            raise ShardFormatError(f"{path}: unknown format_version {shown}; this rainbench "
                                   f"reads versions {', '.join(map(str, READABLE_VERSIONS))}")
        for key in REQUIRED_DATASETS:
            if key not in handle:
                raise ShardFormatError(f"{path}: incomplete shard, /{key} is missing")
        _check_attributes(handle, path)
    except BaseException:
        handle.close()
        raise
    return handle


REQUIRED_DATASETS = ("rates", "rgb", "camera/K", "camera/T_world_cam", "labels/offsets",
                     "labels/bbox", "rain/drop_count", "rain/ssim", "rain/psnr")
"""Datasets every shard of every readable version holds (the other labels are checked by
:func:`check_labels`; ``/ignore``, ``/depth``, ``/instance`` and ``/weather`` are optional)."""
RAIN_MODEL_VALUES = ("jeon2022", "physical")
SKY_VALUES = ("clear", "cloudy", "overcast")
TIME_OF_DAY_VALUES = ("day", "dusk", "night")
LAYOUT_VALUES = ("street", "intersection", "curved", "highway", "residential")
"""The values docs/format.md allows for the ``rain_model``, ``sky``, ``time_of_day`` and
``layout`` attributes (the generator's own lists; a test keeps them equal)."""


def _plain(value):
    """An attribute value as Python shows it in a message (numpy scalars as their item)."""
    return value.item() if isinstance(value, np.generic) else value


def _is_integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _check_attributes(handle: h5py.File, path) -> None:
    """Refuse root attributes of the wrong type or outside docs/format.md's values: ``width`` and
    ``height`` positive integers; where present, ``fps`` a positive finite number, ``rain_model``,
    ``sky``, ``time_of_day`` and ``layout`` among their values, ``weather_follows_rate`` a bool and
    ``config`` a JSON object."""
    attrs = handle.attrs

    def text(key):
        value = attrs[key]
        return value.decode() if isinstance(value, bytes) else value

    for key in ("width", "height"):
        if key not in attrs or not _is_integer(attrs[key]) or attrs[key] < 1:
            raise ShardFormatError(f"{path}: attribute {key} is {_plain(attrs.get(key))!r}; expected a "
                                   "positive integer of pixels")
    if "fps" in attrs:
        fps = attrs["fps"]
        if not isinstance(fps, (int, float, np.integer, np.floating)) or isinstance(fps, (bool, np.bool_)) \
                or not (np.isfinite(fps) and fps > 0):
            raise ShardFormatError(f"{path}: attribute fps is {_plain(fps)!r}; expected a positive number")
    for key, allowed in (("rain_model", RAIN_MODEL_VALUES), ("sky", SKY_VALUES),
                         ("time_of_day", TIME_OF_DAY_VALUES), ("layout", LAYOUT_VALUES)):
        if key in attrs and text(key) not in allowed:
            raise ShardFormatError(f"{path}: attribute {key} is {text(key)!r}; expected one of "
                                   f"{', '.join(allowed)}")
    if "weather_follows_rate" in attrs and not isinstance(attrs["weather_follows_rate"], (bool, np.bool_)):
        raise ShardFormatError(f"{path}: attribute weather_follows_rate is "
                               f"{_plain(attrs['weather_follows_rate'])!r}; expected a bool")
    if "config" in attrs:
        try:
            config = json.loads(text("config"))
        except (TypeError, ValueError, RecursionError):
            config = None
        if not isinstance(config, dict):
            raise ShardFormatError(f"{path}: attribute config is not a JSON object")


SSIM_TOLERANCE = 1e-5
"""How far outside [-1, 1] a stored SSIM may lie: it is computed in float32, and an image against
itself (or one the rain left unchanged) can come out a few units in the last place above 1."""


def _check_frame_data(handle: h5py.File, path, num_rates: int, frames: int) -> None:
    """Refuse the per-frame arrays a reader or an export would serve wrong: ``/rain/*`` (R, N)
    with drop counts >= 0, SSIM in [-1, 1] (to :data:`SSIM_TOLERANCE`) and PSNR >= 0 (``inf``
    allowed); ``/camera/T_world_cam``
    (N, 4, 4) finite; ``/weather/<field>`` (R,) finite where present."""
    try:
        arrays = {key: handle[key][()] for key in ("rain/drop_count", "rain/ssim", "rain/psnr",
                                                   "camera/T_world_cam")}
        weather = {key: handle[f"weather/{key}"][()] for key in handle["weather"]} if "weather" in handle else {}
    except (KeyError, OSError, TypeError, ValueError, AttributeError) as error:
        raise ShardFormatError(f"{path}: per-frame data unreadable ({type(error).__name__}: {error})") from None
    expected = {"rain/drop_count": (num_rates, frames), "rain/ssim": (num_rates, frames),
                "rain/psnr": (num_rates, frames), "camera/T_world_cam": (frames, 4, 4)}
    for key, shape in expected.items():
        if arrays[key].shape != shape or arrays[key].dtype.kind not in "fiu":
            raise ShardFormatError(f"{path}: /{key} has shape {arrays[key].shape} "
                                   f"{arrays[key].dtype}, expected {shape} numbers")
    with np.errstate(invalid="ignore"):
        bad = {
            "rain/drop_count": arrays["rain/drop_count"] < 0,
            "rain/ssim": ~((arrays["rain/ssim"] >= -1 - SSIM_TOLERANCE) & (arrays["rain/ssim"] <= 1 + SSIM_TOLERANCE)),
            "rain/psnr": ~(arrays["rain/psnr"] >= 0),
            "camera/T_world_cam": ~np.isfinite(arrays["camera/T_world_cam"]).all(axis=(1, 2)),
        }
    what = {"rain/drop_count": "a negative drop count", "rain/ssim": "an SSIM outside [-1, 1]",
            "rain/psnr": "a PSNR that is NaN or negative", "camera/T_world_cam": "a non-finite pose"}
    for key, rows in bad.items():
        if rows.any():
            index = np.argwhere(rows)[0]
            frame = int(index[-1]) if rows.ndim == 2 else int(index[0])
            raise ShardFormatError(f"{path}: frame {frame}: /{key} holds {what[key]}")
    for key, values in weather.items():
        if values.shape != (num_rates,) or values.dtype.kind not in "fiu" or not np.isfinite(values).all():
            raise ShardFormatError(f"{path}: /weather/{key} is not {num_rates} finite numbers "
                                   "(one per rate)")


def _frame_rows(handle: h5py.File, group: str, frame: int) -> tuple[int, int]:
    """(start, stop) rows of ``frame`` in ``/<group>``; an IndexError naming the file for a frame
    outside 0..N-1 (a negative frame read ``offsets[-1]:offsets[0]``, an empty slice, before)."""
    offsets = handle[f"{group}/offsets"]
    _check_frame(handle, offsets.shape[0] - 1, frame)
    return int(offsets[frame]), int(offsets[frame + 1])


def _check_frame(handle: h5py.File, frames: int, frame) -> None:
    """An IndexError naming the file unless ``frame`` is an int in 0..``frames`` - 1."""
    if not _is_integer(frame) or not 0 <= frame < frames:
        raise IndexError(f"{handle.filename}: frame {frame!r} is outside its {frames} frames "
                         f"(expected an int in 0..{frames - 1})")


def read_frame_labels(handle: h5py.File, frame: int) -> dict[str, np.ndarray]:
    """Labels of ``frame`` (an int in 0..N-1; else IndexError naming the file) as arrays: the
    keys of /labels, each sliced to that frame's M rows (``bbox``, ``bbox_amodal`` (M, 4)
    float32 xyxy pixel-edge; ``class_id``, ``instance_id`` (M,) int32; ``visible_fraction``,
    ``truncation`` (M,) float32; ``rain_coverage``, ``contrast_loss`` (R, M) float32)."""
    start, stop = _frame_rows(handle, "labels", frame)
    labels = {}
    for key in handle["labels"]:
        if key == "offsets":
            continue
        data = handle[f"labels/{key}"]
        labels[key] = data[:, start:stop] if data.ndim == 2 and key in (
            "rain_coverage", "contrast_loss") else data[start:stop]
    return labels


_LABEL_ARRAYS = (("bbox", np.float32, 4), ("bbox_amodal", np.float32, 4), ("class_id", np.int32, 0),
                 ("instance_id", np.int32, 0), ("visible_fraction", np.float32, 0), ("truncation", np.float32, 0))
"""``/labels/<key>`` (besides offsets and the per-rate rain labels): dtype and row width (0: one
value a row), in the order they are written."""
_IGNORE_ARRAYS = (("bbox", np.float32, 4), ("class_id", np.int32, 0), ("instance_id", np.int32, 0))
"""``/ignore/<key>``: dtype and row width (0: one value a row) of the ignore regions."""


def read_frame_ignore(handle: h5py.File, frame: int) -> dict[str, np.ndarray]:
    """Ignore regions of ``frame``: ``bbox`` (N, 4) float32 xyxy pixel-edge, ``class_id`` and
    ``instance_id`` (N,) int32 (:class:`~rainbench.store.labels.FrameLabels`). Shards written
    before ignore regions have none: every array is empty."""
    if "ignore" not in handle:  # the same frame check as with /ignore (its offsets' length)
        _check_frame(handle, handle["labels/offsets"].shape[0] - 1, frame)
        return {key: np.zeros((0, width) if width else (0,), dtype) for key, dtype, width in _IGNORE_ARRAYS}
    start, stop = _frame_rows(handle, "ignore", frame)
    return {key: handle[f"ignore/{key}"][start:stop] for key, _, _ in _IGNORE_ARRAYS}


def check_labels(handle, path: str | Path | None = None) -> None:
    """Refuse an open shard whose labels a reader would serve wrong: :class:`ShardFormatError`
    naming the file and, for a bad row, the frame.

    Checks ``/rgb`` against ``/rates`` and the ``width``/``height`` attributes, that
    ``/labels/offsets`` starts at 0, never decreases and ends at the label count, that every
    label array has one row per label, boxes finite with ``0 <= x1 < x2 <= W`` and
    ``0 <= y1 < y2 <= H``, amodal boxes finite and ordered, ``class_names`` the first names of
    :data:`rainbench.store.classes.CLASS_NAMES` (older shards list 4, newer 8: the ids mean the
    same), class ids naming a class of ``class_names`` that rainbench labels (not 4 airplane or
    6 train), instance ids >= 0, visible fractions, truncations and the per-box rain statistics
    in [0, 1], and the per-frame data of :func:`_check_frame_data` (``/rain/*``, poses,
    ``/weather``).
    """
    path = path if path is not None else handle.filename
    try:
        rgb = handle["rgb"]
        rgb_shape, _ = tuple(rgb.shape), (rgb.chunks, rgb.compression, rgb.dtype)
        rate_values = handle["rates"][()]
        rates = rate_values.shape
        width, height = int(handle.attrs["width"]), int(handle.attrs["height"])
        class_names = json.loads(handle.attrs["class_names"])
        group = handle["labels"]
        arrays = {key: group[key][()] for key in group if key in _LABEL_SHAPES}
    except (KeyError, OSError, TypeError, ValueError, RecursionError) as error:
        raise ShardFormatError(f"{path}: labels or attributes unreadable "
                               f"({type(error).__name__}: {error})") from None
    if len(rates) != 1 or len(rgb_shape) != 5 or rgb_shape[0] != rates[0] \
            or rgb_shape[2:] != (height, width, 3):
        raise ShardFormatError(f"{path}: /rgb has shape {rgb_shape}; expected (R, N, {height}, "
                               f"{width}, 3) with R = {rates[0] if rates else '?'} rates")
    if not isinstance(class_names, list):
        raise ShardFormatError(f"{path}: class_names is not a JSON list")
    if not class_names or class_names != list(CLASS_NAMES[:len(class_names)]):
        raise ShardFormatError(f"{path}: class_names {str(class_names)[:120]} are not the rainbench "
                               f"classes (the first names of {list(CLASS_NAMES)})")
    if rgb.dtype != np.uint8:
        raise ShardFormatError(f"{path}: /rgb holds {rgb.dtype}, not uint8")
    with np.errstate(invalid="ignore"):
        values = rate_values.astype(np.float64) if rate_values.dtype.kind in "fiu" else None
        if values is None or not (np.isfinite(values).all() and (values >= 0).all()
                                  and (np.diff(values) > 0).all()):
            raise ShardFormatError(f"{path}: /rates {rate_values.tolist()!r:.80} are not "
                                   "ascending finite rates >= 0")
    frames, num_rates = rgb_shape[1], rgb_shape[0]
    for key in _LABEL_SHAPES:
        if key not in arrays:
            raise ShardFormatError(f"{path}: incomplete shard, /labels/{key} is missing")
    _check_frame_data(handle, path, num_rates, frames)
    offsets = arrays["offsets"]
    count = arrays["bbox"].shape[0] if arrays["bbox"].ndim else -1
    _check_offsets(path, "labels", offsets, frames, count)
    for key, shape in _LABEL_SHAPES.items():
        if key == "offsets" or key not in arrays:
            continue
        expected = tuple(count if s == "M" else num_rates if s == "R" else s for s in shape)
        if arrays[key].shape != expected:
            raise ShardFormatError(f"{path}: /labels/{key} has shape {arrays[key].shape}, "
                                   f"expected {expected}")

    def refuse(rows: np.ndarray, what: str) -> None:
        if rows.size:
            row = int(rows[0])
            frame = int(np.searchsorted(offsets, row, side="right") - 1)
            raise ShardFormatError(f"{path}: frame {frame}: label {row - int(offsets[frame])} "
                                   f"{what}")

    with np.errstate(invalid="ignore"):
        box = arrays["bbox"].astype(np.float64)
        rows = np.flatnonzero(_outside_image(box, width, height))
        if rows.size:
            refuse(rows, f"has bbox {box[rows[0]].tolist()}; expected finite 0 <= x1 < x2 <= "
                         f"{width}, 0 <= y1 < y2 <= {height}")
        amodal = arrays["bbox_amodal"].astype(np.float64)
        refuse(np.flatnonzero(~np.isfinite(amodal).all(axis=1) | (amodal[:, 0] > amodal[:, 2])
                              | (amodal[:, 1] > amodal[:, 3])), "has a non-finite or inverted bbox_amodal")
        class_id = arrays["class_id"]
        if not np.issubdtype(class_id.dtype, np.integer):
            raise ShardFormatError(f"{path}: /labels/class_id holds {class_id.dtype}, not integers")
        refuse(np.flatnonzero((class_id < 0) | (class_id >= len(class_names))),
               f"has a class_id outside 0..{len(class_names) - 1}")
        unlabelled = np.flatnonzero(~np.isin(class_id, LABELLED_CLASSES))
        if unlabelled.size:
            refuse(unlabelled, f"has class_id {int(class_id[unlabelled[0]])} "
                               f"({CLASS_NAMES[int(class_id[unlabelled[0]])]}), which rainbench never labels")
        refuse(np.flatnonzero(arrays["instance_id"] < 0), "has a negative instance_id")
        for key in ("visible_fraction", "truncation"):
            values = arrays[key].astype(np.float64)
            refuse(np.flatnonzero(~((values >= 0) & (values <= 1))), f"has {key} outside [0, 1]")
        for key in ("rain_coverage", "contrast_loss"):  # an opacity and a clipped loss: [0, 1]
            values = arrays[key].astype(np.float64)
            refuse(np.flatnonzero(~((values >= 0) & (values <= 1)).all(axis=0)), f"has {key} outside [0, 1]")
    if "ignore" in handle:
        _check_ignore(handle, path, frames, width, height, len(class_names))


def _outside_image(box: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) bool: which of the (N, 4) float64 xyxy boxes are not finite with
    0 <= x1 < x2 <= width and 0 <= y1 < y2 <= height (to 1e-3 px)."""
    tol = 1e-3
    with np.errstate(invalid="ignore"):
        return (~np.isfinite(box).all(axis=1) | (box[:, 0] >= box[:, 2]) | (box[:, 1] >= box[:, 3])
                | (box[:, 0] < -tol) | (box[:, 1] < -tol) | (box[:, 2] > width + tol)
                | (box[:, 3] > height + tol))


def _check_offsets(path, group: str, offsets: np.ndarray, frames: int, count: int) -> None:
    """Refuse ``/<group>/offsets`` unless (frames + 1,) integers from 0, never decreasing, to
    ``count`` (the rows of ``/<group>/bbox``)."""
    if offsets.shape != (frames + 1,) or not np.issubdtype(offsets.dtype, np.integer):
        raise ShardFormatError(f"{path}: /{group}/offsets has shape {offsets.shape} "
                               f"{offsets.dtype}; expected ({frames + 1},) integers for {frames} "
                               "frames")
    if offsets[0] != 0:
        raise ShardFormatError(f"{path}: frame 0: /{group}/offsets starts at {offsets[0]}, not 0")
    steps = np.diff(offsets)
    if np.any(steps < 0):
        frame = int(np.flatnonzero(steps < 0)[0])
        raise ShardFormatError(f"{path}: frame {frame}: /{group}/offsets decreases "
                               f"({offsets[frame]} -> {offsets[frame + 1]})")
    if offsets[-1] != count:
        raise ShardFormatError(f"{path}: frame {frames - 1}: /{group}/offsets ends at "
                               f"{offsets[-1]} but /{group}/bbox has {count} rows")


def _check_ignore(handle, path, frames: int, width: int, height: int, num_classes: int) -> None:
    """Refuse ``/ignore`` (ignore regions, optional) unless complete and consistent: offsets as
    for labels, one row per region in every array, boxes finite and ordered inside the image,
    class ids of labelled classes, instance ids >= 0."""
    try:
        group = handle["ignore"]
        arrays = {key: group[key][()] for key in ("offsets",) + tuple(k for k, _, _ in _IGNORE_ARRAYS)}
    except (KeyError, OSError, TypeError, ValueError) as error:
        raise ShardFormatError(f"{path}: /ignore incomplete or unreadable "
                               f"({type(error).__name__}: {error})") from None
    count = arrays["bbox"].shape[0] if arrays["bbox"].ndim else -1
    _check_offsets(path, "ignore", arrays["offsets"], frames, count)
    for key, _, width_of_row in _IGNORE_ARRAYS:
        expected = (count, width_of_row) if width_of_row else (count,)
        if arrays[key].shape != expected:
            raise ShardFormatError(f"{path}: /ignore/{key} has shape {arrays[key].shape}, expected {expected}")
    box = arrays["bbox"].astype(np.float64)
    class_id = arrays["class_id"]
    bad = _outside_image(box, width, height)
    if not np.issubdtype(class_id.dtype, np.integer):
        raise ShardFormatError(f"{path}: /ignore/class_id holds {class_id.dtype}, not integers")
    bad |= ~np.isin(class_id, LABELLED_CLASSES) | (class_id >= num_classes) | (arrays["instance_id"] < 0)
    rows = np.flatnonzero(bad)
    if rows.size:
        row = int(rows[0])
        frame = int(np.searchsorted(arrays["offsets"], row, side="right") - 1)
        raise ShardFormatError(f"{path}: frame {frame}: ignore region {row - int(arrays['offsets'][frame])} "
                               f"has bbox {box[row].tolist()}, class_id {int(class_id[row])}, instance_id "
                               f"{int(arrays['instance_id'][row])}; expected a finite box with 0 <= x1 < x2 <= "
                               f"{width}, 0 <= y1 < y2 <= {height}, a labelled class, an instance id >= 0")


_LABEL_SHAPES = {
    "offsets": None, "bbox": ("M", 4), "bbox_amodal": ("M", 4), "class_id": ("M",),
    "instance_id": ("M",), "visible_fraction": ("M",), "truncation": ("M",),
    "rain_coverage": ("R", "M"), "contrast_loss": ("R", "M"),
}


def open_checked(path: str | Path):
    """:func:`open_shard` then :func:`check_labels`: how every rainbench reader opens a shard.
    Every failure is one line naming the file: a :class:`ShardFormatError`, or an OSError for a
    file that cannot be opened for a reason outside it (:data:`_NOT_THE_FILES_FAULT`)."""
    with _damage_named(path):
        handle = open_shard(path)
    try:
        # the checks read every group: damaged metadata there surfaces from h5py too (a flipped
        # byte in /weather's links: "Link iteration failed", found by the long fuzz profile)
        with _damage_named(path):
            check_labels(handle, path)
    except BaseException:
        handle.close()
        raise
    return handle


@contextlib.contextmanager
def _damage_named(path: str | Path):
    """Re-raise what h5py raises on a damaged file (KeyError, OSError, RuntimeError, TypeError,
    ValueError) as a one-line :class:`ShardFormatError` naming ``path``; a
    :class:`ShardFormatError` and an OSError that says nothing of the file
    (:data:`_NOT_THE_FILES_FAULT`) pass as they are."""
    try:
        yield
    except ShardFormatError:
        raise
    except OSError as error:
        if error.errno in _NOT_THE_FILES_FAULT:
            raise
        reason = " ".join(str(error).split())
        raise ShardFormatError(f"{path}: not a readable shard ({type(error).__name__}: {reason})") from None
    except (KeyError, RuntimeError, TypeError, ValueError) as error:
        # damaged HDF5 metadata surfaces from h5py as KeyError, OSError, ...
        reason = " ".join(str(error).split())
        raise ShardFormatError(f"{path}: not a readable shard ({type(error).__name__}: "
                               f"{reason})") from None
