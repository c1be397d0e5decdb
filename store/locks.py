"""One run at a time per output directory: an advisory lock file a command holds while it writes.

Two runs into one directory (of one command, or of two: an eval and a paper into the same
``--out`` both write ``report.md``) would remove or overwrite each other's temporaries and leave
outputs of both runs under final names; the second is refused instead, in one line. Every
command takes the same lock file, ``.rainbench.lock``, naming its pid and command in it."""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path


LOCK_NAME = ".rainbench.lock"
"""The lock file in a directory a rainbench command is writing: ``<pid> <command>``."""


@contextlib.contextmanager
def directory_lock(root: str | Path, command: str, *, option: str,
                   error: type[Exception]) -> Iterator[Path]:
    """Hold ``root/.rainbench.lock`` (``fcntl.flock``, non-blocking) for one run of ``rainbench
    <command>``; yields the lock file's path. ``root`` must exist.

    A second run on the same directory, of any command, gets ``error`` with one line naming
    ``option`` (the CLI argument that chose the directory), the directory and the holder's
    command and pid: ``--out: results is being written by another rainbench eval (pid 1234);
    wait for it to finish or choose another --out``. The kernel releases the lock when the holder exits, however it exits; a clean exit
    also removes the file (under the lock: a waiter that locked the removed file tries again).
    Failing to create, lock or write the file is ``error`` naming the file."""
    root = Path(root)
    path = root / LOCK_NAME
    for _attempt in range(100):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as failure:
            raise error(f"{option}: cannot create the lock file {path} ({failure.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").split()
            os.close(fd)
            pid = f" (pid {holder[0]})" if holder and holder[0].isdigit() else ""
            what = holder[1] if len(holder) > 1 and holder[1].isidentifier() else "command"
            raise error(f"{option}: {root} is being written by another rainbench {what}{pid}; "
                        f"wait for it to finish or choose another {option}") from None
        except FileNotFoundError:
            same = False
        except OSError as failure:
            os.close(fd)
            raise error(f"{option}: cannot lock {path} ({failure.strerror})") from None
        if same:
            break
        os.close(fd)
    else:
        raise error(f"{option}: cannot lock {path} (it keeps being replaced)")
    try:
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()} {command}".encode(), 0)
        except OSError as failure:
            raise error(f"{option}: cannot write the lock file {path} ({failure.strerror})") from None
        yield path
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        os.close(fd)


@contextlib.contextmanager
def locked_output_dir(root: str | Path, command: str, *, option: str,
                      error: type[Exception]) -> Iterator[Path]:
    """Make ``root`` (and its missing parents) and hold its :func:`directory_lock` for the block;
    yields ``root``. The folders this made are removed again when the block leaves them empty
    (a run refused or failed before writing anything leaves no empty ``--out`` behind). A file
    where ``root`` goes, or a folder that cannot be made, is ``error`` naming ``option``."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise error(f"{option}: {root} exists and is not a directory")
    created = [folder for folder in (root, *root.parents) if not folder.exists()]
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as failure:
        raise error(f"{option}: cannot create {root} ({failure.strerror})") from None
    try:
        with directory_lock(root, command, option=option, error=error):
            yield root
    finally:
        for folder in created:  # deepest first; only when empty
            with contextlib.suppress(OSError):
                folder.rmdir()
