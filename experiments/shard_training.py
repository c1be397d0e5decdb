"""Training YOLO detectors straight from shards: an ultralytics dataset over :class:`rainbench.store.Dataset`.

No export step: :func:`shard_dataset_class` builds ``ShardYOLODataset``, a subclass of
ultralytics' ``YOLODataset`` whose images and labels come from the shards of a dataset directory
(the one reader's shard order and image numbering), so ultralytics' own augmentations (mosaic,
HSV, flips, scale, letterbox) run on top unchanged. Each time an image is loaded its rain model
and rate are drawn from a :class:`RainCurriculum` with Python's ``random`` module, the
generator ultralytics seeds in every data-loader worker for its own augmentations, so a run is
as deterministic as ultralytics' augmentations are (the same seed, the same number of workers).

Rain models: a curriculum that names rain models (``{physical: {0: 2, 50: 1}, jeon2022: {50:
1}}``) reads each from its own dataset (``rain_data``: rain model -> directory,
:func:`open_rain_data`), generated from the same scenes; image ``i`` is the same scene frame in
every one of them (checked when the dataset is built: same shard names, frames, sizes and
labels), so a load reads image ``i`` of the drawn rain model's data and the labels are those of
``img_path``'s. A flat curriculum (``{0: 2, 50: 1}``) reads ``img_path`` only.

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
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.gen.config import RAIN_MODELS
from rainbench.store import Dataset, read_frame_labels
from rainbench.store.rates import rate_decimal


class CurriculumError(ValueError):
    """A rain curriculum that cannot be honoured; the message is one line naming the field."""


@dataclass(frozen=True)
class RainCurriculum:
    """Which rain models and rain rates training images are drawn at, and how often.

    ``entries``: (K,) distinct ``(rain model, rate)`` pairs: a name of
    :data:`~rainbench.gen.config.RAIN_MODELS`, or None for the training data's own rain model
    (the data ``ShardYOLODataset`` reads at ``img_path``), and a rate in mm/h that every shard
    of that rain model's data stores. A curriculum names the rain model of every entry or of
    none. ``weights``: (K,) relative frequencies >= 0 over all entries together, with a positive
    sum for each rain model. The default is the clean rate of the own rain model only.
    """

    entries: tuple[tuple[str | None, float], ...] = ((None, 0.0),)
    weights: tuple[float, ...] = (1.0,)

    def __post_init__(self) -> None:
        if len(self.entries) == 0 or len(self.entries) != len(self.weights):
            raise CurriculumError(f"rain curriculum: expected one weight per (rain model, rate) entry, got "
                                  f"entries {list(self.entries)} and weights {list(self.weights)}")
        if not all(isinstance(entry, tuple) and len(entry) == 2 for entry in self.entries):
            raise CurriculumError(f"rain curriculum: expected (rain model, rate) pairs, got {list(self.entries)}")
        models = [model for model, _ in self.entries]
        unknown = [model for model in models if model is not None and model not in RAIN_MODELS]
        if unknown:
            raise CurriculumError(f"rain curriculum: unknown rain model {unknown[0]!r}; expected one of "
                                  f"{', '.join(RAIN_MODELS)}")
        if None in models and any(model is not None for model in models):
            raise CurriculumError(f"rain curriculum: entries {list(self.entries)} name the rain model of "
                                  "some rates but not of others")
        decimals = []
        for model, rate in self.entries:
            try:
                decimals.append(rate_decimal(rate))
            except ValueError as error:
                raise CurriculumError(f"rain curriculum: {_where(model)}{error}") from None
        pairs = list(zip(models, decimals))
        for model in dict.fromkeys(models):
            rates = [decimal for other, decimal in pairs if other == model]
            if len(set(rates)) != len(rates):
                raise CurriculumError(f"rain curriculum: {_where(model)}rates "
                                      f"{[float(rate) for rate in rates]} repeat a rate")
            weights = [weight for other, weight in zip(models, self.weights) if other == model]
            if not all(isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) and w >= 0
                       for w in weights) or sum(weights) <= 0:
                raise CurriculumError(f"rain curriculum: {_where(model)}expected weights >= 0 with a positive "
                                      f"sum, got {weights}")
        object.__setattr__(self, "entries", tuple((model, float(decimal)) for model, decimal in pairs))
        object.__setattr__(self, "weights", tuple(float(w) for w in self.weights))

    @classmethod
    def from_mapping(cls, mapping: Mapping[Any, Any]) -> RainCurriculum:
        """A recipe's ``rain_curriculum``: ``{rate: weight}`` (``{0: 2, 50: 1, 100: 1}``: the
        training data's own rain model), or ``{rain model: {rate: weight}}``
        (``{physical: {0: 2, 50: 1}, jeon2022: {50: 1}}``), never both in one mapping."""
        if not isinstance(mapping, Mapping) or not mapping:
            raise CurriculumError(f"rain curriculum: expected a mapping of rate -> weight or of rain model -> "
                                  f"{{rate: weight}}, got {mapping!r}")
        nested = isinstance(next(iter(mapping.values())), Mapping)
        for key, value in mapping.items():
            if isinstance(value, Mapping) != nested:
                raise CurriculumError(f"rain curriculum: entry {key!r}: {value!r} mixes the two forms; expected "
                                      "either {rate: weight} or {rain model: {rate: weight}}")
        if not nested:
            return cls(entries=tuple((None, rate) for rate in mapping), weights=tuple(mapping.values()))
        for model, rates in mapping.items():
            if not rates:
                raise CurriculumError(f"rain curriculum: {model}: expected a mapping of rate -> weight, "
                                      f"got {rates!r}")
        return cls(entries=tuple((model, rate) for model, rates in mapping.items() for rate in rates),
                   weights=tuple(weight for rates in mapping.values() for weight in rates.values()))

    @property
    def rain_models(self) -> tuple[str | None, ...]:
        """The distinct rain models of the entries, in entry order ((None,) for the flat form)."""
        return tuple(dict.fromkeys(model for model, _ in self.entries))

    @property
    def rates(self) -> tuple[float, ...]:
        """The distinct rates of the entries (of every rain model), in entry order."""
        return tuple(dict.fromkeys(rate for _, rate in self.entries))

    def rates_of(self, rain_model: str | None) -> tuple[float, ...]:
        """The rates ``rain_model``'s entries draw at, in entry order."""
        return tuple(rate for model, rate in self.entries if model == rain_model)

    @property
    def shares(self) -> tuple[float, ...]:
        """(K,) the weights normalised to sum 1: the expected share of each entry."""
        total = sum(self.weights)
        return tuple(weight / total for weight in self.weights)

    def draw(self, rng: random.Random) -> tuple[str | None, float]:
        """One entry ``(rain model, rate)``, drawn with probability proportional to its weight; a
        curriculum of one entry returns it without drawing from ``rng``."""
        if len(self.entries) == 1:
            return self.entries[0]
        return rng.choices(self.entries, weights=self.weights)[0]


