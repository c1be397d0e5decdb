"""The one reader of a rainbench dataset: shard order, image ids, rate rows, frame walks.

Every reader in rainbench (the numpy and torch readers, exports, videos, previews, statistics,
the evaluator and the paper report) opens a dataset through :class:`Dataset`, so that:

- shards come in one order: manifest order for a dataset directory (sorted names without a
  manifest), the given order for a list of shards;
- images are numbered one way: ids 1-based, shard order, then frame order (an exported
  ``000007.png`` is image 7 in evaluation too);
- a rate is found one way: :meth:`Dataset.rate_row` compares the decimal the user wrote
  (``"12.5"``, ``0.1``) with each stored rate's shortest decimal
  (:func:`rainbench.store.rates.rate_rows`), whatever the storage dtype;
- every shard is checked once, labels included, when the dataset is built
  (:func:`rainbench.store.shard.open_checked`); later opens check its format.
"""

from __future__ import annotations

import hashlib
import os

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .classes import parse_classes
from .manifest import DatasetError, entry_problem, read_listing, unfinished_count
from .rates import MissingRate, rate_decimal, rate_rows
from .shard import open_checked, open_shard, read_frame_ignore, read_frame_labels, read_rgb, rgb_checksum


MAX_OPEN_SHARDS = 64
"""Shards :meth:`Dataset.handle` keeps open at once in a process (each is an open file; HDF5's
chunk cache is per file)."""


@dataclass(frozen=True)
class Image:
    """One frame of the dataset: ``image_id`` (1-based), ``shard`` (path), ``frame`` (index in
    the shard) and ``shard_index`` (position of the shard in :attr:`Dataset.shards`)."""

    image_id: int
    shard: Path
    frame: int
    shard_index: int


@dataclass(frozen=True)
class Frame:
    """One frame read at the dataset's selected rates.

    ``rgb``: one (H, W, 3) uint8 RGB image per rate of :attr:`Dataset.rates` (in that order);
    ``labels``: :func:`rainbench.store.shard.read_frame_labels` (``bbox`` (M, 4) float32 xyxy
    pixel-edge, ``class_id`` (M,) int32, ...; ``rain_coverage`` and ``contrast_loss`` (R, M)
    sliced to the selected rates); ``size``: (height, width); ``ignore``: the frame's ignore
    regions, :func:`rainbench.store.shard.read_frame_ignore` (``bbox`` (N, 4) float32 xyxy
    pixel-edge, ``class_id``, ``instance_id`` (N,) int32; empty for shards written before them).
    """

    image: Image
    rgb: list[np.ndarray]
    labels: dict[str, np.ndarray]
    size: tuple[int, int]
    ignore: dict[str, np.ndarray]


def class_ids(classes) -> tuple[int, ...]:
    """``classes`` (names or ids of the labelled classes) as ascending ids, else a one-line
    DatasetError (an unknown or misspelt class dropped every label without a word)."""
    if isinstance(classes, (str, bytes)) or not isinstance(classes, (Sequence, np.ndarray, set, frozenset)):
        raise DatasetError(f"classes: expected a list of class names or ids, got {classes!r}")
    try:
        return parse_classes(list(classes))
    except ValueError as error:
        raise DatasetError(str(error).replace("--classes: ", "classes: ", 1)) from None


