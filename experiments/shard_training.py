"""Training YOLO detectors straight from shards: an ultralytics dataset over :class:`rainbench.store.Dataset`.

No export step: :func:`shard_dataset_class` builds ``ShardYOLODataset``, a subclass of
ultralytics' ``YOLODataset`` whose images and labels come from the shards of a dataset directory
(the one reader's shard order and image numbering), so ultralytics' own augmentations (mosaic,
HSV, flips, scale, letterbox) run on top unchanged. Each time an image is loaded its rain rate is
drawn from a :class:`RateCurriculum` with Python's ``random`` module, the generator ultralytics
seeds in every data-loader worker for its own augmentations, so a run is as deterministic as
ultralytics' augmentations are (the same seed, the same number of workers).

Labels: the shard's ``bbox`` (M, 4) float32 xyxy pixel-edge boxes become ultralytics' normalised
``xywh`` (divided by the image width and height); ``cls`` is the COCO class id (the model's
``names`` are the dense ids 0..max, :func:`rainbench.store.export.yolo_names`), and only the
labels of ``classes`` are kept.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rainbench.store import Dataset, read_frame_labels
from rainbench.store.rates import rate_decimal


class CurriculumError(ValueError):
    """A rain curriculum that cannot be honoured; the message is one line naming the field."""


@dataclass(frozen=True)
class RateCurriculum:
    """Which rain rates training images are drawn at, and how often.

    ``rates``: (K,) distinct rates in mm/h (each must be stored in every shard of the training
    data); ``weights``: (K,) relative frequencies >= 0, not all 0. The default is the clean rate
    only.
    """

    rates: tuple[float, ...] = (0.0,)
    weights: tuple[float, ...] = (1.0,)

    def __post_init__(self) -> None:
        if len(self.rates) == 0 or len(self.rates) != len(self.weights):
            raise CurriculumError(f"rain curriculum: expected one weight per rate, got rates "
                                  f"{list(self.rates)} and weights {list(self.weights)}")
        try:
            decimals = [rate_decimal(rate) for rate in self.rates]
        except ValueError as error:
            raise CurriculumError(f"rain curriculum: {error}") from None
        if len(set(decimals)) != len(decimals):
            raise CurriculumError(f"rain curriculum: rates {list(self.rates)} repeat a rate")
        if not all(isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) and w >= 0
                   for w in self.weights) or sum(self.weights) <= 0:
            raise CurriculumError(f"rain curriculum: expected weights >= 0 with a positive sum, got "
                                  f"{list(self.weights)}")
        object.__setattr__(self, "rates", tuple(float(d) for d in decimals))
        object.__setattr__(self, "weights", tuple(float(w) for w in self.weights))

    @classmethod
    def from_mapping(cls, mapping: Mapping[Any, Any]) -> RateCurriculum:
        """``{rate: weight}`` (a recipe's ``rates`` mapping, e.g. ``{0: 2, 50: 1, 100: 1}``)."""
        if not isinstance(mapping, Mapping) or not mapping:
            raise CurriculumError(f"rain curriculum: expected a mapping of rate -> weight, got {mapping!r}")
        return cls(rates=tuple(mapping), weights=tuple(mapping.values()))

    @property
    def shares(self) -> tuple[float, ...]:
        """(K,) the weights normalised to sum 1: the expected share of each rate."""
        total = sum(self.weights)
        return tuple(weight / total for weight in self.weights)

    def draw(self, rng: random.Random) -> float:
        """One rate, drawn with probability proportional to its weight."""
        return rng.choices(self.rates, weights=self.weights)[0]


@dataclass(frozen=True)
class RandomRainAugment:
    """albumentations' ``RandomRain`` on training images, the usual practice that knows nothing of
    mm/h, depth or wet roads: the baseline a rain curriculum is compared with on equal terms (the
    same clean frames, the same training). Each loaded image gets it with probability ``p``;
    ``options`` are ``RandomRain`` arguments (``rain_type``, ``slant_range``, ...)."""

    p: float = 0.5
    options: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        if not (isinstance(self.p, (int, float)) and not isinstance(self.p, bool) and 0 <= self.p <= 1):
            raise CurriculumError(f"random_rain: p must be a probability in [0, 1], got {self.p!r}")
        self.transform()  # unknown or bad options fail when the recipe is read

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> RandomRainAugment:
        """``{p: 0.5, rain_type: heavy, ...}`` (a recipe's ``random_rain``)."""
        if not isinstance(mapping, Mapping):
            raise CurriculumError(f"random_rain: expected a mapping of p and RandomRain options, got {mapping!r}")
        options = dict(mapping)
        return cls(p=options.pop("p", 0.5),
                   options=tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in options.items())))

    def transform(self):
        """The albumentations ``RandomRain`` (always applied: ``p`` is drawn by the dataset)."""
        try:
            import albumentations  # noqa: PLC0415
        except ImportError:
            raise CurriculumError("random_rain: needs albumentations (pip install 'rainbench[bench]', which "
                                  "make venv installs)") from None
        import inspect  # noqa: PLC0415

        known = [name for name in inspect.signature(albumentations.RandomRain).parameters if name != "p"]
        unknown = [name for name, _ in self.options if name not in known]
        if unknown:
            raise CurriculumError(f"random_rain: unknown option {unknown[0]!r}; expected p or some of "
                                  f"{', '.join(known)}")
        try:
            return albumentations.RandomRain(p=1.0, **dict(self.options))
        except (TypeError, ValueError) as error:
            reason = " ".join(str(error).split())[:200]
            raise CurriculumError(f"random_rain: options {dict(self.options)} are not RandomRain's ({reason})") from None