def _where(rain_model: str | None) -> str:
    """The prefix that names a rain model's entries in an error message ('' for the flat form)."""
    return "" if rain_model is None else f"{rain_model}: "


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


def _source_key(data: str | Path | Sequence[str | Path]) -> tuple[Path, ...]:
    """The resolved paths of a dataset directory, a shard, or a list of shards: equal keys, the
    same data."""
    return tuple(Path(path).resolve() for path in (data if isinstance(data, (list, tuple)) else [data]))


def _data_name(store: Dataset) -> str:
    """The directory that names ``store`` in messages (its shards' folder for shard files)."""
    return str(store.root if store.root is not None else store.shards[0].parent)


def open_rain_data(img_path: str | Path | Sequence[str | Path], curriculum: RainCurriculum,
                   rain_data: Mapping[str, str | Path] | None = None) -> tuple[Dataset, dict[str | None, Dataset]]:
    """The datasets a ``ShardYOLODataset`` reads: that of ``img_path`` (whose images and labels
    it yields) and, for each rain model of ``curriculum``, the one its images are read from:
    ``img_path`` for None (the flat form), else ``rain_data[rain model]`` (a dataset directory,
    one shard, or a list of shards). Rain models whose data is the same share one
    :class:`~rainbench.store.Dataset`, opened at the rates their entries read (``img_path`` at
    every rate it stores when no entry reads it). Returns ``(img_path's dataset, {rain model:
    dataset})``; a rain model without data is a :class:`CurriculumError`."""
    rain_data = dict(rain_data or {})
    missing = [model for model in curriculum.rain_models if model is not None and model not in rain_data]
    if missing:
        raise CurriculumError(f"rain curriculum: no training data for rain model {missing[0]!r} (rain_data "
                              f"names {', '.join(sorted(rain_data)) or 'none'})")
    data_of = {model: img_path if model is None else rain_data[model] for model in curriculum.rain_models}
    label_key = _source_key(img_path)
    rates_at: dict[tuple[Path, ...], list[float]] = {label_key: []}
    data_at = {label_key: img_path}
    for model, rate in curriculum.entries:
        key = _source_key(data_of[model])
        rates_at.setdefault(key, []).append(rate)
        data_at.setdefault(key, data_of[model])
    opened = {key: Dataset(data_at[key], rates=rates or None) for key, rates in rates_at.items()}
    return opened[label_key], {model: opened[_source_key(data)] for model, data in data_of.items()}


