"""``rainbench train``: in-domain YOLO detectors trained from scratch on clean rainbench scenes.

A *recipe* (``experiments/recipes/<name>.yaml``, or any YAML file with the same keys) says everything a
training run depends on:

- ``name``: the weights' name (``<name>.pt``);
- ``architecture``: an ultralytics model yaml (``yolo11n.yaml``): no pretrained weights are used;
  it must resolve when the recipe is loaded (:func:`check_architecture`);
- ``train_data`` / ``val_data``: :class:`~rainbench.gen.config.DatasetConfig` fields of the clean
  (0 mm/h) training and validation datasets, ``scenario`` as
  :class:`~rainbench.mjcf.layout.ScenarioConfig` fields (its ``duration_s`` defaults to the
  clip's length); every field is checked when the recipe is loaded;
- ``train``: ultralytics ``train()`` arguments; ``cpu``: overrides of ``train`` used when no CUDA
  device is present (smaller images, fewer epochs). Every stage's arguments are checked when the
  recipe is loaded (:func:`_check_train_arguments`), not first when ultralytics starts training.
- ``restarts`` (optional, in ``train`` or ``cpu``; the ``cpu`` one wins on CPU): a list of argument
  overrides, one per further stage. Stage k starts from stage k-1's best weights with a fresh
  optimizer and learning-rate schedule (a warm restart) and trains into ``OUT/restart<k>``; the
  last stage's best weights are the result (or their ``wise_alpha`` mix).
- ``eval_imgsz`` (optional, default 640): the letterbox size the model is evaluated at, written
  to its card ``<name>.json`` (``rainbench eval`` uses it for a shipped model);
- ``classes`` (optional, default the paper's four: person, bicycle, car, motorcycle): the COCO
  classes trained, names or ids (``[person, bicycle, car, motorcycle, bus, truck]``); labels of
  other classes are left out of the training labels, and the model's ``names`` are the dense ids
  0..max with their COCO names;
- ``tiles`` (optional, in any stage): a :class:`~rainbench.experiments.tiles.TileConfig` mapping. That
  stage trains on tiles of the rescaled frames (:func:`prepare_tiles`) instead of whole frames,
  and must set ``imgsz`` to ``tiles.size``. Its training tiles get the recipe's rain (the
  ``rain_curriculum``'s rain models and rates, or ``random_rain``), as whole frames do; its
  validation tiles are clean.
- ``reader`` (optional, default ``shards``): whole-frame stages read the shards directly
  (:mod:`rainbench.experiments.shard_training`, no export); ``export`` trains on exported YOLO
  folders of the clean frames instead. Tile stages always cut their tiles from an export.
- ``rain_curriculum`` (optional, ``reader: shards`` only): the rain training images are drawn
  with and how often (:class:`~rainbench.experiments.shard_training.RainCurriculum`), either
  ``{rate: weight}`` (``{0: 2, 50: 1, 100: 1}``: half clean), the rates of ``train_data``'s own
  ``rain_model``, or ``{rain model: {rate: weight}}`` (``{physical: {0: 2, 50: 1}, jeon2022:
  {50: 1}}``), the weights then shared by all (rain model, rate) pairs together (here 2/4,
  1/4, 1/4). Each rain model's training data is ``train_data`` with that ``rain_model`` and
  exactly its curriculum rates, the same seeds and fields otherwise (so image ``i`` is the same
  scene frame in each; ``weather_follows_rate`` unset follows each rain model's own default, as
  in :class:`~rainbench.gen.config.DatasetConfig`): ``OUT/data/train`` holds ``train_data``'s
  own rain model (the flat form, or when the mapping names it), ``OUT/data/train-<rain model>``
  each other one (:meth:`Recipe.train_datasets`). Validation stays clean. Default: clean
  frames only.
- ``init_weights`` (optional): a shipped model's name or a ``.pt`` file the first stage starts from
  (a fine-tune with a fresh schedule, like a warm restart); default: from scratch.
- ``random_rain`` (optional, ``reader: shards`` only, not with ``rain_curriculum``): albumentations'
  ``RandomRain`` on the clean training frames, ``{p: 0.5, rain_type: heavy, ...}`` (``p`` the
  share of images it is applied to, the rest ``RandomRain`` arguments): the usual practice, for
  comparing a rain curriculum with on equal terms.
- ``wise_alpha`` (optional, with ``init_weights`` only): the shipped checkpoint is the trained one
  mixed in weight space with the one it started from, ``(1 - a) x init_weights + a x trained``
  (WiSE-FT, Wortsman et al. 2022; :func:`~rainbench.eval.weights.interpolate_checkpoints`), a in
  (0, 1]: a fine-tune that keeps more of its start's clean accuracy. Default: the trained
  checkpoint itself.

:func:`train` generates the datasets (one training dataset per rain model of the curriculum, and
the validation dataset; resuming a partial one), exports them as YOLO folders
when a stage needs them, and trains, resuming from ``last.pt`` when a previous run of the same recipe was cut off. The
last stage's best weights (mixed with ``init_weights`` when ``wise_alpha`` is set) are written to
``OUT/<name>.pt``, with ``OUT/<name>.onnx`` and
``OUT/<name>.json`` beside it (:func:`write_companions`). Nothing is downloaded:
``YOLO_OFFLINE=1``, ``plots=False`` (no font fetch) and ``amp=False`` (no AMP-check download).

Seed split (docs/models.md): evaluation datasets use seeds below :data:`TRAIN_SEED_START`;
training and validation scenes must not.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rainbench.devices import ultralytics_device
from rainbench.gen.config import DatasetConfig
from rainbench.gen.dataset import run_dataset
from rainbench.store.export import yolo_names
from rainbench.store.classes import PAPER_CLASSES, parse_classes
from rainbench.store.locks import locked_output_dir
from rainbench.store.manifest import is_int, sha256_of
from rainbench.store.rates import rate_token
from rainbench.mjcf.layout import ScenarioConfig

from rainbench.eval.weights import DEFAULT_IMGSZ
from rainbench.experiments.shard_training import (CurriculumError, RainCurriculum, RandomRainAugment,
                                                  shard_trainer_class)
from rainbench.experiments.tiles import TileConfig, TileError, export_tiles

TRAIN_CLASSES: tuple[int, ...] = PAPER_CLASSES
"""Class ids a recipe trains unless it says otherwise (its ``classes``): the paper's four, as the
shipped models; labels of other classes (bus 5, truck 7) are left out of the exported training
labels, so the model has 4 classes."""
TRAIN_SEED_START = 1_000_000
"""Seeds of training and validation scenes are >= this; evaluation seeds are below it."""
RECIPES_DIR = Path(__file__).resolve().parent / "recipes"
RECIPE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
"""What a recipe's ``name`` may be: a plain file name (it names ``OUT/<name>.pt`` and the default
``OUT``, ``runs/<name>``), so a recipe never writes outside its ``OUT``."""

RECIPE_KEYS = {"name", "architecture", "train_data", "val_data", "train", "cpu", "eval_imgsz",
               "classes", "reader", "rain_curriculum", "random_rain", "init_weights", "wise_alpha"}
READERS = ("shards", "export")
"""How a whole-frame stage reads its data: straight from the shards (the default; no export) or
from exported YOLO folders. Tile stages always train on tiles cut from the export."""
# Arguments rainbench sets itself (offline, paths, resume); a recipe may not set them.
RESERVED_TRAIN_ARGS = {"data", "project", "name", "exist_ok", "pretrained", "plots", "amp", "resume",
                       "device", "model"}


class TrainError(ValueError):
    """A training request that cannot be honoured; the message is one line."""


@dataclass(frozen=True)
class Recipe:
    """A parsed training recipe (see the module docstring)."""

    name: str
    architecture: str
    train_data: DatasetConfig  # train_data's fields, rates: every rate of the curriculum (train_datasets())
    val_data: DatasetConfig
    train_args: dict[str, Any]
    cpu_args: dict[str, Any]
    source: str
    eval_imgsz: int = DEFAULT_IMGSZ
    classes: tuple[int, ...] = TRAIN_CLASSES  # COCO ids trained (labels of others are left out)
    reader: str = "shards"  # one of READERS
    curriculum: RainCurriculum = RainCurriculum()  # rain training images are drawn with (reader shards)
    random_rain: RandomRainAugment | None = None  # albumentations RandomRain on training images (reader shards)
    init_weights: Path | None = None  # a checkpoint the first stage starts from (a fine-tune); None: from scratch
    wise_alpha: float | None = None  # the trained weights' share in the shipped mix with init_weights; None: 1

    def arguments(self, cuda: bool) -> dict[str, Any]:
        """ultralytics ``train()`` arguments of the first stage (``cpu`` overrides when not ``cuda``)."""
        return self.stages(cuda)[0]

    def stages(self, cuda: bool) -> list[dict[str, Any]]:
        """Arguments of every stage: the first stage's, then one per restart (the first stage's
        arguments with that restart's overrides). Each is ultralytics ``train()`` arguments plus,
        for a tile stage, ``tiles`` (a mapping of :class:`~rainbench.experiments.tiles.TileConfig`)."""
        return _stage_arguments(dict(self.train_args) if cuda else {**self.train_args, **self.cpu_args})

    def train_datasets(self) -> dict[str | None, tuple[str, DatasetConfig]]:
        """The training datasets, by the curriculum's rain models (None: the flat form, which
        uses ``train_data``'s own): the folder under ``OUT/data`` each is generated into and its
        config. ``train`` holds ``train_data``'s own rain model and comes first when present;
        ``train-<rain model>`` each other one, which is ``train_data`` with that ``rain_model``
        and the curriculum's rates of it, ascending. The first one's labels are trained on."""
        own = self.train_data.rain_model
        datasets = {model: ("train", self.train_data) if model is None else
                    ("train" if model == own else f"train-{model}",
                     dataclasses.replace(self.train_data, rain_model=model,
                                         rates=tuple(sorted(self.curriculum.rates_of(model)))))
                    for model in self.curriculum.rain_models}
        return dict(sorted(datasets.items(), key=lambda item: item[1][0] != "train"))


def _stage_arguments(merged: dict[str, Any]) -> list[dict[str, Any]]:
    merged = dict(merged)
    restarts = merged.pop("restarts", None) or []
    return [merged] + [{**merged, **overrides} for overrides in restarts]


def _stage_tiles(arguments: dict[str, Any], where: str) -> TileConfig | None:
    """The stage's tile config (None: whole frames); a stage with tiles must train at
    ``imgsz`` = ``tiles.size`` so that ultralytics does not rescale the tiles again."""
    if arguments.get("tiles") is None:
        return None
    try:
        config = TileConfig.from_mapping(arguments["tiles"], source="tiles")
    except (TileError, TypeError) as error:
        raise TrainError(f"{where}`: {error}") from None
    if arguments.get("imgsz") != config.size:
        raise TrainError(f"{where}.imgsz` must equal tiles.size ({config.size}) in a tile stage, "
                         f"got {arguments.get('imgsz')!r}")
    return config


def recipe_path(recipe: str | Path) -> Path:
    """A recipe file: a path to a YAML file, or the name of a shipped recipe (``rainbench-yolo11n``)."""
    path = Path(recipe)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise TrainError(f"--recipe: {path} does not exist")
        return path
    shipped = RECIPES_DIR / f"{recipe}.yaml"
    if not shipped.is_file():
        names = ", ".join(sorted(p.stem for p in RECIPES_DIR.glob("*.yaml")))
        raise TrainError(f"--recipe: {recipe!r} is neither a .yaml file nor a shipped recipe ({names})")
    return shipped


def _dataset_config(section: Any, key: str, source: str, rates: tuple[float, ...] = (0.0,)) -> DatasetConfig:
    if not isinstance(section, dict):
        raise TrainError(f"{source}: `{key}` must be a mapping of dataset settings")
    fields = dict(section)
    scenario = fields.pop("scenario", None)
    known = {f.name for f in dataclasses.fields(DatasetConfig)} - {"scenario", "rates"}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise TrainError(f"{source}: `{key}.{unknown[0]}` is not a dataset setting "
                         f"(expected some of {', '.join(sorted(known))})")
    if scenario is not None and not isinstance(scenario, dict):
        raise TrainError(f"{source}: `{key}.scenario` must be a mapping of ScenarioConfig fields")
    try:
        config = DatasetConfig(**fields, rates=rates)
        if scenario is not None:
            config = dataclasses.replace(config, scenario=ScenarioConfig(
                **{"duration_s": config.duration_s, **scenario}))
    except (TypeError, ValueError) as error:
        raise TrainError(f"{source}: `{key}`: {' '.join(str(error).split())}") from None
    if config.seed < TRAIN_SEED_START:
        raise TrainError(f"{source}: `{key}.seed` must be >= {TRAIN_SEED_START} (seeds below are for "
                         f"evaluation datasets), got {config.seed}")
    return config


def load_recipe(recipe: str | Path) -> Recipe:
    """Read and check a recipe (a YAML path or a shipped recipe name); errors name the file."""
    import yaml

    path = recipe_path(recipe)
    source = str(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise TrainError(f"{source}: not valid YAML ({' '.join(str(error).split())[:160]})") from None
    if not isinstance(raw, dict):
        raise TrainError(f"{source}: expected a mapping with keys {', '.join(sorted(RECIPE_KEYS))}")
    missing = sorted({"name", "architecture", "train_data", "val_data", "train"} - set(raw))
    unknown = sorted(set(raw) - RECIPE_KEYS)
    if missing or unknown:
        what = f"missing `{missing[0]}`" if missing else f"unknown key `{unknown[0]}`"
        raise TrainError(f"{source}: {what} (expected keys {', '.join(sorted(RECIPE_KEYS))})")
    train_args = raw["train"] or {}
    cpu_args = raw.get("cpu") or {}
    for key, args in (("train", train_args), ("cpu", cpu_args)):
        if not isinstance(args, dict):
            raise TrainError(f"{source}: `{key}` must be a mapping of ultralytics train() arguments")
        reserved = sorted(set(args) & RESERVED_TRAIN_ARGS)
        if reserved:
            raise TrainError(f"{source}: `{key}.{reserved[0]}` is set by rainbench train itself; remove it")
        restarts = args.get("restarts")
        if restarts is not None and not (isinstance(restarts, list) and all(isinstance(r, dict) for r in restarts)):
            raise TrainError(f"{source}: `{key}.restarts` must be a list of mappings of train() arguments, "
                             f"one per stage")
        for number, overrides in enumerate(restarts or [], start=1):
            bad = sorted(set(overrides) & (RESERVED_TRAIN_ARGS | {"restarts"}))
            if bad:
                raise TrainError(f"{source}: `{key}.restarts[{number}].{bad[0]}` cannot be set in a restart")
    for key, merged in (("train", train_args), ("cpu", {**train_args, **cpu_args})):
        for number, arguments in enumerate(_stage_arguments(merged)):
            where = key if number == 0 else f"{key}.restarts[{number}]"
            _check_train_arguments(arguments, f"{source}: `{where}")
            _stage_tiles(arguments, f"{source}: `{where}")
    name = raw["name"]
    if not (isinstance(name, str) and RECIPE_NAME.fullmatch(name)):
        raise TrainError(f"{source}: `name` must be a file name of letters, digits, '.', '_' and '-' "
                         f"(it names OUT/<name>.pt and the default OUT runs/<name>), got {name!r}")
    check_architecture(raw["architecture"], source)
    eval_imgsz = raw.get("eval_imgsz", DEFAULT_IMGSZ)
    if not (is_int(eval_imgsz) and eval_imgsz >= 32):
        raise TrainError(f"{source}: `eval_imgsz` must be an integer >= 32 (px), got {eval_imgsz!r}")
    try:
        classes = parse_classes(raw.get("classes", list(TRAIN_CLASSES)))
    except ValueError as error:
        raise TrainError(f"{source}: `classes`: {str(error).removeprefix('--classes: ')}") from None
    reader = raw.get("reader", "shards")
    if reader not in READERS:
        raise TrainError(f"{source}: `reader` must be one of {', '.join(READERS)}, got {reader!r}")
    try:
        curriculum = (RainCurriculum() if raw.get("rain_curriculum") is None
                      else RainCurriculum.from_mapping(raw["rain_curriculum"]))
    except CurriculumError as error:
        raise TrainError(f"{source}: `rain_curriculum`: {str(error).removeprefix('rain curriculum: ')}") from None
    if curriculum != RainCurriculum() and reader != "shards":
        raise TrainError(f"{source}: `rain_curriculum` needs `reader: shards` (whole frames read from an export "
                       "have one rate)")
    try:
        random_rain = (None if raw.get("random_rain") is None
                       else RandomRainAugment.from_mapping(raw["random_rain"]))
    except CurriculumError as error:
        raise TrainError(f"{source}: `random_rain`: {str(error).removeprefix('random_rain: ')}") from None
    if random_rain is not None and (reader != "shards" or curriculum != RainCurriculum()):
        raise TrainError(f"{source}: `random_rain` needs `reader: shards` and no `rain_curriculum` (it rains on "
                         "the clean frames: the baseline a curriculum is compared with)")
    init_weights = None
    if raw.get("init_weights") is not None:
        from rainbench.eval.backends import BackendError
        from rainbench.eval.weights import checkpoint_file

        try:
            init_weights = checkpoint_file(raw["init_weights"])
        except BackendError as error:
            raise TrainError(f"{source}: `init_weights`: {error}") from None
    wise_alpha = raw.get("wise_alpha")
    if wise_alpha is not None:
        if isinstance(wise_alpha, bool) or not isinstance(wise_alpha, (int, float)) or not 0 < wise_alpha <= 1:
            raise TrainError(f"{source}: `wise_alpha` must be a number in (0, 1], got {wise_alpha!r}")
        if init_weights is None:
            raise TrainError(f"{source}: `wise_alpha` needs `init_weights` (it mixes the trained weights with the "
                             "checkpoint they started from)")
        wise_alpha = float(wise_alpha)
    train_data = _dataset_config(raw["train_data"], "train_data", source, rates=tuple(sorted(curriculum.rates)))
    val_data = _dataset_config(raw["val_data"], "val_data", source)
    if _seed_range(train_data) & _seed_range(val_data):
        raise TrainError(f"{source}: train_data and val_data seeds overlap; validation scenes must be unseen")
    return Recipe(name=name, architecture=str(raw["architecture"]), train_data=train_data,
                  val_data=val_data, train_args=dict(train_args), cpu_args=dict(cpu_args), source=source,
                  eval_imgsz=eval_imgsz, classes=classes, reader=reader, curriculum=curriculum,
                  random_rain=random_rain, init_weights=init_weights, wise_alpha=wise_alpha)


# Integer train() arguments and their least value (ultralytics checks some only when training starts).
_TRAIN_INT_MIN = {"epochs": 1, "imgsz": 32, "patience": 0, "workers": 0, "close_mosaic": 0, "seed": 0, "nbs": 1,
                  "save_period": -1}


def _check_train_arguments(arguments: dict[str, Any], where: str) -> None:
    """Refuse a stage's ultralytics ``train()`` argument that ultralytics would refuse only once
    training starts, after the data is generated: a name it does not know, an integer argument
    out of range (:data:`_TRAIN_INT_MIN`), a bad ``batch`` or ``warmup_epochs``, and whatever
    ultralytics' own ``check_cfg`` refuses (types, fractions in [0, 1]). ``where`` is
    ``"<recipe>: `<section>"``; the error names the key."""
    from rainbench.eval.backends.ultralytics import _offline_ultralytics

    _offline_ultralytics()
    from ultralytics.cfg import DEFAULT_CFG_DICT, check_cfg

    for key, value in arguments.items():
        if key in ("tiles", "restarts"):
            continue
        if key not in DEFAULT_CFG_DICT and key != "augmentations":
            raise TrainError(f"{where}.{key}` is not an ultralytics train() argument")
        if key in _TRAIN_INT_MIN and not (is_int(value) and value >= _TRAIN_INT_MIN[key]):
            unit = " (px)" if key == "imgsz" else ""
            raise TrainError(f"{where}.{key}` must be an integer >= {_TRAIN_INT_MIN[key]}{unit}, got {value!r}")
        if key == "batch" and not (value == -1 or (is_int(value) and value >= 1) or (
                isinstance(value, float) and 0.0 < value < 1.0)):
            raise TrainError(f"{where}.batch` must be an integer >= 1, -1 (AutoBatch) or a GPU memory fraction "
                             f"in (0, 1), got {value!r}")
        if key in ("warmup_epochs", "time") and value is not None and not (
                isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0):
            raise TrainError(f"{where}.{key}` must be a number >= 0, got {value!r}")
        try:
            check_cfg({key: value}, hard=True)
        except (TypeError, ValueError) as error:
            raise TrainError(f"{where}.{key}`: {' '.join(str(error).split())}") from None


def check_architecture(architecture: Any, source: str) -> str:
    """``architecture`` if ultralytics can build it the way :func:`train` does (``YOLO(architecture)``):
    a model yaml that ultralytics finds (a file, or a name of its own such as ``yolo11n.yaml``,
    looked up as ``yaml_model_load`` does, without downloading) holding a ``backbone`` and a
    ``head``, or another existing file (a checkpoint). Anything else is a :class:`TrainError`
    naming the recipe ``source`` and its ``architecture`` key; nothing is built."""
    import re

    import yaml

    text = str(architecture).strip() if isinstance(architecture, (str, Path)) else ""
    bad = TrainError(f"{source}: `architecture`: {architecture!r} is not an ultralytics model yaml or a file")
    if not text or "://" in text:
        raise bad
    if not text.lower().endswith((".yaml", ".yml")):
        if not Path(text).is_file():
            raise bad
        return text
    from rainbench.eval.backends.ultralytics import _offline_ultralytics

    _offline_ultralytics()
    from ultralytics.utils.checks import check_file

    unified = re.sub(r"(\d+)([nslmx])(.+)?$", r"\1\3", text)  # yolo11n.yaml -> yolo11.yaml, as ultralytics
    try:
        found = (check_file(text, download=False, hard=False)
                 or check_file(unified, download=False, hard=False))
    except (OSError, ValueError):
        found = None
    if not found or not Path(found).is_file():
        raise bad
    try:
        model = yaml.safe_load(Path(found).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        model = None
    if not (isinstance(model, dict) and "backbone" in model and "head" in model):
        raise TrainError(f"{source}: `architecture`: {found} is not an ultralytics model yaml (it needs `backbone` "
                         "and `head`)")
    return text


def check_first_model(recipe: Recipe, ultralytics: Any) -> None:
    """Build the first stage's model as :func:`train` does (``YOLO(architecture)``, then
    ``init_weights`` loaded into it) and check that it is a detection model, so that a file that
    is not a checkpoint, or a classification or pose model, fails before the data is generated.
    A :class:`TrainError` names the recipe and the key."""
    model = _load_or_refuse(recipe, "architecture", recipe.architecture, lambda: ultralytics.YOLO(recipe.architecture))
    if getattr(model, "task", None) != "detect":
        raise TrainError(f"{recipe.source}: `architecture`: {recipe.architecture} is a "
                         f"{getattr(model, 'task', 'unknown')!r} model; expected a detection model")
    if recipe.init_weights is not None:
        _load_or_refuse(recipe, "init_weights", recipe.init_weights, lambda: model.load(str(recipe.init_weights)))


def _load_or_refuse(recipe: Recipe, key: str, value: Any, load: Callable[[], Any]) -> Any:
    """``load()``, or a :class:`TrainError` naming the recipe's ``key`` and what ultralytics said."""
    try:
        return load()
    except Exception as error:  # ultralytics raises TypeError, RuntimeError, KeyError, pickle errors
        reason = " ".join(str(error).split()) or type(error).__name__
        if len(reason) > 200:  # ultralytics' advice runs on; keep its start, whole words
            reason = reason[:200].rsplit(" ", 1)[0] + " ..."
        raise TrainError(f"{recipe.source}: `{key}`: {value} does not load as an ultralytics model ({reason})") from None


