"""Inference images/s of each ``rainbench eval`` backend, against ultralytics' own predict.

Workload: ``--images`` frames of 800x600 rendered from the default scene (seed 0, clean), in
batches of ``--batch`` (the eval default, 32), letterboxed to ``--imgsz`` (default 640: 640x480,
rectangular; the shipped nano model's card size is 960: 960x736).

Timed (best of ``--repeats``):

- baseline: ``ultralytics.YOLO(weights).predict(frames, imgsz=IMGSZ, conf=0.001)`` directly;
- ultralytics backend: ``load_detector(weights, pt_backend="ultralytics").predict`` (the same
  model through rainbench: BGR conversion, class filtering, clipping);
- batched backend: ``load_detector(weights).predict`` (the default for a ``.pt``: torch in
  batches, letterbox and NMS on the device, fp16 on CUDA, channels-last), and how its detections
  agree with the ultralytics backend's (share of its detections scoring >= 0.25 that have a twin:
  the same class, every edge within 1 px, the score within 0.02);
- forward pass alone: the batched backend's network on a ready (B, 3, h, w) batch, for scale;
- stages: the batched backend from letterboxed uint8 canvases (what the shard reader hands
  over), ms per image of each stage with the device synchronised between them: copy and
  convert, network, NMS, boxes back to the host (not an images/s figure);
- shard reader alone: ``rainbench eval``'s reader over a shard of the same frames at 11 rates
  (``jeon2022``): decoded, letterboxed with OpenCV and batched, no network; in this process, and
  in ``default_read_workers()`` worker processes (started once for all the rates, every batch
  split among them): what the reader can feed the network;
- eval from shards: the batched backend over that shard, as ``rainbench eval`` runs it
  (parallel decoding and letterbox, network, NMS, COCO records), images/s over all rates;
- onnx backend: the same model exported to ONNX (``rainbench.eval.weights.export_onnx``, dynamic input), run by
  onnxruntime: what a shipped model runs on CPU;
- darknet backend: a YOLOv4-tiny-sized Darknet network (random weights, built here: no download)
  through OpenCV DNN at 416x416 (its cfg size), for scale only: not the same network.

``weights`` is the shipped model ``--weights`` (default ``rainbench-yolo11n``; both shipped
models have a 960 px card) when present, else a yolo11n from its yaml.

The model runs on ``--device`` (default: CUDA when present, else the CPU); ONNX and Darknet run
on the CPU.

Each figure is printed as soon as it is measured (a run cut short still shows what it got);
``--skip`` leaves measurements out by name (``baseline``, ``ultralytics``, ``batched``,
``forward``, ``stages``, ``reader``, ``shards``, ``onnx``, ``darknet``; without the baseline no ratios). A Darknet network
this OpenCV cannot read (OpenCV 5 has no Darknet importer) is reported as unavailable.

Usage: ``python bench/inference.py [--weights rainbench-yolo11n] [--json OUT] [--imgsz 640]
[--images 32] [--batch 32] [--repeats 2] [--device cpu] [--skip onnx,darknet]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rainbench.eval import backends, pipeline, weights as registry
from rainbench.eval.backends.ultralytics import preload_torch

preload_torch()  # before Mesa renders the frames
import torch  # noqa: E402

YOLOV4_TINY_BODY = [  # (filters, size, stride) of the yolov4-tiny backbone's plain convolutions
    (32, 3, 2), (64, 3, 2), (64, 3, 1), (128, 3, 2), (128, 3, 1), (256, 3, 2), (256, 3, 1), (512, 3, 1),
]


def frames(count: int) -> list[np.ndarray]:
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import render_clip

    config = GenerateConfig(seed=0, frames=count, fps=count / 20.0, rates=(0.0,), layout="street",
                            time_of_day="day")
    return [frame.rgb.copy() for _, frame, _ in render_clip(config)]


def darknet_files(folder: Path, classes: int = 80) -> Path:
    """A 416x416 Darknet network of yolov4-tiny's size (plain convolutions, one [yolo] head)."""
    lines = ["[net]", "width=416", "height=416", "channels=3", ""]
    count, channels = 0, 3
    for filters, size, stride in YOLOV4_TINY_BODY:
        lines += ["[convolutional]", "batch_normalize=1", f"filters={filters}", f"size={size}",
                  f"stride={stride}", "pad=1", "activation=leaky", ""]
        count += filters * 4 + filters * channels * size * size
        channels = filters
    head = 3 * (5 + classes)
    lines += ["[convolutional]", f"filters={head}", "size=1", "stride=1", "pad=1", "activation=linear", "",
              "[yolo]", "mask=0,1,2", "anchors=10,14, 23,27, 37,58, 81,82, 135,169, 344,319",
              f"classes={classes}", "num=6", ""]
    count += head + head * channels
    (folder / "tiny4.cfg").write_text("\n".join(lines))
    values = np.random.default_rng(0).normal(0, 0.05, count).astype("<f4")
    weights = folder / "tiny4.weights"
    weights.write_bytes(struct.pack("<iiiq", 0, 2, 0, 0) + values.tobytes())
    return weights


