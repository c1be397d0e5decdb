"""The batched torch backend (rainbench.eval.backends.torch_batched), on the CPU: its letterboxes
(the GPU's, and the CPU's OpenCV one) against the numpy one, its NMS against ultralytics' own,
box mapping, the parallel shard reader, which models it runs, and device errors. The shipped
model's detections against ultralytics' predict are checked on the guard scene in
test_train_paper.py. No file is downloaded."""

import re
from pathlib import Path

import numpy as np
import pytest

from rainbench.eval import backends
from rainbench.eval.backends.letterbox import LETTERBOX_FILL, letterbox, rect_shape, unletterbox
from rainbench.eval.backends.ultralytics import UltralyticsDetector, _offline_ultralytics

# Import torch's lazy modules before anything renders in this process (see test_eval_pipeline).
_offline_ultralytics()
import torch  # noqa: E402
import torch._dynamo  # noqa: E402,F401

from rainbench.eval.backends import torch_batched  # noqa: E402
from rainbench.eval.backends.torch_batched import (  # noqa: E402
    TorchDetector, frame_batches, letterbox_batch, select_batch, shard_batches, supports, torch_device,
    unletterbox_boxes)
from rainbench.gen.config import GenerateConfig  # noqa: E402
from rainbench.gen.generate import generate_shard  # noqa: E402
from rainbench.store import Dataset  # noqa: E402


