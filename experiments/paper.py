"""``rainbench paper`` / ``make paper``: the seed paper's experiment on rainbench data, end to end.

Defaults equal the paper's: one clip of 200 frames of 800x600 (seed 0, the cloudy street by day:
:data:`~rainbench.gen.config.PAPER_CLIP`), rates 0..100 mm/h in steps of 10, the four classes (``PaperConfig.classes`` adds bus and truck: ``--classes``). For each rain model (``jeon2022``, the paper's calibrated law, and
``physical``) a dataset is generated (or finished: it resumes), every model is evaluated with
``run_eval`` into ``OUT/<rain model>/``, and ``OUT/report.md`` sets our Tables I, III and IV beside
the paper's, with the analyses beyond it (half-AP rates, the two rain models side by side, AP by
visible fraction and by box size at 0, 50 and 100 mm/h, and every model's mPC and rPC with
bootstrap intervals, rain-trained models against the clean-trained one they extend:
``OUT/<rain model>/robustness.json`` holds those rows).
"""

from __future__ import annotations

import math
import platform
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rainbench.gen.config import PAPER_CLIP, RAIN_MODELS, DatasetConfig
from rainbench.gen.dataset import run_dataset, start_bar_at
from rainbench.store import Dataset, read_frame_ignore, read_frame_labels

from rainbench.store.locks import locked_output_dir
from rainbench.store.classes import CLASS_NAMES, PAPER_CLASSES, parse_classes
from rainbench.eval.metrics.breakdown import ap_by_size, ap_by_visibility
from rainbench.eval.metrics.coco import DEFAULT_BACKEND
from rainbench.eval.metrics.robustness import half_value_rate
from rainbench.eval.comparison import comparison_references
from rainbench.eval.pipeline import EvalError, check_metrics, ground_truth, load_predictions_file, open_dataset, predictions_path, run_eval
from rainbench.eval.report.markdown import render_paper_md

PAPER_RATES = tuple(float(r) for r in range(0, 101, 10))
"""The seed paper's rain rates in mm/h: 0 (Normal) to 100 in steps of 10."""
VISIBILITY_BINS = (0.1, 0.25, 0.5, 0.75, 1.0)  # labels start at visible_fraction 0.10


@dataclass(frozen=True, kw_only=True)
class PaperConfig:
    """What ``make paper`` runs; defaults are the paper's experiment with the shipped nano model.

    ``dataset`` is the data of every condition (:func:`conditions`), which sets its
    ``rain_model`` and ``weather_follows_rate``; the other fields say what is evaluated and how.
    """

    dataset: DatasetConfig = field(default_factory=lambda: DatasetConfig(**PAPER_CLIP, rates=PAPER_RATES))
    rain_models: tuple[str, ...] = RAIN_MODELS
    weights: tuple[str, ...] = ("rainbench-yolo11n",)
    imgsz: int | None = None  # None: each model's own (rainbench.eval.weights.model_imgsz)
    batch: int = 32
    n_boot: int = 1000
    device: str | None = None
    breakdown_rates: tuple[float, ...] = (0.0, 50.0, 100.0)
    classes: str | tuple[int | str, ...] | None = None  # None: the paper's four; else as run_eval's
    # (model, reference) pairs of the robustness comparison (--compare); run_paper adds default_references
    references: tuple[tuple[str, str], ...] = ()
    metrics: str = DEFAULT_BACKEND  # COCO AP implementation (run_eval's ``metrics``: --metrics)

    def __post_init__(self) -> None:
        if self.classes is not None:
            try:
                parse_classes(self.classes)
            except ValueError as error:
                raise EvalError(str(error)) from None
        if not self.weights:
            raise EvalError("MODELS/WEIGHTS: expected at least one model to evaluate")
        check_metrics(self.metrics)
        unknown = sorted(set(self.rain_models) - set(RAIN_MODELS))
        if unknown or not self.rain_models:
            raise EvalError(f"--rain-models: expected some of {', '.join(RAIN_MODELS)}, got {list(self.rain_models)}")
        twice = [model for number, model in enumerate(self.rain_models) if model in self.rain_models[:number]]
        if twice:
            raise EvalError(f"--rain-models: {twice[0]} is named twice")
        if not isinstance(self.dataset, DatasetConfig):
            raise EvalError(f"dataset: expected a DatasetConfig, got {type(self.dataset).__name__}")
        if 0.0 not in self.dataset.rates:
            raise EvalError(f"RATES: the paper's comparison needs rate 0 (Normal), got {list(self.dataset.rates)}")
        for pair in self.references:
            if not (isinstance(pair, tuple) and len(pair) == 2 and all(isinstance(n, str) and n for n in pair)
                    and pair[0] != pair[1]):
                raise EvalError(f"--compare: expected MODEL=REFERENCE with two different model names, got {pair!r}")


