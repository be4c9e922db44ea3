"""Pulse edges on a GPIO line through libgpiod v2 (the ``gpiod`` package, optional extra ``gpio``),
behind :class:`rigctl.devices.PulseSource`.

``gpiod.request_lines(chip, config={line: LineSettings(edge_detection=..., bias=...,
debounce_period=..., event_clock=...)})``, then a reader thread waits with
``wait_edge_events(timeout)`` and drains ``read_edge_events()``. Each ``EdgeEvent`` carries the
kernel timestamp ``timestamp_ns`` (taken in the interrupt handler, on the chosen clock), and the
sequence numbers ``line_seqno`` / ``global_seqno``: a jump of ``line_seqno`` by more than one means
the kernel's event buffer overflowed and edges were lost; they are counted in ``missed``
(never silently ignored), as are events for other lines or out-of-order sequence numbers.

Time base: MONOTONIC (default) or REALTIME kernel timestamps are mapped onto the run clock by an
offset taken at start: run time = timestamp - (host clock at start - run clock at start), with the
host clock ``time.monotonic_ns`` resp. ``time.time_ns``; for a scaled run clock the host time
difference is multiplied by the speed. HTE timestamps come from a hardware engine whose epoch the
driver cannot relate to the host clock: they are mapped like MONOTONIC (an assumption stated in
docs/hardware.md). ``gpiod`` is imported lazily so rigctl works without it.

Untested without hardware: a real ``/dev/gpiochip*`` (the tests use the real ``gpiod`` classes --
``LineSettings``, ``Edge``, ``Clock``, ``Bias``, ``EdgeEvent`` -- with a request object imitating
``LineRequest``'s ``wait_edge_events`` / ``read_edge_events`` / ``release``), the kernel's
debounce, HTE clocks, and event-buffer overflow on a real chip.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from datetime import timedelta
from typing import Any

from rigctl.devices import Clock

from .reader_thread import HostTimedPulses

log = logging.getLogger(__name__)


def _gpiod():
    try:
        import gpiod
    except ImportError as exc:                     # pragma: no cover - depends on the environment
        raise RuntimeError("GPIO pulses need the 'gpiod' package (libgpiod v2 bindings): "
                           "pip install 'rigctl[gpio]'") from exc
    return gpiod


def line_settings(edge: str = "rising", event_clock: str = "monotonic", debounce_us: int = 0,
                  bias: str = "as-is") -> Any:
    """The ``gpiod.LineSettings`` for an input line with edge detection."""
    gpiod = _gpiod()
    from gpiod.line import Bias, Clock as GClock, Direction, Edge
    return gpiod.LineSettings(direction=Direction.INPUT, edge_detection={"rising": Edge.RISING, "falling": Edge.FALLING,
                                                                        "both": Edge.BOTH}[edge],
                              bias={"as-is": Bias.AS_IS, "pull-up": Bias.PULL_UP, "pull-down": Bias.PULL_DOWN,
                                    "disabled": Bias.DISABLED}[bias],
                              debounce_period=timedelta(microseconds=debounce_us),
                              event_clock={"monotonic": GClock.MONOTONIC, "realtime": GClock.REALTIME,
                                           "hte": GClock.HTE}[event_clock])


class GpioPulses(HostTimedPulses):
    """Edges of GPIO ``line`` on ``chip``; ``connect()``, ``read()``, ``close()``."""

    source, reader_what = "gpio", "GPIO reader"

    def __init__(self, chip: str, line: int, clock: Clock, *, edge: str = "rising", event_clock: str = "monotonic",
                 debounce_us: int = 0, bias: str = "as-is", consumer: str = "rigctl",
                 request_lines: Callable[..., Any] | None = None, name: str = "pulses") -> None:
        self.chip, self.line, self.clock, self.name = chip, int(line), clock, name
        self.edge, self.event_clock, self.debounce_us, self.bias, self.consumer = \
            edge, event_clock, debounce_us, bias, consumer
        self._request_lines = request_lines
        self.request = None
        self.events = 0
        self.missed = 0
        self.foreign = 0
        self.out_of_order = 0
        self._last_seqno: int | None = None
        self._init_pulses()

    def _host_ns(self) -> int:
        return time.time_ns() if self.event_clock == "realtime" else time.monotonic_ns()

    def identify(self) -> str:
        """Open the chip and read its label and the line's name (nothing is requested).
        Raises OSError (no chip, no permission) or RuntimeError (gpiod missing)."""
        with open(self.chip, "rb"):  # the chip's own errno (ENOENT, EACCES) before gpiod's
            pass
        if self._request_lines is not None:
            return f"{self.chip} line {self.line}"
        gpiod = _gpiod()
        with gpiod.Chip(self.chip) as chip:
            info = chip.get_info()
            line = chip.get_line_info(self.line)
        return f"{info.label or info.name}, line {self.line} ({line.name or 'unnamed'})"

    def connect(self) -> None:
        request_lines = self._request_lines or _gpiod().request_lines
        settings = line_settings(self.edge, self.event_clock, self.debounce_us, self.bias)
        try:
            self.request = request_lines(self.chip, config={self.line: settings}, consumer=self.consumer)
        except OSError as exc:
            raise RuntimeError(f"{self.name}: cannot request line {self.line} of {self.chip}: {exc} "
                               "(does the chip exist, and is the user in the 'gpio' group?)") from exc
        self._start_pulses(self._run, self._host_ns(), "gpio")

    def handle(self, events: list) -> None:
        """Account for a list of ``gpiod.EdgeEvent`` (sequence gaps, foreign lines)."""
        times = []
        for ev in events:
            if ev.line_offset != self.line:
                self.foreign += 1
                continue
            if self._last_seqno is not None:
                gap = ev.line_seqno - self._last_seqno
                if gap <= 0:
                    self.out_of_order += 1
                    log.warning("%s: edge event with line_seqno %d after %d rejected", self.name, ev.line_seqno,
                                self._last_seqno)
                    continue
                if gap > 1:
                    self.missed += gap - 1
                    log.warning("%s: %d edge events lost (kernel buffer overflow?)", self.name, gap - 1)
            self._last_seqno = ev.line_seqno
            self.events += 1
            times.append(self.to_run_time(ev.timestamp_ns))  # kernel timestamp (module docstring)
        self._add(times)

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self.request.wait_edge_events(timedelta(milliseconds=100)):
                    self.handle(self.request.read_edge_events())
        except Exception as exc:  # noqa: BLE001 - reported through read()
            log.exception("%s: GPIO reader failed", self.name)
            self._fatal = exc

    def close(self) -> None:
        self._stop_thread(5.0)
        if self.request is not None:
            self.request.release()
            self.request = None
