"""rainbench.store: the dataset layer, the one contract between the generator and its readers.

- :mod:`~rainbench.store.shard`: the HDF5 shard format (writer, :func:`open_shard`,
  :func:`open_checked`, format versions, label checks);
- :mod:`~rainbench.store.labels`: :class:`FrameLabels`, shared by writer and reader;
- :mod:`~rainbench.store.manifest`: ``manifest.json``, hashing, :func:`verify_dataset`;
- :mod:`~rainbench.store.classes` and :mod:`~rainbench.store.rates`: the class and rate
  vocabularies;
- :mod:`~rainbench.store.dataset`: :class:`Dataset`, the one reader (shard order, image ids,
  rate rows);
- :mod:`~rainbench.store.reader`: :class:`ShardReader` (numpy) and ``ShardDataset`` (torch,
  imported on first use);
- :mod:`~rainbench.store.export`, :mod:`~rainbench.store.video`,
  :mod:`~rainbench.store.preview`, :mod:`~rainbench.store.stats`: what is made from a dataset;
  :mod:`~rainbench.store.images`: the image-file writer they and the evaluator share.

Importing it imports neither MuJoCo, nor OpenGL, nor torch.
"""

from .classes import CLASS_NAMES, LABELLED_CLASSES, PAPER_CLASSES
from .dataset import Dataset, Frame, Image
from .labels import FrameLabels
from .manifest import (MANIFEST, SHARD_GLOB, DatasetError, list_shards, read_manifest, unlisted_shards,
                       verify_dataset)
from .rates import RatesError, parse_rates, rate_token
from .reader import ShardReader
from .shard import ShardFormatError, ShardWriter, open_checked, open_shard, read_frame_ignore, read_frame_labels, read_rgb

__all__ = [
    "CLASS_NAMES", "LABELLED_CLASSES", "PAPER_CLASSES", "Dataset", "DatasetError", "Frame",
    "FrameLabels", "Image", "MANIFEST", "RatesError", "SHARD_GLOB", "ShardDataset",
    "ShardFormatError", "ShardReader", "ShardWriter", "list_shards", "open_checked", "open_shard",
    "parse_rates", "rate_token", "read_frame_ignore", "read_frame_labels", "read_manifest", "read_rgb",
    "unlisted_shards", "verify_dataset",
]


def __getattr__(name):
    """The torch ``ShardDataset`` on first use (it imports torch)."""
    if name == "ShardDataset":
        from .torch_dataset import ShardDataset

        return ShardDataset
    raise AttributeError(f"module 'rainbench.store' has no attribute {name!r}")