class Dataset:
    """A dataset directory, one shard, or a list of shards, read through one index.

    ``rates``: the rates to read (mm/h, as decimals, strings or numbers; each must be in every
    shard) or None for every rate, which every shard must then share. Failures are one-line
    :class:`DatasetError` (or :class:`rainbench.store.shard.ShardFormatError`) naming the file.

    ``labels_only``: read labels only (``rainbench stats``): with ``rates`` None the shards'
    rates need not agree and :attr:`rates` is empty.

    Attributes: ``shards`` (list of paths), ``rates`` (tuple of floats: the selected rates as
    their decimals), ``images`` (tuple of :class:`Image` in image-id order), ``root`` (the
    dataset directory, or None for shard files), ``unfinished`` (the finished shards listed by
    the manifest of a dataset whose generation has not finished; None when complete or without
    a manifest).
    """

    def __init__(self, data: str | Path | Sequence[str | Path],
                 rates: Sequence[float | str] | None = None, *, labels_only: bool = False) -> None:
        # each shard with its manifest entry (None without one), and the manifest: read once
        listed, manifest = read_listing(data)
        self.unfinished: int | None = unfinished_count(manifest)
        self.shards: list[Path] = [path for path, _ in listed]
        single = not isinstance(data, (list, tuple))
        self.root: Path | None = Path(data) if single and Path(data).is_dir() else None
        if rates is not None:
            if isinstance(rates, (str, bytes)) or not isinstance(rates, (Sequence, np.ndarray)):
                raise DatasetError(f"rates: expected a list of rates in mm/h, got {rates!r}")
            if len(rates) == 0:
                raise DatasetError("rates: expected at least one rate, got an empty list")
            try:
                wanted = list(dict.fromkeys(rate_decimal(rate) for rate in rates))
            except ValueError as error:
                raise DatasetError(str(error)) from None
        images: list[Image] = []
        self._rows: list[list[int]] = []
        self._sizes: list[tuple[int, int]] = []
        first: np.ndarray | None = None
        for number, (path, entry) in enumerate(listed):
            with open_checked(path) as handle:  # refuses NaN boxes, inconsistent offsets
                disagreement = entry_problem(path, entry, handle) if entry is not None else None
                if disagreement is not None:
                    raise DatasetError(disagreement)
                stored = handle["rates"][()]
                frames = int(handle["labels/offsets"].shape[0]) - 1
                if entry is not None and frames != entry["frames"]:
                    raise DatasetError(f"{path}: {frames} frames, its manifest says {entry['frames']}")
                self._sizes.append((int(handle.attrs["height"]), int(handle.attrs["width"])))
            if labels_only and rates is None:  # statistics: the shards' rates need not agree
                wanted = []
            elif rates is None:
                if first is None:
                    first, wanted = stored, [rate_decimal(value) for value in stored]
                elif stored.shape != first.shape or not np.array_equal(stored, first):
                    raise DatasetError(
                        f"{path.name} has rates {stored.tolist()} but {self.shards[0].name} has "
                        f"{first.tolist()}; all shards of a dataset must share the same rates "
                        "(or select rates that every shard holds)")
            try:
                self._rows.append(rate_rows(stored, wanted))
            except MissingRate as missing:
                raise DatasetError(f"rate {format(missing.rate, 'f')} mm/h is not in the dataset: "
                                   f"{path.name} {missing}") from None
            images += [Image(len(images) + 1 + frame, path, frame, number) for frame in range(frames)]
        self.rates: tuple[float, ...] = tuple(float(decimal) for decimal in wanted)
        self._decimals = tuple(wanted)
        self.images: tuple[Image, ...] = tuple(images)
        self._handles: dict[int, object] = {}  # :meth:`handle`'s open files, of process _handles_pid
        self._handles_pid: int | None = None

    def __len__(self) -> int:
        return len(self.images)

    def image(self, image_id: int) -> Image:
        """The :class:`Image` of ``image_id`` (1-based)."""
        if not 1 <= image_id <= len(self.images):
            raise IndexError(f"image id {image_id} out of range 1..{len(self.images)}")
        return self.images[image_id - 1]

    def rate_number(self, rate: float | str) -> int:
        """Position of ``rate`` in :attr:`rates` (compared as decimals); DatasetError if absent."""
        try:
            decimal = rate_decimal(rate)
        except ValueError as error:
            raise DatasetError(str(error)) from None
        if decimal not in self._decimals:
            raise DatasetError(f"rate {format(decimal, 'f')} mm/h is not among the selected "
                               f"rates ({', '.join(format(d, 'f') for d in self._decimals)})")
        return self._decimals.index(decimal)

    def rate_row(self, rate: float | str, shard: int = 0) -> int:
        """Row of ``/rgb`` (and ``/rates``) holding ``rate`` in shard number ``shard``."""
        return self._rows[shard][self.rate_number(rate)]

    def size(self, shard: int = 0) -> tuple[int, int]:
        """(height, width) of the images of shard number ``shard``."""
        return self._sizes[shard]

    def open(self, shard: int):
        """Open shard number ``shard`` read-only (an ``h5py.File``; close it). Its format is
        checked again; its labels were checked when the dataset was built."""
        return open_shard(self.shards[shard])

    def handle(self, shard: int):
        """Shard number ``shard`` open read-only for random access by this process: opened on
        first use and kept open until :meth:`close`, or until :data:`MAX_OPEN_SHARDS` others
        have been used since (the least recently used is closed: a shuffled epoch over thousands
        of shards stays under the process's open-file limit). So use a handle right away rather
        than keep it, and call this from one thread at a time. A forked ``DataLoader`` worker
        opens its own (open files never cross processes, nor are they pickled), so readers built
        on a dataset are safe with ``num_workers > 0``."""
        if self._handles_pid != os.getpid():
            self._handles, self._handles_pid = {}, os.getpid()
        handle = self._handles.pop(shard, None)
        if handle is None:
            if len(self._handles) >= MAX_OPEN_SHARDS:
                self._handles.pop(next(iter(self._handles))).close()
            handle = self.open(shard)
        self._handles[shard] = handle  # the most recently used last
        return handle

    def close(self) -> None:
        """Close the files :meth:`handle` opened in this process."""
        if self._handles_pid == os.getpid():
            for handle in self._handles.values():
                handle.close()
        self._handles = {}

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_handles"], state["_handles_pid"] = {}, None
        return state

    def walk(self, images: Sequence[Image] | None = None) -> Iterator[tuple[Image, object]]:
        """Yield ``(image, handle)`` for ``images`` (default all) in their order: each shard is
        opened once while its frames follow each other, and closed when the walk moves on."""
        handle, current = None, None
        try:
            for image in self.images if images is None else images:
                if image.shard_index != current:
                    if handle is not None:
                        handle.close()
                        handle = None
                    handle, current = self.open(image.shard_index), image.shard_index
                yield image, handle
        finally:
            if handle is not None:
                handle.close()

    def read_rgb(self, handle, image: Image, rate: float | str) -> np.ndarray:
        """(H, W, 3) uint8 RGB of ``image`` at ``rate`` from its open shard ``handle``."""
        return read_rgb(handle, self.rate_row(rate, image.shard_index), image.frame)

    def images_fingerprint(self, rate: float | str) -> str:
        """sha256 hex digest of the images at ``rate`` in image-id order, from each stored chunk's
        checksum (:func:`rainbench.store.shard.rgb_checksum`; nothing is decoded): equal for the
        same images in the same order, whatever the shards' names, labels or other rates. Caches
        of per-image results (``rainbench eval``'s detections) key on it."""
        digest = hashlib.sha256()
        raw, raw_shard = None, None
        try:
            for image, handle in self.walk():
                if image.shard_index != raw_shard:  # the shard file itself, once per shard
                    if raw is not None:
                        raw.close()
                    raw, raw_shard = open(handle.filename, "rb"), image.shard_index
                height, width = self._sizes[image.shard_index]
                digest.update(f"{image.image_id}:{height}x{width}:".encode())
                digest.update(rgb_checksum(handle, self.rate_row(rate, image.shard_index), image.frame, raw))
        finally:
            if raw is not None:
                raw.close()
        return digest.hexdigest()

    def frames(self, classes: Sequence[int | str] | None = None) -> Iterator[Frame]:
        """Every frame at the selected rates (:class:`Frame`), in image-id order; with
        ``classes`` (names or ids of labelled classes,
        :func:`rainbench.store.classes.parse_classes`), only the labels and ignore regions of
        those classes. An unknown class or an empty list is a one-line :class:`DatasetError`,
        not frames without labels."""
        keep_classes = None if classes is None else np.asarray(class_ids(classes), np.int64)
        for image, handle in self.walk():
            rows = self._rows[image.shard_index]
            labels = read_frame_labels(handle, image.frame)
            ignore = read_frame_ignore(handle, image.frame)
            for key in ("rain_coverage", "contrast_loss"):
                if key in labels:
                    labels[key] = labels[key][rows]
            if keep_classes is not None:
                keep = np.isin(labels["class_id"], keep_classes)
                labels = {key: value[:, keep] if key in ("rain_coverage", "contrast_loss")
                          else value[keep] for key, value in labels.items()}
                keep = np.isin(ignore["class_id"], keep_classes)
                ignore = {key: value[keep] for key, value in ignore.items()}
            rgb = [read_rgb(handle, row, image.frame) for row in rows]
            yield Frame(image, rgb, labels, self._sizes[image.shard_index], ignore)
