"""Live progress of a run (or a long analysis) on the console.

On a terminal (``stream.isatty()``) one line is redrawn in place with ``\\r`` at most
``redraw_hz`` times per second of wall time::

    [12/43] orientation x north, phi 45 deg | [#########-------]  58 % | left ~5 min 2 s |
    table 0.0 90.0 45.0 deg, +0.0 +0.0 +0.0 deg/s | IMU 100.0 Hz | dropped 0

Otherwise (piped to a file, a log, ``rigctl status --watch`` output) it writes plain lines: one
at every step start and end, and one every ``interval_s`` of wall time in between.

The engine calls, in order: :meth:`Progress.start` with the plan's estimates
(:func:`rigctl.engine.estimate.estimate`), then per step :meth:`~Progress.step_started`,
:meth:`~Progress.update` at every poll (rig time in s, the table state, IMU samples recorded,
samples dropped), :meth:`~Progress.step_finished`; finally :meth:`~Progress.finish`. Log lines
that must not be torn by the bar go through :meth:`Progress.message` or the file-like
:attr:`Progress.console`. :class:`NullProgress` does nothing (tests, the daemon).

Remaining time (rig time, s) = estimate of the current step minus the rig time spent in it
(never below zero) + estimates of the steps not yet started. When the rig clock runs faster
than the wall clock (emulator), the wall-time equivalent is shown too, scaled by the observed
ratio wall / rig time.
"""
from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Iterable
from typing import IO, Any

import numpy as np

from .units import format_duration

BAR_WIDTH = 20


def _step_key(step: Any, fallback: int) -> int:
    idx = getattr(step, "index", None)
    return int(idx) if idx is not None else fallback


def _describe(step: Any) -> str:
    label = getattr(step, "label", None)
    kind = getattr(step, "kind", None)
    if label is not None and kind is not None:
        return f"{kind} {label}"
    if hasattr(step, "describe"):
        return " ".join(str(step.describe()).split())
    return str(step)


def format_table_state(state: Any) -> str:
    """``table a b c deg, r1 r2 r3 deg/s`` from a TableState (angles rad, rates rad/s)."""
    if state is None:
        return "table ?"
    ang = np.degrees(np.asarray(getattr(state, "angle", [math.nan] * 3), dtype=float))
    rate = np.degrees(np.asarray(getattr(state, "rate", [math.nan] * 3), dtype=float))
    a = " ".join(f"{x:.1f}" for x in ang)
    r = " ".join(f"{x:+.1f}" for x in rate)
    return f"table {a} deg, {r} deg/s"


class CounterGaps:
    """Dropped IMU samples from gaps in the sample counter: sum of (c[i+1] - c[i] - 1) > 0.

    Feed every block's counters in order with :meth:`add`; :attr:`dropped` is the total.
    """

    def __init__(self) -> None:
        self.last: int | None = None
        self.dropped = 0

    def add(self, counter: Iterable[int] | np.ndarray) -> int:
        c = np.asarray(counter, dtype=np.int64)
        if c.size == 0:
            return self.dropped
        if self.last is not None:
            c = np.concatenate(([self.last], c))
        d = np.diff(c) - 1
        self.dropped += int(d[d > 0].sum())
        self.last = int(c[-1])
        return self.dropped


class _Console:
    """File-like wrapper: complete lines written here go out through Progress.message."""

    def __init__(self, progress: "Progress") -> None:
        self._p = progress
        self._buf = ""

    def write(self, text: str) -> int:
        self._buf += text
        while "\n" in self._buf:
            line, self._buf = self._buf.split("\n", 1)
            self._p.message(line)
        return len(text)

    def flush(self) -> None:
        if self._buf:
            self._p.message(self._buf)
            self._buf = ""

    def isatty(self) -> bool:
        return False