def check_device(device: str | None) -> str | None:
    """``device`` (``--device``) as ultralytics takes it
    (:func:`rainbench.devices.ultralytics_device`): None (None, ``""`` or ``"auto"``: CUDA 0 when
    present, else the CPU), ``"cpu"``, or CUDA indices (``"0"``, ``"0,1"``; ``cuda`` /
    ``cuda:N`` accepted). A device that is neither, or a CUDA device this machine does not have,
    is a one-line error naming ``--device``, as ``rainbench eval`` refuses it."""
    chosen = ultralytics_device(device, TrainError)
    if chosen in (None, "cpu"):
        return chosen
    import torch

    if not torch.cuda.is_available():  # eval's message (torch_device)
        raise TrainError(f"--device {device}: CUDA is not available on this machine")
    count = torch.cuda.device_count()
    missing = [index for index in map(int, chosen.split(",")) if index >= count]
    if missing:
        raise TrainError(f"--device {device}: there is no CUDA device {missing[0]} ({count} visible)")
    return chosen


def _seed_range(config: DatasetConfig) -> set[int]:
    return set(range(config.seed, config.seed + config.scenes))


def prepare_data(recipe: Recipe, out: str | Path, *, workers: int = 1, export: bool = True,
                 progress: Callable[[int], None] | None = None) -> Path:
    """Generate (or finish) the training datasets (one per rain model of the curriculum,
    :meth:`Recipe.train_datasets`) and the validation dataset under ``OUT/data``; with
    ``export``, also export them as YOLO folders: ``OUT/yolo/<folder>/rate_<token>`` for each
    training dataset at each of its curriculum rates (``OUT/yolo/train/rate_0`` alone without
    a curriculum) and ``OUT/yolo/val/rate_0``. Each export's stamp ``OUT/yolo/<folder>/.exported``
    records the trained classes and the dataset's manifest; an export is redone when they change
    or a rate's folder is missing. Returns the ultralytics dataset yaml: ``OUT/dataset.yaml``
    (the first training dataset at its first curriculum rate, and validation, as YOLO folders)
    with ``export``, else ``OUT/shards.yaml`` (the shard folders of the first training dataset
    and of validation, read by :func:`shard_trainer_class`'s trainer with
    :func:`train_data_dirs`)."""
    from rainbench.store.export import export_yolo  # noqa: PLC0415

    out = Path(out)
    yolo = out / "yolo"
    train_sets = recipe.train_datasets()
    exported = {folder: recipe.curriculum.rates_of(model) for model, (folder, _) in train_sets.items()}
    exported["val"] = (0.0,)
    first = next(iter(train_sets.values()))[0]
    for folder, config in [*train_sets.values(), ("val", recipe.val_data)]:
        data_dir = out / "data" / folder
        manifest = data_dir / "manifest.json"
        before = manifest.read_bytes() if manifest.is_file() else None
        run_dataset(config, data_dir, workers=workers, progress=progress,
                    remedy=f"delete {data_dir} to generate it again, or choose another --out")
        if not export:
            continue
        done_marker = yolo / folder / ".exported"
        # the export is redone when the data or the trained classes change
        stamp = json.dumps({"classes": list(recipe.classes), "manifest": manifest.read_text()})
        if (before != manifest.read_bytes() or not done_marker.is_file()
                or done_marker.read_text() != stamp
                or not all((yolo / folder / f"rate_{rate_token(rate)}").is_dir() for rate in exported[folder])):
            done_marker.unlink(missing_ok=True)
            export_yolo(data_dir, yolo / folder, rates=list(exported[folder]), image_format="png",
                        overwrite=True, classes=recipe.classes)
            done_marker.write_text(stamp)
    if not export:
        return _dataset_yaml(out / "shards.yaml", out / "data", first, "val", recipe.classes)
    return _dataset_yaml(out / "dataset.yaml", yolo, f"{first}/rate_{rate_token(exported[first][0])}/images",
                         "val/rate_0/images", recipe.classes)


