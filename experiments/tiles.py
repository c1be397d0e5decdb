"""Training tiles: crops of rescaled frames, so a detector learns objects at the size it meets them.

A detector evaluated at ``--imgsz 800`` sees an 800x600 frame at its rendered size, where half of
all people are under 21 px tall. Training on whole frames at a small ``imgsz`` shrinks them
(to 0.52 of that at 416 px), and training on whole frames at full size spends most of its
compute on sky and empty road. A tile stage instead rescales each frame by
:attr:`TileConfig.scale` (the evaluator's letterbox factor: 1.0 for ``--imgsz 800``, 0.8 for
``--imgsz 640``) and cuts ``TileConfig.size`` squares from it, most of them placed on an object
(rare classes more often), some anywhere (background and negatives). ultralytics then trains at
``imgsz`` = ``size``, so the tiles are not resized again and objects keep the evaluator's scale.

Rain on training tiles (:func:`export_tiles`'s ``rain_sources`` and ``random_rain``): a tile's
pixels may be cut from the same frame rendered otherwise (another rain model or rate: one YOLO
folder each, drawn per tile by weight), and albumentations' RandomRain may rain on the frame a
tile is cut from. Both draw from a generator of their own (:func:`rain_generator`), so a rainy
tile set places its tiles exactly where the clean one with the same :class:`TileConfig` does,
with the same labels; validation tiles stay clean.

Pure functions (:func:`cut_boxes`, :func:`sample_tile_origins`, :func:`grid_tile_origins`)
decide what goes in a tile; :func:`export_tiles` reads YOLO folders and writes a tiled one.
Boxes are float ``x1, y1, x2, y2`` in pixel-edge coordinates throughout.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

if TYPE_CHECKING:
    from rainbench.experiments.shard_training import RandomRainAugment


class TileError(ValueError):
    """A tile setting or folder that cannot be honoured; the message is one line."""


@dataclass(frozen=True)
class TileConfig:
    """How a tile stage cuts its training and validation images.

    - ``size``: tile side in pixels after rescaling (train that stage at ``imgsz`` = ``size``);
    - ``scale``: factor applied to each frame before cutting: the evaluator's letterbox factor
      (1.0 at ``--imgsz 800`` for 800x600 frames, 0.8 at ``--imgsz 640``);
    - ``per_image``: training tiles cut from each frame;
    - ``background``: share of training tiles placed uniformly at random instead of on an object;
    - ``min_area_fraction``: a box cut by a tile edge is kept when at least this share of its
      area lies inside the tile (otherwise it is dropped);
    - ``seed``: seed of the tile placement (the same seed gives the same tiles).

    Validation images are cut into a grid that covers every pixel (:func:`grid_tile_origins`).
    """

    size: int = 320
    scale: float = 1.0
    per_image: int = 2
    background: float = 0.2
    min_area_fraction: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.size, int) and 32 <= self.size <= 4096 and self.size % 32 == 0):
            raise TileError(f"tiles.size: expected a multiple of 32 in 32..4096 px, got {self.size!r}")
        if not (isinstance(self.scale, (int, float)) and 0.05 <= self.scale <= 4.0):
            raise TileError(f"tiles.scale: expected a factor in 0.05..4, got {self.scale!r}")
        if not (isinstance(self.per_image, int) and 1 <= self.per_image <= 64):
            raise TileError(f"tiles.per_image: expected an integer in 1..64, got {self.per_image!r}")
        if not (isinstance(self.background, (int, float)) and 0.0 <= self.background <= 1.0):
            raise TileError(f"tiles.background: expected a share in 0..1, got {self.background!r}")
        if not (isinstance(self.min_area_fraction, (int, float)) and 0.0 < self.min_area_fraction <= 1.0):
            raise TileError(f"tiles.min_area_fraction: expected a share in (0, 1], got "
                            f"{self.min_area_fraction!r}")
        if not (isinstance(self.seed, int) and self.seed >= 0):
            raise TileError(f"tiles.seed: expected an integer >= 0, got {self.seed!r}")

    @classmethod
    def from_mapping(cls, mapping: Any, source: str = "tiles") -> TileConfig:
        """A config from a recipe's ``tiles:`` mapping; unknown keys are a one-line error."""
        if not isinstance(mapping, dict):
            raise TileError(f"{source}: expected a mapping of tile settings, got {mapping!r}")
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(mapping) - set(known))
        if unknown:
            raise TileError(f"{source}.{unknown[0]} is not a tile setting (expected some of {', '.join(known)})")
        return cls(**mapping)

    def token(self, rain: Mapping[str, Any] | None = None) -> str:
        """A folder name that differs whenever a setting differs. ``rain``: a JSON-able
        description of the training tiles' rain (None: clean tiles, the name has no rain part);
        it appends ``_rain<the first 10 hex digits of its sha256>``, so other rain, another name."""
        token = (f"tiles_s{self.size}_x{self.scale:g}_n{self.per_image}_b{self.background:g}"
                 f"_a{self.min_area_fraction:g}_r{self.seed}")
        if rain is None:
            return token
        digest = hashlib.sha256(json.dumps(rain, sort_keys=True, default=str).encode()).hexdigest()
        return f"{token}_rain{digest[:10]}"