FIXED_WEATHER = "-fixed-weather"


def conditions(rain_models: Sequence[str]) -> list[tuple[str, str, bool]]:
    """``(name, rain model, weather follows the rate)`` of every dataset ``make paper`` builds:
    each rain model with its default (jeon2022 over the unchanged scene, the paper's method;
    physical with the weather following the rate), and physical again over the unchanged base
    weather, so the report separates the drops' share of the AP loss from the light's."""
    out = [(model, model, model == "physical") for model in rain_models]
    if "physical" in rain_models:
        out.append(("physical" + FIXED_WEATHER, "physical", False))
    return out


CONTROL_MODEL = "rainbench-yolo11n-weak"
"""A deliberately weak in-domain detector (the nano recipe's first epochs): clean AP near the
seed paper's COCO detectors', so the report shows whether the paper's size of drop appears for a
detector of the paper's strength."""


RAIN_TRAINED = ("-randomrain", "-rain")
"""Suffixes of the shipped rain-trained twins of a clean-trained model (issue 19,
docs/models.md): ``<model>-randomrain`` (albumentations RandomRain, the usual practice) and
``<model>-rain`` (rainbench's rain curriculum)."""


def default_models(cuda: bool) -> tuple[str, ...]:
    """The shipped models ``make paper`` evaluates, those of them that are shipped: on a GPU the
    nano and the small model, each followed by its rain-trained twins (:data:`RAIN_TRAINED`), and
    the weak control; on a CPU the nano model and the weak control only (each model adds about 7
    minutes per dataset there; ``MODELS=`` evaluates the twins too, docs/models.md)."""
    from rainbench.eval.weights import shipped_models

    if cuda:
        wanted = tuple(size + suffix for size in ("rainbench-yolo11n", "rainbench-yolo11s")
                       for suffix in ("", *RAIN_TRAINED))
    else:
        wanted = ("rainbench-yolo11n",)
    return tuple(name for name in wanted + (CONTROL_MODEL,) if name in shipped_models()) or ("rainbench-yolo11n",)


def default_references(models: Sequence[str], chosen: Sequence[tuple[str, str]] = ()) -> tuple[tuple[str, str], ...]:
    """The robustness comparison's ``(model, reference)`` pairs of ``make paper`` (and
    ``bench/quality.py --rain``): the user's ``chosen`` pairs (``--compare``), and for each
    evaluated ``<model>-rain`` whose ``<model>-randomrain`` is evaluated too and that ``chosen``
    does not name, the pair ``(<model>-rain, <model>-randomrain)`` (the question of issue 19: does
    rendered rain beat the usual augmentation?). ``models`` are model names or weights files (a
    file's model name is its stem). Every other model keeps
    :func:`rainbench.eval.comparison.comparison_references`' default."""
    names = [Path(str(model)).stem for model in models]
    named = {model for model, _ in chosen}
    bases = dict.fromkeys(name.removesuffix("-rain") for name in names if name.endswith("-rain"))
    return tuple((base + "-rain", base + "-randomrain") for base in bases
                 if base + "-randomrain" in names and base + "-rain" not in named) + tuple(chosen)


def check_models(specs: Sequence[tuple[str, str | Path]], device: str | None = None) -> None:
    """Refuse, before anything is generated, a model that :func:`run_paper` could not evaluate:
    ``specs`` are ``(flag, model)`` pairs, the flag the user gave it with (``--model`` or
    ``--weights``). Each model must be a shipped model's name or an existing weights file
    (:func:`rainbench.eval.weights.resolve_weights`' rule, without building anything), and the
    model names (a shipped name, else the file's stem) must be unique, as ``run_eval`` requires.
    An ONNX file on a CUDA ``device`` needs onnxruntime's CUDA provider
    (:func:`rainbench.eval.backends.onnx.onnx_cuda_device`; a shipped name on a GPU runs its
    ``.pt``). The error is one line naming the flag and the model."""
    from rainbench.eval.backends.onnx import onnx_cuda_device
    from rainbench.eval.weights import IS_A_DIRECTORY, shipped_models, weights_location

    seen: dict[str, str] = {}
    for flag, spec in specs:
        text = str(spec)
        checkpoint, path, name = weights_location(text)
        if checkpoint is None and path.is_dir():
            raise EvalError(f"{flag}: {path} {IS_A_DIRECTORY}")
        if checkpoint is None and not path.is_file():
            if path.suffix == "":
                raise EvalError(f"{flag}: {text!r} is neither a shipped model "
                                f"({', '.join(shipped_models()) or 'none'}) nor an existing weights file")
            raise EvalError(f"{flag}: {path} does not exist (weights are loaded from local files only)")
        if name in seen:
            raise EvalError(f"{flag}: {text} is a second model named {name!r} (after {seen[name]}); model names "
                            "(file stems) must be unique")
        seen[name] = f"{flag} {text}"
        if checkpoint is None and path.suffix.lower() == ".onnx":
            onnx_cuda_device(path, device)