def train_data_dirs(recipe: Recipe, out: str | Path) -> dict[str, Path]:
    """The training data directory of each rain model ``recipe``'s curriculum names (none for a
    flat curriculum): ``rain_data`` of :func:`shard_trainer_class`."""
    return {model: (Path(out) / "data" / folder).resolve()
            for model, (folder, _) in recipe.train_datasets().items() if model is not None}


def _dataset_yaml(path: Path, root: Path, train_images: str, val_images: str,
                  classes: tuple[int, ...]) -> Path:
    names = "\n".join(f"  {i}: {n}" for i, n in enumerate(yolo_names(classes)))
    path.write_text(f"path: {root.resolve()}\ntrain: {train_images}\nval: {val_images}\nnames:\n{names}\n")
    return path


def tile_rain(recipe: Recipe) -> dict[str, Any] | None:
    """The rain of ``recipe``'s training tiles, as its model card records it
    (:func:`_rain_record`), or None for clean tiles (no curriculum beyond the clean default, no
    RandomRain): part of the tile set's folder name and stamp (:func:`prepare_tiles`)."""
    if recipe.curriculum == RainCurriculum() and recipe.random_rain is None:
        return None
    return _rain_record(recipe)


def prepare_tiles(recipe: Recipe, out: str | Path, config: TileConfig) -> Path:
    """Cut the exported YOLO folders of :func:`prepare_data` (``OUT/yolo``) into tiles under
    ``OUT/<config.token(rain)>/{train,val}`` (sampled training tiles, a covering grid for
    validation; ``rain`` is :func:`tile_rain`); returns that tile set's ultralytics dataset yaml.

    Training tiles carry ``recipe``'s rain (:func:`~rainbench.experiments.tiles.export_tiles`):
    with a rain curriculum, each tile's pixels are cut from the export of a (rain model, rate)
    entry drawn with the curriculum's weights (labels from the first entry's export: the same
    frames); with ``random_rain``, RandomRain on that share of them. Validation tiles are cut
    from the clean validation frames. A tile set whose stamp (the config, the rain and the
    source exports' stamps) matches is kept; a clean recipe's stamp and tiles are those of
    earlier versions."""
    out = Path(out)
    rain = tile_rain(recipe)
    token = config.token(rain)
    root = out / token
    train_sets = recipe.train_datasets()
    entries = [(out / "yolo" / train_sets[model][0], rate, weight)
               for (model, rate), weight in zip(recipe.curriculum.entries, recipe.curriculum.weights)]
    for split in ("train", "val"):
        exports = entries if split == "train" else [(out / "yolo" / "val", 0.0, 1.0)]
        markers = {}
        for export, _, _ in exports:
            marker = export / ".exported"
            if not marker.is_file():
                raise TrainError(f"{export}: no finished export to cut into tiles; run prepare_data first")
            markers[export.name] = marker.read_text()
        sources = [(export / f"rate_{rate_token(rate)}", weight) for export, rate, weight in exports]
        rainy = split == "train" and rain is not None
        stamp = {"tiles": dataclasses.asdict(config), "source": markers[exports[0][0].name]}
        if rainy:
            stamp.update(rain=rain, sources=markers)
        done_marker = root / split / ".exported"
        if done_marker.is_file() and done_marker.read_text() == json.dumps(stamp):
            continue
        done_marker.unlink(missing_ok=True)
        export_tiles(sources[0][0], root / split, config, grid=split == "val",
                     num_classes=len(yolo_names(recipe.classes)),
                     rain_sources=sources if rainy and recipe.curriculum != RainCurriculum() else None,
                     random_rain=recipe.random_rain if rainy else None)
        done_marker.write_text(json.dumps(stamp))
    return _dataset_yaml(out / f"{token}.yaml", root, "train/images", "val/images", recipe.classes)


