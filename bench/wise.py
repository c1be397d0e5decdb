"""Weight-space interpolation of a rain fine-tune with the clean model it started from (WiSE-FT,
Wortsman et al. 2022), measured: builds ``(1 - a) x BASE + a x TUNED`` for each ``--alpha``
(:func:`rainbench.eval.weights.interpolate_checkpoints`, with their ONNX copies) in
``--models-dir``, then runs ``bench/quality.py --rain`` on BASE, TUNED and every interpolation,
each interpolation's mPC paired against TUNED. Shows the trade between clean AP and robustness along the line between
the two models (issue 19: clean AP within 0.02 of the clean model, rPC >= 0.90).

    python bench/wise.py [--base rainbench-yolo11n] [--tuned rainbench-yolo11n-rain]
        [--alpha 0.5,0.7,0.9] [--models-dir runs/wise] [--rain physical] [quality.py options ...]

Unknown options go to ``bench/quality.py`` (``--data``, ``--out``, ``--json``, ``--imgsz``, ...).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import quality  # noqa: E402 -- bench/quality.py, beside this file


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="rainbench-yolo11n")
    parser.add_argument("--tuned", default="rainbench-yolo11n-rain")
    parser.add_argument("--alpha", default="0.5,0.7,0.9", help="comma list of weights of TUNED")
    parser.add_argument("--models-dir", default="runs/wise", help="where the interpolated models go")
    parser.add_argument("--rain", default="physical", choices=("physical", "jeon2022"))
    args, rest = parser.parse_known_args(argv)
    try:
        alphas = [float(text) for text in args.alpha.split(",")]
    except ValueError:
        parser.error(f"--alpha: expected a comma list of numbers in [0, 1], got {args.alpha!r}")

    from rainbench.eval.weights import export_onnx, interpolate_checkpoints

    weights, compare = [args.base, args.tuned], []
    for alpha in alphas:
        stem = f"{Path(str(args.tuned)).stem}-wise{round(alpha * 100):03d}"
        checkpoint = interpolate_checkpoints(args.base, args.tuned, alpha,
                                             Path(args.models_dir) / f"{stem}.pt")
        weights.append(str(export_onnx(checkpoint, checkpoint.with_suffix(".onnx"))))
        compare.append(f"{stem}={Path(str(args.tuned)).stem}")
    return quality.main(["--rain", args.rain, *(f"--weights={w}" for w in weights),
                         *(f"--compare={c}" for c in compare), *rest])


if __name__ == "__main__":
    sys.exit(main())