def table_one(data_dir: Path, classes: Sequence[int] = PAPER_CLASSES) -> dict[str, tuple[int, int]]:
    """``{class: (objects, instances)}`` of the class ids ``classes`` (default the paper's four), in
    that order: distinct (scene seed, instance id) and labelled boxes over all frames
    (:func:`rainbench.store.stats.dataset_stats`)."""
    from rainbench.store.stats import dataset_stats

    try:
        stats = dataset_stats(data_dir)
    except ValueError as error:
        raise EvalError(str(error)) from None
    found = {entry["class_id"]: (entry["objects"], entry["instances"]) for entry in stats["classes"]}
    return {CLASS_NAMES[c]: found.get(c, (0, 0)) for c in classes}


def breakdowns(data_dir: Path, results_dir: Path, model: str, rates: Sequence[float],
               classes: Sequence[int] = PAPER_CLASSES, metrics: str = DEFAULT_BACKEND) -> dict:
    """``{"visible fraction" | "box size": {rate: {bin: {class name: BreakdownAP}}}}`` of one model
    and the class ids ``classes``, from the cached predictions of :func:`run_eval` in
    ``results_dir``, computed by the metrics backend ``metrics``."""
    dataset = open_dataset(data_dir)
    gt = ground_truth(dataset)
    # aligned with ground_truth's annotations: each image's labels, then its ignore regions
    # (no visible fraction: left out of every bin, as they are out of every score)
    visible = np.concatenate([np.concatenate([
        np.asarray(read_frame_labels(handle, image.frame)["visible_fraction"], np.float64),
        np.full(len(read_frame_ignore(handle, image.frame)["class_id"]), np.nan)])
        for image, handle in dataset.walk()] or [np.zeros(0)])
    if len(visible) != len(gt["annotations"]):
        raise EvalError(f"{data_dir}: {len(visible)} visible fractions for {len(gt['annotations'])} boxes")
    image_ids = {image.image_id for image in dataset.images}
    result: dict[str, dict] = {"visible fraction": {}, "box size": {}}
    for rate in rates:
        detections = load_predictions_file(predictions_path(results_dir / "predictions", model, rate), image_ids,
                                           classes)
        by_visibility = ap_by_visibility(gt, detections, visible, bins=VISIBILITY_BINS, unmatched="ignore",
                                         class_ids=classes, backend=metrics)
        by_size = ap_by_size(gt, detections, class_ids=classes, backend=metrics)
        for what, table in (("visible fraction", by_visibility), ("box size", by_size)):
            result[what][float(rate)] = {label: {CLASS_NAMES[c]: entry for c, entry in per_class.items()}
                                         for label, per_class in table.items()}
    return result


def ignore_region_counts(data_dir: Path, classes: Sequence[int] = PAPER_CLASSES) -> dict[str, int]:
    """``{class: ignore regions over all frames}`` of the class ids ``classes``, in that order: the
    visible actors too small or hidden to be labels (:func:`rainbench.store.read_frame_ignore`),
    which the evaluator scores as COCO crowd boxes."""
    dataset = open_dataset(data_dir)
    found = np.concatenate([read_frame_ignore(handle, image.frame)["class_id"] for image, handle in dataset.walk()]
                           or [np.zeros(0, np.int32)])
    return {CLASS_NAMES[c]: int(np.count_nonzero(found == c)) for c in classes}


def same_clean_frames(first: Path, other: Path) -> bool:
    """Whether two datasets hold rate 0 and the same rate-0 images, byte for byte, in the same
    image-id order (every condition of :func:`run_paper` renders the same clip, and rate 0 is its
    clean render under the base weather whatever the rain model)."""
    a, b = Dataset(first), Dataset(other)
    if 0.0 not in a.rates or 0.0 not in b.rates or len(a.images) != len(b.images):
        return False
    for (image_a, handle_a), (image_b, handle_b) in zip(a.walk(), b.walk(), strict=True):
        if image_a.image_id != image_b.image_id or not np.array_equal(a.read_rgb(handle_a, image_a, 0.0),
                                                                      b.read_rgb(handle_b, image_b, 0.0)):
            return False
    return True


