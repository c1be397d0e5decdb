"""Reading shards in training code: :class:`ShardReader`, numpy samples over :class:`Dataset`.

The torch ``Dataset`` over it is :class:`rainbench.store.torch_dataset.ShardDataset`.

Samples are (shard, frame, rate) triples in that order: shards in manifest order (sorted paths
without a manifest), then frames, then the selected rates. Shard files are opened lazily, once
per process, so both classes are safe with ``DataLoader(num_workers > 0)``. Every shard is
checked when the reader is built (:func:`rainbench.store.shard.check_labels`): NaN boxes or
inconsistent ``/labels/offsets`` raise ``ShardFormatError`` naming the file and the frame.

Target keys (numpy arrays from :class:`ShardReader`, tensors from ``ShardDataset``):

- ``boxes`` (M, 4) float32 x1, y1, x2, y2 in pixel-edge coordinates (``x2 = last column + 1``)
- ``labels`` (M,) int64 COCO-80 class ids (0 person, 1 bicycle, 2 car, 3 motorcycle, 5 bus, 7 truck)
- ``instance_id`` (M,) int64, stable per actor within a scene
- ``visible_fraction`` (M,) float32, ``truncation`` (M,) float32
- ``rate`` float32 scalar, mm/h; ``image_id`` int (1-based, the numbering of exports and eval:
  shard order, then frame order); ``shard`` str (file name); ``frame`` int
"""

from __future__ import annotations

import math
import operator
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .dataset import Dataset, class_ids as _class_ids
from .manifest import DatasetError
from .shard import read_rgb

_LABEL_KEYS = ("bbox", "class_id", "instance_id", "visible_fraction", "truncation")


def _fraction(value) -> float:
    """``min_visible_fraction`` as a float in [0, 1], else a one-line DatasetError (a percentage
    or NaN dropped every label without a word)."""
    try:
        fraction = float(value)
    except (TypeError, ValueError):
        fraction = math.nan
    if isinstance(value, bool) or not 0.0 <= fraction <= 1.0:
        raise DatasetError(f"min_visible_fraction: expected a fraction in [0, 1], got {value!r}")
    return fraction


class ShardReader:
    """Numpy access to the (image, target) samples of one or more shards.

    ``data``: a dataset directory, one shard, or a list of shards. ``rates``: the rates to read
    (mm/h, each present in every shard) or None for all. Optional filters drop labels with
    ``visible_fraction < min_visible_fraction`` (a fraction in [0, 1]) or a class not in
    ``classes`` (names or ids of the labelled classes, :func:`rainbench.store.classes.parse_classes`).

    A dataset directory whose manifest says generation has not finished (``rainbench generate``
    interrupted or still running) is refused, as the command line refuses it: training on it
    would use its finished shards as if they were the whole dataset. ``allow_incomplete=True``
    reads the shards it lists, with a warning.
    """

    def __init__(self, data: str | Path | Sequence[str | Path], rates: Sequence[float] | None = None,
                 *, min_visible_fraction: float = 0.0, classes: Sequence[int | str] | None = None,
                 allow_incomplete: bool = False) -> None:
        self.min_visible_fraction = _fraction(min_visible_fraction)
        self.classes = None if classes is None else np.asarray(_class_ids(classes), np.int64)
        self.dataset = Dataset(data, rates)
        listed = self.dataset.unfinished
        if listed is not None and not allow_incomplete:
            raise DatasetError(f"{data} is an incomplete dataset (its manifest lists {listed} finished shards "
                               "and says \"complete\": false): run the same rainbench generate again to finish "
                               "it, or pass allow_incomplete=True to read the finished shards only")
        if listed is not None:
            warnings.warn(f"{data} is incomplete: reading its {listed} finished shards only", stacklevel=2)
        self.shards = self.dataset.shards
        self.rates: tuple[float, ...] = self.dataset.rates
        self._rate_rows = [np.asarray([self.dataset.rate_row(rate, shard) for rate in self.rates])
                           for shard in range(len(self.shards))]
        self._labels: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.dataset.images) * len(self.rates)

    def locate(self, index: int) -> tuple[int, int, int]:
        """(shard number, frame, rate number) of sample ``index`` (an integer, numpy or 0-d tensor
        included; negative counts from the end, as for a list)."""
        image, rate = divmod(self._position(index), len(self.rates))  # samples: images in id order, then rates
        return self.dataset.images[image].shard_index, self.dataset.images[image].frame, rate

    def _position(self, index) -> int:
        """``index`` as a position in 0..len - 1 (:meth:`locate`'s rules); errors name it."""
        try:
            index = operator.index(index)
        except TypeError:
            raise TypeError(f"sample index: expected an integer, got {index!r}") from None
        if not -len(self) <= index < len(self):
            raise IndexError(f"sample index {index} out of range 0..{len(self) - 1}")
        return index % len(self)

    def _shard_labels(self, shard: int) -> dict[str, np.ndarray]:
        if shard not in self._labels:
            handle = self.dataset.handle(shard)
            self._labels[shard] = {key: handle[f"labels/{key}"][()] for key in _LABEL_KEYS}
            self._labels[shard]["offsets"] = handle["labels/offsets"][()]
        return self._labels[shard]

    def sample(self, index: int) -> tuple[np.ndarray, dict]:
        """Image (H, W, 3) uint8 RGB and its target (numpy; keys in the module docstring)."""
        index = self._position(index)
        shard, frame, rate_number = self.locate(index)
        handle = self.dataset.handle(shard)
        image = read_rgb(handle, int(self._rate_rows[shard][rate_number]), frame)
        labels = self._shard_labels(shard)
        rows = slice(int(labels["offsets"][frame]), int(labels["offsets"][frame + 1]))
        keep = labels["visible_fraction"][rows] >= self.min_visible_fraction
        if self.classes is not None:
            keep &= np.isin(labels["class_id"][rows], self.classes)
        target = {
            "boxes": labels["bbox"][rows][keep].astype(np.float32),
            "labels": labels["class_id"][rows][keep].astype(np.int64),
            "instance_id": labels["instance_id"][rows][keep].astype(np.int64),
            "visible_fraction": labels["visible_fraction"][rows][keep].astype(np.float32),
            "truncation": labels["truncation"][rows][keep].astype(np.float32),
            "rate": np.float32(self.rates[rate_number]),
            "image_id": self.dataset.images[index // len(self.rates)].image_id,
            "shard": self.shards[shard].name,
            "frame": frame,
        }
        return image, target

    def close(self) -> None:
        self.dataset.close()