def _resize_long_side(image: np.ndarray, imgsz: int) -> np.ndarray:
    """``image`` with its long side resized to ``imgsz`` (aspect kept, bilinear): what
    ultralytics' ``BaseDataset.load_image`` does to an image it reads from a file."""
    import cv2  # noqa: PLC0415

    height, width = image.shape[:2]
    ratio = imgsz / max(height, width)
    if ratio == 1:
        return image
    size = (min(math.ceil(width * ratio), imgsz), min(math.ceil(height * ratio), imgsz))
    return cv2.resize(image, size, interpolation=cv2.INTER_LINEAR)


def shard_dataset_class():
    """The ``ShardYOLODataset`` class (ultralytics is imported here, offline)."""
    from rainbench.eval.backends.ultralytics import _offline_ultralytics

    _offline_ultralytics()
    from ultralytics.data.dataset import YOLODataset  # noqa: PLC0415

    class ShardYOLODataset(YOLODataset):
        """ultralytics' ``YOLODataset`` over the shards of ``img_path`` (a dataset directory, one
        shard, or a list of shards). Extra keyword arguments: ``curriculum`` (the
        :class:`RateCurriculum` images are drawn at), ``keep_classes`` (the COCO class ids
        whose labels are kept; None keeps all) and ``random_rain`` (a
        :class:`RandomRainAugment` applied to training images, or None). ``im_files`` are
        ``<shard>#<frame>`` names; ``images`` the :class:`rainbench.store.Image` of each index
        (the first ones of the dataset when ultralytics' ``fraction`` is below 1)."""

        def __init__(self, *args, curriculum: RateCurriculum = RateCurriculum(),
                     keep_classes: Sequence[int] | None = None,
                     random_rain: RandomRainAugment | None = None, **kwargs) -> None:
            self.curriculum = curriculum
            self.random_rain = random_rain
            self._random_rain = None if random_rain is None else random_rain.transform()
            self.keep_classes = None if keep_classes is None else np.asarray(keep_classes, np.int64)
            self._handles: dict[int, Any] = {}
            self._handles_pid = None
            super().__init__(*args, **kwargs)

        def get_img_files(self, img_path) -> list[str]:
            self.store = Dataset(img_path, rates=[format(rate_decimal(r), "f") for r in self.curriculum.rates])
            images = self.store.images  # ultralytics' ``fraction``: a share, or a count of images
            count = (self.fraction if isinstance(self.fraction, int)
                     else max(1, round(len(images) * self.fraction)))
            self.images = images[:count]
            return [f"{image.shard}#{image.frame}" for image in self.images]

        def get_labels(self) -> list[dict[str, Any]]:
            labels = []
            for image, handle in self.store.walk(self.images):
                frame = read_frame_labels(handle, image.frame)
                height, width = self.store.size(image.shard_index)
                keep = (np.ones(len(frame["class_id"]), bool) if self.keep_classes is None
                        else np.isin(frame["class_id"], self.keep_classes))
                x1, y1, x2, y2 = np.asarray(frame["bbox"], np.float64)[keep].reshape(-1, 4).T
                xywh = np.stack([(x1 + x2) / 2 / width, (y1 + y2) / 2 / height,
                                 (x2 - x1) / width, (y2 - y1) / height], axis=1)
                labels.append({"im_file": f"{image.shard}#{image.frame}", "shape": (height, width),
                               "cls": frame["class_id"][keep].astype(np.float32).reshape(-1, 1),
                               "bboxes": xywh.astype(np.float32).reshape(-1, 4), "segments": [],
                               "keypoints": None, "normalized": True, "bbox_format": "xywh"})
            return labels

        def _handle(self, shard: int):
            import os  # noqa: PLC0415

            if self._handles_pid != os.getpid():  # a data-loader worker opens its own files
                self._handles, self._handles_pid = {}, os.getpid()
            if shard not in self._handles:
                self._handles[shard] = self.store.open(shard)
            return self._handles[shard]

        def load_image(self, i: int, rect_mode: bool = True, resize_short: bool = False):
            """Image ``i`` (BGR, long side resized to ``imgsz``) at a rate drawn from the
            curriculum; returns (image, (h0, w0), (h, w)) as ultralytics' ``load_image``. As
            there, a training image stays in memory while it is among the recent loads that
            mosaic draws its other images from (with the rate it was drawn at); a load that is
            not in memory reads the shard and draws a new rate."""
            if not rect_mode or resize_short:
                raise ValueError("ShardYOLODataset: only rect_mode resizing of the long side is supported")
            if self.ims[i] is not None:
                return self.ims[i], self.im_hw0[i], self.im_hw[i]
            image = self.images[i]
            rate = self.curriculum.draw(random) if len(self.curriculum.rates) > 1 else self.curriculum.rates[0]
            rgb = self.store.read_rgb(self._handle(image.shard_index), image, rate)
            if self.augment and self._random_rain is not None and random.random() < self.random_rain.p:
                self._random_rain.set_random_seed(random.getrandbits(32))  # by ultralytics' seeded generator
                rgb = self._random_rain(image=rgb)["image"]
            height, width = rgb.shape[:2]
            imgsz = max(self.imgsz) if isinstance(self.imgsz, (tuple, list)) else self.imgsz
            resized = _resize_long_side(np.ascontiguousarray(rgb[:, :, ::-1]), imgsz)
            if self.augment:  # mosaic picks its other images among the recent loads
                self.ims[i], self.im_hw0[i], self.im_hw[i] = resized, (height, width), resized.shape[:2]
                self.buffer.append(i)
                if 1 < len(self.buffer) >= self.max_buffer_length:
                    evicted = self.buffer.pop(0)
                    self.ims[evicted], self.im_hw0[evicted], self.im_hw[evicted] = None, None, None
            return resized, (height, width), resized.shape[:2]

        def __getstate__(self) -> dict[str, Any]:
            state = self.__dict__.copy()
            state["_handles"], state["_handles_pid"] = {}, None  # open files never cross processes
            return state

    return ShardYOLODataset