class _Display:
    """A status line on ``stream``: redrawn in place with ``\\r`` on a terminal (at most
    ``redraw_hz`` times per wall second), else written as plain lines (see subclasses)."""

    def __init__(self, stream: IO[str] | None = None, *, tty: bool | None = None,
                 interval_s: float = 10.0, redraw_hz: float = 5.0,
                 wall: Callable[[], float] = time.monotonic, width: int | None = None) -> None:
        self.stream = stream if stream is not None else sys.stdout
        if tty is None:
            isatty = getattr(self.stream, "isatty", None)
            tty = bool(isatty()) if callable(isatty) else False
        self.tty = tty
        self.interval_s = float(interval_s)
        self.min_redraw_s = 1.0 / redraw_hz if redraw_hz > 0 else 0.0
        self.wall = wall
        self._width = width
        self._last_draw = -math.inf
        self._last_line = -math.inf
        self._bar_visible = False

    def bar_text(self) -> str:  # pragma: no cover - overridden
        return ""

    def message(self, text: str) -> None:
        """Write a log line without tearing the bar (the bar is redrawn beneath it)."""
        had_bar = self._bar_visible
        self._clear()
        self.stream.write(text + "\n")
        self.stream.flush()
        if had_bar:
            self._draw(force=True)

    def _term_width(self) -> int:
        if self._width:
            return self._width
        try:
            return os.get_terminal_size(self.stream.fileno()).columns
        except (OSError, AttributeError, ValueError):
            return 100

    def _draw(self, force: bool = False) -> None:
        w = self.wall()
        if not force and w - self._last_draw < self.min_redraw_s:
            return
        width = max(20, self._term_width() - 1)
        text = self.bar_text()[:width]
        self.stream.write("\r" + text + "\x1b[K")
        self.stream.flush()
        self._bar_visible = True
        self._last_draw = w

    def _clear(self) -> None:
        if self._bar_visible:
            self.stream.write("\r\x1b[K")
            self._bar_visible = False

    def _line(self, text: str) -> None:
        self._clear()
        self.stream.write(text + "\n")
        self.stream.flush()
        self._last_line = self.wall()


def _bar(fraction: float) -> str:
    filled = int(round(min(1.0, max(0.0, fraction)) * BAR_WIDTH))
    return "[" + "#" * filled + "-" * (BAR_WIDTH - filled) + "]"


