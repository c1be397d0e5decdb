"""The `rainbench` command line. Every failure is one line on stderr and a non-zero exit."""

from __future__ import annotations

import argparse
import os
import select
import signal
import sys
import threading
import tempfile
from pathlib import Path

try:  # about a second of imports: Ctrl-C meanwhile is one line too, not a traceback
    from rainbench import gl
    from rainbench.devices import parse_device, runs_on_cuda
    from rainbench.eval.metrics.coco import DEFAULT_BACKEND, METRICS_BACKENDS
    from rainbench.gen.config import (HFOV_DEG, MAX_CLIP_SECONDS, MAX_FPS, MAX_FRAME_OFFSET, MAX_FRAMES,
                                      MAX_SCENES, MAX_SEED, PAPER_CLIP, SIDE_PX, DatasetConfig, stats_device_for)
    from rainbench.rain.config import RAIN_MODELS, RAIN_OPTIONS, RainConfig
    from rainbench.rain.weather import SKIES, TIMES_OF_DAY
    from rainbench.store.signals import TERMINATING_SIGNALS
except KeyboardInterrupt:
    print("rainbench: interrupted", file=sys.stderr)
    raise SystemExit(130) from None

EXIT_USAGE = 2


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP (a job scheduler's time limit, a closed terminal), raised in the main
    thread as Ctrl-C's KeyboardInterrupt is, so that a terminated run stops its workers and cleans
    up the same way; the exit status is 128 + the signal's number."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_terminations: list[int] = []
"""Signals :func:`_raise_terminated` received in this run (Ray's waits re-raise what a handler
raised as a plain KeyboardInterrupt: the exit status and message still follow the signal)."""


def _raise_terminated(signum: int, frame) -> None:
    _terminations.append(signum)
    raise Terminated(signum)


def _shown(text) -> str:
    text = repr(text) if isinstance(text, str) else str(text)
    return text if len(text) <= 40 else text[:37] + "..."


def _positive_int(name: str, high: int | None = None, low: int = 1):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: expected an integer, got {_shown(text)}") \
                from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{name}: expected >= {low}, got {_shown(value)}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"{name}: expected <= {high}, got {_shown(value)}")
        return value
    return parse


_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def _rain_option(text: str) -> tuple[str, object]:
    """``NAME=VALUE``: one :class:`~rainbench.rain.RainConfig` field and its value, typed by the
    field's default (bool: true/false; int; float; ``airlight_rgb``: ``R,G,B`` or ``none``).
    The value's range is checked by RainConfig when the dataset config is built."""
    name, equals, value = text.partition("=")
    name, value = name.strip(), value.strip()
    if not equals or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {_shown(text)}")
    if name not in RAIN_OPTIONS:
        raise argparse.ArgumentTypeError(f"unknown option {_shown(name)}; expected "
                                         f"one of {', '.join(RAIN_OPTIONS)} (docs/rain.md)")
    default = getattr(RainConfig(), name)
    try:
        if name == "airlight_rgb":
            if value.lower() == "none":
                return name, None
            colour = tuple(float(part) for part in value.split(","))
            if len(colour) != 3:
                raise ValueError
            return name, colour
        if isinstance(default, bool):
            if value.lower() not in _TRUE + _FALSE:
                raise ValueError
            return name, value.lower() in _TRUE
        return name, type(default)(value)
    except ValueError:
        if name == "airlight_rgb":
            kind = "R,G,B or none"
        elif isinstance(default, bool):
            kind = "true or false"
        else:
            kind = "an integer" if isinstance(default, int) else "a number"
        raise argparse.ArgumentTypeError(f"{name}: expected {kind}, got {_shown(value)}") from None


def _number(name: str, low: float, high: float, low_open: bool = False):
    """A float flag in [low, high] (or (low, high] with ``low_open``); NaN is refused."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: expected a number, got {_shown(text)}") \
                from None
        if not ((low < value) if low_open else (low <= value)) or not value <= high:
            raise argparse.ArgumentTypeError(f"{name}: expected a number in {'(' if low_open else '['}"
                                             f"{low:g}, {high:g}], got {_shown(text)}")
        return value
    return parse


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"SEED: expected an integer, got {_shown(text)}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"SEED: expected 0..{MAX_SEED}, got {_shown(value)}")
    return value


def _store(text: str) -> tuple[str, ...]:
    items = tuple(sorted({item.strip() for item in text.split(",") if item.strip()}))
    unknown = [item for item in items if item not in ("depth", "instance")]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"STORE: expected a comma list of depth,instance, got {text!r}")
    return items


def _choose_gl(requested: str | None) -> None:
    """Honour --gl before anything imports mujoco; refuse a MUJOCO_GL that cannot render."""
    if requested is None:
        if not os.environ.get("MUJOCO_GL"):
            gl.find_backend(None)  # raises the clear error naming the packages
        gl.check_environment(os.environ)
        return
    if "mujoco" in sys.modules:
        raise CliError("--gl: mujoco is already imported; set MUJOCO_GL instead")
    os.environ["MUJOCO_GL"] = gl.find_backend(requested)


def _writable_dir(path: Path, what: str) -> Path:
    """``path`` if a directory can be made there and written to, checked by doing it: missing
    directories are created, a temporary file is written and removed, then the directories
    this created are removed again (nothing is left; permission bits alone do not tell, e.g. for
    root under /proc or on a read-only mount)."""
    missing = []
    probe = path
    while not probe.exists() and probe != probe.parent:
        missing.append(probe)
        probe = probe.parent
    if not probe.is_dir():
        raise CliError(f"{what}: {path} is not a writable directory ({probe} is not a directory)")
    created: list[Path] = []
    try:
        for directory in reversed(missing):
            directory.mkdir()
            created.append(directory)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as error:
        raise CliError(f"{what}: {path} is not a writable directory "
                       f"({error.strerror or error})") from None
    finally:
        for directory in reversed(created):
            try:
                directory.rmdir()
            except OSError:
                pass  # something else wrote there meanwhile: it is no longer ours to remove
    return path


def _rain_options(pairs: list[tuple[str, object]]) -> dict:
    options: dict = {}
    for name, value in pairs:
        if name in options and options[name] != value:
            raise CliError(f"--rain-option {name}: given twice ({options[name]!r} and {value!r})")
        options[name] = value
    return options


def cmd_generate(args: argparse.Namespace) -> int:
    from rainbench.store.rates import parse_rates

    if args.ray_address is not None and args.executor != "ray":
        raise CliError("--ray-address: only used with --executor ray")
    if args.workers is not None and args.executor == "ray":  # run_dataset never reads it for Ray
        raise CliError("--workers: has no effect with --executor ray (each Ray task renders one "
                       "shard on one CPU; the cluster decides how many run); leave it out")
    # the whole config is checked before anything is written or rendered
    config = DatasetConfig(**_scene_fields(args), scenes=args.scenes,
                           frames_per_shard=args.frames_per_shard, first_frame=args.first_frame,
                           clip_frames=args.clip_frames, rates=parse_rates(args.rates),
                           rain_model=args.rain_model, rain_seed=args.rain_seed, store=args.store,
                           weather_follows_rate=args.weather_follows_rate,
                           rain_options=_rain_options(args.rain_option),
                           stats_device=_stats_device(args.device))
    out = _writable_dir(Path(args.out), "OUT")
    _choose_gl(args.gl)
    from tqdm import tqdm

    from rainbench.gen.dataset import run_dataset, start_bar_at

    workers = args.workers or min(os.cpu_count() or 1, config.shard_count)
    if args.threads is not None:
        import cv2  # noqa: PLC0415 -- OpenCV's own thread pool follows --threads as well

        cv2.setNumThreads(args.threads)
    with tqdm(total=config.scenes * config.frames, unit="frame", desc="rainbench generate",
              disable=args.quiet, dynamic_ncols=True) as bar:
        manifest = run_dataset(config, out, workers=workers, executor=args.executor,
                               ray_address=args.ray_address, render_threads=args.render_threads,
                               threads=args.threads,
                               overwrite=args.overwrite, progress=bar.update,
                               kept=start_bar_at(bar))
    print(manifest)
    return 0


def _stats_device(device: str | None) -> str:
    """The dataset's ``stats_device`` of ``--device`` (:func:`stats_device_for`); a CUDA device
    asked for by name on a machine where torch sees none is refused here, before anything
    renders."""
    resolved = stats_device_for(device)
    if resolved != "cpu" and parse_device(device) is not None:  # a GPU asked for by name
        import torch  # noqa: PLC0415 -- only when a GPU is asked for

        from rainbench.rain.metrics_torch import cuda_device_problem  # noqa: PLC0415

        problem = cuda_device_problem(torch.device(resolved), "use --device cpu")
        if problem is not None:
            raise CliError(f"--device {device}: {problem}")
    return resolved


def _printable(text: str) -> str:
    """``text`` on one line: control characters (a file name may hold a newline) escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))


