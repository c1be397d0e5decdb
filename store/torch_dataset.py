"""``ShardDataset``: a ``torch.utils.data.Dataset`` over :class:`~rainbench.store.reader.ShardReader`.

Kept apart from the numpy reader so that ``import rainbench.store`` does not import torch.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset as _TorchDataset

from .reader import ShardReader


class ShardDataset(_TorchDataset):
    """``torch.utils.data.Dataset`` of (image, target) in torchvision detection style.

    ``image`` is a (3, H, W) uint8 tensor: a channels-last view of the decoded (H, W, 3) RGB
    memory (``image.contiguous()`` packs it; models take it as it is). ``target`` holds tensors
    ``boxes`` (M, 4) float32 xyxy, ``labels`` (M,) int64, ``instance_id`` (M,) int64,
    ``visible_fraction`` (M,), ``truncation`` (M,), ``rate`` (float32 scalar) and the plain
    ``image_id``, ``shard``, ``frame``. Arguments as :class:`ShardReader`.

    Items are the same in a ``DataLoader`` worker as in the main process. With
    ``DataLoader(num_workers > 0)`` use ``collate_fn=ShardDataset.collate_fn``: it packs a
    batch's images of one size and each target key into one block, so a batch crosses between
    processes as a few shared-memory segments rather than one per tensor.
    """

    def __init__(self, data, rates=None, *, min_visible_fraction: float = 0.0,
                 classes=None, allow_incomplete: bool = False) -> None:
        self.reader = ShardReader(data, rates, min_visible_fraction=min_visible_fraction,
                                  classes=classes, allow_incomplete=allow_incomplete)

    @property
    def rates(self) -> tuple[float, ...]:
        return self.reader.rates

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, index: int):
        image, target = self.reader.sample(index)
        image = torch.from_numpy(image).permute(2, 0, 1)  # CHW view, no copy
        # the target's tensors share one storage: from a DataLoader worker, whatever the collate,
        # an item crosses as two shared-memory segments (image and target), not seven
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
    """Targets of one batch (numpy arrays or tensors) as tensors that are views of one block
    (:func:`_one_storage`): each key's values are joined (arrays) or stacked (scalars), and each
    sample gets its part of them."""
    out = [dict(target) for target in targets]
    keys, joined, splits = [], [], []
    for key, value in targets[0].items():
        values = [target[key].numpy() if isinstance(target[key], torch.Tensor) else target[key]
                  for target in targets]
        value = values[0]
        if isinstance(value, np.ndarray) and value.ndim >= 1:
            joined.append(np.concatenate(values))
            splits.append([len(v) for v in values])
        elif isinstance(value, (np.ndarray, np.floating)):
            joined.append(np.stack(values))
            splits.append(None)
        else:  # plain values: image_id, shard, frame
            continue
        keys.append(key)
    for key, block, split in zip(keys, _one_storage(joined), splits):
        parts = torch.split(block, split) if split is not None else block
        for target, part in zip(out, parts):
            target[key] = part
    return tuple(out)


_ALIGN = 8


def _one_storage(arrays: Sequence[np.ndarray]) -> list[torch.Tensor]:
    """Tensors equal to ``arrays`` (copied) that are typed views of one byte storage, each at an
    8-byte aligned offset: a tensor crossing from a DataLoader worker costs a shared-memory
    segment and an open file, and views of one storage cross as one."""
    offsets, total = [], 0
    for array in arrays:
        offsets.append(total)
        total += -(-array.nbytes // _ALIGN) * _ALIGN
    buffer = np.empty(max(total, _ALIGN), np.uint8)
    storage = torch.from_numpy(buffer)
    tensors = []
    for array, offset in zip(arrays, offsets):
        array = np.ascontiguousarray(array)
        buffer[offset:offset + array.nbytes] = array.reshape(-1).view(np.uint8)
        dtype = torch.from_numpy(array[:0].reshape(-1)).dtype
        tensors.append(storage[offset:offset + array.nbytes].view(dtype).reshape(array.shape))
    return tensors