class Progress(_Display):
    """Progress display for a plan of steps (see the module docstring).

    Args:
        stream: where to write (default ``sys.stdout``).
        tty: force bar (True) or plain lines (False); default ``stream.isatty()``.
        interval_s: wall seconds between plain periodic lines (non-terminal).
        redraw_hz: maximum bar redraws per wall second (terminal).
        wall: wall clock, s (monotonic; injectable for tests).
        width: line width on a terminal (default: the terminal's width, else 100).
    """

    def __init__(self, stream: IO[str] | None = None, **kw: Any) -> None:
        super().__init__(stream, **kw)
        self.estimates: dict[int, float] = {}
        self.order: list[int] = []
        self.done_before = 0  # motion steps an earlier session finished (a resume)
        self.finished: set[int] = set()
        self.step: Any = None
        self.step_key: int | None = None
        self.step_t0: float | None = None  # rig time at which the current step started
        self.now_s: float | None = None
        self.t_first: float | None = None
        self.wall_first: float | None = None
        self.state: Any = None
        self.n_imu: int | None = None
        self.dropped: int = 0
        self.rate_hz: float | None = None
        self._rate_ref: tuple[float, int] | None = None
        self.console = _Console(self)

    # -- engine API ----------------------------------------------------------------------------
    def start(self, plan_estimates: Iterable[Any] = (), title: str = "", done_before: int = 0) -> None:
        """Register the plan: items with ``.step`` and ``.total_s`` (s); solve steps count 0.
        ``done_before``: motion steps of the procedure an earlier session finished (a resume):
        the steps are numbered in the whole procedure, [6/25] for its sixth, not [1/20]."""
        self.done_before = done_before
        for n, e in enumerate(plan_estimates):
            step = getattr(e, "step", None)
            if step is not None and not getattr(step, "is_motion", True):
                continue
            key = _step_key(step, n) if step is not None else n
            self.estimates[key] = float(getattr(e, "total_s", e))
            self.order.append(key)
        self.wall_first = self.wall()
        total = sum(self.estimates.values())
        head = f"{title}: " if title else ""
        left = (f"{len(self.order)} steps" if not done_before else
                f"{len(self.order)} of {done_before + len(self.order)} steps left")
        self._line(f"{head}{left}, about {format_duration(total)} of rig time")

    def step_started(self, step: Any) -> None:
        """A step begins (its rig start time is the latest ``update`` time)."""
        self.step = step
        self.step_key = _step_key(step, len(self.finished))
        self.step_t0 = self.now_s
        if self.tty:
            self._draw(force=True)
        else:
            est = self.estimates.get(self.step_key)
            extra = f", estimate {format_duration(est)}" if est is not None else ""
            self._line(f"{self._position()} started: {_describe(step)}{extra}; "
                       f"{self._remaining_text()}")

    def update(self, now_s: float, table_state: Any = None, n_imu_samples: int | None = None,
               dropped: int | None = None) -> None:
        """Latest rig time (s), table state, IMU samples recorded so far, samples dropped."""
        self.now_s = float(now_s)
        if self.t_first is None:
            self.t_first = self.now_s
            if self.wall_first is None:
                self.wall_first = self.wall()
        if self.step is not None and self.step_t0 is None:
            self.step_t0 = self.now_s
        if table_state is not None:
            self.state = table_state
        if dropped is not None:
            self.dropped = int(dropped)
        if n_imu_samples is not None:
            self.n_imu = int(n_imu_samples)
            self._update_rate()
        w = self.wall()
        if self.tty:
            if w - self._last_draw >= self.min_redraw_s:
                self._draw()
        elif w - self._last_line >= self.interval_s:
            self._line(self.status_text())

    def step_finished(self, step: Any, segment: Any = None) -> None:
        """A step is done; ``segment`` (optional) gives its sample range."""
        key = _step_key(step, len(self.finished))
        self.finished.add(key)
        spent = self._in_step_s()
        n = ""
        if segment is not None and hasattr(segment, "last_sample"):
            n = f", {int(segment.last_sample) - int(segment.first_sample)} samples"
        text = (f"{self._position(key)} done: {_describe(step)} in "
                f"{format_duration(spent)} rig time{n}; {self._remaining_text()}")
        self.step, self.step_key, self.step_t0 = None, None, None
        if self.tty:
            self.message(text)
        else:
            self._line(text)

    def finish(self, status: str) -> None:
        """The run ended with ``status`` (complete, interrupted, failed)."""
        rig = (self.now_s - self.t_first) if self.now_s is not None and self.t_first is not None else 0.0
        wall = self.wall() - self.wall_first if self.wall_first is not None else 0.0
        text = (f"{status}: {self.done_before + len(self.finished)}/{self.done_before + len(self.order)} steps, "
                f"{format_duration(rig)} of rig time in {format_duration(wall)} wall over the steps, "
                f"dropped {self.dropped} samples")
        self._clear()
        self._line(text)

    def message(self, text: str) -> None:
        """Write a log line without tearing the bar (the bar is redrawn beneath it)."""
        super().message(text)
        if self.tty and self.step is not None and not self._bar_visible:
            self._draw(force=True)

    # -- text --------------------------------------------------------------------------------
    def remaining_s(self) -> float:
        """Estimated rig time left, s (see the module docstring)."""
        left = 0.0
        for k in self.order:
            if k in self.finished:
                continue
            est = self.estimates[k]
            if k == self.step_key:
                left += max(0.0, est - self._in_step_s())
            else:
                left += est
        return left

    def fraction(self) -> float:
        """Progress within the current step, 0..1 (rig time spent / estimate, capped at 0.99)."""
        est = self.estimates.get(self.step_key) if self.step_key is not None else None
        if not est:
            return 0.0
        return min(0.99, max(0.0, self._in_step_s() / est))

    def status_text(self) -> str:
        """One-line state without the bar."""
        parts = [f"{self._position()} {_describe(self.step) if self.step is not None else 'between steps'}",
                 f"{100 * self.fraction():.0f} %", self._remaining_text(), format_table_state(self.state)]
        parts.append(f"IMU {self.rate_hz:.1f} Hz" if self.rate_hz is not None else "IMU ? Hz")
        parts.append(f"dropped {self.dropped}")
        return " | ".join(parts)

    def bar_text(self) -> str:
        f = self.fraction()
        bar = _bar(f)[1:-1]
        head = f"{self._position()} {_describe(self.step) if self.step is not None else ''}".rstrip()
        parts = [head, f"[{bar}] {100 * f:3.0f} %", self._remaining_text(),
                 format_table_state(self.state),
                 f"IMU {self.rate_hz:.1f} Hz" if self.rate_hz is not None else "IMU ? Hz",
                 f"dropped {self.dropped}"]
        return " | ".join(parts)

    # -- internals ---------------------------------------------------------------------------
    def _in_step_s(self) -> float:
        if self.step_t0 is None or self.now_s is None:
            return 0.0
        return max(0.0, self.now_s - self.step_t0)

    def _position(self, key: int | None = None) -> str:
        key = self.step_key if key is None else key
        n, before = len(self.order), self.done_before
        if key in self.order:
            return f"[{before + self.order.index(key) + 1}/{before + n}]"
        return f"[{before + len(self.finished) + 1}/{before + n}]" if n else "[-]"

    def _remaining_text(self) -> str:
        left = self.remaining_s()
        text = f"left ~{format_duration(left)}"
        if (self.now_s is not None and self.t_first is not None and self.wall_first is not None):
            rig = self.now_s - self.t_first
            wall = self.wall() - self.wall_first
            if rig > 1.0 and wall > 0 and abs(wall / rig - 1.0) > 0.1:
                text += f" (~{format_duration(left * wall / rig)} wall)"
        return text

    def _update_rate(self) -> None:
        if self.now_s is None or self.n_imu is None:
            return
        if self._rate_ref is None:
            self._rate_ref = (self.now_s, self.n_imu)
            return
        t0, n0 = self._rate_ref
        if self.now_s - t0 >= 1.0:  # samples per rig second over >= 1 s windows
            r = (self.n_imu - n0) / (self.now_s - t0)
            self.rate_hz = r if self.rate_hz is None else 0.5 * (self.rate_hz + r)
            self._rate_ref = (self.now_s, self.n_imu)