def share_clean_predictions(first_results: Path, results: Path, models: Sequence[str]) -> list[str]:
    """Copy each model's cached rate-0 predictions (``predictions/<model>/rate_0.json`` and its
    ``settings.json``, :func:`rainbench.eval.pipeline.run_eval`'s cache) from ``first_results`` to
    ``results``, where that model has no cache of its own yet; ``run_eval`` then reuses them when
    its settings are the same (weights file, letterbox size, thresholds, classes) and the rate-0
    images are (the fingerprints in ``settings.json``), and infers the other rates. Only for datasets with the same rate-0 images (:func:`same_clean_frames`).
    Returns the models whose predictions were copied."""
    import shutil

    shared = []
    for model in models:
        source, target = first_results / "predictions" / model, results / "predictions" / model
        clean = predictions_path(first_results / "predictions", model, 0.0)
        if not ((source / "settings.json").is_file() and clean.is_file()) or (target / "settings.json").exists():
            continue
        target.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(clean, predictions_path(results / "predictions", model, 0.0))
        shutil.copyfile(source / "settings.json", target / "settings.json")
        shared.append(model)
    return shared


def run_paper(config: PaperConfig, out_dir: str | Path, data_root: str | Path, *, workers: int = 1,
              force: bool = False, progress: bool = True) -> Path:
    """Generate, evaluate and report; returns ``OUT/report.md``. Datasets go to
    ``data_root/<rain model>/`` and are reused (resumed) by later runs with the same config.
    With ``progress``, progress bars and, as each phase ends, its wall time
    (``paper: generate jeon2022: 14.2 s``) go to stderr."""
    from rainbench.eval.backends import check_model_classes, load_detector
    from rainbench.eval.backends.ultralytics import preload_torch
    from rainbench.eval.weights import resolve_weights

    from rainbench.experiments.train import check_device

    preload_torch()  # before generating: triton after Mesa rendering crashes
    # every model and the device are checked before anything is generated
    check_device(config.device)
    check_models([("--weights", spec) for spec in config.weights], config.device)
    out_dir, data_root = Path(out_dir), Path(data_root)
    class_ids = PAPER_CLASSES if config.classes is None else parse_classes(config.classes)
    if config.classes is not None:  # a model that cannot predict a requested class fails before generating
        for spec in config.weights:
            detector = load_detector(spec, device=config.device, classes=class_ids)
            check_model_classes(detector, resolve_weights(spec, config.device)[1], class_ids)
            del detector
    references = default_references(config.weights, config.references)
    if references:  # a --compare naming no evaluated model fails before generating
        comparison_references([resolve_weights(spec, config.device)[1] for spec in config.weights], references)
    with locked_output_dir(out_dir, "paper", option="--out", error=EvalError):
        return _paper_into(config, out_dir, data_root, class_ids=class_ids, references=references,
                           workers=workers, force=force, progress=progress)