def _finished(path: Path, epochs: int | None = None) -> bool:
    """Whether an ultralytics ``last.pt`` is of a finished run: its epoch is -1 once ultralytics
    has stripped it, or its last epoch was saved (``epoch + 1 >= epochs``: a run cut off after
    its last epoch but before the strip, which ultralytics refuses to resume)."""
    import torch

    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
        epoch = int(checkpoint.get("epoch", -1))
    except Exception as error:  # noqa: BLE001 -- torch.load raises many kinds for a damaged file
        reason = " ".join(str(error).split())[:200] or type(error).__name__
        raise TrainError(f"{path}: cannot be read to resume the run ({type(error).__name__}: {reason}); "
                         f"delete it to train that stage again") from None
    return epoch == -1 or (epochs is not None and epoch + 1 >= epochs)


def _trained_with(recipe: Recipe) -> dict[str, Any]:
    """What a trained stage depends on besides its train() arguments (``OUT/recipe.json``)."""
    return {"architecture": recipe.architecture, "classes": list(recipe.classes), "reader": recipe.reader,
            "curriculum": repr(recipe.curriculum), "random_rain": repr(recipe.random_rain),
            "init_weights": None if recipe.init_weights is None else sha256_of(recipe.init_weights),
            "wise_alpha": recipe.wise_alpha}