class WorkProgress(_Display):
    """Progress of one long analysis (``rigctl allan`` on a night's recording): ``done`` of
    ``total`` units of work, the rate and the time left (wall), as a bar on a terminal or a plain
    line every ``interval_s`` otherwise. ``enabled=False`` shows nothing.

    Time left, s = (total - done) / rate, rate = done / wall time since :meth:`start`."""

    def __init__(self, label: str, total: float, unit: str = "samples",
                 stream: IO[str] | None = None, enabled: bool = True, **kw: Any) -> None:
        super().__init__(stream if enabled else _Sink(), **kw)
        self.label, self.total, self.unit, self.enabled = label, float(total), unit, enabled
        self.done = 0.0
        self.t0 = self.wall()

    def _rate(self) -> float:
        dt = self.wall() - self.t0
        return self.done / dt if dt > 0 else math.nan

    def status_text(self) -> str:
        rate = self._rate()
        left = (self.total - self.done) / rate if rate > 0 else math.nan
        pct = 100.0 * self.done / self.total if self.total else 100.0
        text = f"{self.label}: {self.done:,.0f}/{self.total:,.0f} {self.unit} ({pct:.0f} %)"
        if math.isfinite(rate):
            text += f", {rate:,.3g} {self.unit}/s"
        if math.isfinite(left):
            text += f", left ~{format_duration(left)}"
        return text

    def bar_text(self) -> str:
        return f"{_bar(self.done / self.total if self.total else 1.0)} {self.status_text()}"

    def update(self, done: float) -> None:
        """``done`` units of work finished so far."""
        if not self.enabled:
            return
        self.done = float(done)
        if self.tty:
            self._draw()
        elif self.wall() - self._last_line >= self.interval_s:
            self._line(self.status_text())

    def finish(self, text: str = "") -> None:
        """Remove the bar; write ``text`` (or the final status) as a plain line."""
        if not self.enabled:
            return
        elapsed = self.wall() - self.t0
        self._line(text or f"{self.label}: {self.done:,.0f} {self.unit} in {format_duration(elapsed)}")


class NullProgress(Progress):
    """Progress that shows nothing (same API); :meth:`message` still writes the line to
    ``stream`` (default: discarded), so a log routed through :attr:`console` keeps working."""

    def __init__(self, stream: IO[str] | None = None) -> None:
        super().__init__(stream=stream if stream is not None else _Sink(), tty=False)

    def start(self, plan_estimates: Iterable[Any] = (), title: str = "", done_before: int = 0) -> None:
        pass

    def step_started(self, step: Any) -> None:
        pass

    def update(self, now_s: float, table_state: Any = None, n_imu_samples: int | None = None,
               dropped: int | None = None) -> None:
        pass

    def step_finished(self, step: Any, segment: Any = None) -> None:
        pass

    def finish(self, status: str) -> None:
        pass


class _Sink:
    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False


def make_progress(stream: IO[str] | None = None, enabled: bool = True, **kw: Any) -> Progress:
    """A :class:`Progress` on ``stream`` (default stdout), or a :class:`NullProgress`."""
    return Progress(stream, **kw) if enabled else NullProgress(stream)