def shard_dataset_class():
    """The ``ShardYOLODataset`` class (ultralytics is imported here, offline)."""
    from rainbench.eval.backends.ultralytics import _offline_ultralytics

    _offline_ultralytics()
    from ultralytics.data.dataset import YOLODataset  # noqa: PLC0415

    class ShardYOLODataset(YOLODataset):
        """ultralytics' ``YOLODataset`` over the shards of ``img_path`` (a dataset directory, one
        shard, or a list of shards). Extra keyword arguments: ``curriculum`` (the
        :class:`RainCurriculum` images are drawn at), ``rain_data`` (the data of each rain
        model the curriculum names, :func:`open_rain_data`; entries without a rain model read
        ``img_path``), ``keep_classes`` (the COCO class ids whose labels are kept; None keeps
        all) and ``random_rain`` (a :class:`RandomRainAugment` applied to training images, or
        None). ``im_files`` are ``<shard>#<frame>`` names; ``images`` the
        :class:`rainbench.store.Image` of each index (the first ones of the dataset when
        ultralytics' ``fraction`` is below 1); ``store`` the dataset of ``img_path``, whose
        labels are yielded; ``stores`` the dataset of each rain model. Image ``i`` of every
        rain model's data must be the same scene frame (the same shard name, frame, size and
        labels): a :class:`CurriculumError` naming the directory otherwise."""

        def __init__(self, *args, curriculum: RainCurriculum = RainCurriculum(),
                     rain_data: Mapping[str, str | Path] | None = None,
                     keep_classes: Sequence[int] | None = None,
                     random_rain: RandomRainAugment | None = None, **kwargs) -> None:
            self.curriculum = curriculum
            self.rain_data = dict(rain_data or {})
            self.random_rain = random_rain
            self._random_rain = None if random_rain is None else random_rain.transform()
            self.keep_classes = None if keep_classes is None else np.asarray(keep_classes, np.int64)
            super().__init__(*args, **kwargs)

        def get_img_files(self, img_path) -> list[str]:
            self.store, self.stores = open_rain_data(img_path, self.curriculum, self.rain_data)
            for store in self.stores.values():
                if len(store) != len(self.store):
                    raise CurriculumError(
                        f"rain curriculum: {_data_name(store)} holds {len(store)} images but "
                        f"{_data_name(self.store)} holds {len(self.store)}; every rain model's training "
                        "data must hold the same frames")
            images = self.store.images  # ultralytics' ``fraction``: a share, or a count of images
            count = (self.fraction if isinstance(self.fraction, int)
                     else max(1, round(len(images) * self.fraction)))
            self.images = images[:count]
            return [f"{image.shard}#{image.frame}" for image in self.images]

        def get_labels(self) -> list[dict[str, Any]]:
            labels = []
            others = [store for store in dict.fromkeys(self.stores.values()) if store is not self.store]
            walks = [store.walk(store.images[:len(self.images)]) for store in others]
            for (image, handle), *same_frames in zip(self.store.walk(self.images), *walks):
                frame = read_frame_labels(handle, image.frame)
                height, width = self.store.size(image.shard_index)
                for store, (other_image, other_handle) in zip(others, same_frames):
                    self._check_same_frame(image, frame, store, other_image, other_handle)
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

        def _check_same_frame(self, image, frame: dict[str, np.ndarray], store: Dataset, other_image,
                              other_handle) -> None:
            """Raise CurriculumError unless ``other_image`` of ``store`` is the scene frame of
            ``image`` of :attr:`store` (labels ``frame``): the same shard name, frame, size,
            class ids and (M, 4) xyxy boxes."""
            other = read_frame_labels(other_handle, other_image.frame)
            if ((other_image.shard.name, other_image.frame) != (image.shard.name, image.frame)
                    or store.size(other_image.shard_index) != self.store.size(image.shard_index)
                    or not np.array_equal(other["class_id"], frame["class_id"])
                    or not np.array_equal(other["bbox"], frame["bbox"])):
                raise CurriculumError(
                    f"rain curriculum: {_data_name(store)} image {other_image.image_id} "
                    f"({other_image.shard.name}#{other_image.frame}) is not the frame of "
                    f"{_data_name(self.store)} ({image.shard.name}#{image.frame}); every rain model's "
                    "training data must hold the same frames")

        def load_image(self, i: int, rect_mode: bool = True, resize_short: bool = False):
            """Image ``i`` (BGR, long side resized to ``imgsz``) of a rain model and at a rate
            drawn from the curriculum; returns (image, (h0, w0), (h, w)) as ultralytics'
            ``load_image``. As there, a training image stays in memory while it is among the
            recent loads that mosaic draws its other images from (with the rain it was drawn
            at); a load that is not in memory reads the shard and draws anew."""
            if not rect_mode or resize_short:
                raise ValueError("ShardYOLODataset: only rect_mode resizing of the long side is supported")
            if self.ims[i] is not None:
                return self.ims[i], self.im_hw0[i], self.im_hw[i]
            rain_model, rate = self.curriculum.draw(random)
            store = self.stores[rain_model]
            image = store.images[i]
            rgb = store.read_rgb(store.handle(image.shard_index), image, rate)
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

    return ShardYOLODataset


def shard_trainer_class(curriculum: RainCurriculum, classes: Sequence[int] | None,
                        random_rain: RandomRainAugment | None = None,
                        rain_data: Mapping[str, str | Path] | None = None):
    """An ultralytics ``DetectionTrainer`` subclass whose training data is a ``ShardYOLODataset``
    drawn at ``curriculum`` (each named rain model read from its ``rain_data`` directory) and
    whose validation data is the clean (0 mm/h) frames of the validation shards; both keep the
    labels of ``classes`` (COCO ids). Pass it as ``YOLO(...).train(trainer=...)`` with a data
    yaml whose ``train`` and ``val`` are dataset directories of shards. ``random_rain``:
    albumentations' RandomRain on training images."""
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
                curriculum=curriculum if training else RainCurriculum(),
                rain_data=rain_data if training else None, keep_classes=classes,
                random_rain=random_rain if training else None)

    return ShardDetectionTrainer
