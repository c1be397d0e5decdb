"""Reading shards in training code: a numpy reader and a torch ``Dataset`` over it.

Samples are (shard, frame, rate) triples in that order: shards in manifest order (sorted paths
without a manifest), then frames, then the selected rates. Shard files are opened lazily, once
per process, so both classes are safe with ``DataLoader(num_workers > 0)``. Every shard is
checked when it is opened (:func:`rainbench.gen.dataset.check_labels`): NaN boxes or
inconsistent ``/labels/offsets`` raise ``ShardFormatError`` naming the file and the frame.

Target keys (numpy arrays from :class:`ShardReader`, tensors from :class:`ShardDataset`):

- ``boxes`` (M, 4) float32 x1, y1, x2, y2 in pixel-edge coordinates (``x2 = last column + 1``)
- ``labels`` (M,) int64 COCO-80 class ids (0 person, 1 bicycle, 2 car, 3 motorcycle, 5 bus, 7 truck)
- ``instance_id`` (M,) int64, stable per actor within a scene
- ``visible_fraction`` (M,) float32, ``truncation`` (M,) float32
- ``rate`` float32 scalar, mm/h; ``image_id`` int (1-based, the numbering of exports and eval:
  shard order, then frame order); ``shard`` str (file name); ``frame`` int
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .dataset import DatasetError, list_shards, open_checked
from .shard import read_rgb

_LABEL_KEYS = ("bbox", "class_id", "instance_id", "visible_fraction", "truncation")


class ShardReader:
    """Numpy access to the (image, target) samples of one or more shards.

    ``data``: a dataset directory, one shard, or a list of shards. ``rates``: the rates to read
    (mm/h, each present in every shard) or None for all. Optional filters drop labels with
    ``visible_fraction < min_visible_fraction`` or a class not in ``classes``.
    """

    def __init__(self, data: str | Path | Sequence[str | Path], rates: Sequence[float] | None = None,
                 *, min_visible_fraction: float = 0.0, classes: Sequence[int] | None = None) -> None:
        self.shards = list_shards(data)
        self.min_visible_fraction = float(min_visible_fraction)
        self.classes = None if classes is None else np.asarray(sorted(set(classes)), np.int64)
        self._rate_rows: list[np.ndarray] = []
        self._frames: list[int] = []
        self.rates: tuple[float, ...] | None = None
        for path in self.shards:
            with open_checked(path) as handle:  # refuses NaN boxes, inconsistent offsets
                shard_rates = handle["rates"][()].astype(np.float64)
                frames = int(handle["labels/offsets"].shape[0]) - 1
                if handle["rgb"].shape[1] != frames:
                    raise DatasetError(f"{path}: /rgb holds {handle['rgb'].shape[1]} frames, "
                                       f"/labels/offsets {frames}")
            wanted = shard_rates if rates is None else np.asarray(rates, np.float64)
            rows = []
            for rate in wanted:
                match = np.flatnonzero(np.isclose(shard_rates, rate))
                if match.size == 0:
                    raise DatasetError(f"{path}: has no rate {rate:g} mm/h (it has "
                                       f"{', '.join(f'{r:g}' for r in shard_rates)})")
                rows.append(int(match[0]))
            if self.rates is None:
                self.rates = tuple(float(r) for r in wanted)
            elif tuple(float(r) for r in wanted) != self.rates:
                raise DatasetError(f"{path}: its rates differ from {self.shards[0]}; pass rates=")
            self._rate_rows.append(np.asarray(rows))
            self._frames.append(frames)
        self._first_image_id = np.concatenate([[1], 1 + np.cumsum(self._frames)[:-1]])
        per_shard = np.array([f * len(self.rates) for f in self._frames])
        self._sample_starts = np.concatenate([[0], np.cumsum(per_shard)])
        self._pid = None
        self._handles: dict[int, object] = {}
        self._labels: dict[int, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return int(self._sample_starts[-1])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_handles"], state["_pid"] = {}, None  # handles never cross processes
        return state

    def locate(self, index: int) -> tuple[int, int, int]:
        """(shard number, frame, rate number) of sample ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(f"sample index {index} out of range 0..{len(self) - 1}")
        shard = int(np.searchsorted(self._sample_starts, index, side="right") - 1)
        frame, rate = divmod(index - int(self._sample_starts[shard]), len(self.rates))
        return shard, frame, rate

    def _handle(self, shard: int):
        if self._pid != os.getpid():  # a forked DataLoader worker: open its own handles
            self._handles, self._pid = {}, os.getpid()
        if shard not in self._handles:
            self._handles[shard] = open_checked(self.shards[shard])
        return self._handles[shard]

    def _shard_labels(self, shard: int) -> dict[str, np.ndarray]:
        if shard not in self._labels:
            handle = self._handle(shard)
            self._labels[shard] = {key: handle[f"labels/{key}"][()] for key in _LABEL_KEYS}
            self._labels[shard]["offsets"] = handle["labels/offsets"][()]
        return self._labels[shard]

    def sample(self, index: int) -> tuple[np.ndarray, dict]:
        """Image (H, W, 3) uint8 RGB and its target (numpy; keys in the module docstring)."""
        shard, frame, rate_number = self.locate(index)
        handle = self._handle(shard)
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
            "image_id": int(self._first_image_id[shard]) + frame,
            "shard": self.shards[shard].name,
            "frame": frame,
        }
        return image, target

    def close(self) -> None:
        for handle in self._handles.values():
            handle.close()
        self._handles = {}