def shard_trainer_class(curriculum: RateCurriculum, classes: Sequence[int] | None,
                        random_rain: RandomRainAugment | None = None):
    """An ultralytics ``DetectionTrainer`` subclass whose training data is a ``ShardYOLODataset``
    drawn at ``curriculum`` and whose validation data is the clean (0 mm/h) frames of the
    validation shards; both keep the labels of ``classes`` (COCO ids). Pass it as
    ``YOLO(...).train(trainer=...)`` with a data yaml whose ``train`` and ``val`` are dataset
    directories of shards. ``random_rain``: albumentations' RandomRain on training images."""
    from rainbench.eval.backends.ultralytics import _offline_ultralytics

    _offline_ultralytics()
    from ultralytics.data.utils import get_split_fraction  # noqa: PLC0415
    from ultralytics.models.yolo.detect import DetectionTrainer  # noqa: PLC0415
    from ultralytics.utils import colorstr  # noqa: PLC0415
    from ultralytics.utils.torch_utils import unwrap_model  # noqa: PLC0415

    dataset_class = shard_dataset_class()

    class ShardDetectionTrainer(DetectionTrainer):
        """ultralytics' detection trainer reading rainbench shards (no export)."""

        def build_dataset(self, img_path, mode: str = "train", batch: int | None = None):
            stride = max(int(unwrap_model(self.model).stride.max()), 32)
            training = mode == "train"
            return dataset_class(
                img_path=img_path, imgsz=self.args.imgsz, batch_size=batch, augment=training,
                hyp=self.args, rect=self.args.rect or not training, cache=None,
                single_cls=self.args.single_cls or False, stride=stride, pad=0.0 if training else 0.5,
                prefix=colorstr(f"{mode}: "), task=self.args.task, classes=self.args.classes,
                data=self.data, fraction=get_split_fraction(self.args.fraction, "train" if training else "val"),
                curriculum=curriculum if training else RateCurriculum(), keep_classes=classes,
                random_rain=random_rain if training else None)

    return ShardDetectionTrainer