def best_rate(run, images: list[np.ndarray], batch: int, repeats: int) -> float:
    """Images per second of ``run(batch_of_images)`` over all images, best of ``repeats``."""
    run(images[:batch])  # warm-up (lazy init, thread pools)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for index in range(0, len(images), batch):
            run(images[index:index + batch])
        best = min(best, time.perf_counter() - start)
    return len(images) / best


def agreement(reference: list, other: list) -> float:
    """Share of ``reference``'s detections scoring >= 0.25 (over all images) with a twin in
    ``other``: the same class, every box edge within 1 px, the score within 0.02."""
    wanted = twins = 0
    for (ref_boxes, ref_scores, ref_ids), (boxes, scores, ids) in zip(reference, other, strict=True):
        for index in np.flatnonzero(ref_scores >= 0.25):
            wanted += 1
            close = ((np.abs(boxes - ref_boxes[index]).max(axis=1) < 1.0) & (ids == ref_ids[index])
                     & (np.abs(scores - ref_scores[index]) < 0.02))
            twins += bool(close.any())
    return twins / max(wanted, 1)


def forward_rate(detector, images: list[np.ndarray], imgsz: int, batch: int, repeats: int) -> float:
    """Images per second of the batched backend's network alone on a ready letterboxed batch."""
    from rainbench.eval.backends.letterbox import rect_shape
    from rainbench.eval.backends.torch_batched import letterbox_batch

    height, width = images[0].shape[:2]
    block = torch.from_numpy(np.stack(images[:batch])).to(detector.device)
    with torch.inference_mode():
        canvas, _, _ = letterbox_batch(block, rect_shape(height, width, imgsz), detector.dtype)
        step = len(canvas) if detector.device.type == "cuda" else 1  # as predict_frames runs it

        def run(_):
            for start in range(0, len(canvas), step):
                detector.network(canvas[start:start + step])
            if detector.device.type == "cuda":
                torch.cuda.synchronize()
        return best_rate(run, [None] * len(canvas), len(canvas), repeats)


def batched_stages(detector, images: list[np.ndarray], imgsz: int, batch: int, repeats: int) -> dict[str, float]:
    """Milliseconds per image of each stage of the batched backend's path from the reader's
    letterboxed uint8 canvases (:meth:`TorchDetector.predict_canvases`), on its device, the
    device synchronised after each stage (best of ``repeats`` over the frames, in batches of
    ``batch``): the canvases' copy to the device and conversion, the network, NMS
    (``select_batch``), and the boxes' mapping and copy back."""
    from rainbench.eval.backends.letterbox import letterbox, letterbox_geometry, rect_shape
    from rainbench.eval.backends.torch_batched import (CPU_BATCH, _to_host, network_input, select_batch,
                                                       unletterbox_boxes)

    height, width = images[0].shape[:2]
    shape = rect_shape(height, width, imgsz)
    gain, _, (top, left) = letterbox_geometry(height, width, shape)
    blocks = [torch.from_numpy(np.stack([letterbox(image, shape)[0] for image in images[start:start + batch]]))
              for start in range(0, len(images), batch)]
    if detector.device.type == "cuda":
        blocks = [block.pin_memory() for block in blocks]
    step = batch if detector.device.type == "cuda" else CPU_BATCH  # as _detect runs it

    def sync():
        if detector.device.type == "cuda":
            torch.cuda.synchronize()

    best: dict[str, float] = {}
    for attempt in range(repeats + 1):  # the first pass warms up
        seconds = dict.fromkeys(("copy and convert", "network", "nms", "boxes back"), 0.0)
        with torch.inference_mode():
            for block in blocks:
                for start in range(0, len(block), step):
                    clock = time.perf_counter()
                    canvas = network_input(block[start:start + step].to(detector.device, non_blocking=True),
                                           detector.dtype)
                    sync()
                    now = time.perf_counter()
                    seconds["copy and convert"] += now - clock
                    raw = detector.network(canvas)
                    raw = raw[0] if isinstance(raw, (tuple, list)) else raw
                    sync()
                    clock, now = now, time.perf_counter()
                    seconds["network"] += now - clock
                    selected = select_batch(raw, detector._lookup, conf=0.001, iou=0.7, max_det=300)
                    sync()
                    clock, now = now, time.perf_counter()
                    seconds["nms"] += now - clock
                    _to_host([(unletterbox_boxes(boxes, gain, (float(left), float(top)), width, height), scores, ids)
                              for boxes, scores, ids in selected])
                    seconds["boxes back"] += time.perf_counter() - now
        if attempt or not repeats:
            for stage, value in seconds.items():
                best[stage] = min(best.get(stage, float("inf")), value)
    return {stage: round(value / len(images) * 1e3, 3) for stage, value in best.items()}