def _check_fits(image_size: tuple[int, int], size: int) -> None:
    height, width = image_size
    if height < size or width < size:
        raise TileError(f"tiles.size: {size} px is larger than the rescaled image ({width}x{height}); "
                        f"lower tiles.size or raise tiles.scale")


def cut_boxes(boxes: np.ndarray, class_ids: np.ndarray, origin: tuple[int, int], size: int,
              min_area_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """The labels of one tile.

    ``boxes``: (M, 4) float xyxy pixel-edge boxes in the (rescaled) image; ``class_ids``: (M,)
    ints; ``origin``: the tile's top-left corner ``(x0, y0)`` in the same pixels; ``size``: its
    side. Returns ``(boxes (K, 4) float32 xyxy in tile pixels, class_ids (K,) int32)``: each box
    clipped to the tile, kept when its clipped area is at least ``min_area_fraction`` of its
    whole area and both clipped sides are at least 1 px.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    class_ids = np.asarray(class_ids).reshape(-1)
    if boxes.shape[0] != class_ids.shape[0]:
        raise TileError(f"expected one class id per box: got {boxes.shape[0]} boxes and "
                        f"{class_ids.shape[0]} class ids")
    x0, y0 = origin
    shifted = boxes - np.array([x0, y0, x0, y0], dtype=np.float64)
    clipped = np.clip(shifted, 0.0, float(size))
    width = clipped[:, 2] - clipped[:, 0]
    height = clipped[:, 3] - clipped[:, 1]
    area = np.maximum(shifted[:, 2] - shifted[:, 0], 0) * np.maximum(shifted[:, 3] - shifted[:, 1], 0)
    keep = (width >= 1.0) & (height >= 1.0) & (width * height >= min_area_fraction * area - 1e-9)
    return clipped[keep].astype(np.float32), class_ids[keep].astype(np.int32)


def sample_tile_origins(boxes: np.ndarray, class_ids: np.ndarray, image_size: tuple[int, int],
                        config: TileConfig, class_weights: np.ndarray,
                        rng: np.random.Generator) -> np.ndarray:
    """Top-left corners of ``config.per_image`` training tiles of one image.

    ``boxes``: (M, 4) float xyxy pixel-edge boxes in the rescaled image; ``class_ids``: (M,)
    ints; ``image_size``: ``(height, width)`` of the rescaled image, each >= ``config.size``;
    ``class_weights``: (C,) float, the chance of a box being picked is proportional to the
    weight of its class. A tile is placed anywhere with probability ``config.background`` (and
    always when the image has no box); otherwise on a picked box: uniformly among the positions
    that hold the whole box (or its centre, for a box larger than the tile). Returns (N, 2) int
    ``(x0, y0)`` with ``0 <= x0 <= width - size`` and ``0 <= y0 <= height - size``.
    """
    height, width = image_size
    size = config.size
    _check_fits(image_size, size)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    class_ids = np.asarray(class_ids, dtype=np.int64).reshape(-1)
    weights = np.asarray(class_weights, dtype=np.float64)[class_ids] if len(class_ids) else np.zeros(0)
    origins = np.zeros((config.per_image, 2), dtype=np.int64)
    for row in range(config.per_image):
        anywhere = rng.random() < config.background or weights.sum() <= 0
        if anywhere:
            origins[row] = rng.integers(0, width - size + 1), rng.integers(0, height - size + 1)
            continue
        pick = rng.choice(len(weights), p=weights / weights.sum())
        x1, y1, x2, y2 = boxes[pick]
        for axis, (low, high, extent) in enumerate(((x1, x2, width), (y1, y2, height))):
            if high - low <= size:  # the whole box fits: its far edge inside, its near edge too
                start, stop = math.ceil(high - size), math.floor(low)
            else:  # a box larger than the tile: keep its centre inside
                centre = (low + high) / 2
                start, stop = math.ceil(centre - size), math.floor(centre)
            start = min(max(start, 0), extent - size)
            stop = max(min(stop, extent - size), start)
            origins[row, axis] = rng.integers(start, stop + 1)
    return origins


def grid_tile_origins(image_size: tuple[int, int], size: int) -> np.ndarray:
    """Top-left corners of the fewest ``size`` tiles, evenly spaced, that cover an image of
    ``image_size`` = ``(height, width)`` (each side >= ``size``); (N, 2) int ``(x0, y0)``, row-major."""
    height, width = image_size
    _check_fits(image_size, size)

    def starts(extent: int) -> np.ndarray:
        count = math.ceil(extent / size)
        return np.round(np.linspace(0, extent - size, count)).astype(np.int64) if count > 1 \
            else np.zeros(1, np.int64)

    xs, ys = starts(width), starts(height)
    return np.array([(x, y) for y in ys for x in xs], dtype=np.int64)


def rescaled_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """``(height, width)`` of an image rescaled by ``scale`` (rounded to whole pixels)."""
    return max(1, round(height * scale)), max(1, round(width * scale))


def class_weights_of(label_dir: Path, num_classes: int) -> np.ndarray:
    """(C,) weights ``1 / sqrt(count)`` of each class's boxes over a YOLO ``labels/`` folder
    (0 for a class with no box), so that tiles land on rare classes more often than their share."""
    counts = np.zeros(num_classes, dtype=np.float64)
    for path in sorted(label_dir.glob("*.txt")):
        for line in path.read_text().splitlines():
            if line.strip():
                class_id = int(line.split()[0])
                if not 0 <= class_id < num_classes:
                    raise TileError(f"{path}: class {class_id} is outside 0..{num_classes - 1}")
                counts[class_id] += 1
    return np.where(counts > 0, 1.0 / np.sqrt(np.maximum(counts, 1.0)), 0.0)


def rain_generator(seed: int) -> np.random.Generator:
    """The generator of a tile set's rain draws (each tile's rain source, RandomRain's chance and
    seed): a stream of its own derived from ``seed`` (:attr:`TileConfig.seed`), apart from the
    placements' ``default_rng(seed)``, so rain never moves a tile."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1,)))


