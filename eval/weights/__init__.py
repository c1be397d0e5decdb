"""The registry of the weights shipped with rainbench, in this folder (docs/models.md).

Each shipped model ``<name>`` is ``<name>.pt`` (the ultralytics checkpoint) and ``<name>.json``
(its card: ``imgsz``, the letterbox size it is evaluated at), selectable by name
(``rainbench eval --weights <name>``, :func:`resolve_weights`). On CPU a shipped model runs as
its ONNX copy: ``<name>.onnx`` when one sits beside the checkpoint, else the copy
:func:`export_onnx` builds on first use into the user cache (:func:`cached_onnx`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.devices import runs_on_cuda
from rainbench.eval.backends import BackendError
from rainbench.eval.backends.ultralytics import _offline_ultralytics

WEIGHTS_DIR = Path(__file__).resolve().parent
"""Shipped weights, selectable by name (docs/models.md): ``<name>.pt`` (the ultralytics
checkpoint), ``<name>.onnx`` (the same network exported by :func:`export_onnx`, run on CPU) and
``<name>.json`` (the model's card: ``imgsz``, the letterbox size it is evaluated at)."""
DEFAULT_IMGSZ = 640
"""Letterbox size of models that do not declare their own (ultralytics' default)."""


def shipped_models() -> list[str]:
    """Names of the weights shipped with rainbench (``rainbench eval --weights NAME``)."""
    return sorted(p.stem for p in WEIGHTS_DIR.glob("*.pt"))


def _shipped_file(spec: str | Path, suffix: str) -> Path | None:
    """``WEIGHTS_DIR/<spec><suffix>`` when ``spec`` names a shipped model (a bare name whose
    ``.pt`` is shipped) and that file exists; else None."""
    text = str(spec)
    if Path(text).suffix != "" or not (WEIGHTS_DIR / f"{text}.pt").is_file():
        return None
    path = WEIGHTS_DIR / f"{text}{suffix}"
    return path if path.is_file() else None


def cache_dir() -> Path:
    """Where rainbench keeps files it builds on first use: ``$XDG_CACHE_HOME/rainbench``
    (default ``~/.cache/rainbench``)."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "rainbench"


def cached_onnx(checkpoint: Path) -> Path:
    """The ONNX copy of a shipped ``.pt`` that ships without one, exported by
    :func:`export_onnx` on first use into :func:`cache_dir` (named by the checkpoint's sha256, so
    a new checkpoint gets a new copy) and reused afterwards. Written under a temporary name and
    renamed, so a cut-off export never leaves a partial file."""
    import hashlib

    digest = hashlib.sha256(checkpoint.read_bytes()).hexdigest()[:16]
    path = cache_dir() / "onnx" / f"{checkpoint.stem}-{digest}.onnx"
    if path.is_file():
        return path
    try:
        export_onnx(checkpoint, path)  # written under a temporary name and renamed
    except BackendError:
        raise
    except Exception as error:  # torch/onnx export failures come as many exception types
        raise BackendError(f"--weights: {checkpoint}: could not build its ONNX copy in {path.parent} "
                           f"({type(error).__name__}: {error})") from error
    return path


def checkpoint_file(spec: str | Path) -> Path:
    """The ultralytics checkpoint of a shipped model's name (its ``.pt``) or of a local ``.pt``
    file; anything else raises :class:`BackendError` naming it."""
    shipped = _shipped_file(str(spec), ".pt")
    if shipped is not None:
        return shipped
    path = Path(spec)
    if path.suffix != ".pt" or not path.is_file():
        raise BackendError(f"{spec}: expected a shipped model name ({', '.join(shipped_models()) or 'none'}) "
                           "or an existing .pt checkpoint")
    return path


def weights_location(spec: str | Path) -> tuple[Path | None, Path, str]:
    """Where a weights spec points, without checking or building anything: (the shipped ``.pt``
    when ``spec`` is a shipped model's name, else None; the local file it names otherwise, a
    Darknet ``.cfg``'s ``.weights`` beside it; the model name: the shipped name, else that
    file's stem). :func:`resolve_weights` and ``make paper``'s up-front check share this rule."""
    text = str(spec)
    checkpoint = _shipped_file(text, ".pt")
    path = Path(text)
    if path.suffix.lower() == ".cfg":
        path = path.with_suffix(".weights")
    return checkpoint, path, text if checkpoint is not None else path.stem


IS_A_DIRECTORY = ("is a directory, not a weights file (expected an ultralytics .pt, an .onnx export or a "
                  "Darknet .cfg/.weights file, or a shipped model name)")
"""What a weights argument that names a directory is told (``eval``, and ``paper`` before it generates)."""


def resolve_weights(spec: str | Path, device: str | None = None) -> tuple[Path, str]:
    """``(file, model name)`` for a weights spec: a shipped model's name, or a local file.

    A shipped name resolves to its ONNX copy (``<name>.onnx``, run by onnxruntime: 2.3 to 2.8
    times ultralytics' speed on CPU, the same detections) unless ``device`` is a CUDA device,
    where it resolves to the ``.pt`` (the batched torch backend in fp16 on the GPU). The model
    name is the shipped name or the file stem. Darknet models resolve to their ``.weights`` file (the ``.cfg`` must sit
    beside it). Raises :class:`BackendError` for a missing file.
    """
    text = str(spec)
    if not text.strip():
        raise BackendError(f"--weights: expected a shipped model name ({', '.join(shipped_models()) or 'none'}) "
                           "or a weights file, got an empty name")
    checkpoint, path, name = weights_location(text)
    if checkpoint is not None:
        if runs_on_cuda(device, BackendError):
            return checkpoint, name
        return (_shipped_file(text, ".onnx") or cached_onnx(checkpoint)), name
    if path.is_dir():
        raise BackendError(f"--weights: {path} {IS_A_DIRECTORY}")
    if not path.is_file():
        hint = ""
        if path.suffix == "":
            hint = f"; shipped models: {', '.join(shipped_models()) or 'none'}"
        raise BackendError(f"--weights: {path} does not exist (weights are loaded from local files only{hint})")
    return path, name


def trained_classes(spec: str | Path) -> tuple[int, ...] | None:
    """The rainbench class ids a model was trained on, from its card: a shipped model's
    ``<name>.json``, or the ``.json`` beside a ``.pt`` / ``.onnx`` file (what ``rainbench train``
    writes: ``"classes": {"0": "person", "2": "car"}``); None when there is no such card (or it
    names no classes). A model trained on some classes still has outputs for the others (YOLO
    names are dense ids 0..max), and what it predicts there is noise."""
    text = str(spec)
    card = _shipped_file(text, ".json")
    if card is None and Path(text).suffix.lower() in (".pt", ".onnx"):
        card = Path(text).with_suffix(".json")
    try:
        classes = json.loads(card.read_text()).get("classes") if card is not None and card.is_file() else None
    except (OSError, ValueError, AttributeError):
        return None  # not a card: a .json of something else beside the weights
    if not (isinstance(classes, dict) and classes and all(str(key).isdigit() for key in classes)):
        return None
    return tuple(sorted(int(key) for key in classes))


def model_imgsz(spec: str | Path) -> int:
    """The letterbox size a model is evaluated at by default: its card's ``imgsz`` (a shipped
    model's ``<name>.json``, or the ``.json`` beside a ``.pt`` / ``.onnx`` file that holds an
    ``imgsz``, as ``rainbench train`` writes it), else :data:`DEFAULT_IMGSZ`. A ``.json`` beside
    the weights without ``imgsz`` (not a card) is passed over, as :func:`trained_classes` does."""
    card = _shipped_file(spec, ".json")
    if card is None and Path(str(spec)).suffix.lower() in (".pt", ".onnx"):
        beside = Path(str(spec)).with_suffix(".json")
        try:
            loaded = json.loads(beside.read_text()) if beside.is_file() else None
        except (OSError, ValueError):
            loaded = None
        card = beside if isinstance(loaded, dict) and "imgsz" in loaded else None
    if card is not None:
        try:
            imgsz = json.loads(card.read_text())["imgsz"]
        except (OSError, ValueError, KeyError, TypeError):
            raise BackendError(f"{card}: expected a JSON object with an integer `imgsz`") from None
        if not (isinstance(imgsz, int) and imgsz >= 32):
            raise BackendError(f"{card}: imgsz: expected an integer >= 32, got {imgsz!r}")
        return imgsz
    return DEFAULT_IMGSZ


def export_onnx(weights: str | Path, out: str | Path) -> Path:
    """Export an ultralytics detection checkpoint to ONNX for
    :func:`rainbench.eval.backends.load_detector`: an fp32 graph, opset 17, dynamic batch and
    image size (input ``images`` (B, 3, H, W), output ``output0`` (B, 4 + nc, N)), class names in
    the ``names`` metadata. Needs the ``onnx`` package.

    Batch norms are exported unfused, so every weight is the checkpoint's own value, and each
    float32 weight that fp16 holds exactly is stored as fp16 behind a Cast to float32
    (:func:`_store_exact_halves`): for a stripped ultralytics checkpoint (fp16 weights, as shipped)
    the file is half the size of a fused fp32 export, with nothing lost. onnxruntime folds the
    casts and fuses the batch norms when it loads the model, so it runs the same optimized graph
    as a fused fp32 export."""
    import onnx
    import torch

    ultralytics = _offline_ultralytics()
    model = ultralytics.YOLO(str(weights))
    net = model.model.float().eval()
    for module in net.modules():
        if hasattr(module, "export"):
            module.export = True
            module.format = "onnx"
        if hasattr(module, "dynamic"):
            module.dynamic = True  # anchors from the input's shape, not the traced one
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(f".{out.stem}.tmp-{os.getpid()}.onnx")  # a cut-off export never takes the name
    try:
        with torch.no_grad():
            # PRESERVE keeps the (eval-mode) batch norms as nodes instead of folding them into the
            # convolutions, which would make weights that fp16 cannot hold.
            torch.onnx.export(net, torch.zeros(1, 3, 480, 640), str(partial), dynamo=False, opset_version=17,
                              training=torch.onnx.TrainingMode.PRESERVE, do_constant_folding=False,
                              input_names=["images"], output_names=["output0"],
                              dynamic_axes={"images": {0: "batch", 2: "height", 3: "width"},
                                            "output0": {0: "batch", 2: "anchors"}})
        proto = _store_exact_halves(onnx.load(str(partial)))
        entry = proto.metadata_props.add()
        entry.key, entry.value = "names", str(model.names)
        onnx.checker.check_model(proto)
        onnx.save(proto, str(partial))
        os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
    return out


def interpolate_checkpoints(base: str | Path, fine_tuned: str | Path, alpha: float,
                            out: str | Path) -> Path:
    """Write ``out``, an ultralytics checkpoint whose weights are ``(1 - alpha) x base + alpha x
    fine_tuned`` (WiSE-FT, Wortsman et al. 2022: a fine-tuned model interpolated in weight
    space with the model it started from): every floating-point tensor of the state dict,
    batch-norm running statistics included, is interpolated in float32 and stored in fp16 as
    shipped checkpoints are; integer tensors are ``fine_tuned``'s. Everything else (class names,
    training arguments) is ``fine_tuned``'s, and ``interpolated`` records the two files' names
    and ``alpha``.

    Both files are read with Python's full unpickler (``torch.load(weights_only=False)``), which
    runs code from the file: unlike ``rainbench eval``'s safe loading (:mod:`rainbench.eval.backends`),
    nothing is refused here, so pass only files you would run as code.

    Args:
        base, fine_tuned: shipped model names or ``.pt`` checkpoints of one architecture
            (``fine_tuned`` trained from ``base``: the interpolation is meaningless otherwise).
        alpha: 0 gives ``base``, 1 ``fine_tuned``; in [0, 1].
        out: the ``.pt`` to write (written under a temporary name and renamed).

    Raises:
        BackendError: one line, for an alpha outside [0, 1], a file that is not a checkpoint, or
        two checkpoints whose tensors differ in names or shapes.
    """
    import copy

    import torch

    if not 0.0 <= float(alpha) <= 1.0:
        raise BackendError(f"alpha: expected a number in [0, 1], got {alpha!r}")
    checkpoints = []
    for spec in (base, fine_tuned):
        path = checkpoint_file(spec)
        try:
            checkpoint = torch.load(path, map_location="cpu", weights_only=False)
            state = checkpoint["model"].float().state_dict()
        except Exception as error:  # unpickling failures come as many exception types
            raise BackendError(f"{path}: expected an ultralytics checkpoint with a 'model' "
                               f"({type(error).__name__}: {error})") from None
        checkpoints.append((path, checkpoint, state))
    (base_path, _, base_state), (tuned_path, tuned, tuned_state) = checkpoints
    differ = sorted(set(base_state) ^ set(tuned_state)) or sorted(
        name for name in tuned_state if base_state[name].shape != tuned_state[name].shape)
    if differ:
        raise BackendError(f"{tuned_path}: its tensors differ from {base_path}'s (first: "
                           f"{differ[0]}); expected a fine-tune of the same architecture")
    mixed = {name: ((1.0 - alpha) * base_state[name] + alpha * value)
             if value.is_floating_point() else value for name, value in tuned_state.items()}
    model = copy.deepcopy(tuned["model"]).float()
    model.load_state_dict(mixed)
    checkpoint = dict(tuned, model=model.half(), ema=None, optimizer=None,
                      interpolated={"base": base_path.name, "fine_tuned": tuned_path.name,
                                    "alpha": float(alpha)})
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        torch.save(checkpoint, partial)
        os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
    return out


def _store_exact_halves(proto: Any) -> Any:
    """Return ``proto`` (an ``onnx.ModelProto``, changed in place) with each float32 initializer
    whose every value fp16 represents exactly stored as fp16, feeding a Cast back to float32 under
    the original name. The graph computes bit for bit what it did; other initializers are kept."""
    import onnx
    from onnx import numpy_helper

    graph = proto.graph
    casts = []
    for initializer in list(graph.initializer):
        values = numpy_helper.to_array(initializer)
        if values.dtype != np.float32 or values.size == 0:
            continue
        halves = values.astype(np.float16)
        if not np.array_equal(halves.astype(np.float32), values):
            continue
        stored = numpy_helper.from_array(halves, f"{initializer.name}__fp16")
        graph.initializer.remove(initializer)
        graph.initializer.append(stored)
        casts.append(onnx.helper.make_node("Cast", [stored.name], [initializer.name], to=onnx.TensorProto.FLOAT,
                                           name=f"{initializer.name}__cast"))
    nodes = casts + list(graph.node)
    del graph.node[:]
    graph.node.extend(nodes)
    return proto