def _check_same_training(out: Path, record: dict[str, Any]) -> None:
    """Refuse to go on in ``out`` when it holds a training run (a stage's ``last.pt``) made with
    other settings than ``record`` (``OUT/recipe.json``'s): finished stages would be reused while
    the card describes the new recipe. Keys an older ``recipe.json`` lacks are not compared."""
    previous_path = out / "recipe.json"
    started = any((_stage_dir(out, stage) / "weights" / "last.pt").is_file() for stage in range(len(record["restarts"]) + 1))
    if not (started and previous_path.is_file()):
        return
    try:
        previous = json.loads(previous_path.read_text())
    except (OSError, ValueError):
        return
    for key in (key for key in record if key not in ("recipe", "device")):
        if key in previous and json.loads(json.dumps(record[key], default=str)) != previous[key]:
            raise TrainError(f"{out}: holds a training run made with another `{key}` ({previous_path}); "
                             "choose another --out, or delete it to train again")


def _stage_dir(out: Path, stage: int) -> Path:
    return out / ("run" if stage == 0 else f"restart{stage}")


def train(recipe: Recipe, out: str | Path, *, device: str | None = None, workers: int = 1,
          progress: Callable[[int], None] | None = None) -> Path:
    """Run ``recipe`` into ``out`` (resuming a cut-off run there); returns ``OUT/<name>.pt``.

    ``device``: torch device (``cpu``, ``0``); None picks CUDA device 0 when present, else CPU.
    ``workers``: processes generating the datasets.

    Stages run in order into ``OUT/run``, ``OUT/restart1``, ...: a finished stage is skipped, a
    cut-off one resumes from its ``last.pt``, and a restart starts from the previous stage's
    ``best.pt``.
    """
    from rainbench.eval.backends.ultralytics import preload_torch

    ultralytics = preload_torch()  # before generating: triton after Mesa rendering crashes
    import torch

    # everything that would fail only once training starts fails here, before anything is written
    device = check_device(device)
    check_architecture(recipe.architecture, recipe.source)
    check_first_model(recipe, ultralytics)
    with locked_output_dir(out, "train", option="--out", error=TrainError) as out:
        return _train_into(recipe, out, device=device, workers=workers, progress=progress,
                           ultralytics=ultralytics, cuda_available=torch.cuda.is_available())