def _read_bgr(path: Path) -> np.ndarray:
    """The (H, W, 3) uint8 BGR image at ``path``."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise TileError(f"{path}: not a readable image")
    return bgr


def _rescale(bgr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) ``bgr`` resized to ``size`` = ``(height, width)`` (bilinear, as ultralytics'
    letterbox), itself when it has that size already."""
    if bgr.shape[:2] == size:
        return bgr
    return cv2.resize(bgr, (size[1], size[0]), interpolation=cv2.INTER_LINEAR)


def _check_rain_sources(source: Path, names: list[str], folders: Sequence[Path]) -> None:
    """Raise TileError unless every YOLO folder of ``folders`` holds the frames of ``source``:
    the same image names (``names``, sorted) and the same label files."""
    for folder in dict.fromkeys(folders):
        if folder == source:
            continue
        if sorted(path.name for path in (folder / "images").glob("*.png")) != names:
            raise TileError(f"{folder / 'images'}: holds other images than {source / 'images'}; a rain "
                            "source must hold the frames of the source")
        for name in names:
            label = Path(name).with_suffix(".txt").name
            if (folder / "labels" / label).read_text() != (source / "labels" / label).read_text():
                raise TileError(f"{folder / 'labels' / label}: labels differ from {source / 'labels' / label}; "
                                "a rain source must hold the frames of the source")


