"""Emulated NovAtel receiver on a pty: MARK1TIMEA / MARKTIMEA logs for mark pulses, MARKCONTROL.

Commands (abbreviated ASCII, one per line, case-insensitive), each answered ``<OK`` or
``<ERROR:<reason>``: ``LOG [port] MARK1TIMEA|MARKTIMEA ONNEW``, ``UNLOG [port] <log>``,
``UNLOGALL``, ``MARKCONTROL MARK1 [ENABLE|DISABLE [polarity [timebias_ns [timeguard_ms]]]]``.

Pulses: ``pulse(t)`` with t in s on the shared clock, or a ``source()`` callable polled every few
ms that returns an iterable of new pulse times. MARK1 behaves as the receiver does: pulses while
disabled are ignored, pulses within ``timeguard`` ms after the last accepted mark are suppressed
(counted in ``suppressed``), ``timebias`` ns is added to the reported time, times are quantised
to 10 ns. Mark time = GPS (week0, seconds0) at clock 0 + t + timebias. The log is written
``log_delay_s`` after the pulse (clock time), as the receiver reports marks tens of ms late.
Polarity is accepted and reported but pulses are abstract edges here.
"""
from __future__ import annotations

import heapq
import threading
import time
from collections.abc import Callable, Iterable

from rigctl.drivers.novatel import (MarkControl, MarkTime, NovatelError, format_mark, normalize_week_seconds,
                                    parse_markcontrol)

from .links import PtyEndpoint


class GnssServer:
    """NovAtel mark-log emulator; ``path`` is the client's port; ``close()`` stops it."""

    def __init__(self, clock: Callable[[], float] | None = None,
                 source: Callable[[], Iterable[float]] | None = None, gps_week0: int = 2300,
                 gps_seconds0: float = 345_600.0, utc_offset: float = -18.0, log_delay_s: float = 0.02,
                 port_name: str = "COM1", autolog: bool = False) -> None:
        t_wall0 = time.monotonic()
        self.clock = clock if clock is not None else (lambda: time.monotonic() - t_wall0)
        self.source = source
        self.week0, self.seconds0, self.utc_offset = gps_week0, gps_seconds0, utc_offset
        self.log_delay_s, self.port_name = log_delay_s, port_name
        self.control = MarkControl()
        self.logs: set[str] = {"MARK1TIMEA"} if autolog else set()
        self.accepted = self.suppressed = self.ignored = 0
        self._last_mark: float | None = None
        self._queue: list[tuple[float, float]] = []     # (due clock time, pulse time)
        self._buf = b""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.port = PtyEndpoint(self._on_data, name="gnss-pty")
        self.path = self.port.path
        self._thread = threading.Thread(target=self._run, name="gnss-marks", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------ pulses
    def pulse(self, t: float) -> bool:
        """Register a mark pulse at clock time ``t`` (s); returns True if the receiver accepts it."""
        with self._lock:
            if not self.control.enable:
                self.ignored += 1
                return False
            if self._last_mark is not None and t - self._last_mark < self.control.timeguard_ms * 1e-3:
                self.suppressed += 1
                return False
            self._last_mark = t
            self.accepted += 1
            heapq.heappush(self._queue, (t + self.log_delay_s, t))
            return True

    def mark_time(self, t: float) -> tuple[int, float]:
        """(GPS week, seconds of week) reported for a pulse at clock time t, 10 ns resolution."""
        s = self.seconds0 + t + self.control.timebias_ns * 1e-9
        week, sec = normalize_week_seconds(self.week0, s)
        return week, round(sec * 1e8) / 1e8

    def _run(self) -> None:
        while not self._stop.wait(0.002):
            if self.source is not None:
                for t in self.source() or ():
                    self.pulse(float(t))
            now = self.clock()
            out = []
            with self._lock:
                while self._queue and self._queue[0][0] <= now:
                    due, t = heapq.heappop(self._queue)
                    week, sec = self.mark_time(t)
                    hw, hs = normalize_week_seconds(self.week0, self.seconds0 + due)
                    for name in sorted(self.logs):
                        out.append(format_mark(MarkTime(
                            week=week, seconds=sec, offset=0.0, offset_std=0.0, utc_offset=self.utc_offset,
                            clock_status="VALID", log_name=name, port=self.port_name, idle_pct=90.0,
                            header_week=hw, header_seconds=hs)))
            if out:
                self.port.write(b"".join(out))

    # ------------------------------------------------------------------------ commands
    def _on_data(self, data: bytes, write: Callable[[bytes], None]) -> None:
        self._buf += data
        *lines, self._buf = self._buf.split(b"\n")
        for raw in lines:
            line = raw.strip().decode("ascii", "replace")
            if line:
                write(self._command(line).encode("ascii") + b"\r\n")

    def _command(self, line: str) -> str:
        tok = line.upper().split()
        with self._lock:
            if tok[0] == "MARKCONTROL":
                try:
                    mc = parse_markcontrol(line)
                except NovatelError as exc:
                    return f"<ERROR:{exc}"
                if mc.signal != "MARK1":
                    return "<ERROR:only MARK1 is emulated"
                self.control = mc
                return "<OK"
            if tok[0] == "UNLOGALL":
                self.logs.clear()
                return "<OK"
            if tok[0] in ("LOG", "UNLOG"):
                args = [t for t in tok[1:] if not t.startswith("COM") and not t.startswith("USB")
                        and t not in ("THISPORT",)]
                if not args or args[0] not in ("MARK1TIMEA", "MARKTIMEA"):
                    return "<ERROR:unsupported log"
                if tok[0] == "LOG":
                    if len(args) > 1 and args[1] != "ONNEW":
                        return "<ERROR:only the ONNEW trigger is supported"
                    self.logs.add(args[0])
                else:
                    self.logs.discard(args[0])
                return "<OK"
            return "<ERROR:Invalid Message"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.port.close()

    def __enter__(self) -> GnssServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