def _train_into(recipe: Recipe, out: Path, *, device: str | None, workers: int,
                progress: Callable[[int], None] | None, ultralytics, cuda_available: bool) -> Path:
    """:func:`train`'s work once the recipe is checked and ``out`` is locked."""
    cuda = cuda_available if device is None else device != "cpu"
    device = device if device is not None else ("0" if cuda else "cpu")
    stages = recipe.stages(cuda)
    record = {"recipe": recipe.source, "device": device, "train_args": stages[0], "restarts": stages[1:],
              **_trained_with(recipe)}
    _check_same_training(out, record)
    (out / "recipe.json").write_text(json.dumps(record, indent=1, sort_keys=True, default=str))
    tiles_of = [_stage_tiles(arguments, f"{recipe.source}: `stage {stage}") for stage, arguments in enumerate(stages)]
    from_shards = recipe.reader == "shards"
    needs_export = not from_shards or any(tiles is not None for tiles in tiles_of)
    shards_yaml = prepare_data(recipe, out, workers=workers, export=False, progress=progress) if from_shards else None
    export_yaml = prepare_data(recipe, out, workers=workers, progress=progress) if needs_export else None
    stage_data = [(shards_yaml if from_shards else export_yaml) if tiles is None
                  else prepare_tiles(recipe, out, tiles) for tiles in tiles_of]
    shard_trainer = (shard_trainer_class(recipe.curriculum, recipe.classes, recipe.random_rain,
                                         rain_data=train_data_dirs(recipe, out)) if from_shards else None)
    best = None
    for stage, arguments in enumerate(stages):
        arguments = {key: value for key, value in arguments.items() if key != "tiles"}
        stage_dir = _stage_dir(out, stage)
        last = stage_dir / "weights" / "last.pt"
        if last.is_file() and not _finished(last, arguments.get("epochs")):
            model = ultralytics.YOLO(str(last))
            resumed = {"trainer": shard_trainer} if from_shards and tiles_of[stage] is None else {}
            model.train(resume=True, device=device, **resumed)
        elif not last.is_file():
            model = ultralytics.YOLO(recipe.architecture)
            start = best if best is not None else recipe.init_weights
            if start is not None:  # a warm restart or a fine-tune: those weights, a fresh schedule
                model.load(str(start))
            reads_shards = from_shards and tiles_of[stage] is None
            if reads_shards:
                arguments = {**arguments, "cache": False}  # images are drawn at a new rate each time
            # an absolute path: a resumed run reads it back from last.pt, from any working directory
            model.train(data=str(Path(stage_data[stage]).resolve()), project=str(out.resolve()), name=stage_dir.name, exist_ok=True,
                        pretrained=start is not None, plots=False, amp=False, device=device,
                        **({"trainer": shard_trainer} if reads_shards else {}), **arguments)
        best = stage_dir / "weights" / "best.pt"
        if not best.is_file():
            raise TrainError(f"training finished without {best}; see the log above")
    final = out / f"{recipe.name}.pt"
    if recipe.wise_alpha is None:
        partial = final.with_name(f".{final.stem}.tmp-{os.getpid()}.pt")  # a cut-off copy never takes the name
        try:
            shutil.copyfile(best, partial)
            os.replace(partial, final)
        finally:
            partial.unlink(missing_ok=True)
    else:  # the shipped weights: the trained ones mixed with those they started from (written atomically)
        from rainbench.eval.weights import interpolate_checkpoints

        interpolate_checkpoints(recipe.init_weights, best, recipe.wise_alpha, final)
    write_companions(final, recipe.eval_imgsz, model_card(recipe, out, device, stages))
    return final