def _finished_dataset(data: str | Path, allow_incomplete: bool, flag: str = "DATA") -> None:
    """Refuse a dataset directory whose manifest says it is incomplete (an interrupted or running
    ``rainbench generate``): results from it would cover only its finished shards while looking
    whole. With ``allow_incomplete`` it is read, with a one-line warning."""
    from rainbench.store.manifest import MANIFEST, missing_shards_problem, read_manifest, unfinished_count

    if not Path(data).is_dir():
        return  # one shard file: no manifest to say
    manifest = read_manifest(data)
    listed = unfinished_count(manifest)
    if listed is None:
        # a manifest edited by hand (or by another tool) may say complete and list fewer shards
        missing = missing_shards_problem(Path(data) / MANIFEST, manifest) if manifest is not None else None
        if missing:
            raise CliError(f"{flag}: {missing} (rainbench verify {data} lists every problem)")
        return
    if not allow_incomplete:
        raise CliError(f"{flag}: {data} is an incomplete dataset (its manifest lists {listed} "
                       "finished shards and says \"complete\": false): run the same rainbench "
                       "generate again to finish it, or pass --allow-incomplete to read the "
                       "finished shards only")
    print(_printable(f"rainbench: warning: {data} is incomplete: reading its {listed} finished "
                     "shards only"), file=sys.stderr)


def cmd_verify(args: argparse.Namespace) -> int:
    from rainbench.store import MANIFEST, unlisted_shards, verify_dataset

    root = Path(args.out)
    if not root.is_dir():
        found = "a file" if root.exists() else "no such directory"
        raise CliError(f"DATA: {root} is not a dataset directory ({found}; expected the directory "
                       f"that rainbench generate wrote, with its {MANIFEST})")
    if not (root / MANIFEST).exists():
        raise CliError(f"DATA: {root} is not a dataset directory (no {MANIFEST})")
    problems = verify_dataset(args.out, images=args.images)
    for path in unlisted_shards(args.out):
        print(_printable(f"rainbench: warning: {path}: not listed in the manifest, so not part of "
                         "the dataset (ignored)"), file=sys.stderr)
    for problem in problems:
        print(_printable(f"rainbench: bad: {problem}"), file=sys.stderr)
    if problems:
        return 1
    print(f"{args.out}: ok")
    return 0


def cmd_stats(args: argparse.Namespace) -> int:
    import json

    from rainbench.store.stats import dataset_stats, render_stats

    _finished_dataset(args.data, args.allow_incomplete)
    stats = dataset_stats(args.data)
    print(json.dumps(stats, indent=1) if args.json else render_stats(stats).rstrip("\n"))
    return 0


