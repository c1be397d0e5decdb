"""Holding off Ctrl-C and termination signals while a short section must finish: a stopped run's
cleanup, an export's swap into place or its rollback."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator, Sequence

TERMINATING_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
"""What a job scheduler (or ``kill``) and a closed terminal send."""

STOP_SIGNALS = (signal.SIGINT, *TERMINATING_SIGNALS)
"""Ctrl-C and :data:`TERMINATING_SIGNALS`."""


@contextlib.contextmanager
def signals_held(signals: Sequence[int] = STOP_SIGNALS) -> Iterator[None]:
    """Ignore ``signals`` inside the block and restore their handlers after it (a second Ctrl-C
    cut a cleanup short with a traceback). Only the main thread can set handlers: elsewhere the
    block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.getsignal(signum) for signum in signals}
    for signum in signals:
        signal.signal(signum, signal.SIG_IGN)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