def _stage_record(stage_dir: Path, arguments: dict[str, Any]) -> dict[str, Any]:
    """A stage of a model card: its folder, ultralytics ``train()`` arguments, epochs run, the
    training time ultralytics logged (``results.csv`` column ``time``, seconds, its last row) and
    the best validation mAP@0.5 and mAP@0.5:0.95 with their epochs (None without a results file)."""
    import csv  # noqa: PLC0415

    record: dict[str, Any] = {"dir": stage_dir.name, "args": arguments, "epochs": None, "seconds": None,
                              "best_map50": None, "best_map50_epoch": None, "best_map50_95": None,
                              "best_map50_95_epoch": None}
    results = stage_dir / "results.csv"
    if not results.is_file():
        return record
    with results.open(newline="") as handle:
        rows = [{key.strip(): value for key, value in row.items()} for row in csv.DictReader(handle)]
    if not rows:
        return record
    record["epochs"] = len(rows)
    record["seconds"] = round(float(rows[-1]["time"]), 1) if rows[-1].get("time") else None
    for key, column in (("best_map50", "metrics/mAP50(B)"), ("best_map50_95", "metrics/mAP50-95(B)")):
        values = [float(row[column]) for row in rows if row.get(column)]
        if values:
            best = max(range(len(values)), key=values.__getitem__)
            record[key], record[f"{key}_epoch"] = round(values[best], 4), best + 1
    return record