def export_tiles(source: Path, out: Path, config: TileConfig, *, grid: bool, num_classes: int,
                 rain_sources: Sequence[tuple[Path, float]] | None = None,
                 random_rain: RandomRainAugment | None = None) -> int:
    """Cut the YOLO folder ``source`` (``images/*.png`` with ``labels/*.txt`` of the same stem)
    into tiles under ``out/images`` and ``out/labels``; returns the number of tiles written.

    Tile ``k`` of image ``<stem>`` is ``<stem>_t<k:02d>.png``. ``grid=False`` samples
    :func:`sample_tile_origins` (training, seeded by ``config.seed``: the same folder and config
    give the same tiles); ``grid=True`` covers each image with :func:`grid_tile_origins`
    (validation). Images are rescaled by ``config.scale`` with bilinear interpolation, as
    ultralytics' letterbox does. ``out`` is replaced.

    Rain, on training tiles only (a grid with rain is a :class:`TileError`), drawn per tile from
    :func:`rain_generator` (``config.seed``), so the tiles' places and labels are those without
    rain and the same arguments give the same files:

    - ``rain_sources``: (K,) ``(YOLO folder, weight >= 0)`` pairs, each holding the frames of
      ``source`` (the same image names and label files; ``source`` itself may be one) rendered
      otherwise, e.g. at another rain rate. Each tile's pixels are cut from one of them, drawn
      with probability proportional to its weight (no draw when K is 1); its labels are
      ``source``'s. None: ``source``'s pixels.
    - ``random_rain``: albumentations' RandomRain with probability ``random_rain.p`` per tile,
      seeded by the generator; it rains on the whole frame (RGB, before the rescale) the tile is
      then cut from, as on a whole training frame: RandomRain's drop count and length grow with
      the image's height, so raining on the tile alone would give denser, shorter drops.
    """
    from rainbench.store.export import _yolo_lines, read_yolo_labels

    images = sorted((source / "images").glob("*.png"))
    if not images:
        raise TileError(f"{source / 'images'}: no .png images to cut into tiles")
    rainy = rain_sources is not None or random_rain is not None
    if rainy and grid:
        raise TileError(f"{source}: rain is for training tiles only; a validation grid is cut clean")
    folders = [Path(folder) for folder, _ in rain_sources] if rain_sources is not None else [source]
    shares = np.asarray([weight for _, weight in rain_sources] if rain_sources is not None else [1.0], np.float64)
    if len(folders) == 0 or not (np.isfinite(shares).all() and (shares >= 0).all() and shares.sum() > 0):
        raise TileError(f"rain_sources: expected (folder, weight) pairs with weights >= 0 and a positive sum, "
                        f"got {list(rain_sources or [])}")
    shares = shares / shares.sum()
    _check_rain_sources(source, [path.name for path in images], folders)
    transform = None if random_rain is None else random_rain.transform()
    weights = class_weights_of(source / "labels", num_classes)
    rng = np.random.default_rng(config.seed)
    rain_rng = rain_generator(config.seed)
    for sub in ("images", "labels"):
        folder = out / sub
        if folder.is_dir():
            for stale in folder.iterdir():
                stale.unlink()
        folder.mkdir(parents=True, exist_ok=True)
    written = 0
    for image_path in images:
        bgr = _read_bgr(image_path)
        height, width = bgr.shape[:2]
        boxes, class_ids = read_yolo_labels(source / "labels" / f"{image_path.stem}.txt", width, height)
        new_size = new_height, new_width = rescaled_size(height, width, config.scale)
        if new_size != (height, width):
            boxes = boxes * np.array([new_width / width, new_height / height] * 2, dtype=np.float32)
        origins = (grid_tile_origins(new_size, config.size) if grid else
                   sample_tile_origins(boxes, class_ids, new_size, config, weights, rng))
        stored = {source: bgr}  # rain source folder -> (H, W, 3) BGR frame as stored
        rescaled: dict[Path, np.ndarray] = {}  # the same, rescaled
        for number, (x0, y0) in enumerate(origins):
            tile_boxes, tile_classes = cut_boxes(boxes, class_ids, (int(x0), int(y0)), config.size,
                                                 config.min_area_fraction)
            stem = f"{image_path.stem}_t{number:02d}"
            folder = folders[int(rain_rng.choice(len(folders), p=shares))] if len(folders) > 1 else folders[0]
            if folder not in stored:
                stored[folder] = _read_bgr(folder / "images" / image_path.name)
                if stored[folder].shape != bgr.shape:
                    raise TileError(f"{folder / 'images' / image_path.name}: {stored[folder].shape[1]}x"
                                    f"{stored[folder].shape[0]} px, but {image_path} is {width}x{height}; a rain "
                                    "source must hold the frames of the source")
            if transform is not None and rain_rng.random() < random_rain.p:
                transform.set_random_seed(int(rain_rng.integers(2**32)))
                rained = transform(image=np.ascontiguousarray(stored[folder][:, :, ::-1]))["image"][:, :, ::-1]
                frame = _rescale(rained, new_size)
            else:
                if folder not in rescaled:
                    rescaled[folder] = _rescale(stored[folder], new_size)
                frame = rescaled[folder]
            crop = np.ascontiguousarray(frame[y0:y0 + config.size, x0:x0 + config.size])
            if not cv2.imwrite(str(out / "images" / f"{stem}.png"), crop):
                raise OSError(f"{out / 'images' / stem}.png: could not write the tile")
            (out / "labels" / f"{stem}.txt").write_text(
                _yolo_lines(tile_boxes, tile_classes, config.size, config.size))
            written += 1
    return written