def rate_shard(count: int, folder: Path) -> Path:
    """A shard of ``count`` frames at 11 rates (``jeon2022``) in ``folder/shard``, generated on
    first use."""
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import generate_shard

    out = folder / "shard"
    if not out.is_dir():
        generate_shard(GenerateConfig(seed=0, frames=count, fps=count / 20.0, layout="street", time_of_day="day",
                                      rates=tuple(float(r) for r in range(0, 101, 10)), rain_model="jeon2022"), out)
    return out


def shard_rate(detector, count: int, imgsz: int, batch: int, repeats: int, folder: Path) -> float:
    """Images per second of ``rainbench eval``'s inference over a shard of ``count`` frames at 11
    rates (``jeon2022``), from the shard to COCO records."""
    from rainbench.eval import pipeline

    dataset = pipeline.open_dataset(rate_shard(count, folder))

    class Bar:
        def update(self, _):
            pass

    def run(_):
        for _rate, _records in pipeline._infer(detector, dataset, dataset.rates, batch=batch, imgsz=imgsz, conf=0.001,
                                               iou=0.7, max_det=300, bar=Bar(), classes=(0, 1, 2, 3),
                                               workers=pipeline.default_read_workers()):
            pass
    images = len(dataset.images) * len(dataset.rates)
    return best_rate(run, [None] * images, images, repeats)


def reader_rate(count: int, imgsz: int, batch: int, repeats: int, folder: Path, workers: int) -> float:
    """Images per second of ``rainbench eval``'s shard reader alone (decoded, letterboxed and
    batched by ``workers`` processes, no network) over the shard of :func:`shard_rate`."""
    from rainbench.eval import pipeline
    from rainbench.eval.backends.torch_batched import frame_batches

    dataset = pipeline.open_dataset(rate_shard(count, folder))

    def run(_):
        for _batch in frame_batches(dataset, dataset.rates, batch, workers, imgsz=imgsz):
            pass
    images = len(dataset.images) * len(dataset.rates)
    return best_rate(run, [None] * images, images, repeats)


