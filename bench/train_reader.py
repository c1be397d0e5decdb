"""Training-data benchmark (issue 19): images/s into ultralytics' trainer, straight from shards
against the exported-PNG path, measured in the same run.

Both sides build the dataset ultralytics' detection trainer builds (training mode: mosaic and
the other default augmentations, 640 px) over the same frames (one scene of 200 frames of 800x600 at rates 0
and 50 mm/h): ``ShardYOLODataset`` over the shards (drawing each image at 0 or 50 mm/h, the
curriculum ``{0: 1, 50: 1}``), and ultralytics' own ``YOLODataset`` over the clean frames exported
as PNG (``rainbench export --format yolo``); ``cache`` is off on both sides, and both keep
ultralytics' in-memory buffer of recent loads that mosaic draws from. Each is read through
ultralytics' ``build_dataloader`` with 2 workers; after a warm-up epoch, the medians of
``--repeats`` interleaved timed epochs are reported. Target: shards / PNG >= 1.

    python bench/train_reader.py [--frames 200] [--repeats 7] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--imgsz", type=int, default=640)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()

    from rainbench.eval.backends.ultralytics import _offline_ultralytics

    _offline_ultralytics()
    from ultralytics.cfg import get_cfg
    from ultralytics.data.build import build_dataloader
    from ultralytics.data.dataset import YOLODataset

    from rainbench.experiments.shard_training import RainCurriculum, shard_dataset_class

    tmp = Path(tempfile.mkdtemp(prefix="rainbench-train-reader-"))
    try:
        data = tmp / "data"
        subprocess.run([sys.executable, "-m", "rainbench.cli", "generate", "--quiet", "--out", str(data),
                        "--frames", str(args.frames), "--rates", "0,50"], check=True, stdout=subprocess.DEVNULL)
        subprocess.run([sys.executable, "-m", "rainbench.cli", "export", str(data), "--format", "yolo",
                        "--out", str(tmp / "yolo"), "--rates", "0"], check=True, stdout=subprocess.DEVNULL)
        hyp = get_cfg(overrides={"imgsz": args.imgsz})
        names = {"names": {i: str(i) for i in range(4)}, "channels": 3}
        common = dict(imgsz=args.imgsz, augment=True, hyp=hyp, rect=False, batch_size=16, stride=32, pad=0.0,
                      task="detect", data=names, cache=None)
        shard_set = shard_dataset_class()(img_path=str(data), curriculum=RainCurriculum.from_mapping({0: 1, 50: 1}),
                                          **common)
        png_set = YOLODataset(img_path=str(tmp / "yolo" / "rate_0" / "images"), **common)
        loaders = {name: build_dataloader(dataset, batch=16, workers=2, shuffle=True)
                   for name, dataset in (("shards", shard_set), ("png", png_set))}

        def epoch(loader) -> float:
            start = time.perf_counter()
            count = sum(len(batch["img"]) for batch in loader)
            return count / (time.perf_counter() - start)

        for loader in loaders.values():
            epoch(loader)  # warm-up: worker start-up, page cache
        runs: dict[str, list[float]] = {name: [] for name in loaders}
        for _ in range(args.repeats):
            for name, loader in loaders.items():
                runs[name].append(epoch(loader))
        rates = {name: statistics.median(values) for name, values in runs.items()}
        result = {"benchmark": "train_reader", "frames": args.frames, "imgsz": args.imgsz,
                  "repeats": args.repeats, "machine": platform.machine(),
                  "images_per_s": rates, "runs": runs, "ratio_shards_over_png": rates["shards"] / rates["png"],
                  "target_ratio": 1.0}
        print(f"training data: shards {rates['shards']:.1f} images/s, exported PNG {rates['png']:.1f} "
              f"images/s, ratio {result['ratio_shards_over_png']:.2f} (target >= 1)")
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