try:
    import torch
    from torch.utils.data import Dataset as _TorchDataset
except ImportError:  # pragma: no cover -- torch is a dependency; the numpy reader works without
    torch = None
    _TorchDataset = object


class ShardDataset(_TorchDataset):
    """``torch.utils.data.Dataset`` of (image, target) in torchvision detection style.

    ``image`` is a (3, H, W) uint8 tensor: a channels-last view of the decoded (H, W, 3) RGB
    memory (``image.contiguous()`` packs it; models take it as it is). ``target`` holds tensors
    ``boxes`` (M, 4) float32 xyxy, ``labels`` (M,) int64, ``instance_id`` (M,) int64,
    ``visible_fraction`` (M,), ``truncation`` (M,), ``rate`` (float32 scalar) and the plain
    ``image_id``, ``shard``, ``frame``. Arguments as :class:`ShardReader`.

    With ``DataLoader(num_workers > 0)`` use ``collate_fn=ShardDataset.collate_fn``: workers
    hand targets over as numpy arrays (cheaper between processes), and the images of a batch
    cross as one shared-memory block.
    """

    def __init__(self, data, rates=None, *, min_visible_fraction: float = 0.0,
                 classes=None) -> None:
        self.reader = ShardReader(data, rates, min_visible_fraction=min_visible_fraction,
                                  classes=classes)

    @property
    def rates(self) -> tuple[float, ...]:
        return self.reader.rates

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, index: int):
        image, target = self.reader.sample(index)
        image = torch.from_numpy(image).permute(2, 0, 1)  # CHW view, no copy
        if torch.utils.data.get_worker_info() is not None:
            # In a DataLoader worker the target stays numpy: collate_fn makes one tensor block
            # per key for the whole batch (each tensor costs a shared-memory segment).
            return image, target
        return image, _targets_to_tensors((target,))[0]

    @staticmethod
    def collate_fn(batch):
        """Keep variable box counts: (tuple of (3, H, W) images, tuple of targets of tensors).

        Runs in the DataLoader worker. Every tensor crossing to the main process costs a
        shared-memory segment, so the batch's images of one size are packed into one
        (B, H, W, 3) block and each target key into one block, and each sample gets views of
        them (measured 2x more images/s through two workers than one tensor per array).
        """
        images, targets = zip(*batch)
        if len({image.shape for image in images}) == 1:
            block = torch.stack([image.permute(1, 2, 0) for image in images])
            images = tuple(block.permute(0, 3, 1, 2))
        return images, _targets_to_tensors(targets)


def _targets_to_tensors(targets: Sequence[dict]) -> tuple[dict, ...]:
    """Numpy targets of one batch as tensors that are views of one block per key."""
    out = [dict(target) for target in targets]
    for key, value in targets[0].items():
        values = [target[key] for target in targets]
        if isinstance(value, np.ndarray) and value.ndim >= 1:
            parts = torch.split(torch.from_numpy(np.concatenate(values)),
                                [len(v) for v in values])
        elif isinstance(value, (np.ndarray, np.floating)):
            parts = torch.from_numpy(np.stack(values))
        else:  # already tensors (a DataLoader without workers) or plain values
            continue
        for target, part in zip(out, parts):
            target[key] = part
    return tuple(out)
