"""Writing image files: encoded in memory, then written by Python, so a failure (a full disk, a
folder that is gone) is one OSError naming the file and libpng prints nothing of its own."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np


def write_image(path: str | Path, rgb: np.ndarray, params: Sequence[int] = ()) -> Path:
    """Write an image file in the format of ``path``'s suffix (``.png``: lossless; ``.jpg``:
    OpenCV's ``params``, e.g. ``[cv2.IMWRITE_JPEG_QUALITY, 95]``); the bytes are those
    ``cv2.imwrite`` writes.

    Args:
        path: file to write (its folder must exist).
        rgb: (H, W, 3) uint8, channels R, G, B.
        params: OpenCV encoder parameters.

    Returns:
        ``path``.

    Raises:
        OSError: one line, ``PATH: <reason>``, when the image cannot be encoded or written.
    """
    path = Path(path)
    try:
        encoded, data = cv2.imencode(path.suffix, np.ascontiguousarray(rgb[:, :, ::-1]), list(params))
    except cv2.error as error:
        raise OSError(f"{path}: could not encode the image ({' '.join(str(error).split())[-160:]})") from None
    if not encoded:
        raise OSError(f"{path}: could not encode the image")
    try:
        path.write_bytes(data.tobytes())
    except OSError as error:
        raise file_error(error, path) from error
    return path


_HDF5_SYSTEM_ERROR = re.compile(r"errno = (\d+), error message = '([^']*)'")
"""HDF5's report of a failed system call (h5py raises it as one long message naming the
temporary file, a buffer address and offsets): its errno and reason."""


def file_error(error: OSError, path: str | Path) -> OSError:
    """A one-line OSError ``PATH: <reason>`` for ``error`` raised while writing ``path``
    (``No space left on device`` rather than ``[Errno 28] ...``, which names no file, or
    HDF5's 300-character report of the failed write); its ``errno`` is kept, and a message that
    already starts with the path is kept as it is."""
    path = str(path)
    detail = error.strerror or " ".join(str(error).split()) or type(error).__name__
    errno = error.errno
    system = _HDF5_SYSTEM_ERROR.search(detail)
    if system:
        errno, detail = int(system.group(1)), system.group(2)
    named = OSError(detail if detail.startswith(f"{path}: ") else f"{path}: {detail}")
    named.errno = errno
    return named