def model_card(recipe: Recipe, out: str | Path, device: str, stages: list[dict[str, Any]]) -> dict[str, Any]:
    """What a trained model's card ``<name>.json`` says besides ``imgsz``: the recipe (file and
    sha256), the classes, the data (each dataset's manifest config, by folder under
    ``OUT/data``), the rain it was trained with (curriculum entries, RandomRain, the checkpoint
    it was fine-tuned from, ``wise_alpha``), every stage (:func:`_stage_record`), the device and the software
    versions, and the checkpoint's sha256 (``OUT/<name>.pt``). Reads only files of the run."""
    import platform  # noqa: PLC0415
    from importlib.metadata import PackageNotFoundError, version  # noqa: PLC0415

    from rainbench import __version__  # noqa: PLC0415
    from rainbench.store.classes import CLASS_NAMES  # noqa: PLC0415

    out = Path(out)
    folders = [folder for folder, _ in recipe.train_datasets().values()] + ["val"]
    data = {}
    for folder in folders:
        manifest = out / "data" / folder / "manifest.json"
        data[folder] = json.loads(manifest.read_text())["config"] if manifest.is_file() else None
    software = {"rainbench": __version__, "python": platform.python_version()}
    for package in ("ultralytics-opencv-headless", "torch", "mujoco", "numpy"):
        try:
            software[package] = version(package)
        except PackageNotFoundError:
            software[package] = None
    source = Path(recipe.source)
    return {
        "name": recipe.name,
        "architecture": recipe.architecture,
        "classes": {str(class_id): CLASS_NAMES[class_id] for class_id in recipe.classes},
        "recipe": {"file": source.name, "sha256": sha256_of(source) if source.is_file() else None},
        "data": data,
        "reader": recipe.reader,
        **_rain_record(recipe),
        "init_weights": (None if recipe.init_weights is None
                         else {"file": recipe.init_weights.name, "sha256": sha256_of(recipe.init_weights)}),
        "wise_alpha": recipe.wise_alpha,
        "stages": [_stage_record(_stage_dir(out, stage), arguments) for stage, arguments in enumerate(stages)],
        "device": device,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores" + _gpu_name(device),
        "software": software,
        "checkpoint_sha256": sha256_of(out / f"{recipe.name}.pt") if (out / f"{recipe.name}.pt").is_file() else None,
    }


def _rain_record(recipe: Recipe) -> dict[str, Any]:
    """``recipe``'s rain as its model card records it: ``rain_curriculum`` (a list of ``{rain_model,
    rate, weight}``, the own rain model named) and ``random_rain`` (``{p, **options}`` or None)."""
    own_model = recipe.train_data.rain_model
    return {
        "rain_curriculum": [{"rain_model": model or own_model, "rate": rate, "weight": weight}
                            for (model, rate), weight in zip(recipe.curriculum.entries, recipe.curriculum.weights)],
        "random_rain": (None if recipe.random_rain is None
                        else {"p": recipe.random_rain.p, **dict(recipe.random_rain.options)}),
    }


def _gpu_name(device: str) -> str:
    """``", <GPU name>"`` when ``device`` is a CUDA device, else empty."""
    if device == "cpu":
        return ""
    import torch  # noqa: PLC0415

    return f", {torch.cuda.get_device_name(int(device) if device.isdigit() else 0)}" if torch.cuda.is_available() else ""


def write_companions(weights: Path, eval_imgsz: int, card: dict[str, Any] | None = None) -> tuple[Path, Path]:
    """Beside ``<name>.pt``, write what a shipped model needs besides its checkpoint: ``<name>.onnx``
    (:func:`~rainbench.eval.weights.export_onnx`, run on CPU) and the card ``<name>.json``
    (``{"imgsz": eval_imgsz}`` and the fields of ``card``, :func:`model_card`). Shipping a model is
    copying the ``.pt`` and the card to ``eval/weights/`` (docs/models.md). Returns ``(onnx path,
    card path)``."""
    from rainbench.eval.weights import export_onnx

    onnx = export_onnx(weights, weights.with_suffix(".onnx"))
    card_path = weights.with_suffix(".json")
    card_path.write_text(json.dumps({"imgsz": eval_imgsz, **(card or {})}, indent=1, default=str) + "\n")
    return onnx, card_path