def cmd_scene(args: argparse.Namespace) -> int:
    if args.list:
        from rainbench.mjcf.layout import LAYOUTS

        for name, description in LAYOUTS.items():
            print(f"{name:<13} {description}")
        return 0
    if args.out is None:
        raise CliError("scene: expected --out DIR (or --list)")
    out = _writable_dir(Path(args.out), "--out")
    if (out / "scene.xml").exists() and not args.overwrite:
        raise CliError(f"--out: {out / 'scene.xml'} exists; use --overwrite to replace it "
                       "(and its textures)")
    # before mujoco is imported: a MUJOCO_GL that breaks the import (exporting renders nothing)
    gl.check_environment(os.environ, rendering=False)
    from rainbench.gen.config import GenerateConfig
    from rainbench.mjcf import layout as L
    from rainbench.mjcf.scene import build_spec, export_scene

    import numpy as np

    config = GenerateConfig(**_scene_fields(args))
    layout = L.sample_layout(config.seed, config.scenario_config(),
                             np.random.default_rng(config.seed))
    path = export_scene(build_spec(layout, config.width, config.height, config.hfov_deg), out)
    print(path)
    return 0


def _rate_list(text: str | None) -> list[float] | None:
    if text is None:
        return None
    from rainbench.store.rates import parse_rates

    return list(parse_rates(text))


def cmd_export(args: argparse.Namespace) -> int:
    from rainbench.store.export import export_coco, export_yolo

    _finished_dataset(args.data, args.allow_incomplete)
    out = _writable_dir(Path(args.out), "--out")
    export = export_yolo if args.format == "yolo" else export_coco
    for path in export(args.data, out, rates=_rate_list(args.rates), overwrite=args.overwrite):
        print(path)
    return 0


def _videos_dir(data: str | Path) -> Path:
    """Where ``preview --video`` writes without ``--out``: ``DATA/videos`` for a dataset
    directory, the ``videos`` folder beside a shard (its dataset directory's) for one shard."""
    data = Path(data)
    return data / "videos" if data.is_dir() else data.parent / "videos"


DEFAULT_TILE_WIDTH = 400
"""``preview``'s tile width in pixels: four 800x600 rates side by side fit a 1600 px screen."""
TILE_WIDTH_RANGE = (32, 8192)
"""``preview --tile-width`` bounds: a legible rate label; a sheet of four tiles at most 2^15 px wide
(the sheet's pixels are bounded too: :data:`rainbench.store.preview.MAX_SHEET_PIXELS`)."""


def cmd_preview(args: argparse.Namespace) -> int:
    if not args.video:
        for flag, given in (("--rates", args.rates is not None), ("--overwrite", args.overwrite)):
            if given:
                raise CliError(f"{flag}: only used with --video (a montage shows every rate of "
                               "one frame)")
    elif args.frame is not None:
        raise CliError("--frame: only used without --video (a video shows every frame; --frame "
                       "picks the montage's frame)")
    elif args.tile_width is not None:
        raise CliError("--tile-width: only used without --video (a video keeps the images' size; "
                       "--tile-width sizes the montage's tiles)")
    tile_width = DEFAULT_TILE_WIDTH if args.tile_width is None else args.tile_width
    if not TILE_WIDTH_RANGE[0] <= tile_width <= TILE_WIDTH_RANGE[1]:
        raise CliError(f"--tile-width: expected {TILE_WIDTH_RANGE[0]}..{TILE_WIDTH_RANGE[1]} "
                       f"pixels, got {tile_width}")
    _finished_dataset(args.shard, args.allow_incomplete, "SHARD")
    if args.video:
        from rainbench.store.video import write_videos

        out = _writable_dir(Path(args.out) if args.out else _videos_dir(args.shard), "--out")
        for path in write_videos(args.shard, out, rates=_rate_list(args.rates),
                                 boxes=args.boxes, overwrite=args.overwrite):
            print(path)
        return 0
    import numpy as np

    from rainbench.store import Dataset, list_shards, read_frame_ignore, read_frame_labels
    from rainbench.store.preview import montage, write_png

    path = Path(args.shard)
    if path.is_dir():
        path = list_shards(path)[0]
    frame = 0 if args.frame is None else args.frame
    name = f"{path.stem}_frame{frame:04d}_rates.png"
    out = Path(args.out) if args.out else path.with_name(name)
    if args.out and (out.is_dir() or not out.suffix or str(args.out).endswith(("/", os.sep))):
        out = out / name  # a directory, made if missing
    elif out.suffix.lower() != ".png":
        raise CliError(f"--out: expected a .png file name or a directory, got {out}")
    _writable_dir(out.parent, "--out")
    dataset = Dataset(path)
    if not 0 <= frame < len(dataset):
        raise CliError(f"--frame: expected 0..{len(dataset) - 1} for {path.name}, got {frame}")
    image = dataset.images[frame]
    with dataset.open(0) as handle:
        try:
            images = np.stack([dataset.read_rgb(handle, image, rate) for rate in dataset.rates])
            labels = read_frame_labels(handle, frame)
            ignore = read_frame_ignore(handle, frame)["bbox"]
        except OSError as error:
            raise CliError(f"{path}: frame {frame} does not decode ({error})") from None
    rates = np.asarray(dataset.rates)
    boxes = (labels["bbox"], labels["class_id"]) if args.boxes else (None, None)
    sheet = montage(images, rates, boxes=boxes[0], class_ids=boxes[1],
                    ignore_boxes=ignore if args.boxes else None, tile_width=tile_width)
    out.parent.mkdir(parents=True, exist_ok=True)  # a missing folder is made, as export and generate do
    write_png(out, sheet)
    print(out)
    return 0


