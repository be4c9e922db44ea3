"""The console is not the run: standard output and error that survive their reader.

A run left overnight from a terminal or over SSH outlives its console: the reader of a pipe
exits (``rigctl run ... | head``), the SSH session or the terminal closes (the pty goes away:
writes fail with EIO, the kernel sends SIGHUP), or the operator hangs up. None of that may change
the run. :class:`ConsoleStream` wraps a text stream; the first write or flush that fails because
the reader went away (EPIPE, EIO, ENXIO, a closed file) *detaches* it: that write and every
later one are dropped, the listeners registered with :func:`on_lost` are told once (the runner
writes it into the run log, where every message goes anyway), and the process goes on.

:func:`guarded_std_streams` (used by :func:`rigctl.cli.main`) puts such wrappers on
``sys.stdout`` and ``sys.stderr`` for the duration of a command, so that every command, not only
``run``, survives a closed pipe (``rigctl validate ... | head -1`` prints no traceback). When the
real file descriptor is gone, it is pointed at ``/dev/null`` so that the interpreter's final
flush at exit cannot fail either. :func:`detach_all` detaches both (the runner calls it on SIGHUP:
the terminal that hung up is gone).
"""
from __future__ import annotations

import errno
import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import IO, Any

#: errno values meaning "the reader of this stream is gone"
GONE = frozenset({errno.EPIPE, errno.EIO, errno.ENXIO, errno.EBADF, errno.ECONNRESET, errno.ENODEV})

_listeners: list[Callable[[str, str], None]] = []
_lock = threading.RLock()  # re-entrant: a signal handler may detach while the main thread is inside


def _reason(exc: BaseException) -> str | None:
    """Why ``exc`` means the reader is gone ("broken pipe", "terminal gone"...), else None."""
    if isinstance(exc, BrokenPipeError):
        return "broken pipe (the reader exited)"
    if isinstance(exc, ValueError) and "closed file" in str(exc):
        return "the stream was closed"
    if isinstance(exc, OSError) and exc.errno in GONE:
        if exc.errno == errno.EIO:
            return "terminal gone (I/O error)"
        return os.strerror(exc.errno).lower()
    return None


class ConsoleStream:
    """A text stream that survives its reader (see the module docstring). ``name`` is what it
    stands for ("stdout", "stderr") in the message the listeners get."""

    def __init__(self, stream: IO[str], name: str = "console") -> None:
        self.stream = stream
        self.name = name
        self.lost: str | None = None

    @classmethod
    def wrap(cls, stream: IO[str] | None, name: str = "console") -> ConsoleStream:
        """``stream`` itself if it is already a ConsoleStream, else a new one around it."""
        if isinstance(stream, ConsoleStream):
            return stream
        return cls(stream if stream is not None else sys.stdout, name)

    def detach(self, reason: str, notify: bool = True) -> None:
        """Stop writing to the stream (once); tell the listeners unless ``notify`` is False (a
        signal handler, which must not write files: the caller notes it later)."""
        with _lock:
            if self.lost is not None:
                return
            self.lost = reason
            listeners = list(_listeners) if notify else []
        _silence_fd(self.stream)
        for fn in listeners:
            try:
                fn(self.name, reason)
            except Exception:  # noqa: BLE001,S110 - a listener must not break the writer
                pass

    def _guard(self, op: Callable[[], Any], default: Any) -> Any:
        if self.lost is not None:
            return default
        try:
            return op()
        except (OSError, ValueError) as exc:
            why = _reason(exc)
            if why is None:
                raise
            self.detach(why)
            return default

    def write(self, text: str) -> int:
        self._guard(lambda: self.stream.write(text), 0)
        return len(text)

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        self._guard(self.stream.flush, None)

    def isatty(self) -> bool:
        if self.lost is not None:
            return False
        return bool(self._guard(lambda: self.stream.isatty(), False))

    def fileno(self) -> int:
        return self.stream.fileno()

    def __getattr__(self, name: str) -> Any:  # encoding, errors, buffer, ...
        return getattr(self.stream, name)


def _silence_fd(stream: Any) -> None:
    """Point the file descriptor under ``stream`` at /dev/null (the reader is gone), so buffered
    bytes and the interpreter's last flush go nowhere instead of raising."""
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):
        return
    try:
        null = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        return
    try:
        os.dup2(null, fd)
    except OSError:
        pass
    finally:
        os.close(null)


@contextmanager
def on_lost(fn: Callable[[str, str], None]) -> Iterator[None]:
    """Call ``fn(stream name, reason)`` when a console stream is detached, inside the block."""
    with _lock:
        _listeners.append(fn)
    try:
        yield
    finally:
        with _lock:
            if fn in _listeners:
                _listeners.remove(fn)


def detach_all(reason: str, notify: bool = True) -> None:
    """Detach ``sys.stdout`` and ``sys.stderr`` where they are console streams (a hang-up)."""
    for s in (sys.stdout, sys.stderr):
        if isinstance(s, ConsoleStream):
            s.detach(reason, notify)


@contextmanager
def guarded_std_streams() -> Iterator[None]:
    """``sys.stdout`` / ``sys.stderr`` wrapped in :class:`ConsoleStream` inside the block."""
    old_out, old_err = sys.stdout, sys.stderr
    sys.stdout = ConsoleStream.wrap(old_out, "stdout")  # type: ignore[assignment]
    sys.stderr = ConsoleStream.wrap(old_err, "stderr")  # type: ignore[assignment]
    try:
        yield
    finally:
        for s in (sys.stdout, sys.stderr):
            if isinstance(s, ConsoleStream):
                s.flush()
        sys.stdout, sys.stderr = old_out, old_err
