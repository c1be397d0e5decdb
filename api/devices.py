"""What a ``--device`` value names, read one way by every command (``generate``, ``eval``,
``train``, ``paper``) and every backend (torch, ONNX Runtime, the per-rate statistics).

:func:`parse_device` is pure: it asks nothing of the machine; each caller checks the device it
got against the machine (and says so in its own one-line error). :func:`runs_on_cuda` asks torch
only for the default.
"""

from __future__ import annotations

DEVICE_FORMS = "auto, cpu, cuda, cuda:N or CUDA indices (0 or 0,1)"
"""The ``--device`` values :func:`parse_device` accepts, as its error message lists them."""


def parse_device(device: object, error: type[Exception] = ValueError
                 ) -> tuple[str, tuple[int, ...]] | None:
    """``(kind, cuda_indices)`` of a ``--device`` value, any case, spaces around it ignored:

    - None, ``""`` or ``"auto"``: None (the caller's default device);
    - ``"cpu"``: ``("cpu", ())``;
    - ``"cuda"``: ``("cuda", ())`` (the current CUDA device, index 0 unless CUDA says otherwise);
    - ``"cuda:N"`` or CUDA indices as ultralytics takes them (``"0"``, ``"0,1"``, ``"cuda:0,1"``):
      ``("cuda", (N, ...))``; a caller that runs on one device uses the first.

    Anything else raises ``error`` (a one-line message naming ``--device`` and the value).
    """
    text = "" if device is None else str(device).strip().lower()
    if text in ("", "auto"):
        return None
    if text in ("cpu", "cuda"):
        return text, ()
    listed = text.removeprefix("cuda:")
    indices = [part.strip() for part in listed.split(",")]
    if not all(index.isdigit() and index.isascii() for index in indices):
        raise error(f"--device: expected {DEVICE_FORMS}, got {device!r}")
    return "cuda", tuple(int(index) for index in indices)


def runs_on_cuda(device: object, error: type[Exception] = ValueError) -> bool:
    """Whether work on ``--device`` ``device`` runs on CUDA: a CUDA device named, or the default
    (None, ``""``, ``"auto"``) where torch sees a CUDA GPU. A value :func:`parse_device` refuses
    raises ``error``."""
    parsed = parse_device(device, error)
    if parsed is None:
        import torch  # noqa: PLC0415 -- only for the default

        return torch.cuda.is_available()
    return parsed[0] == "cuda"


def ultralytics_device(device: object, error: type[Exception] = ValueError) -> str | None:
    """``--device`` as ultralytics' ``predict`` / ``train`` ``device=`` takes it: None (its own
    default, CUDA 0 when present) for None, ``""`` and ``"auto"``, which ultralytics' parser
    refuses; ``"cpu"``; CUDA indices comma-joined (``"cuda"`` -> ``"0"``, ``"cuda:1"`` -> ``"1"``,
    ``"0,1"``). A value :func:`parse_device` refuses raises ``error``."""
    parsed = parse_device(device, error)
    if parsed is None:
        return None
    kind, indices = parsed
    if kind == "cpu":
        return "cpu"
    return ",".join(str(index) for index in indices or (0,))
