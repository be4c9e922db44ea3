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

from .novatel import MarkControl, MarkLogReader, MarkTime, format_markcontrol, gps_total_seconds
from .serial_link import LineReader, SerialLink

log = logging.getLogger(__name__)


class NovatelConfigError(RuntimeError):
    """The receiver refused a command."""


class NovatelMarks:
    """Mark pulses from a NovAtel receiver on ``url``; ``connect()``, ``read()``, ``close()``."""

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
        self._stop = threading.Event()
        self._configured = threading.Event()
        self._fatal: BaseException | None = None
        self._down_since: float | None = None
        self._thread: threading.Thread | None = None

    def connect(self) -> None:
        """Configure the receiver and start the reader thread (raises if it refuses)."""
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-reader", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + 4 * self.timeout_s + 1.0
        while not self._configured.wait(0.01):
            if self._fatal is not None or time.monotonic() > deadline:
                err = self._fatal or LinkLost(self.name, f"no answer from the receiver on {self.link.url}")
                self.close()
                raise err

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
        self._down_since = None
        self._configured.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                if not self._configured.is_set():
                    self._configure()
                data = self.link.read_some(0.05)
                if data:
                    self._handle(self.reader.feed(data))
            except LinkLost:
                self._configured.clear()
                if self._down_since is None:
                    self._down_since = time.monotonic()
                self._stop.wait(max(0.01, self.link.backoff.wait_s()))
            except NovatelConfigError as exc:
                self._fatal = exc
                return
            except Exception as exc:  # noqa: BLE001 - reported through read()
                log.exception("%s: reader thread failed", self.name)
                self._fatal = exc
                return

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
            if self._down_since is not None and time.monotonic() - self._down_since > self.link_timeout_s:
                raise LinkLost(self.name, f"no link to the receiver on {self.link.url} for "
                                          f"{time.monotonic() - self._down_since:.1f} s (reconnecting)")
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

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        self.link.close()