def _paper_into(config: PaperConfig, out_dir: Path, data_root: Path, *, class_ids, references, workers: int,
                force: bool, progress: bool) -> Path:
    """:func:`run_paper`'s work once every model is checked and ``out_dir`` is locked."""
    from rainbench.eval.weights import model_imgsz, resolve_weights

    data = config.dataset
    records_by_rain: dict[str, list] = {}
    robustness: dict[str, list] = {}
    timings: dict[str, float] = {}
    skies = set()
    first: tuple[str, Path] | None = None  # the first condition: its rate-0 predictions are shared
    shared: dict[str, list[str]] = {}
    for name, rain_model, follows in conditions(config.rain_models):
        data_dir = data_root / name
        start = time.perf_counter()
        # the frames as they render (the phases ran minutes in silence)
        with tqdm(total=data.scenes * data.frames, unit="frame", desc=f"generate {name}", disable=not progress,
                  dynamic_ncols=True) as bar:
            run_dataset(replace(data, rain_model=rain_model, weather_follows_rate=follows), data_dir,
                        workers=workers, progress=bar.update, kept=start_bar_at(bar),
                        remedy=f"delete {data_dir} to generate it again, or choose another --data")
        timings[f"generate {name}"] = time.perf_counter() - start
        if progress:  # each phase's time as it ends: a run cut short still shows where it went
            print(f"paper: generate {name}: {timings[f'generate {name}']:.1f} s", file=sys.stderr, flush=True)
        written = Dataset(data_dir)
        for shard in range(len(written.shards)):
            with written.open(shard) as handle:
                skies.add(str(handle.attrs.get("sky", "clear (format v1)")))
        start = time.perf_counter()
        if first is None:
            first = (name, data_dir)
        elif not force and same_clean_frames(first[1], data_dir):
            names = [resolve_weights(spec, config.device)[1] for spec in config.weights]
            shared[name] = share_clean_predictions(out_dir / first[0], out_dir / name, names)
        outputs = run_eval(data_dir, out_dir / name, weights=list(config.weights), imgsz=config.imgsz,
                           batch=config.batch, n_boot=config.n_boot, device=config.device, force=force,
                           progress=progress, classes=config.classes, references=references,
                           metrics=config.metrics)
        timings[f"evaluate {name}"] = time.perf_counter() - start
        if progress:
            print(f"paper: evaluate {name}: {timings[f'evaluate {name}']:.1f} s", file=sys.stderr, flush=True)
        records_by_rain[name] = outputs.records
        robustness[name] = outputs.robustness
    models = list(dict.fromkeys(record["model"] for record in records_by_rain[config.rain_models[0]]))
    half_rates = {}
    for rain_model, records in records_by_rain.items():
        for model in models:
            for class_name in (CLASS_NAMES[c] for c in class_ids):
                values = {float(r["rate"]): float(r["ap50"]) for r in records
                          if r["model"] == model and r["class"] == class_name}
                half_rates[(rain_model, model, class_name)] = half_value_rate(values) if values else math.nan
    paper_rain = "jeon2022" if "jeon2022" in config.rain_models else config.rain_models[0]
    breakdown_rates = [r for r in config.breakdown_rates if r in data.rates]
    tables = breakdowns(data_root / paper_rain, out_dir / paper_rain, models[0], breakdown_rates, class_ids,
                        config.metrics)
    counts = table_one(data_root / paper_rain, class_ids)
    ignored = ignore_region_counts(data_root / paper_rain, class_ids)
    paper_clip = all(getattr(data, name) == value for name, value in PAPER_CLIP.items())
    setup = [
        f"Data: {data.scenes} scene(s) from seed {data.seed}, {data.frames} frames of "
        f"{data.width}x{data.height} each, rates {', '.join(f'{r:g}' for r in data.rates)} mm/h, "
        f"rain models {', '.join(config.rain_models)}. Classes: {', '.join(CLASS_NAMES[c] for c in class_ids)}. "
        f"Road layout: {data.layout or 'each seed its own'}; time of day: "
        f"{data.time_of_day or 'each seed its own'}. Base weather: {', '.join(sorted(skies))} "
        f"({'the paper clip' if paper_clip else 'as chosen'}). "
        "Weather following the rate (sky, light, wet road, puddles, spray, exposure, noise): "
        + ", ".join(f"{name} {'yes' if follows else 'no'}" for name, _, follows in conditions(config.rain_models))
        + ". Models: "
        f"{', '.join(f'{model} (letterboxed to {config.imgsz or model_imgsz(spec)})' for model, spec in zip(models, config.weights))}; "
        f"conf 0.001, NMS IoU 0.7. Intervals: {config.n_boot} bootstrap resamples of frames. "
        "Scoring: COCO AP, with the clip's ignore regions (actors in view too small or hidden to be labels: "
        + ", ".join(f"{name} {count}" for name, count in ignored.items())
        + ") as crowd boxes, so a detection of one is neither right nor wrong (docs/eval.md).",
        "",
        f"Machine: {platform.machine()}, {platform.processor() or 'cpu'}; device {config.device or 'auto'}. "
        "Wall times: " + ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()) + ".",
    ]
    if any(shared.values()):
        setup += ["", f"Rate 0 is the same clean render in every condition (byte for byte, checked): its "
                  f"detections were inferred on {first[0]} and reused for "
                  + ", ".join(f"{name} ({', '.join(models)})" for name, models in shared.items() if models) + "."]
    text = render_paper_md(setup_lines=setup, table_one=counts, records_by_rain=records_by_rain,
                           half_rates=half_rates, breakdowns=tables, breakdown_model=models[0],
                           paper_rain_model=paper_rain, robustness=robustness)
    out_dir.mkdir(parents=True, exist_ok=True)
    report = out_dir / "report.md"
    report.write_text(text, encoding="utf-8")
    return report