EVAL_INFERENCE_DEFAULTS = {"batch": 32, "conf": 0.001, "iou": 0.7, "max_det": 300, "pt_backend": "batched"}
"""``rainbench eval``'s inference settings whose flags default to None (so that a flag the user gave
is known: with ``--predictions`` it is refused) and the values they stand for."""
def cmd_eval(args: argparse.Namespace) -> int:
    if bool(args.weights) == (args.predictions is not None):
        raise CliError("eval: expected exactly one of --weights W [--weights W2 ...] or --predictions DIR")
    if args.predictions is not None:
        from rainbench.eval.pipeline import INFERENCE_SETTINGS  # the flags only inference uses

        for dest in INFERENCE_SETTINGS:
            value = getattr(args, dest)
            if value is not None and value is not False:
                flag = "--" + dest.replace("_", "-")
                raise CliError(f"{flag}: has no effect with --predictions (detections are read from "
                               "its files, not inferred); leave it out, or evaluate with --weights")
    inference = {name: EVAL_INFERENCE_DEFAULTS[name] if getattr(args, name) is None else getattr(args, name)
                 for name in EVAL_INFERENCE_DEFAULTS}
    _finished_dataset(args.data, args.allow_incomplete, "--data")
    out = _writable_dir(Path(args.out), "--out")
    from rainbench.eval.pipeline import TargetFilter, run_eval

    outputs = run_eval(args.data, out, predictions_dir=args.predictions, weights=args.weights or (),
                       imgsz=args.imgsz, batch=inference["batch"], conf=inference["conf"], iou=inference["iou"],
                       max_det=inference["max_det"], report_conf=args.report_conf, n_boot=args.n_boot,
                       class_map=args.class_map, device=args.device, force=args.force,
                       progress=not args.quiet, trust_pickle=args.trust_pickle or None, classes=args.classes,
                       references=tuple(_compare_pair(text) for text in args.compare or ()), metrics=args.metrics,
                       pt_backend=inference["pt_backend"], workers=args.workers, ignore_regions=args.ignore_regions,
                       targets=TargetFilter(args.min_height, args.min_visible, args.max_truncation))
    print(outputs.paths["report.md"])
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    if Path(args.recipe).is_dir():
        raise CliError(f"--recipe: {args.recipe} is a directory, not a file (expected a recipe .yaml "
                       "file or a shipped recipe name)")
    _choose_gl(None)
    from rainbench.experiments.train import load_recipe, train

    recipe = load_recipe(args.recipe)
    out = _writable_dir(Path(args.out or Path("runs") / recipe.name), "--out")
    print(train(recipe, out, device=args.device, workers=args.workers))
    return 0


def cmd_paper(args: argparse.Namespace) -> int:
    from rainbench.store.rates import parse_rates

    from rainbench.experiments.train import check_device

    # the evaluation's device (its own one-line errors) is also where the statistics run
    stats_device = stats_device_for(check_device(args.device))
    dataset = DatasetConfig(**_scene_fields(args), scenes=args.scenes, rates=parse_rates(args.rates),
                            stats_device=stats_device)
    out = _writable_dir(Path(args.out), "--out")
    _choose_gl(None)
    from rainbench.experiments.paper import PaperConfig, check_models, default_models, run_paper

    # the default models are the GPU's set where the evaluation runs on CUDA, not wherever one is
    models = tuple(args.model) if args.model else default_models(runs_on_cuda(args.device, CliError))
    # before anything is generated, each model under the flag it came with
    specs = ([("--model" if args.model else "--model (default)", model) for model in models]
             + [("--weights", weights) for weights in args.weights or ()])
    check_models(specs, args.device)
    config = PaperConfig(dataset=dataset, rain_models=tuple(args.rain_models.split(",")),
                         weights=models + tuple(args.weights or ()), imgsz=args.imgsz, batch=args.batch,
                         n_boot=args.n_boot, device=args.device, classes=args.classes,
                         references=tuple(_compare_pair(text) for text in args.compare or ()), metrics=args.metrics)
    # each weights file loads as eval loads it (seconds each): after the cheap checks, before generating
    _check_weights_files(specs, args.device)
    print(run_paper(config, out, _writable_dir(Path(args.data), "--data"), workers=args.workers,
                    force=args.force, progress=not args.quiet))
    return 0


def _check_weights_files(specs: list[tuple[str, str]], device: str | None) -> None:
    """Refuse, before ``rainbench paper`` generates anything, a weights file that ``rainbench eval``
    could not load, naming the flag it came with (``--model`` or ``--weights``): every local file
    is loaded on ``device`` as ``eval`` loads it before inferring (shipped models are known to
    load)."""
    from rainbench.eval.backends import BackendError, load_detector
    from rainbench.eval.weights import weights_location

    for flag, spec in specs:
        shipped, _, _ = weights_location(spec)
        if shipped is not None:
            continue
        try:
            detector = load_detector(spec, device=device)
        except BackendError as error:
            message = str(error)
            if message.startswith("--weights") and flag != "--weights":
                message = flag + message[len("--weights"):]
            raise CliError(message) from None
        del detector


def _add_compare_arg(parser: argparse.ArgumentParser, default: str = "the model its name extends, else the first that extends none") -> None:
    parser.add_argument("--compare", action="append", default=None, metavar="MODEL=REFERENCE",
                        help="robustness comparison: the model's paired mPC difference is taken from "
                             f"REFERENCE (repeatable; default: {default})")


def _add_metrics_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--metrics", choices=METRICS_BACKENDS, default=DEFAULT_BACKEND,
                        help="implementation of COCO matching and AP (default: %(default)s): numpy is vectorised, "
                             "pycocotools the reference COCOeval (slower); the figures agree to 1e-9")


def _compare_pair(text: str) -> tuple[str, str]:
    """``(model, reference)`` of a ``--compare MODEL=REFERENCE`` value."""
    model, sep, reference = text.partition("=")
    if not sep or not model.strip() or not reference.strip():
        raise CliError(f"--compare: expected MODEL=REFERENCE (model names as in the report), got {text!r}")
    return model.strip(), reference.strip()


