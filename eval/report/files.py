"""Errors of report files that name the file: ``PATH: No space left on device`` in one line
rather than ``[Errno 28] No space left on device``, which names none."""

from __future__ import annotations

from pathlib import Path


def file_error(error: OSError, path: str | Path) -> OSError:
    """A one-line OSError ``PATH: <reason>`` for ``error`` raised while writing ``path`` (its
    ``errno`` kept; a message that already starts with the path is kept as it is)."""
    path = str(path)
    detail = error.strerror or " ".join(str(error).split()) or type(error).__name__
    message = detail if detail.startswith(f"{path}: ") else f"{path}: {detail}"
    named = OSError(message)
    named.errno = error.errno
    return named
