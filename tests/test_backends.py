"""Detector backends: letterbox maths, ONNX (v5 and v8 layouts) and Darknet on models built here,
shipped weights by name, and one-line errors. No file is downloaded."""

import json
import struct
import warnings

import numpy as np
import pytest

from rainbench.eval import backends
from rainbench.eval.backends import BackendError
from rainbench.eval import weights as registry
from rainbench.eval.backends.darknet import decode_darknet
from rainbench.eval.backends.letterbox import LETTERBOX_FILL, letterbox, rect_shape, unletterbox
from rainbench.eval.backends.ultralytics import _offline_ultralytics
from conftest import assert_same_detections

# Import torch's lazy modules before anything renders in this process (see test_eval_pipeline).
_offline_ultralytics()
import onnx  # noqa: E402
import torch  # noqa: E402
import torch._dynamo  # noqa: E402,F401

# Boxes of the synthetic case, xyxy in the original 800x600 image, with their class and score.
ORIGINAL_BOXES = np.array([[100, 50, 300, 250], [400.5, 300, 520, 590], [10, 20, 30, 60]], np.float32)
CLASS_OF_BOX = [2, 0, 3]  # car, person, motorcycle (model class index = COCO index here)
SCORE_OF_BOX = [0.9, 0.8, 0.6]


class ConstantHead(torch.nn.Module):
    """A 'detector' whose raw output is a fixed tensor (plus 0 x input, so the graph uses it)."""

    def __init__(self, output: np.ndarray):
        super().__init__()
        self.register_buffer("output", torch.from_numpy(output.astype(np.float32)))

    def forward(self, images):
        return self.output.expand(images.shape[0], *self.output.shape) + 0 * images.mean()