MEASUREMENTS = ("baseline", "ultralytics", "batched", "forward", "stages", "reader", "shards", "onnx", "darknet")
"""The measurements in the order they run (``--skip`` takes their names)."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", default="rainbench-yolo11n", help="shipped model name")
    parser.add_argument("--json", default=None)
    parser.add_argument("--imgsz", type=int, default=640)
    parser.add_argument("--images", type=int, default=32)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--device", default=None, help="torch device (default: CUDA when present, else cpu)")
    parser.add_argument("--skip", default="", help="comma-separated measurements to leave out, of "
                        + ", ".join(MEASUREMENTS) + " (e.g. onnx,darknet on a GPU machine: both run on the CPU)")
    args = parser.parse_args(argv)
    skip = {name for name in args.skip.split(",") if name}
    if skip - set(MEASUREMENTS):
        parser.error(f"--skip: expected names among {', '.join(MEASUREMENTS)}, got {', '.join(sorted(skip - set(MEASUREMENTS)))}")
    device = args.device or ("0" if torch.cuda.is_available() else "cpu")
    threads = torch.get_num_threads()
    started = time.perf_counter()

    from ultralytics import YOLO

    images = frames(args.images)
    settings = dict(imgsz=args.imgsz, conf=0.001, iou=0.7, max_det=300)
    rates: dict[str, float] = {}
    unavailable: dict[str, str] = {}

    def measure(name: str, label: str, rate) -> None:
        """Run the measurement ``name`` (``rate()`` gives images/s) unless skipped, and print its
        figure at once, so a run cut short still shows what it measured."""
        if name in skip:
            return
        start = time.perf_counter()
        rates[label] = rate()
        print(f"{label}: {rates[label]:.1f} images/s (measured in {time.perf_counter() - start:.0f} s, "
              f"{time.perf_counter() - started:.0f} s since the start)", flush=True)

    agreed, stages = None, None
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if args.weights in registry.shipped_models():
            weights, label = str(registry.WEIGHTS_DIR / f"{args.weights}.pt"), args.weights
        else:
            from ultralytics.nn.tasks import DetectionModel

            print(f"inference: {args.weights} is not a shipped model here ({', '.join(registry.shipped_models())}): "
                  "timing a yolo11n of random weights instead", flush=True)
            weights, label = str(folder / "yolo11n.pt"), "yolo11n, 4 classes (random weights)"
            model = YOLO("yolo11n.yaml")
            model.model = DetectionModel("yolo11n.yaml", nc=4, verbose=False)
            model.model.names = {0: "person", 1: "bicycle", 2: "car", 3: "motorcycle"}
            model.save(weights)
        print(f"{len(images)} frames rendered, {time.perf_counter() - started:.0f} s since the start", flush=True)
        direct = YOLO(weights)
        bgr = [np.ascontiguousarray(image[..., ::-1]) for image in images]
        def baseline_predict(chunk):
            # ultralytics' first predict sets torch's threads to cores - 1 on the CPU (select_device):
            # put them back so that the baseline runs on the threads every other row runs on
            try:
                return direct.predict(chunk, verbose=False, device=device, **settings)
            finally:
                torch.set_num_threads(threads)

        measure("baseline", "baseline ultralytics predict", lambda: best_rate(
            baseline_predict, bgr, args.batch, args.repeats))
        detector = backends.load_detector(weights, device=device, pt_backend="ultralytics")
        measure("ultralytics", "ultralytics backend", lambda: best_rate(
            lambda chunk: detector.predict(chunk, **settings), images, args.batch, args.repeats))
        batched = backends.load_detector(weights, device=device)  # a .pt path: the batched backend
        measure("batched", "batched backend", lambda: best_rate(
            lambda chunk: batched.predict(chunk, **settings), images, args.batch, args.repeats))
        if not {"ultralytics", "batched"} & skip:
            agreed = agreement(detector.predict(images, **settings), batched.predict(images, **settings))
            print(f"batched backend's agreement with the ultralytics backend: {agreed:.4f}", flush=True)
        measure("forward", "forward pass alone (batched backend's network)", lambda: forward_rate(
            batched, images, args.imgsz, args.batch, args.repeats))
        if "stages" not in skip:
            stages = batched_stages(batched, images, args.imgsz, args.batch, args.repeats)
            print("batched backend's stages from letterboxed canvases, ms per image: "
                  + ", ".join(f"{stage} {value:.3f}" for stage, value in stages.items()), flush=True)
        read_workers = pipeline.default_read_workers()
        measure("reader", "shard reader alone, one process", lambda: reader_rate(
            args.images, args.imgsz, args.batch, args.repeats, folder, 0))
        measure("reader", f"shard reader alone, {read_workers} worker processes", lambda: reader_rate(
            args.images, args.imgsz, args.batch, args.repeats, folder, read_workers))
        measure("shards", "eval from shards, 11 rates (batched backend)", lambda: shard_rate(
            batched, args.images, args.imgsz, args.batch, args.repeats, folder))
        if "onnx" not in skip:
            onnx_detector = backends.load_detector(registry.export_onnx(weights, folder / "model.onnx"))
            measure("onnx", "onnx backend", lambda: best_rate(
                lambda chunk: onnx_detector.predict(chunk, **settings), images, args.batch, args.repeats))
        if "darknet" not in skip:
            try:
                darknet = backends.load_detector(darknet_files(folder))
            except backends.BackendError as error:  # OpenCV 5 has no Darknet importer
                unavailable["darknet"] = str(error)
                print(f"darknet backend: not measured: {error}", flush=True)
            else:
                measure("darknet", "darknet backend (yolov4-tiny-sized, 416)", lambda: best_rate(
                    lambda chunk: darknet.predict(chunk, **settings), images, args.batch, args.repeats))
    baseline = rates.get("baseline ultralytics predict")
    result = {
        "benchmark": "inference", "model": label, "images": len(images), "batch": args.batch,
        "imgsz": args.imgsz, "machine": platform.machine(), "cpus": os.cpu_count(),
        "torch_threads": threads, "cuda": torch.cuda.is_available(), "device": device,
        "batched_precision": "fp16" if batched.half else "fp32",
        "batched_agreement_with_ultralytics_backend": None if agreed is None else round(agreed, 4),
        "batched_stages_ms_per_image": stages,
        "images_per_s": {k: round(v, 2) for k, v in rates.items()},
        "ratio_vs_baseline": {k: round(v / baseline, 3) for k, v in rates.items()} if baseline else {},
        "skipped": sorted(skip), "unavailable": unavailable,
    }
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
