"""NovAtel mark-input driver: MARKCONTROL + ``LOG MARK1TIMEA ONNEW``, behind
:class:`rigctl.devices.PulseSource`.

On connect the driver sends ``MARKCONTROL <signal> ENABLE <polarity> <timebias_ns> <timeguard_ms>``
and ``LOG THISPORT <log> ONNEW`` (``<log>`` = MARK1TIMEA, or the deprecated MARKTIMEA), each
answered ``<OK`` (an ``<ERROR`` reply raises :class:`NovatelConfigError`). A reader thread parses
the sentences with :class:`~rigctl.drivers.novatel.MarkLogReader`: bad CRCs and malformed
sentences are counted (``counters.bad_crc`` / ``malformed``), logged and dropped.

Times (s): each mark carries GPS week and seconds of week at the pulse's leading edge (receiver
clock; ``gps_seconds`` below is corrected by the log's clock offset: GPS time = seconds -
offset). ``Pulses.time`` puts it on the run's time base: run time = GPS time - anchor, with the
anchor (header GPS time - rig clock at arrival) taken from the first log received and then
frozen, so intervals between pulses on the run time base are exactly the GPS intervals (an
anchor refined later would shift later pulses by milliseconds). The anchor carries the first
log's transport latency (tens of ms): keep the exact ``gps_week`` / ``gps_seconds`` for anything
finer than that. Marks are
matched to events by time, never by arrival order (logs arrive tens of ms after the pulse).

Link loss: the thread reopens the port with backoff and re-sends the configuration; ``read``
raises :class:`rigctl.devices.LinkLost` after ``link_timeout_s`` of wall time without a link.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import asdict

import numpy as np

from rigctl.devices import Clock, LinkLost, Pulses
from rigctl.errors import InputError

from .novatel import MarkControl, MarkLogReader, MarkTime, format_markcontrol, gps_total_seconds
from .reader_thread import ReconnectingReader
from .serial_link import LineReader, SerialLink

log = logging.getLogger(__name__)


class NovatelConfigError(InputError, RuntimeError):
    """The receiver refused a command carrying the rig config's mark settings: fix the config
    (:class:`rigctl.errors.InputError`, exit code 2)."""


class NovatelMarks(ReconnectingReader):
    """Mark pulses from a NovAtel receiver on ``url``; ``connect()``, ``read()``, ``close()``."""

    config_error = NovatelConfigError

    def __init__(self, url: str, clock: Clock, *, baudrate: int = 115200, timeout_s: float = 1.0,
                 signal: str = "MARK1", polarity: str = "NEGATIVE", timebias_ns: int = 0, timeguard_ms: int = 4,
                 log_name: str = "MARK1TIMEA", link_timeout_s: float = 2.0, name: str = "pulses") -> None:
        self.clock, self.name, self.timeout_s, self.link_timeout_s = clock, name, timeout_s, link_timeout_s
        self.control = MarkControl(signal=signal, polarity=polarity, timebias_ns=timebias_ns,
                                   timeguard_ms=timeguard_ms)
        self.log_name = log_name
        self.link = SerialLink(url, name, baudrate=baudrate, timeout_s=timeout_s)
        self.lines = LineReader(self.link, max_line=4096)
        self.reader = MarkLogReader()
        self.anchor: float | None = None          # GPS seconds since epoch at run time 0
        self._marks: list[MarkTime] = []
        self._lock = threading.Lock()
        self._init_reader()

    def connect(self) -> None:
        """Configure the receiver and start the reader thread (raises if it refuses)."""
        self._start_reader(4 * self.timeout_s + 1.0, f"no answer from the receiver on {self.link.url}")

    def identify(self) -> str:
        """Open the link and send the configured MARKCONTROL (what the run sends first): the
        receiver must answer ``<OK``. Raises LinkLost (the port, or no answer)."""
        self.link.open()
        self.link.drain_input()
        try:
            self._command(format_markcontrol(self.control))
        finally:
            self.link.close()
        return f"NovAtel receiver answers ({self.control.signal})"

    def _command(self, line: bytes) -> None:
        self.link.write(line)
        deadline = time.monotonic() + self.timeout_s
        while True:
            raw = self.lines.readline(max(1e-3, deadline - time.monotonic()))
            if raw.startswith(b"#"):
                self._handle(self.reader.feed(raw + b"\n"))
                continue
            text = raw.decode("ascii", "replace").strip()
            if text.startswith("<OK"):
                return
            if text.startswith("<ERROR"):
                raise NovatelConfigError(f"{self.name}: receiver refused {line.decode().strip()!r}: {text}")

    def _configure(self) -> None:
        self.link.ensure()
        self.lines.clear()
        self._command(format_markcontrol(self.control))
        self._command(f"LOG THISPORT {self.log_name} ONNEW\r\n".encode("ascii"))
        self._handle(self.reader.feed(self.lines.take()))   # bytes read past the last reply
        self._configured.set()

    def _pump(self) -> None:
        data = self.link.read_some(0.05)
        if data:
            self._handle(self.reader.feed(data))

    def _handle(self, marks: list[MarkTime]) -> None:
        if not marks:
            return
        arrival = self.clock.now()
        for m in marks:
            if m.header_week:
                if self.anchor is None:  # frozen after the first log (see module docstring)
                    self.anchor = gps_total_seconds(m.header_week, m.header_seconds) - arrival
        with self._lock:
            self._marks.extend(marks)

    def read(self) -> Pulses:
        if self._fatal is not None:
            raise self._fatal
        with self._lock:
            marks, self._marks = self._marks, []
        if not marks:
            down = self.link_down_s()
            if down is not None and down > self.link_timeout_s:
                raise LinkLost(self.name, f"no link to the receiver on {self.link.url} for "
                                          f"{down:.1f} s (reconnecting)")
            return Pulses(np.empty(0), np.empty(0, np.int32), np.empty(0), source="gnss")
        week = np.array([m.week for m in marks], dtype=np.int32)
        sec = np.array([m.gps_seconds for m in marks])
        total = week.astype(np.float64) * 604_800.0 + sec
        t = total - (self.anchor if self.anchor is not None else total[0])
        return Pulses(time=t, gps_week=week, gps_seconds=sec, source="gnss")

    @property
    def counters(self) -> dict:
        d = asdict(self.reader.counters)
        d.update(link_losses=self.link.losses, reconnects=self.link.reconnects)
        return d