def _scene_fields(args: argparse.Namespace) -> dict:
    """The config fields of the scene flags (:func:`_add_scene_args`, :func:`_add_layout_args`):
    seed, sky, layout, time of day, frames, fps, image size and, where the command has --hfov,
    the field of view."""
    seed, sky = _seed_and_sky(args)
    fields = dict(seed=seed, sky=sky, **_layout_and_time(args), frames=args.frames, fps=args.fps,
                  width=args.width, height=args.height)
    if "hfov" in vars(args):
        fields["hfov_deg"] = args.hfov
    return fields


def _seed_and_sky(args: argparse.Namespace) -> tuple[int, str | None]:
    """(seed, sky): given none of --seed, --sky, --layout, --time, the paper's default clip
    (seed 0, cloudy); otherwise --sky, or the seed's own base weather when --sky is not given."""
    if _is_paper_clip(args):
        return PAPER_CLIP["seed"], PAPER_CLIP["sky"]
    return (DatasetConfig.seed if args.seed is None else args.seed), args.sky


def _is_paper_clip(args: argparse.Namespace) -> bool:
    return (args.seed is None and args.sky is None and getattr(args, "layout", None) is None
            and getattr(args, "time", None) is None)


def _layout_and_time(args: argparse.Namespace) -> dict:
    """``layout`` and ``time_of_day`` of --layout and --time (the paper's clip: the street by
    day); None where the seed decides."""
    if _is_paper_clip(args):
        return {"layout": PAPER_CLIP["layout"], "time_of_day": PAPER_CLIP["time_of_day"]}
    return {"layout": args.layout, "time_of_day": args.time}


def _layout_name(text: str) -> str:
    from rainbench.mjcf.layout import LAYOUTS  # plain data: no mujoco import

    if text not in LAYOUTS:
        raise argparse.ArgumentTypeError(f"LAYOUT: expected one of {', '.join(LAYOUTS)}, "
                                         f"got {_shown(text)}")
    return text


def _add_layout_args(parser: argparse.ArgumentParser, hfov: bool = True) -> None:
    parser.add_argument("--layout", type=_layout_name, default=None,
                        help="road scene: street, intersection, curved, highway, residential "
                             "(default: the seed decides; `rainbench scene --list`)")
    parser.add_argument("--time", choices=TIMES_OF_DAY, default=None,
                        help="time of day (default: the seed decides; the paper's clip: day)")
    if not hfov:
        return
    parser.add_argument("--hfov", type=_number("HFOV", *HFOV_DEG), default=DatasetConfig.hfov_deg,
                        help="horizontal field of view of the ego camera in degrees, "
                             f"[{HFOV_DEG[0]:g}, {HFOV_DEG[1]:g}] "
                             f"(default {DatasetConfig.hfov_deg:g}, the paper's)")


