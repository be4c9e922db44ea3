"""Ending a foreground loop on SIGINT or SIGTERM, whatever SIGINT disposition was inherited.

Python turns SIGINT into KeyboardInterrupt only when SIGINT was not ignored at start-up; a process
started in the background by a non-interactive shell (a CI script, ``cmd &``) inherits it
ignored, so a loop that waits for KeyboardInterrupt never ends. The loops of ``rigctl sim up``
and ``rigctl status --watch`` install their own handlers through :func:`stop_on_signals`.
"""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator


@contextmanager
def stop_on_signals() -> Iterator[threading.Event]:
    """An Event set by SIGINT or SIGTERM while the block runs; the previous handlers are put back
    when it ends. Main thread only (Python's signal rule)."""
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h)
