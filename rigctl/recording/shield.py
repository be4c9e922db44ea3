"""Writes that a signal must not cut in half.

While ``rigctl run`` (or ``rigctl resume``, or a job of ``rigctl serve``) analyses a complete
recording, its SIGINT/SIGTERM handler (rigctl.run.runner) stops the analysis by raising an
exception from wherever the main thread is. A write of results -- /results/<name> in the
recording, the ``RECORDING.*.json`` beside it, a results-database row, report.html and its plots
-- runs inside :func:`shielded`: an interruption raised through :func:`interrupt` while it runs is
held until the write is whole, then raised. So an interrupted analysis leaves each result either
written whole or not at all (an earlier analysis' results stay as they were, or are replaced
whole).

Python runs signal handlers in the main thread only, so only the main thread's writes can be
interrupted: the count of open shielded blocks is the main thread's own. A shielded block in
another thread (the daemon's web server building a report, its log writes) runs as a plain
block and never delays, nor counts towards, the main thread's interruption.
"""
from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

_depth = 0   # open shielded blocks of the main thread
_held: list[BaseException] = []


@contextmanager
def shielded() -> Iterator[None]:
    """Run the block whole: an interruption that arrives while it runs is raised when the
    outermost shielded block ends (also when the block itself raised: the interruption wins).
    Outside the main thread: a plain block (no signal handler can interrupt that thread)."""
    global _depth
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if _depth == 0 and _held:
            exc = _held.pop()
            _held.clear()
            raise exc


def interrupt(exc: BaseException) -> None:
    """Raise ``exc`` now, or, inside a :func:`shielded` block, as soon as it ends (the first one
    held wins). For signal handlers (they run in the main thread)."""
    if _depth:
        if not _held:
            _held.append(exc)
        return
    raise exc