def _frame(height=600, width=800, seed=0):
    """A smooth random frame (a real frame's neighbouring pixels are alike), uint8 RGB."""
    coarse = np.random.default_rng(seed).integers(0, 256, (height // 8 + 1, width // 8 + 1, 3))
    return np.ascontiguousarray(np.kron(coarse, np.ones((8, 8, 1)))[:height, :width].astype(np.uint8))


@pytest.mark.parametrize("imgsz", [640, 800, 960, 1280])
def test_letterbox_batch_matches_the_opencv_letterbox(imgsz):
    """The same canvas geometry as the numpy letterbox (ultralytics' LetterBox with auto=True); the
    pixels within one grey level of OpenCV's INTER_LINEAR (its fixed-point rounding); exact where
    no resize is needed (800 px: the frame's own size)."""
    frames = np.stack([_frame(seed=0), _frame(seed=1)])
    shape = rect_shape(600, 800, imgsz)
    canvas, gain, pad = letterbox_batch(torch.from_numpy(frames), shape, torch.float32)
    assert canvas.shape == (2, 3, *shape) and canvas.dtype == torch.float32
    assert canvas.is_contiguous(memory_format=torch.channels_last)
    levels = (canvas.permute(0, 2, 3, 1) * 255).round().to(torch.int64).numpy()
    for frame, ours in zip(frames, levels):
        reference, reference_gain, reference_pad = letterbox(frame, shape)
        assert (gain, pad) == (reference_gain, reference_pad)
        difference = np.abs(ours - reference.astype(np.int64))
        assert difference.max() <= (0 if imgsz == 800 else 1)
        assert (difference > 0).mean() < 0.2
    top = int(pad[1])
    if top:  # the grey border
        assert (levels[:, :top] == LETTERBOX_FILL).all()


def test_cpu_letterbox_gives_the_network_ultralytics_own_pixels():
    """On the CPU the canvas is OpenCV's letterbox (ultralytics' LetterBox) exactly, as floats."""
    from rainbench.eval.backends.torch_batched import letterbox_frames

    frames = np.stack([_frame(seed=0), _frame(seed=1)])
    shape = rect_shape(600, 800, 960)
    canvas, gain, pad = letterbox_frames(torch.from_numpy(frames), shape)
    assert canvas.is_contiguous(memory_format=torch.channels_last) and canvas.dtype == torch.float32
    for frame, ours in zip(frames, canvas):
        reference, reference_gain, reference_pad = letterbox(frame, shape)
        assert (gain, pad) == (reference_gain, reference_pad)
        torch.testing.assert_close(ours.permute(1, 2, 0), torch.from_numpy(reference).float() / 255.0, rtol=0, atol=0)


def test_letterbox_batch_refuses_frames_that_are_not_uint8_rgb():
    with pytest.raises(ValueError, match=r"frames: expected \(B, H, W, 3\) uint8, got \(2, 600, 800\)"):
        letterbox_batch(torch.zeros(2, 600, 800, dtype=torch.uint8), (608, 800), torch.float32)
    with pytest.raises(ValueError, match="torch.float32"):
        letterbox_batch(torch.zeros(1, 60, 80, 3), (64, 96), torch.float32)


def _clustered_prediction(generator, images=3, nc=6, anchors=400):
    """(B, 4 + nc, N) head output: boxes in clusters (so NMS has work), scores in 0..1 with ties
    unlikely, cx, cy, w, h in a 640x480 canvas."""
    centres = torch.rand(images, 8, 2, generator=generator) * torch.tensor([640.0, 480.0])
    which = torch.randint(0, 8, (images, anchors), generator=generator)
    cxcy = torch.gather(centres, 1, which[..., None].expand(-1, -1, 2)) + 6 * torch.randn(images, anchors, 2,
                                                                                       generator=generator)
    wh = 20 + 60 * torch.rand(images, anchors, 2, generator=generator)
    scores = torch.rand(images, anchors, nc, generator=generator) ** 4
    return torch.cat([cxcy, wh, scores], dim=2).transpose(1, 2).contiguous()


@pytest.mark.parametrize("conf,iou,max_det", [(0.001, 0.7, 300), (0.25, 0.45, 300), (0.01, 0.7, 5)])
def test_select_batch_equals_ultralytics_non_max_suppression(conf, iou, max_det):
    """Against ultralytics' own NMS with ``classes=`` the evaluated model classes: the same
    boxes, scores and classes in the same order, image by image; the classes are then mapped to
    rainbench ids."""
    from ultralytics.utils.nms import non_max_suppression

    prediction = _clustered_prediction(torch.Generator().manual_seed(0))
    lookup = torch.tensor([0, 1, 2, 3, -1, -1])  # model classes 4, 5 not evaluated
    ours = select_batch(prediction, lookup, conf=conf, iou=iou, max_det=max_det)
    reference = non_max_suppression(prediction.clone(), conf, iou, classes=[0, 1, 2, 3], max_det=max_det)
    assert len(ours) == len(reference) == 3
    for (boxes, scores, ids), expected in zip(ours, reference, strict=True):
        assert len(boxes) > 0 and len(boxes) <= max_det
        torch.testing.assert_close(boxes, expected[:, :4], rtol=0, atol=0)
        torch.testing.assert_close(scores, expected[:, 4], rtol=0, atol=0)
        assert ids.tolist() == lookup[expected[:, 5].long()].tolist()
        assert (scores > conf).all() and (ids >= 0).all()


def test_select_batch_maps_classes_and_drops_the_unevaluated_ones():
    """One image, two overlapping boxes of different classes (both kept: NMS is per class), one
    box whose best class is not evaluated (dropped even though its second class is), one under the
    confidence floor."""
    rows = torch.tensor([
        # cx, cy, w, h, class scores (4 model classes)
        [100.0, 100.0, 40.0, 40.0, 0.9, 0.0, 0.0, 0.0],
        [102.0, 100.0, 40.0, 40.0, 0.0, 0.8, 0.0, 0.0],
        [300.0, 300.0, 40.0, 40.0, 0.0, 0.3, 0.0, 0.7],  # best class 3: not evaluated
        [500.0, 300.0, 40.0, 40.0, 0.0, 0.0, 0.2, 0.0],  # under conf
    ])
    lookup = torch.tensor([2, 0, 1, -1])  # model class -> rainbench id
    (boxes, scores, ids), = select_batch(rows.T[None], lookup, conf=0.25, iou=0.5, max_det=10)
    assert ids.tolist() == [2, 0] and scores.tolist() == pytest.approx([0.9, 0.8])
    assert boxes.tolist() == [[80.0, 80.0, 120.0, 120.0], [82.0, 80.0, 122.0, 120.0]]


def test_unletterbox_boxes_equals_the_numpy_mapping():
    boxes = np.array([[-10, 0, 700, 700], [100.5, 88, 300, 250.25], [0, 0, 960, 736]], np.float32)
    for gain, pad in ((1.2, (0.0, 8.0)), (0.8, (0.0, 0.0))):
        expected = unletterbox(boxes, gain, pad, 800, 600)
        np.testing.assert_allclose(unletterbox_boxes(torch.from_numpy(boxes), gain, pad, 800, 600).numpy(),
                                   expected, atol=1e-4)


@pytest.fixture(scope="module")
def two_shards(tmp_path_factory):
    """Two shards of different frame sizes: 3 frames of 64x48, then 2 of 96x72."""
    root = tmp_path_factory.mktemp("shards")
    paths = []
    for seed, (width, height, frames) in enumerate(((64, 48, 3), (96, 72, 2))):
        out = root / f"s{seed}"
        generate_shard(GenerateConfig(seed=seed, frames=frames, width=width, height=height, rates=(0.0, 50.0),
                                      layout="street", time_of_day="day"), out)
        paths += sorted(out.glob("*.h5"))
    return paths


def test_shard_batches_never_mix_shards():
    class Image:
        def __init__(self, shard_index):
            self.shard_index = shard_index

    images = [Image(s) for s in (0, 0, 0, 1, 1, 2)]
    assert shard_batches(images, 2) == [[0, 1], [2], [3, 4], [5]]
    assert shard_batches(images, 32) == [[0, 1, 2], [3, 4], [5]]


@pytest.mark.parametrize("workers", [0, 1, 2])
def test_frame_batches_read_every_frame_at_every_rate_in_id_order(two_shards, workers):
    """Rate by rate, in image-id order, one frame size per batch, the bytes the dataset reader
    reads; the same with one worker process and with two (each batch then read in two chunks)."""
    dataset = Dataset(two_shards)
    seen = []
    for rate, image_ids, block in frame_batches(dataset, [50.0, 0.0], batch=2, workers=workers):
        assert block.dtype == torch.uint8 and block.ndim == 4 and len(block) == len(image_ids) <= 2
        for image_id, frame in zip(image_ids, block):
            image = dataset.image(image_id)
            with dataset.open(image.shard_index) as handle:
                np.testing.assert_array_equal(frame.numpy(), dataset.read_rgb(handle, image, rate))
        seen.append((rate, image_ids))
    # the first shard holds images 1..3, the second 4 and 5 (batches never mix shards)
    assert seen == [(50.0, [1, 2]), (50.0, [3]), (50.0, [4, 5]), (0.0, [1, 2]), (0.0, [3]), (0.0, [4, 5])]


def test_frame_batches_letterbox_in_the_reader_with_opencv(two_shards):
    """With imgsz the reader's workers hand over each frame on its canvas exactly as the numpy
    (OpenCV) letterbox draws it: ultralytics' predict's own pixels."""
    dataset = Dataset(two_shards)
    for rate, image_ids, canvases in frame_batches(dataset, [50.0], batch=3, workers=1, imgsz=64):
        for image_id, canvas in zip(image_ids, canvases):
            image = dataset.image(image_id)
            with dataset.open(image.shard_index) as handle:
                frame = dataset.read_rgb(handle, image, rate)
            np.testing.assert_array_equal(canvas.numpy(), letterbox(frame, rect_shape(*frame.shape[:2], 64))[0])


def test_frame_batches_start_the_workers_once_and_split_each_batch_among_them(two_shards, monkeypatch):
    """One DataLoader for all the rates (its workers start once, not once a rate), whose keys cut
    each batch into ceil(batch / workers) frames, so that every worker decodes part of it."""
    loaders = []
    real = torch.utils.data.DataLoader

    def recording(dataset, **options):
        loaders.append(list(options["sampler"]))
        return real(dataset, **options)

    monkeypatch.setattr(torch.utils.data, "DataLoader", recording)
    dataset = Dataset(two_shards)
    batches = list(frame_batches(dataset, [0.0, 50.0], batch=3, workers=2))
    assert len(loaders) == 1
    assert [indices for _, indices in loaders[0]] == [(0, 1), (2,), (3, 4)] * 2
    assert [image_ids for _, image_ids, _ in batches] == [[1, 2, 3], [4, 5]] * 2


def _saved_model(tmp_path, yaml):
    from ultralytics import YOLO

    torch.manual_seed(0)
    model = YOLO(yaml)
    model.model.names = dict(enumerate(["person", "bicycle", "car", "motorcycle"] +
                                       [f"coco{i}" for i in range(4, 80)]))
    path = tmp_path / f"{yaml.split('.')[0]}.pt"
    model.save(str(path))
    return path


def test_batched_backend_runs_detect_heads_and_leaves_end_to_end_ones_to_ultralytics(tmp_path):
    v11 = backends.load_detector(_saved_model(tmp_path, "yolo11n.yaml"), device="cpu")
    assert isinstance(v11, TorchDetector) and supports(v11.network)
    assert v11.device == torch.device("cpu") and not v11.half and v11.dtype == torch.float32
    assert v11.lookup.tolist()[:5] == [0, 1, 2, 3, -1]
    # YOLOv10's head is end-to-end (no NMS): ultralytics' predict runs it.
    v10 = backends.load_detector(_saved_model(tmp_path, "yolov10n.yaml"), device="cpu")
    assert isinstance(v10, UltralyticsDetector) and not supports(v10.model.model)
    frames = [_frame(72, 96, seed) for seed in range(3)]
    threads = torch.get_num_threads()
    torch.set_num_threads(3)  # ultralytics' predict sets cores - 1 (at most 8): rainbench puts it back
    for detector in (v11, v10):
        for boxes, scores, ids in detector.predict(frames, imgsz=96, conf=0.0001, iou=0.7, max_det=20):
            assert boxes.shape == (len(scores), 4) and len(scores) <= 20 and set(ids.tolist()) <= {0, 1, 2, 3}
            assert (boxes[:, [0, 2]] <= 96).all() and (boxes[:, [1, 3]] <= 72).all() and (boxes >= 0).all()
        assert torch.get_num_threads() == 3
    torch.set_num_threads(threads)
    # The ultralytics reference on request.
    assert isinstance(backends.load_detector(tmp_path / "yolo11n.pt", device="cpu", pt_backend="ultralytics"),
                      UltralyticsDetector)
    with pytest.raises(backends.BackendError, match="--pt-backend: expected one of batched, ultralytics, got 'onnx'"):
        backends.load_detector(tmp_path / "yolo11n.pt", pt_backend="onnx")


def test_torch_device_strings():
    assert torch_device("cpu") == torch.device("cpu")
    assert torch_device(None) == torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    with pytest.raises(backends.BackendError, match=r"--device: expected auto, cpu, cuda, cuda:N or CUDA indices \(0 or 0,1\), got .tpu."):
        torch_device("tpu")
    if torch.cuda.is_available():
        assert torch_device("0") == torch.device("cuda:0")
    else:
        with pytest.raises(backends.BackendError, match="--device 0: CUDA is not available on this machine"):
            torch_device("0")


def test_cpu_runs_the_network_one_image_at_a_time(monkeypatch, tmp_path):
    """On the CPU the network sees CPU_BATCH images per call (whatever the eval batch), and the
    detections do not depend on it."""
    detector = backends.load_detector(_saved_model(tmp_path, "yolo11n.yaml"), device="cpu")
    calls = []
    network = detector.network
    detector.network = lambda canvas: calls.append(len(canvas)) or network(canvas)
    frames = torch.from_numpy(np.stack([_frame(72, 96, seed) for seed in range(3)]))
    settings = dict(imgsz=96, conf=0.0001, iou=0.7, max_det=20)
    one_by_one = detector.predict_frames(frames, **settings)
    assert calls == [torch_batched.CPU_BATCH] * 3
    monkeypatch.setattr(torch_batched, "CPU_BATCH", 3)
    together = detector.predict_frames(frames, **settings)
    assert calls[3:] == [3]
    for a, b in zip(one_by_one, together, strict=True):
        for x, y in zip(a, b):
            np.testing.assert_allclose(x, y, atol=1e-3)


def test_inference_yields_every_rate_in_turn_even_without_frames(two_shards):
    """rainbench eval's inference over several rates gives each rate its records in the rates'
    order, one reader for them all; a dataset without frames still gives every rate (empty)."""
    from rainbench.eval.pipeline import _infer

    class Detector:  # the batched backend's interface, one fixed detection a frame
        device = torch.device("cpu")

        def predict_canvases(self, canvases, size, **_):
            assert canvases.shape[1:3] == tuple(rect_shape(*size, 64))
            return [(np.array([[1.0, 2.0, 5.0, 9.0]], np.float32), np.array([0.5], np.float32),
                     np.array([2], np.int64))] * len(canvases)

    class Bar:
        def update(self, _):
            pass

    settings = dict(batch=2, imgsz=64, conf=0.001, iou=0.7, max_det=10, bar=Bar(), classes=(0, 1, 2, 3))
    got = list(_infer(Detector(), Dataset(two_shards), [50.0, 0.0], workers=1, **settings))
    assert [rate for rate, _ in got] == [50.0, 0.0]
    assert all(sorted(r["image_id"] for r in records) == [1, 2, 3, 4, 5] for _, records in got)

    class Empty:
        images: list = []

        def close(self):
            pass

    assert list(_infer(Detector(), Empty(), [0.0, 50.0], workers=0, **settings)) == [(0.0, []), (50.0, [])]


@pytest.mark.parametrize("workers", [0, 1])
def test_a_corrupt_chunk_stops_the_reader_with_its_own_one_line_error(two_shards, tmp_path, workers):
    """A chunk that does not inflate, read by a worker process or here, raises the reader's own
    ShardFormatError naming the file, the rate row and the frame, not a worker's traceback."""
    import shutil

    import h5py

    from rainbench.store.shard import ShardFormatError

    paths = [Path(shutil.copy(path, tmp_path / path.name)) for path in two_shards]
    with h5py.File(paths[1], "r") as handle:
        offset = handle["rgb"].id.get_chunk_info_by_coord((1, 1, 0, 0, 0)).byte_offset
    with open(paths[1], "r+b") as raw:
        raw.seek(offset + 20)
        raw.write(b"\xff" * 200)
    dataset = Dataset(paths)
    message = rf"^{re.escape(str(paths[1]))}: /rgb chunk of rate row 1, frame 1 is corrupt \([^\n]*\)$"
    with pytest.raises(ShardFormatError, match=message):
        for _ in frame_batches(dataset, [0.0, 50.0], batch=2, workers=workers):
            pass


def test_frame_batches_workers_run_opencv_on_one_thread(two_shards, monkeypatch):
    """Each reader worker resizes on one OpenCV thread (the workers are the parallelism); this
    process keeps its own setting."""
    import cv2

    def threads_seen(self, key):
        rate, indices = key
        return [self.dataset.images[i].image_id for i in indices], torch.full((len(indices), 1, 1, 3),
                                                                            cv2.getNumThreads(), dtype=torch.uint8)

    monkeypatch.setattr(torch_batched._FrameChunks, "__getitem__", threads_seen)
    before = cv2.getNumThreads()
    blocks = [block for _, _, block in frame_batches(Dataset(two_shards), [0.0], batch=2, workers=1)]
    assert blocks and all((block == 1).all() for block in blocks)
    assert cv2.getNumThreads() == before


def test_letterboxed_canvases_give_the_frames_detections(tmp_path):
    """predict_canvases of the reader's letterboxed canvases gives exactly predict_frames'
    detections on the CPU (both draw the canvas with OpenCV), boxes in frame pixels; a canvas
    that is not (B, h, w, 3) uint8 is refused, naming what came."""
    detector = backends.load_detector(_saved_model(tmp_path, "yolo11n.yaml"), device="cpu")
    frames = np.stack([_frame(72, 96, seed) for seed in range(3)])
    settings = dict(conf=0.0001, iou=0.7, max_det=20)
    canvases = torch.from_numpy(np.stack([letterbox(frame, rect_shape(72, 96, 128))[0] for frame in frames]))
    assert canvases.shape == (3, 96, 128, 3)
    found = detector.predict_canvases(canvases, (72, 96), **settings)
    expected = detector.predict_frames(torch.from_numpy(frames), imgsz=128, **settings)
    assert sum(len(scores) for _, scores, _ in found) > 0
    for ours, theirs in zip(found, expected, strict=True):
        for x, y in zip(ours, theirs, strict=True):
            np.testing.assert_array_equal(x, y)
        assert (ours[0][:, [0, 2]] <= 96).all() and (ours[0][:, [1, 3]] <= 72).all()
    with pytest.raises(ValueError, match=r"canvases: expected \(B, h, w, 3\) uint8, got \(3, 96, 128, 3\) torch.float32"):
        detector.predict_canvases(canvases.float(), (72, 96), **settings)


def test_detections_come_back_to_the_host_in_one_transfer_per_kind_with_each_image_its_own():
    """_to_host gives each image its own boxes, scores and ids (an image without any too), as
    converting them one image at a time would."""
    from rainbench.eval.backends.torch_batched import _to_host

    generator = torch.Generator().manual_seed(0)
    results = [(torch.rand(count, 4, generator=generator, dtype=torch.float16), torch.rand(count, generator=generator),
                torch.randint(0, 4, (count,), generator=generator)) for count in (3, 0, 5, 1)]
    host = _to_host(results)
    assert len(host) == 4 and _to_host([]) == []
    for (boxes, scores, ids), (ours_boxes, ours_scores, ours_ids) in zip(results, host, strict=True):
        assert ours_boxes.dtype == np.float32 and ours_scores.dtype == np.float32 and ours_ids.dtype == np.int64
        np.testing.assert_array_equal(ours_boxes, boxes.float().numpy().reshape(-1, 4))
        np.testing.assert_array_equal(ours_scores, scores.float().numpy())
        np.testing.assert_array_equal(ours_ids, ids.numpy())


def test_default_read_workers_leave_a_core_to_the_network():
    from rainbench.eval.pipeline import default_read_workers

    assert [default_read_workers(cores) for cores in (1, 2, 4, 16, 64)] == [0, 1, 3, 8, 8]
