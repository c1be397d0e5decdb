"""The `rainbench` command line. Every failure is one line on stderr and a non-zero exit."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from rainbench.gen import gl

EXIT_USAGE = 2


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def _positive_int(name: str):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: expected an integer, got {text!r}") from None
        if value < 1:
            raise argparse.ArgumentTypeError(f"{name}: expected >= 1, got {value}")
        return value
    return parse


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"SEED: expected an integer, got {text!r}") from None
    if not 0 <= value <= 2**31 - 1:
        raise argparse.ArgumentTypeError(f"SEED: expected 0..2147483647, got {value}")
    return value


def _store(text: str) -> tuple[str, ...]:
    items = tuple(sorted({item.strip() for item in text.split(",") if item.strip()}))
    unknown = [item for item in items if item not in ("depth", "instance")]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"STORE: expected a comma list of depth,instance, got {text!r}")
    return items


def _choose_gl(requested: str | None) -> None:
    """Honour --gl before anything imports mujoco."""
    if requested is None:
        if not os.environ.get("MUJOCO_GL"):
            gl.find_backend(None)  # raises the clear error naming the packages
        return
    if "mujoco" in sys.modules:
        raise CliError("--gl: mujoco is already imported; set MUJOCO_GL instead")
    os.environ["MUJOCO_GL"] = gl.find_backend(requested)


def _writable_dir(path: Path, what: str) -> Path:
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise CliError(f"{what}: {path} is not a writable directory")
    return path


def cmd_generate(args: argparse.Namespace) -> int:
    from rainbench.rain import RAIN_MODELS, parse_rates

    rates = parse_rates(args.rates)
    if args.rain_model not in RAIN_MODELS:
        raise CliError(f"RAIN_MODEL: expected one of {', '.join(RAIN_MODELS)}, "
                       f"got {args.rain_model!r}")
    out = _writable_dir(Path(args.out), "OUT")
    _choose_gl(args.gl)
    from tqdm import tqdm

    from rainbench.gen.generate import GenerateConfig, generate_shard

    config = GenerateConfig(seed=args.seed, frames=args.frames, width=args.width,
                            height=args.height, rates=rates, rain_model=args.rain_model,
                            rain_seed=args.rain_seed, store=args.store, fps=args.fps)
    with tqdm(total=config.frames, unit="frame", desc=f"scene {config.seed}",
              disable=args.quiet, dynamic_ncols=True) as bar:
        path = generate_shard(config, out, progress=bar.update)
    print(path)
    return 0


def cmd_scene(args: argparse.Namespace) -> int:
    out = _writable_dir(Path(args.out), "OUT")
    from rainbench.gen.generate import GenerateConfig
    from rainbench.mjcf import layout as L
    from rainbench.mjcf.scene import build_spec, export_scene

    import numpy as np

    config = GenerateConfig(seed=args.seed, frames=args.frames, width=args.width,
                            height=args.height, fps=args.fps)
    layout = L.sample_layout(config.seed, config.scenario_config(),
                             np.random.default_rng(config.seed))
    path = export_scene(build_spec(layout, config.width, config.height, config.hfov_deg), out)
    print(path)
    return 0


def cmd_preview(args: argparse.Namespace) -> int:
    from rainbench.gen.preview import montage, write_png
    from rainbench.gen.shard import open_shard, read_frame_labels

    path = Path(args.shard)
    if path.is_dir():
        shards = sorted(path.glob("scene*_f*.h5"))
        if not shards:
            raise CliError(f"preview: no shard (scene*_f*.h5) in {path}")
        path = shards[0]
    with open_shard(path) as handle:
        frames = handle["rgb"].shape[1]
        if not 0 <= args.frame < frames:
            raise CliError(f"--frame: expected 0..{frames - 1} for {path.name}, got {args.frame}")
        images = handle["rgb"][:, args.frame]
        rates = handle["rates"][()]
        labels = read_frame_labels(handle, args.frame)
    boxes = (labels["bbox"], labels["class_id"]) if args.boxes else (None, None)
    out = Path(args.out or path.with_name(f"{path.stem}_frame{args.frame:04d}_rates.png"))
    _writable_dir(out.parent, "--out")
    write_png(out, montage(images, rates, boxes=boxes[0], class_ids=boxes[1]))
    print(out)
    return 0


def _add_scene_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=_seed, default=0,
                        help="scene seed: layout, actors, colours, speeds, sun, camera height")
    parser.add_argument("--frames", type=_positive_int("FRAMES"), default=200)
    parser.add_argument("--fps", type=float, default=10.0)
    parser.add_argument("--width", type=_positive_int("WIDTH"), default=800)
    parser.add_argument("--height", type=_positive_int("HEIGHT"), default=600)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, not argparse's usage block
        print(f"rainbench: error: {message}", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="rainbench", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    generate = sub.add_parser("generate", help="render a clip with rain into an HDF5 shard")
    generate.add_argument("--out", default="data", help="output directory (default: data)")
    _add_scene_args(generate)
    generate.add_argument("--rates", default="0",
                          help="rain rates in mm/h: 0:100:10, 0,25,50 or 50 (default: 0)")
    generate.add_argument("--rain-model", default="jeon2022")
    generate.add_argument("--rain-seed", type=_seed, default=0)
    generate.add_argument("--store", type=_store, default=(),
                          help="extra per-frame arrays: depth,instance")
    generate.add_argument("--gl", choices=sorted(gl.BACKENDS), default=None,
                          help="offscreen GL backend (default: MUJOCO_GL, else egl, else osmesa)")
    generate.add_argument("--quiet", action="store_true", help="no progress bar")
    generate.set_defaults(run=cmd_generate)
    scene = sub.add_parser("scene", help="write the composed scene as a standalone MJCF file")
    scene.add_argument("--out", required=True, help="directory for scene.xml and its textures")
    _add_scene_args(scene)
    scene.set_defaults(run=cmd_scene)
    preview = sub.add_parser("preview", help="PNG montage of one frame across all rain rates")
    preview.add_argument("shard", help="a shard, or a dataset directory (its first shard)")
    preview.add_argument("--frame", type=int, default=0)
    preview.add_argument("--out", default=None, help="PNG path (default: beside the shard)")
    preview.add_argument("--boxes", action="store_true", help="draw the labels")
    preview.set_defaults(run=cmd_preview)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.run(args)
    except (CliError, ValueError, gl.GLBackendError, OSError) as error:
        message = " ".join(str(error).split())
        print(f"rainbench: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("rainbench: interrupted; no shard was written under a final name", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
