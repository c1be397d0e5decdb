"""``rainbench train``: in-domain YOLO detectors trained from scratch on clean rainbench scenes.

A *recipe* (``eval/recipes/<name>.yaml``, or any YAML file with the same keys) says everything a
training run depends on:

- ``name``: the weights' name (``<name>.pt``);
- ``architecture``: an ultralytics model yaml (``yolo11n.yaml``): no pretrained weights are used;
- ``train_data`` / ``val_data``: :class:`~rainbench.gen.dataset.DatasetConfig` fields of the clean
  (0 mm/h) training and validation datasets, ``scenario`` as
  :class:`~rainbench.mjcf.layout.ScenarioConfig` fields;
- ``train``: ultralytics ``train()`` arguments; ``cpu``: overrides of ``train`` used when no CUDA
  device is present (smaller images, fewer epochs).
- ``restarts`` (optional, in ``train`` or ``cpu``; the ``cpu`` one wins on CPU): a list of argument
  overrides, one per further stage. Stage k starts from stage k-1's best weights with a fresh
  optimizer and learning-rate schedule (a warm restart) and trains into ``OUT/restart<k>``; the
  last stage's best weights are the result.

:func:`train` generates both datasets (resuming a partial one), exports them as YOLO folders,
and trains, resuming from ``last.pt`` when a previous run of the same recipe was cut off. The
last stage's best weights are copied to ``OUT/<name>.pt``. Nothing is downloaded:
``YOLO_OFFLINE=1``, ``plots=False`` (no font fetch) and ``amp=False`` (no AMP-check download).

Seed split (docs/models.md): evaluation datasets use seeds below :data:`TRAIN_SEED_START`;
training and validation scenes must not.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rainbench.gen.dataset import DatasetConfig, run_dataset
from rainbench.mjcf.layout import CLASS_NAMES, ScenarioConfig

TRAIN_SEED_START = 1_000_000
"""Seeds of training and validation scenes are >= this; evaluation seeds are below it."""
RECIPES_DIR = Path(__file__).resolve().parent / "recipes"
RECIPE_KEYS = {"name", "architecture", "train_data", "val_data", "train", "cpu"}
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
    train_data: DatasetConfig
    val_data: DatasetConfig
    train_args: dict[str, Any]
    cpu_args: dict[str, Any]
    source: str

    def arguments(self, cuda: bool) -> dict[str, Any]:
        """ultralytics ``train()`` arguments of the first stage (``cpu`` overrides when not ``cuda``)."""
        return self.stages(cuda)[0]

    def stages(self, cuda: bool) -> list[dict[str, Any]]:
        """ultralytics ``train()`` arguments of every stage: the first stage's, then one per restart
        (the first stage's arguments with that restart's overrides)."""
        merged = dict(self.train_args) if cuda else {**self.train_args, **self.cpu_args}
        restarts = merged.pop("restarts", None) or []
        return [merged] + [{**merged, **overrides} for overrides in restarts]


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


def _dataset_config(section: Any, key: str, source: str) -> DatasetConfig:
    if not isinstance(section, dict):
        raise TrainError(f"{source}: `{key}` must be a mapping of dataset settings")
    fields = dict(section)
    scenario = fields.pop("scenario", None)
    known = {f.name for f in dataclasses.fields(DatasetConfig)} - {"scenario", "rates"}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise TrainError(f"{source}: `{key}.{unknown[0]}` is not a dataset setting "
                         f"(expected some of {', '.join(sorted(known))})")
    try:
        if scenario is not None:
            if not isinstance(scenario, dict):
                raise TrainError(f"{source}: `{key}.scenario` must be a mapping of ScenarioConfig fields")
            duration = fields.get("frames", 200) / fields.get("fps", 10.0)
            scenario = ScenarioConfig(**{"duration_s": duration, **scenario})
        config = DatasetConfig(**fields, rates=(0.0,), scenario=scenario)
    except TrainError:
        raise
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
    train_data = _dataset_config(raw["train_data"], "train_data", source)
    val_data = _dataset_config(raw["val_data"], "val_data", source)
    if _seed_range(train_data) & _seed_range(val_data):
        raise TrainError(f"{source}: train_data and val_data seeds overlap; validation scenes must be unseen")
    return Recipe(name=str(raw["name"]), architecture=str(raw["architecture"]), train_data=train_data,
                  val_data=val_data, train_args=dict(train_args), cpu_args=dict(cpu_args), source=source)


def _seed_range(config: DatasetConfig) -> set[int]:
    return set(range(config.seed, config.seed + config.scenes))


def prepare_data(recipe: Recipe, out: str | Path, *, workers: int = 1,
                 progress: Callable[[int], None] | None = None) -> Path:
    """Generate (or finish) the clean training and validation datasets under ``OUT/data`` and
    export them as YOLO folders under ``OUT/yolo``; returns the ultralytics ``dataset.yaml``."""
    from rainbench.gen.export import export_yolo

    out = Path(out)
    yolo = out / "yolo"
    for split, config in (("train", recipe.train_data), ("val", recipe.val_data)):
        data_dir = out / "data" / split
        manifest = data_dir / "manifest.json"
        before = manifest.read_bytes() if manifest.is_file() else None
        run_dataset(config, data_dir, workers=workers, progress=progress)
        done_marker = yolo / split / ".exported"
        if before != manifest.read_bytes() or not done_marker.is_file():
            done_marker.unlink(missing_ok=True)
            export_yolo(data_dir, yolo / split, rates=[0.0], image_format="png", overwrite=True)
            done_marker.write_text(manifest.read_text())
    dataset_yaml = out / "dataset.yaml"
    names = "\n".join(f"  {i}: {n}" for i, n in enumerate(CLASS_NAMES))
    dataset_yaml.write_text(f"path: {yolo.resolve()}\ntrain: train/rate_0/images\n"
                            f"val: val/rate_0/images\nnames:\n{names}\n")
    return dataset_yaml


def _finished(path: Path) -> bool:
    """Whether an ultralytics ``last.pt`` is of a finished run (its epoch is then -1)."""
    import torch

    return int(torch.load(path, map_location="cpu", weights_only=False).get("epoch", -1)) == -1


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
    from .backends import preload_torch

    ultralytics = preload_torch()  # before generating: triton after Mesa rendering crashes
    import torch

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cuda = torch.cuda.is_available() if device is None else device != "cpu"
    device = device if device is not None else ("0" if cuda else "cpu")
    stages = recipe.stages(cuda)
    (out / "recipe.json").write_text(json.dumps(
        {"recipe": recipe.source, "device": device, "train_args": stages[0], "restarts": stages[1:]},
        indent=1, sort_keys=True))
    dataset_yaml = prepare_data(recipe, out, workers=workers, progress=progress)
    best = None
    for stage, arguments in enumerate(stages):
        stage_dir = _stage_dir(out, stage)
        last = stage_dir / "weights" / "last.pt"
        if last.is_file() and not _finished(last):
            model = ultralytics.YOLO(str(last))
            model.train(resume=True, device=device)
        elif not last.is_file():
            model = ultralytics.YOLO(recipe.architecture)
            if best is not None:  # a warm restart: the previous stage's weights, a fresh schedule
                model.load(str(best))
            model.train(data=str(dataset_yaml), project=str(out.resolve()), name=stage_dir.name, exist_ok=True,
                        pretrained=best is not None, plots=False, amp=False, device=device, **arguments)
        best = stage_dir / "weights" / "best.pt"
        if not best.is_file():
            raise TrainError(f"training finished without {best}; see the log above")
    final = out / f"{recipe.name}.pt"
    shutil.copyfile(best, final)
    return final