def _head_rows(gain, pad, nc, objectness, anchors=200):
    """The synthetic boxes as rows cx, cy, w, h (canvas pixels), [objectness], class scores,
    then empty rows up to ``anchors`` (real heads have thousands of anchors)."""
    rows = []
    for box, class_id, score in zip(ORIGINAL_BOXES, CLASS_OF_BOX, SCORE_OF_BOX):
        x0, y0, x1, y1 = box * gain + np.array([pad[0], pad[1], pad[0], pad[1]])
        classes = np.zeros(nc, np.float32)
        classes[class_id] = score / 0.5 if objectness else score
        classes[(class_id + 1) % nc] = 0.05  # a weaker second class: not reported (best class only)
        head = [(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0] + ([0.5] if objectness else [])
        rows.append(np.concatenate([head, classes]))
    rows += [np.full(len(rows[0]), 1.0, np.float32) * (np.arange(len(rows[0])) < 4)] * (anchors - len(rows))
    return np.array(rows, np.float32)


def _export(module, path, size, dynamic, names=None, anchors_axis=2):
    kwargs = {}
    if dynamic:  # ultralytics' exporter: symbolic batch, image size and anchor count
        kwargs["dynamic_axes"] = {"images": {0: "batch", 2: "height", 3: "width"},
                                  "output0": {0: "batch", anchors_axis: "anchors"}}
    torch.onnx.export(module, torch.zeros(1, 3, *size), str(path), dynamo=False, opset_version=17,
                      input_names=["images"], output_names=["output0"], **kwargs)
    if names is not None:  # what ultralytics' exporter writes
        model = onnx.load(str(path))
        entry = model.metadata_props.add()
        entry.key, entry.value = "names", str(dict(enumerate(names)))
        onnx.save(model, str(path))
    return path


def _image():
    return np.random.default_rng(0).integers(0, 255, (600, 800, 3), dtype=np.uint8)


def test_letterbox_maps_points_exactly():
    image = _image()
    canvas, gain, pad = letterbox(image, (640, 640))
    assert canvas.shape == (640, 640, 3) and gain == pytest.approx(0.8) and pad == (0.0, 80.0)
    assert (canvas[:80] == LETTERBOX_FILL).all() and (canvas[560:] == LETTERBOX_FILL).all()
    assert rect_shape(600, 800, 640) == (480, 640)
    assert rect_shape(72, 96, 96) == (96, 96)
    moved = ORIGINAL_BOXES * gain + np.array([0, 80, 0, 80], np.float32)
    np.testing.assert_allclose(unletterbox(moved, gain, pad, 800, 600), ORIGINAL_BOXES, atol=1e-4)
    # Clipping to the original image.
    assert unletterbox(np.array([[-10, 0, 700, 700]]), gain, pad, 800, 600).tolist() == [[0, 0, 800, 600]]


@pytest.mark.parametrize("layout,dynamic", [("v8", True), ("v8", False), ("v5", True), ("v5", False)])
def test_onnx_boxes_back_in_the_original_frame(tmp_path, layout, dynamic):
    nc = 80
    shape = (480, 640) if dynamic else (640, 640)
    gain, pad = 0.8, ((0.0, 0.0) if dynamic else (0.0, 80.0))
    rows = _head_rows(gain, pad, nc, objectness=layout == "v5")
    output = rows.T if layout == "v8" else rows
    path = _export(ConstantHead(output), tmp_path / f"const_{layout}.onnx", shape, dynamic,
                   anchors_axis=2 if layout == "v8" else 1)
    detector = backends.load_detector(path)
    assert detector.name == f"const_{layout}" and detector.layout == layout
    (boxes, scores, ids), (boxes2, _, _) = detector.predict([_image(), _image()], imgsz=640, conf=0.25,
                                                            iou=0.7, max_det=300)
    # COCO-80 without names metadata: ids 0..3 kept; the weak second classes fall under conf.
    order = np.argsort(-scores)
    np.testing.assert_allclose(boxes[order], ORIGINAL_BOXES, atol=1e-3)
    np.testing.assert_allclose(scores[order], SCORE_OF_BOX, atol=1e-6)
    assert ids[order].tolist() == CLASS_OF_BOX
    np.testing.assert_array_equal(boxes, boxes2)
    # max_det and the confidence floor.
    boxes, scores, _ = detector.predict([_image()], imgsz=640, conf=0.7, iou=0.7, max_det=1)[0]
    assert scores.tolist() == pytest.approx([0.9])
    if not dynamic:
        with pytest.raises(backends.BackendError, match="fixed 640x640 input; pass --imgsz 640"):
            detector.predict([_image()], imgsz=320, conf=0.25, iou=0.7, max_det=300)


def test_an_onnx_model_on_a_cuda_device_is_refused_without_the_cuda_provider(tmp_path, monkeypatch):
    """``--device cuda`` ran an explicit .onnx on the CPU without a word (the CPU wheel has no CUDA
    provider), and ``cuda:1`` would have run on GPU 0."""
    import onnxruntime  # noqa: PLC0415
    path = _export(ConstantHead(_head_rows(1.0, (0.0, 0.0), 80, objectness=False).T), tmp_path / "m.onnx",
                   (640, 640), True)
    assert "CUDAExecutionProvider" not in onnxruntime.get_available_providers()  # the CPU wheel here
    for device in ("cuda", "cuda:1", "0"):
        with pytest.raises(backends.BackendError, match=rf"^--device {device}: .*m\.onnx is an ONNX model and "
                                                        r"this onnxruntime has no CUDA provider"):
            backends.load_detector(path, device=device)
    assert backends.load_detector(path, device="cpu").name == "m"
    assert backends.load_detector(path, device=" CPU ").name == "m"  # any case, as --device is read
    # where the provider exists, the device's index reaches it
    seen = []
    monkeypatch.setattr(onnxruntime, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    real = onnxruntime.InferenceSession
    monkeypatch.setattr(onnxruntime, "InferenceSession", lambda model, options, providers: (
        seen.append(providers), real(model, options, providers=["CPUExecutionProvider"]))[1])
    backends.load_detector(path, device="cuda:1")
    assert seen == [[("CUDAExecutionProvider", {"device_id": 1}), "CPUExecutionProvider"]]


def test_onnx_names_metadata_and_class_map(tmp_path):
    names = ["pedestrian", "auto", "bike", "truck"]
    rows = _head_rows(1.0, (0.0, 0.0), 4, objectness=False)
    rows[:, 4:] = 0
    rows[0, 4 + 1], rows[1, 4 + 0], rows[2, 4 + 2] = 0.9, 0.8, 0.6  # auto, pedestrian, bike
    path = _export(ConstantHead(rows.T), tmp_path / "custom.onnx", (608, 800), True, names=names)
    with pytest.raises(backends.BackendError, match="not COCO-80; pass --class-map"):
        backends.load_detector(path)
    detector = backends.load_detector(path, class_map="auto=2,pedestrian=0")
    boxes, scores, ids = detector.predict([_image()], imgsz=800, conf=0.1, iou=0.7, max_det=300)[0]
    order = np.argsort(ids)
    assert ids[order].tolist() == [0, 2]  # bike dropped
    np.testing.assert_allclose(scores[order], [0.8, 0.9], atol=1e-6)


def test_a_models_card_limits_it_to_the_classes_it_was_trained_on(tmp_path):
    """`rainbench train` with classes [person, car] writes a model whose YOLO names are the dense
    ids 0..3 (person, bicycle, car, motorcycle) and a card naming person and car: `eval --classes bicycle`
    scored its untrained output; now the card says what it predicts."""
    rows = _head_rows(1.0, (0.0, 0.0), 4, objectness=False)
    rows[:, 4:] = 0
    rows[0, 4 + 1], rows[1, 4 + 0], rows[2, 4 + 2] = 0.9, 0.8, 0.6  # bicycle, person, car
    path = _export(ConstantHead(rows.T), tmp_path / "subset.onnx", (608, 800), True,
                   names=["person", "bicycle", "car", "motorcycle"])
    assert backends.model_classes(backends.load_detector(path)) == (0, 1, 2, 3)  # no card: every output
    (tmp_path / "subset.json").write_text(json.dumps({"imgsz": 640, "classes": {"0": "person", "2": "car"}}))
    assert registry.trained_classes(path) == (0, 2) and registry.trained_classes(tmp_path / "subset.pt") == (0, 2)
    detector = backends.load_detector(path)
    assert backends.model_classes(detector) == (0, 2)
    _, _, ids = detector.predict([_image()], imgsz=800, conf=0.1, iou=0.7, max_det=300)[0]
    assert sorted(ids.tolist()) == [0, 2]  # the untrained bicycle output is dropped
    with pytest.raises(backends.BackendError, match=r"^--classes: model 'subset' cannot predict 'bicycle' \(class 1\); "
                       r"it predicts person, car$"):
        backends.check_model_classes(detector, "subset", [1])
    (tmp_path / "subset.json").write_text("[1, 2]")  # a JSON file that is not a card: ignored
    assert registry.trained_classes(path) is None
    assert registry.trained_classes("rainbench-yolo11n") == (0, 1, 2, 3, 5, 7)


def test_onnx_export_of_an_ultralytics_model_matches_its_checkpoint(tmp_path):
    """The same random-weights yolo11n through .pt and through ONNX: the same detections."""
    from ultralytics import YOLO
    from ultralytics.nn.tasks import DetectionModel

    torch.manual_seed(0)  # the initial weights too: the same network every run
    model = YOLO("yolo11n.yaml")
    model.model = DetectionModel("yolo11n.yaml", nc=4, verbose=False)  # rainbench's four classes
    names = ["person", "bicycle", "car", "motorcycle"]
    model.model.names = dict(enumerate(names))
    with torch.no_grad():  # varied, non-trivial scores instead of the initial constant ones
        for parameter in model.model.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
        for branch in model.model.model[-1].cv3:
            branch[-1].bias.add_(6.0)
        for name, buffer in model.model.named_buffers():  # batch-norm statistics of a trained net
            if name.endswith("running_mean"):
                buffer.add_(0.1 * torch.randn_like(buffer))
            elif name.endswith("running_var"):
                buffer.mul_(torch.exp(0.2 * torch.randn_like(buffer)))
        for tensor in [*model.model.parameters(), *model.model.buffers()]:
            if tensor.is_floating_point():  # fp16 values, as in a stripped (shipped) checkpoint
                tensor.copy_(tensor.half().float())
    pt_path = tmp_path / "net.pt"
    model.save(str(pt_path))
    onnx_path = registry.export_onnx(pt_path, tmp_path / "net.onnx")  # traced at 640x480
    # Batch norms unfused, so every weight is stored as the checkpoint's fp16 value.
    proto = onnx.load(str(onnx_path))
    stored = {init.name: onnx.numpy_helper.to_array(init) for init in proto.graph.initializer}
    weights = [*model.model.parameters(), *(b for b in model.model.buffers() if b.is_floating_point())]
    assert sum(v.size for v in stored.values() if v.dtype == np.float16) == sum(w.numel() for w in weights)
    assert not [name for name, v in stored.items() if v.dtype == np.float32 and v.size > 1]
    assert "BatchNormalization" in {node.op_type for node in proto.graph.node}
    image = np.ascontiguousarray(np.random.default_rng(1).integers(0, 255, (600, 800, 3), dtype=np.uint8))
    # A random network's scores nearly tie (1e-7 apart), and which of two overlapping near-tied
    # boxes NMS keeps then depends on rounding; with NMS almost off this compares decoding and the
    # letterbox (NMS itself is checked on the synthetic heads above). 960 px checks that the
    # anchors follow the input size rather than the traced one.
    pt_detector = backends.load_detector(pt_path, device="cpu", pt_backend="ultralytics")
    onnx_detector = backends.load_detector(onnx_path)
    assert onnx_detector.names == dict(enumerate(names))
    for imgsz in (640, 960):
        settings = dict(imgsz=imgsz, conf=0.001, iou=0.99, max_det=300)
        assert_same_detections(pt_detector.predict([image], **settings)[0],
                               onnx_detector.predict([image], **settings)[0])


def test_store_exact_halves_keeps_the_graph_bit_exact():
    """Y = X @ W + B with W exact in fp16 and B not: W is stored as fp16 behind a Cast, B stays
    fp32, and onnxruntime computes the same bytes as before."""
    import onnxruntime

    from onnx import TensorProto, helper, numpy_helper

    weight = np.array([[0.5, -2.0, 3.0], [1.25, 65504.0, -0.0009765625]], np.float32)  # all fp16
    bias = np.array([0.1, 0.2, 1 / 3], np.float32)  # none fp16
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["x", "w"], ["xw"]), helper.make_node("Add", ["xw", "b"], ["y"])], "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3])],
        [numpy_helper.from_array(weight, "w"), numpy_helper.from_array(bias, "b")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    x = np.array([[0.7, -1.3]], np.float32)

    def run(proto):
        session = onnxruntime.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
        return session.run(None, {"x": x})[0]

    before = run(model)
    halved = registry._store_exact_halves(model)
    onnx.checker.check_model(halved)
    stored = {init.name: numpy_helper.to_array(init) for init in halved.graph.initializer}
    assert stored.keys() == {"w__fp16", "b"}
    assert stored["w__fp16"].dtype == np.float16 and stored["b"].dtype == np.float32
    assert [(n.op_type, list(n.input), list(n.output)) for n in halved.graph.node][0] == ("Cast", ["w__fp16"], ["w"])
    assert run(halved).tobytes() == before.tobytes()


def _darknet_files(folder, classes=4, width=64, height=64):
    """A tiny Darknet YOLO network (one conv, one [yolo] head) with random weights."""
    filters = 3 * (5 + classes)
    cfg = folder / "tiny.cfg"
    cfg.write_text(f"""[net]
batch=1
width={width}
height={height}
channels=3

[convolutional]
batch_normalize=0
filters=8
size=3
stride=2
pad=1
activation=leaky

[convolutional]
filters={filters}
size=1
stride=1
pad=1
activation=linear

[yolo]
mask=0,1,2
anchors=10,14, 23,27, 37,58
classes={classes}
num=3
""")
    rng = np.random.default_rng(0)
    count = (8 + 8 * 3 * 3 * 3) + (filters + filters * 8)
    weights = folder / "tiny.weights"
    weights.write_bytes(struct.pack("<iiiq", 0, 2, 0, 0) + (rng.normal(0, 0.1, count)).astype("<f4").tobytes())
    return cfg, weights


def test_darknet_backend_runs_through_opencv(tmp_path):
    cfg, weights = _darknet_files(tmp_path, classes=4)
    with pytest.raises(backends.BackendError, match="not COCO-80; pass --class-map"):
        backends.load_detector(weights)
    detector = backends.load_detector(cfg, class_map="0=0,1=1,2=2,3=3")  # the cfg resolves to its .weights
    assert detector.name == "tiny" and detector.input_size == (64, 64)
    outputs = detector.predict([_image(), _image()[:300]], imgsz=640, conf=0.0, iou=0.7, max_det=20)
    for (boxes, scores, ids), (height, width) in zip(outputs, [(600, 800), (300, 800)]):
        assert boxes.dtype == np.float32 and boxes.shape == (len(scores), 4) and 0 < len(boxes) <= 20
        assert set(ids.tolist()) <= {0, 1, 2, 3}
        assert (boxes[:, 0] >= 0).all() and (boxes[:, 2] <= width).all() and (boxes[:, 3] <= height).all()


def test_darknet_decode_is_exact():
    rows = np.array([[0.5, 0.25, 0.1, 0.2, 0.9, 0.1, 0.7]], np.float32)
    boxes, scores = decode_darknet(rows, (416, 608))
    np.testing.assert_allclose(boxes, [[0.45 * 608, 0.15 * 416, 0.55 * 608, 0.35 * 416]], rtol=1e-6)
    np.testing.assert_allclose(scores, [[0.1, 0.7]])


def test_weights_errors_are_one_line(tmp_path):
    with pytest.raises(backends.BackendError, match=r"nope\.onnx does not exist"):
        backends.load_detector(tmp_path / "nope.onnx")
    with pytest.raises(backends.BackendError, match="does not exist .*shipped models"):
        backends.load_detector("no-such-model")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(backends.BackendError, match=r"bad\.onnx is not a loadable ONNX model"):
        backends.load_detector(bad)
    lonely = tmp_path / "lonely.weights"
    lonely.write_bytes(b"\0" * 20)
    with pytest.raises(backends.BackendError, match=r"lonely\.cfg must sit beside"):
        backends.load_detector(lonely)
    cfg, weights = _darknet_files(tmp_path)
    weights.write_bytes(weights.read_bytes()[:40])  # truncated
    with pytest.raises(backends.BackendError, match=r"tiny\.weights does not load with tiny\.cfg"):
        backends.load_detector(weights, class_map="0=0")
    other = tmp_path / "model.tflite"
    other.write_bytes(b"x")
    with pytest.raises(backends.BackendError, match="unsupported format '.tflite'"):
        backends.load_detector(other)


def test_shipped_names_resolve_by_device_and_carry_their_imgsz(tmp_path, monkeypatch):
    monkeypatch.setattr(registry, "WEIGHTS_DIR", tmp_path)
    (tmp_path / "m.pt").write_bytes(b"pt")
    # Without a shipped ONNX copy, CPU runs the copy built on first use (cached_onnx); CUDA the
    # checkpoint; without a card, 640.
    monkeypatch.setattr(registry, "cached_onnx", lambda checkpoint: tmp_path / f"{checkpoint.stem}-cache.onnx")
    assert registry.resolve_weights("m", "cpu") == (tmp_path / "m-cache.onnx", "m")
    assert registry.resolve_weights("m", "cuda:0") == (tmp_path / "m.pt", "m")
    assert registry.model_imgsz("m") == registry.DEFAULT_IMGSZ == 640
    (tmp_path / "m.onnx").write_bytes(b"onnx")
    (tmp_path / "m.json").write_text('{"imgsz": 960}')
    assert registry.resolve_weights("m", "cpu") == (tmp_path / "m.onnx", "m")
    assert registry.resolve_weights("m", "0") == (tmp_path / "m.pt", "m")
    assert registry.resolve_weights("m", "cuda:0") == (tmp_path / "m.pt", "m")
    assert registry.resolve_weights("m", None)[0].suffix == (".pt" if torch.cuda.is_available() else ".onnx")
    assert registry.model_imgsz("m") == 960
    # Weights given by path take the card beside them (what `rainbench train` writes): a trained
    # model was evaluated at 640 by path and at its card's 960 by name, 3-12 AP points apart.
    assert registry.model_imgsz(tmp_path / "m.pt") == 960
    assert registry.model_imgsz(str(tmp_path / "m.onnx")) == 960
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    assert registry.model_imgsz(elsewhere / "m.pt") == 640  # no card beside it
    (elsewhere / "m.json").write_text('{"notes": "not a card"}')
    assert registry.model_imgsz(elsewhere / "m.pt") == 640  # a .json that is not a card
    (elsewhere / "m.json").write_text('{"imgsz": 8}')
    with pytest.raises(backends.BackendError, match=r"elsewhere/m\.json: imgsz: expected an integer >= 32, got 8"):
        registry.model_imgsz(elsewhere / "m.pt")
    assert registry.model_imgsz("other") == 640
    (tmp_path / "m.json").write_text('{"imgsz": "big"}')
    with pytest.raises(backends.BackendError, match=r"m\.json: imgsz: expected an integer >= 32, got 'big'"):
        registry.model_imgsz("m")
    (tmp_path / "m.json").write_text("[]")
    with pytest.raises(backends.BackendError, match=r"m\.json: expected a JSON object with an integer `imgsz`"):
        registry.model_imgsz("m")


def test_onnx_and_darknet_backends_through_run_eval_on_a_tiny_shard(tmp_path):
    from rainbench.eval import pipeline
    from rainbench.gen.config import GenerateConfig
    from rainbench.gen.generate import generate_shard

    data = tmp_path / "data"
    generate_shard(GenerateConfig(frames=2, width=96, height=72, rates=(0.0, 50.0)), data)
    # Boxes scaled into the 96x72 frame, on its 96x96 canvas (12 px of padding above).
    rows = _head_rows(96 / 800, (0.0, 12.0), 4, objectness=True)
    onnx_path = _export(ConstantHead(rows), tmp_path / "const.onnx", (96, 96), True, anchors_axis=1)
    _cfg, darknet_weights = _darknet_files(tmp_path, classes=4)
    # Neither model has class names: their class indices are mapped (one map for both models).
    result = pipeline.run_eval(data, tmp_path / "out", weights=[onnx_path, darknet_weights], imgsz=96,
                               n_boot=3, class_map="0=0,1=1,2=2,3=3", progress=False)
    assert {r["model"] for r in result.records} == {"const", "tiny"}
    assert sorted({r["rate"] for r in result.records}) == [0.0, 50.0]
    for model in ("const", "tiny"):
        for rate in ("0", "50"):
            detections = json.loads((tmp_path / "out" / "predictions" / model / f"rate_{rate}.json").read_text())
            assert detections and {d["category_id"] for d in detections} <= {0, 1, 2, 3}
            assert {d["image_id"] for d in detections} <= {1, 2}
    const = json.loads((tmp_path / "out" / "predictions" / "const" / "rate_0.json").read_text())
    car = next(d for d in const if d["category_id"] == 2)
    np.testing.assert_allclose(car["bbox"], [12, 6, 24, 24], atol=1e-3)  # (100, 50, 300, 250) x 0.12


def test_onnx_on_the_cpu_runs_small_batches(tmp_path, monkeypatch):
    """onnxruntime on the CPU gets at most CPU_BATCH images per call (faster than the eval's 32);
    the detections do not depend on it."""
    from rainbench.eval.backends import onnx as onnx_backend

    rows = _head_rows(0.8, (0.0, 0.0), 80, objectness=False)
    path = _export(ConstantHead(rows.T), tmp_path / "const.onnx", (480, 640), True)
    detector = backends.load_detector(path)
    sizes = []

    class CountingSession:  # the real session, with the images of each call counted
        def __init__(self, session):
            self.session = session

        def __getattr__(self, name):
            return getattr(self.session, name)

        def run(self, outputs, feeds):
            sizes.append(len(next(iter(feeds.values()))))
            return self.session.run(outputs, feeds)

    detector.session = CountingSession(detector.session)
    images = [_image()] * 6
    settings = dict(imgsz=640, conf=0.25, iou=0.7, max_det=300)
    small = detector.predict(images, **settings)
    assert sizes == [onnx_backend.CPU_BATCH, 6 - onnx_backend.CPU_BATCH] and onnx_backend.CPU_BATCH == 4
    monkeypatch.setattr(onnx_backend, "CPU_BATCH", 6)
    whole = detector.predict(images, **settings)
    assert sizes[2:] == [6]
    for a, b in zip(small, whole, strict=True):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("value, message", [
    (1e30, r"--weights huge\.onnx: its scores span 0 to 1e\+30; expected probabilities in \[0, 1\] "
           r"\(an export with its sigmoid, as ultralytics writes\)"),
    (float("nan"), r"--weights huge\.onnx: its output holds inf or nan; expected a YOLO detection "
                   r"head's finite boxes and scores"),
])
def test_a_head_no_working_detector_gives_is_refused_quietly(tmp_path, value, message):
    """A broken export (scores of 1e30, or nan) is one error naming the file, not numpy's
    overflow warnings followed by nonsense detections."""
    rows = _head_rows(0.8, (0.0, 0.0), 80, objectness=False)
    rows[:3, 4:] = np.where(rows[:3, 4:] > 0, value, 0.0)
    detector = backends.load_detector(_export(ConstantHead(rows.T), tmp_path / "huge.onnx",
                                              (480, 640), True))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning on the way
        with pytest.raises(BackendError, match="^" + message + "$"):
            detector.predict([_image()], imgsz=640, conf=0.25, iou=0.7, max_det=300)