def _add_scene_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=_seed, default=None,
                        help="scene seed: road layout, time of day, actors, colours, speeds, sky, "
                             "sun, camera rig (default 0; given none of --seed, --sky, --layout, "
                             "--time: the paper's clip, the cloudy street by day)")
    parser.add_argument("--sky", choices=SKIES, default=None,
                        help="base weather (default: the seed decides; the paper's clip: cloudy)")
    parser.add_argument("--frames", type=_positive_int("FRAMES", MAX_FRAMES), default=DatasetConfig.frames,
                        help=f"frames per scene, 1..{MAX_FRAMES} (default {DatasetConfig.frames}); "
                             "a scene is planned for its clip's length, at most "
                             f"{MAX_CLIP_SECONDS:g} s (frames / fps)")
    parser.add_argument("--fps", type=_number("FPS", 0, MAX_FPS, low_open=True), default=DatasetConfig.fps,
                        help=f"frames per second, (0, {MAX_FPS:g}] (default {DatasetConfig.fps:g})")
    parser.add_argument("--width", type=_positive_int("WIDTH", SIDE_PX[1], SIDE_PX[0]),
                        default=DatasetConfig.width,
                        help=f"image width in pixels, {SIDE_PX[0]}..{SIDE_PX[1]} (default {DatasetConfig.width})")
    parser.add_argument("--height", type=_positive_int("HEIGHT", SIDE_PX[1], SIDE_PX[0]),
                        default=DatasetConfig.height,
                        help=f"image height in pixels, {SIDE_PX[0]}..{SIDE_PX[1]} (default {DatasetConfig.height})")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, not argparse's usage block
        print(f"rainbench: error: {message}", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rainbench", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    generate = sub.add_parser("generate", help="render scenes with rain into HDF5 shards and a manifest")
    generate.add_argument("--out", default="data", help="output directory (default: data)")
    _add_scene_args(generate)
    _add_layout_args(generate)
    generate.add_argument("--rates", default="0",
                          help="rain rates in mm/h: 0:100:10, 0,25,50 or 50 (default: 0, clean frames only; "
                               "the paper's sweep, as make dataset: 0:100:10)")
    generate.add_argument("--rain-model", default=DatasetConfig.rain_model,
                          help=f"rain model: {', '.join(RAIN_MODELS)} (default {DatasetConfig.rain_model})")
    generate.add_argument("--rain-seed", type=_seed, default=DatasetConfig.rain_seed,
                          help=f"seed of the rain's drops, lens water and spray; the clean frames do not depend "
                               f"on it (default {DatasetConfig.rain_seed})")
    generate.add_argument("--rain-option", type=_rain_option, action="append", default=[],
                          metavar="NAME=VALUE",
                          help="a rain model parameter (repeatable; rainbench.rain.RainConfig, "
                               "docs/rain.md), e.g. lens_drops=false or exposure_s=0.002")
    generate.add_argument("--weather-follows-rate", action=argparse.BooleanOptionalAction,
                          default=None,
                          help="sky, light, wet road, spray and camera follow the rain rate "
                               "(default: on for physical, off for jeon2022)")
    generate.add_argument("--store", type=_store, default=(),
                          help="extra per-frame arrays: depth,instance")
    generate.add_argument("--scenes", type=_positive_int("SCENES", MAX_SCENES), default=DatasetConfig.scenes,
                          help="number of scenes; scene k uses seed SEED + k")
    generate.add_argument("--frames-per-shard", type=_positive_int("FRAMES_PER_SHARD"),
                          default=DatasetConfig.frames_per_shard,
                          help="split longer clips into shards of this many frames")
    generate.add_argument("--clip-frames", type=_positive_int("CLIP_FRAMES", MAX_FRAME_OFFSET),
                          default=None,
                          help="length of the clip each scene is planned for (its actors, sky and "
                               "time of day depend on it); --frames of it are rendered (default: "
                               "--first-frame + --frames; e.g. --frames 10 --clip-frames 200: the "
                               "first 10 frames of the seed's 200-frame clip)")
    generate.add_argument("--first-frame", type=_positive_int("FIRST_FRAME", MAX_FRAME_OFFSET, low=0),
                          default=0,
                          help="first frame of the clip to render (default 0)")
    generate.add_argument("--workers", type=_positive_int("WORKERS", 1024), default=None,
                          help="parallel worker processes (default: cores, at most one per shard); "
                               "more workers than shards render each shard in pieces of at least 8 "
                               "frames, joined into the same file")
    generate.add_argument("--render-threads", type=_positive_int("RENDER_THREADS", 1024), default=None,
                          help="Mesa software-render threads per worker (LP_NUM_THREADS)")
    generate.add_argument("--threads", type=_positive_int("THREADS", 1024), default=None,
                          help="rain, statistics and compression threads per worker (default: "
                               "cores / workers; 1 = each worker on one core)")
    generate.add_argument("--device", default="auto",
                          help="where each rate's statistics (SSIM, PSNR, per-box rain labels) are "
                               "computed: auto (a CUDA GPU if torch sees one, else cpu), cpu, cuda, "
                               "cuda:N or a CUDA index (0); the figures agree to float32 rounding, and "
                               "the manifest records the device")
    generate.add_argument("--executor", choices=("local", "ray"), default="local",
                          help="local worker processes, or tasks on a Ray cluster (default local; docs/datasets.md)")
    generate.add_argument("--ray-address", default=None,
                          help="address of an existing Ray cluster (default: start a local one)")
    generate.add_argument("--overwrite", action="store_true",
                          help="replace a dataset of another config in OUT")
    generate.add_argument("--gl", choices=sorted(gl.BACKENDS), default=None,
                          help="offscreen GL backend (default: MUJOCO_GL, else egl, else osmesa)")
    generate.add_argument("--quiet", action="store_true", help="no progress bar")
    generate.set_defaults(run=cmd_generate)
    verify = sub.add_parser("verify", help="re-hash a dataset against its manifest")
    verify.add_argument("out", metavar="DATA", help="dataset directory (with manifest.json)")
    verify.add_argument("--images", action="store_true",
                        help="also decode every stored image, depth and instance map (about 4 ms "
                             "an 800x600 image; finds a damaged chunk whose manifest was rewritten)")
    verify.set_defaults(run=cmd_verify)
    stats = sub.add_parser("stats", help="objects, instances, box sizes, visibility per class of a dataset")
    stats.add_argument("data", help="dataset directory, or one shard")
    stats.add_argument("--json", action="store_true", help="JSON instead of tables (keys: docs/datasets.md)")
    stats.add_argument("--allow-incomplete", action="store_true",
                       help="read a dataset whose generation has not finished (its finished "
                            "shards only; default: refuse it)")
    stats.set_defaults(run=cmd_stats)
    scene = sub.add_parser("scene", help="write the composed scene as a standalone MJCF file")
    scene.add_argument("--out", default=None, help="directory for scene.xml and its textures")
    scene.add_argument("--list", action="store_true",
                       help="print the layouts (name and description, one a line) and exit")
    scene.add_argument("--overwrite", action="store_true",
                       help="replace an existing OUT/scene.xml and its textures")
    _add_scene_args(scene)
    _add_layout_args(scene)
    scene.set_defaults(run=cmd_scene)
    preview = sub.add_parser("preview", help="PNG montage of one frame across all rain rates")
    preview.add_argument("shard", help="a shard, or a dataset directory (its first shard)")
    preview.add_argument("--frame", type=int, default=None,
                         help="the montage's frame (default 0; not with --video)")
    preview.add_argument("--out", default=None,
                         help="PNG path or directory, made if missing (default: beside the shard)")
    preview.add_argument("--boxes", action="store_true",
                         help="draw the labels (class colours) and the ignore regions (grey)")
    preview.add_argument("--tile-width", type=int, default=None,
                         help=f"each rate's tile width in pixels, {TILE_WIDTH_RANGE[0]}.."
                              f"{TILE_WIDTH_RANGE[1]} (default {DEFAULT_TILE_WIDTH}; the "
                              "image's own width for full resolution; not with --video)")
    preview.add_argument("--video", action="store_true",
                         help="one MP4 per rate over every frame instead (in --out, default "
                              "DATA/videos; for one shard, the videos folder beside it)")
    preview.add_argument("--rates", default=None, help="with --video: rates to write (RATES spec)")
    preview.add_argument("--overwrite", action="store_true", help="with --video: replace videos")
    preview.add_argument("--allow-incomplete", action="store_true",
                         help="read a dataset whose generation has not finished (its finished "
                              "shards only; default: refuse it)")
    preview.set_defaults(run=cmd_preview)
    export = sub.add_parser("export", help="export a dataset as YOLO folders or COCO JSON")
    export.add_argument("data", help="dataset directory, or one shard")
    export.add_argument("--format", choices=("yolo", "coco"), required=True)
    export.add_argument("--out", required=True, help="export directory")
    export.add_argument("--rates", default=None, help="rates to export (RATES spec; default all)")
    export.add_argument("--overwrite", action="store_true")
    export.add_argument("--allow-incomplete", action="store_true",
                        help="read a dataset whose generation has not finished (its finished "
                             "shards only; default: refuse it)")
    export.set_defaults(run=cmd_export)
    evaluate = sub.add_parser("eval", help="AP / F1 per class and rain rate of detectors on a dataset")
    evaluate.add_argument("--data", required=True, help="dataset directory of scene*_f*.h5 shards")
    evaluate.add_argument("--allow-incomplete", action="store_true",
                          help="evaluate a dataset whose generation has not finished (its "
                               "finished shards only; default: refuse it)")
    evaluate.add_argument("--weights", action="append", default=None,
                          help="a shipped model name, or a local .pt, .onnx or Darknet .weights "
                               "file (repeat for several models); a .pt is read with ultralytics' "
                               "safe loading (see --trust-pickle)")
    evaluate.add_argument("--predictions", default=None,
                          help="instead of --weights: DIR/<model>/rate_<rate>.json COCO results files")
    evaluate.add_argument("--out", required=True, help="results directory")
    evaluate.add_argument("--imgsz", type=_positive_int("IMGSZ", 8192, 32), default=None,
                          help="letterbox size (default: the model's card, a shipped model's or the .json beside "
                               "a weights file: 960 for the nano and small models and their rain twins, 640 for "
                               "the weak control; 640 without a card)")
    # inference flags default to None (EVAL_INFERENCE_DEFAULTS): refused with --predictions when given
    evaluate.add_argument("--batch", type=_positive_int("BATCH", 4096), default=None,
                          help=f"frames per detector call (default {EVAL_INFERENCE_DEFAULTS['batch']})")
    evaluate.add_argument("--conf", type=_number("CONF", 0, 1), default=None,
                          help=f"detector confidence floor (default {EVAL_INFERENCE_DEFAULTS['conf']:g})")
    evaluate.add_argument("--iou", type=_number("IOU", 0, 1), default=None,
                          help=f"detector NMS IoU (default {EVAL_INFERENCE_DEFAULTS['iou']:g})")
    evaluate.add_argument("--max-det", type=_positive_int("MAX_DET", 100_000), default=None,
                          help=f"detections per image (default {EVAL_INFERENCE_DEFAULTS['max_det']})")
    evaluate.add_argument("--report-conf", type=_number("REPORT_CONF", 0, 1), default=0.25,
                          help="fixed threshold of the *_at_conf metrics and the detection strip (default 0.25)")
    evaluate.add_argument("--n-boot", type=_positive_int("N_BOOT", 1_000_000), default=1000,
                          help="bootstrap resamples of the AP confidence intervals (default 1000)")
    evaluate.add_argument("--class-map", default=None,
                          help="model class name -> rainbench id, e.g. car=2,pedestrian=0 "
                               "(needed unless the model is COCO-80)")
    evaluate.add_argument("--classes", default=None,
                          help="classes to score, names or ids, e.g. person,car,bus,truck (default: the "
                               "paper's person,bicycle,car,motorcycle; also bus, truck)")
    evaluate.add_argument("--device", default=None,
                          help="auto, cpu, cuda, cuda:N or CUDA indices, e.g. 0 (default: CUDA 0 if "
                               "present, else cpu)")
    evaluate.add_argument("--pt-backend", choices=("batched", "ultralytics"), default=None,
                          help="how a .pt runs: batched (torch in batches, letterbox and NMS on the device, "
                               "fp16 on CUDA; default) or ultralytics (its own predict, the reference); "
                               "shipped models run their ONNX copy on CPU either way")
    evaluate.add_argument("--workers", type=_positive_int("WORKERS", 1024, 0), default=None,
                          help="processes decoding and letterboxing shard frames for the batched backend (default: "
                               "min(8, cores - 1))")
    evaluate.add_argument("--min-height", type=_number("MIN_HEIGHT", 0, 100_000), default=0.0,
                          help="score only labels at least this many pixels tall (KITTI moderate: 25); the "
                               "others become ignore regions (default 0: every label)")
    evaluate.add_argument("--min-visible", type=_number("MIN_VISIBLE", 0, 1), default=0.0,
                          help="score only labels with at least this visible fraction; the others become "
                               "ignore regions (default 0)")
    evaluate.add_argument("--max-truncation", type=_number("MAX_TRUNCATION", 0, 1), default=1.0,
                          help="score only labels at most this truncated (KITTI moderate: 0.3); the others "
                               "become ignore regions (default 1)")
    evaluate.add_argument("--no-ignore-regions", dest="ignore_regions", action="store_false",
                          help="score detections of actors too small or too hidden to be labels as false "
                               "positives (default: such actors are ignore regions, as KITTI's DontCare)")
    _add_compare_arg(evaluate)
    _add_metrics_arg(evaluate)
    evaluate.add_argument("--force", action="store_true", help="re-run detectors despite cached predictions")
    evaluate.add_argument("--trust-pickle", action="store_true",
                          help="load a .pt that ultralytics' safe loading refuses with Python's full "
                               "unpickler (runs code from the file: only for files you trust)")
    evaluate.add_argument("--quiet", action="store_true", help="no progress bars")
    evaluate.set_defaults(run=cmd_eval)
    training = sub.add_parser("train", help="train a YOLO detector from scratch on clean scenes (a recipe)")
    training.add_argument("--recipe", default="rainbench-yolo11n",
                          help="a shipped recipe name (experiments/recipes: rainbench-yolo11n, rainbench-yolo11s, rainbench-yolo11n-rain, ...) or a .yaml file")
    training.add_argument("--out", default=None, help="run directory (default: runs/<name>); "
                          "running the same command again resumes a cut-off run there")
    training.add_argument("--device", default=None,
                          help="auto, cpu, cuda, cuda:N or CUDA indices, e.g. 0 or 0,1 (default: CUDA 0 "
                               "if present, else cpu)")
    training.add_argument("--workers", type=_positive_int("WORKERS", 1024), default=1,
                          help="processes generating the training scenes")
    training.set_defaults(run=cmd_train)
    paper = sub.add_parser("paper", help="the seed paper's experiment: generate, evaluate, report beside the paper")
    _add_scene_args(paper)
    _add_layout_args(paper, hfov=False)
    paper.add_argument("--scenes", type=_positive_int("SCENES", MAX_SCENES), default=DatasetConfig.scenes,
                       help=f"number of scenes; scene k uses seed SEED + k (default {DatasetConfig.scenes})")
    paper.add_argument("--rates", default="0:100:10", help="RATES spec (default 0:100:10, the paper's)")
    paper.add_argument("--rain-models", default=",".join(RAIN_MODELS),
                       help=f"comma-separated rain models (default: {','.join(RAIN_MODELS)})")
    paper.add_argument("--model", action="append", default=None,
                       help="shipped model to evaluate (repeatable; replaces the defaults: "
                       "rainbench-yolo11n and rainbench-yolo11n-weak, on a GPU also "
                       "rainbench-yolo11s and the shipped rain-trained twins)")
    paper.add_argument("--weights", action="append", default=None, help="extra weights to evaluate (repeatable)")
    paper.add_argument("--data", default="data/paper", help="dataset root (default data/paper)")
    paper.add_argument("--out", default="results/paper", help="results directory (default results/paper)")
    paper.add_argument("--imgsz", type=_positive_int("IMGSZ", 8192, 32), default=None,
                       help="letterbox size (default: each model's own, as rainbench eval)")
    paper.add_argument("--batch", type=_positive_int("BATCH", 4096), default=32,
                       help="frames per detector call (default 32)")
    paper.add_argument("--n-boot", type=_positive_int("N_BOOT", 1_000_000), default=1000,
                       help="bootstrap resamples of the intervals (default 1000)")
    paper.add_argument("--device", default=None,
                       help="device for evaluation and for the datasets' statistics: auto, cpu, cuda, "
                            "cuda:N or a CUDA index, e.g. 0 (default: CUDA 0 if present, else cpu)")
    paper.add_argument("--workers", type=_positive_int("WORKERS", 1024), default=1,
                       help="generation processes (the clip is rendered in up to that many pieces, "
                            "docs/datasets.md)")
    paper.add_argument("--classes", default=None,
                       help="classes to report, names or ids (default: the paper's four; e.g. add bus,truck)")
    _add_compare_arg(paper, "X-rain against X-randomrain when both are evaluated, else the model its "
                            "name extends, else the first that extends none")
    _add_metrics_arg(paper)
    paper.add_argument("--force", action="store_true", help="re-run detectors despite cached predictions")
    paper.add_argument("--quiet", action="store_true", help="no progress bars")
    paper.set_defaults(run=cmd_paper)
    return parser


def _stdout_closed() -> bool:
    """Whether standard output is a pipe whose reader has gone (poll reports an error on it)."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no real file behind sys.stdout
        return False


def worker_error_message(error: BaseException) -> str:
    """``error``'s message; for an error that torch re-raised from a ``DataLoader`` worker (a
    corrupt shard read while training, say), the worker's own message without the traceback
    torch folds into it (``Caught ShardFormatError in DataLoader worker process 0. Original
    Traceback ...``): the last line of that traceback, less its exception type."""
    text = str(error)
    first, _, rest = text.partition("\n")
    if not (first.startswith("Caught ") and " in DataLoader worker process " in first and rest):
        return text
    last = rest.rstrip().rsplit("\n", 1)[-1]
    kind = type(error)
    for prefix in (f"{kind.__module__}.{kind.__qualname__}: ", f"{kind.__qualname__}: "):
        if last.startswith(prefix):
            return last[len(prefix):]
    return last


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:
        print("rainbench: interrupted", file=sys.stderr)
        return 130
    handlers = {}
    _terminations.clear()
    if threading.current_thread() is threading.main_thread():
        # a signal already ignored stays ignored (`nohup rainbench generate ... &` outlives its terminal)
        handlers = {signum: signal.signal(signum, _raise_terminated) for signum in TERMINATING_SIGNALS
                    if signal.getsignal(signum) is not signal.SIG_IGN}
    try:
        return _run(args)
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


def _says_complete(root: Path) -> bool:
    """Whether ``root``'s manifest reads and says the dataset is complete (an interrupt that came
    as the last shard was listed)."""
    from rainbench.store.manifest import DatasetError, read_manifest

    try:
        manifest = read_manifest(root)
    except (DatasetError, OSError):
        return False
    return manifest is not None and bool(manifest["complete"])


def _run(args: argparse.Namespace) -> int:
    try:
        return args.run(args)
    except (CliError, ValueError, gl.GLBackendError, OSError, RuntimeError) as error:
        if isinstance(error, BrokenPipeError) and _stdout_closed():
            # the reader of our output went away (`rainbench stats DATA | head`): end quietly,
            # as a shell tool stopped by SIGPIPE, with 128 + SIGPIPE
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 141
        message = " ".join(worker_error_message(error).split())
        print(f"rainbench: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as interrupt:
        signum = interrupt.signum if isinstance(interrupt, Terminated) else (_terminations[-1] if _terminations else None)
        how = f"terminated by {signal.Signals(signum).name}" if signum is not None else "interrupted"
        manifest = Path(args.out) / "manifest.json" if args.command == "generate" else None
        if manifest is not None and _says_complete(manifest.parent):
            print(f"rainbench: {how}; {manifest} says the dataset is complete (rainbench verify {args.out} "
                  "checks it)", file=sys.stderr)
        elif manifest is not None and manifest.is_file():
            print(f"rainbench: {how}; the workers are stopped, {manifest} lists the complete shards and nothing "
                  "partial is under a final name; run the same command again to resume", file=sys.stderr)
        elif manifest is not None:
            print(f"rainbench: {how} before a shard was finished; nothing of the run is kept: run the same command "
                  "again to start it", file=sys.stderr)
        else:
            print(f"rainbench: {how}", file=sys.stderr)
        return 128 + signum if signum is not None else 130


if __name__ == "__main__":
    sys.exit(main())
