"""Turntable driver for the ACL-style ASCII command set (docs/protocols.md section 2) over any pyserial URL.

Implements the engine's :class:`rigctl.devices.Turntable` protocol: one request line, one reply
line, a single outstanding request, a per-request timeout. The commands of one engine call go in
one ``;``-chained line (``:MODE:POSITION 1;:DEMAND:POSITION 1,90.000000;...``), so a move is one
round trip; :meth:`AclTable.read` is ``:READ:ALL? 1;ALL? 2;ALL? 3`` (an atomic snapshot per
axis: position, rate, acceleration, status word, controller time in ms).

Settling: the status words are passed through unchanged (``TARGET_REACHED`` / ``AT_RATE`` from the
controller's own window and dwell); the engine adds its measured-window check and hold time.

Time: ``TableState.time`` = controller time + an offset (rig clock when a probe's reply arrived -
controller time) taken as the lower envelope over the 8 probes at connect and every
``read`` after (:mod:`rigctl.drivers.probe_offset`: a stale controller time at connect is
corrected by the first on-time read), so table times are on the run's time base but tick with the
controller's clock.

Errors: ``ERR -221`` (interlock open / fault / wrong mode) raises :class:`rigctl.devices.DeviceFault`;
``ERR -222`` (out of range) raises ValueError; a reply timeout raises
:class:`~rigctl.drivers.serial_link.ReplyTimeout` naming the request, a garbled reply
:class:`~rigctl.drivers.serial_link.BadReply` (both counted in ``counters``). After either, input
is drained and the next request is preceded by a resynchronisation: ``*IDN?`` chained ``n`` times
in one line (``*IDN?;*IDN?``), answered by the identity ``n`` times joined with ``;``. The
controller answers in order, so a reply still in flight can only answer a line sent since the
last answer the driver matched: ``n`` is one more than the chain of the last unanswered
identity query, and only a reply of exactly ``n`` identities ends the resync. A late reply to an
earlier ``*IDN?`` (a resync or an identify that timed out) is thus never taken for the resync's
own, which would leave its own reply to be misread as the answer to the next request. After
:data:`MAX_SYNC_CHAIN` unanswered resyncs the port is reopened. Read-only requests are retried
once.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from rigctl.config.config import TableLimits
from rigctl.devices import Clock, DeviceFault, LinkLost, TableState

from .acl import AclCode, AclError, parse_read_all, parse_reply
from .probe_offset import ProbeOffset
from .serial_link import BadReply, LineReader, ReplyTimeout, SerialLink

log = logging.getLogger(__name__)
DEG = math.pi / 180.0

#: the longest identity query of a resync (``*IDN?`` chained this many times, 6 bytes each): after
#: that many unanswered in a row the controller is silent, and the port is reopened (closed, its
#: input is gone) instead of the chain growing on
MAX_SYNC_CHAIN = 4


def repeated(reply: str, n: int) -> str | None:
    """The text ``x`` when ``reply`` is ``x`` repeated ``n`` times joined with ``;`` (the
    reply to ``*IDN?`` chained ``n`` times), else None."""
    parts = reply.split(";")
    if not reply or len(parts) % n:
        return None
    x = ";".join(parts[:len(parts) // n])
    return x if reply == ";".join([x] * n) else None


@dataclass
class AclCounters:
    requests: int = 0
    timeouts: int = 0
    bad_replies: int = 0
    error_replies: int = 0
    resyncs: int = 0


class AclTable:
    """ACL turntable over ``url`` (``/dev/ttyUSB0``, a pty, ``socket://host:9878``, ...)."""

    def __init__(self, url: str, limits: TableLimits, clock: Clock, *, baudrate: int = 115200,
                 timeout_s: float = 0.5, close_interlocks: bool = True, open_interlocks_on_stop: bool = False,
                 name: str = "table") -> None:
        self.limits, self.clock, self.name = limits, clock, name
        self.link = SerialLink(url, name, baudrate=baudrate, timeout_s=timeout_s)
        self.reader = LineReader(self.link)
        self.timeout_s = timeout_s
        self.close_interlocks, self.open_interlocks_on_stop = close_interlocks, open_interlocks_on_stop
        self.counters = AclCounters()
        self.idn = ""
        self.time_base = ProbeOffset(name)
        self._dirty = False
        #: the chain length of the last identity query sent and not answered (0: all answered)
        self._unanswered = 0

    # ------------------------------------------------------------------------- transport
    def _resync(self) -> None:
        """Drain input, then the identity query (:meth:`_sync`) until its own reply comes back."""
        self.counters.resyncs += 1
        self._drain()
        self._sync()
        self._dirty = False

    def _drain(self) -> None:
        self.link.ensure()
        self.link.drain_input()
        self.reader.clear()

    def _sync(self) -> str:
        """Send ``*IDN?`` chained ``n`` times (``n`` one more than the chain of the last identity
        query left unanswered) and read lines until the reply of exactly ``n`` identities (equal
        to :attr:`idn` once known); returns the identity. Lines before it are late replies to
        earlier requests and are discarded. Raises ReplyTimeout (the query stays unanswered)."""
        n = self._unanswered + 1
        if n > MAX_SYNC_CHAIN:
            self._unanswered = 0
            raise self.link.lost(f"no reply to {MAX_SYNC_CHAIN} identity queries in a row; reopening the port")
        self.link.write(";".join(["*IDN?"] * n).encode("ascii") + b"\n")
        self._unanswered = n
        deadline = time.monotonic() + self.timeout_s
        while True:
            line = self.reader.readline(max(1e-3, deadline - time.monotonic())).decode("ascii", "replace").strip()
            idn = repeated(line, n) if line.isascii() and line.isprintable() else None
            if idn is not None and (idn == self.idn or not self.idn):
                self._unanswered = 0
                return idn

    def request(self, line: str, *, retry: bool = False) -> str:
        """Send one line, return its reply line (ERR replies raise AclError)."""
        for attempt in (0, 1):
            try:
                if not self.link.is_open:
                    self._dirty = True          # reconnected: whatever is buffered is stale
                if self._dirty:
                    self._resync()
                self.counters.requests += 1
                self.link.write(line.encode("ascii") + b"\n")
                raw = self.reader.readline(self.timeout_s)
                text = raw.decode("ascii")
                if not text or any(c < " " for c in text):
                    raise UnicodeDecodeError("ascii", raw, 0, len(raw), "control characters")
            except ReplyTimeout as exc:
                self.counters.timeouts += 1
                self._dirty = True
                if retry and attempt == 0:
                    continue
                raise ReplyTimeout(self.name, f"no reply to {line!r} from {self.link.url} within "
                                              f"{self.timeout_s:g} s (controller stalled or link down)") from exc
            except UnicodeDecodeError as exc:
                self.counters.bad_replies += 1
                self._dirty = True
                log.warning("%s: garbled reply to %r: %r", self.name, line, exc.object)
                if retry and attempt == 0:
                    continue
                raise BadReply(self.name, f"garbled reply to {line!r}: {exc.object!r}") from exc
            return text
        raise AssertionError("unreachable")

    def _check(self, reply: str, line: str) -> None:
        """Every ``;``-separated part of a command reply must be OK."""
        for part in reply.split(";"):
            try:
                r = parse_reply(part)
            except AclError as exc:
                self.counters.error_replies += 1
                if exc.code == AclCode.SETTINGS_CONFLICT:
                    raise DeviceFault(f"{self.name}: controller refused {line!r}: {exc.text}") from exc
                if exc.code == AclCode.OUT_OF_RANGE:
                    raise ValueError(f"{self.name}: controller refused {line!r}: {exc.text}") from exc
                raise
            if r != "OK":
                self.counters.bad_replies += 1
                self._dirty = True
                raise BadReply(self.name, f"expected OK to {line!r}, got {r!r}")

    def command(self, *parts: str) -> None:
        line = ";".join(parts)
        self._check(self.request(line), line)

    # -------------------------------------------------------------------------- set-up
    def identify(self) -> str:
        """Open the link and ask the controller who it is (``*IDN?``, nothing else is sent);
        its reply. Raises LinkLost (the port, or no reply)."""
        self.link.open()
        self.idn = ""
        for attempt in (0, 1):
            try:
                self._drain()
                self.counters.requests += 1
                self.idn = self._sync()
            except ReplyTimeout as exc:
                self.counters.timeouts += 1
                if attempt:
                    raise ReplyTimeout(self.name, f"no reply to '*IDN?' from {self.link.url} within "
                                                  f"{self.timeout_s:g} s (controller stalled or link down)") from exc
            else:
                self._dirty = False
                return self.idn
        raise AssertionError("unreachable")

    def connect(self) -> None:
        """Open the link, identify the controller, close the interlocks, set the limits and
        estimate the controller-time offset."""
        self.identify()
        self.command("*CLS")
        parts = []
        for ax in (1, 2, 3):
            r, a = math.degrees(self.limits.rate[ax - 1]), math.degrees(self.limits.accel[ax - 1])
            parts += [f":LIMIT:RATE P,{ax},{r:.6f}", f":LIMIT:ACCELERATION P,{ax},{a:.6f}",
                      f":LIMIT:RATE R,{ax},{r:.6f}", f":LIMIT:ACCELERATION R,{ax},{a:.6f}"]
        self.command(*parts)
        if self.close_interlocks:
            self.command(":INTERLOCK:CLOSE ALL")
        for _ in range(8):
            t0 = self.clock.now()
            snap = self._read_all()
            t1 = self.clock.now()
            self.time_base.probe(t0, t1, snap[0][4] * 1e-3)
        self.time_base.connected()
        log.info("%s: %s on %s; controller time offset %.6f s (probe round trip %.3g s)", self.name,
                 self.idn, self.link.url, self.time_base.offset, self.time_base.best_rtt)

    def close(self) -> None:
        self.link.close()

    # ---------------------------------------------------------------------- Turntable API
    def move(self, angles: NDArray[np.float64]) -> None:
        angles = np.asarray(angles, float)
        self.check_value(angles, None)
        parts = []
        for ax in (1, 2, 3):
            parts += [f":MODE:POSITION {ax}", f":DEMAND:POSITION {ax},{math.degrees(angles[ax - 1]):.6f}"]
        self.command(*parts)

    def set_rate(self, rates: NDArray[np.float64]) -> None:
        rates = np.asarray(rates, float)
        self.check_value(None, rates)
        parts = []
        for ax in (1, 2, 3):
            r = rates[ax - 1]
            if not math.isnan(r):
                parts += [f":MODE:RATE {ax}", f":DEMAND:RATE {ax},{math.degrees(r):.6f}"]
        if parts:
            self.command(*parts)

    def stop(self) -> None:
        """Controlled stop on every axis (``:MODE:OFF ALL``); optionally open the interlocks."""
        self.command(":MODE:OFF ALL")
        if self.open_interlocks_on_stop:
            self.command(":INTERLOCK:OPEN ALL")

    def _read_all(self) -> list[tuple[float, float, float, int, int]]:
        """Atomic snapshot of the three axes; an unparseable reply is counted and retried once."""
        line = ":READ:ALL? 1;ALL? 2;ALL? 3"
        for attempt in (0, 1):
            reply = self.request(line, retry=True)
            try:
                snaps = [parse_read_all(p) for p in reply.split(";")]
                if len(snaps) != 3:
                    raise AclError(AclCode.COMMAND_ERROR, f"{len(snaps)} axis snapshots")
                return [(s.position_deg, s.rate_deg_s, s.accel_deg_s2, s.status, s.t_ms) for s in snaps]
            except AclError as exc:
                self.counters.bad_replies += 1
                self._dirty = True
                log.warning("%s: bad reply to %r: %s", self.name, line, exc)
                if attempt:
                    raise BadReply(self.name, f"bad reply to {line!r}: {exc}") from exc
        raise AssertionError("unreachable")

    @property
    def time_offset(self) -> float:
        """Controller time -> run time offset, s (:mod:`rigctl.drivers.probe_offset`)."""
        return self.time_base.offset or 0.0

    def read(self) -> TableState:
        t0 = self.clock.now()
        snaps = self._read_all()
        t1 = self.clock.now()
        self.time_base.probe(t0, t1, snaps[0][4] * 1e-3)
        return TableState(time=self.time_base.stamp(snaps[0][4] * 1e-3),
                          angle=np.array([s[0] for s in snaps]) * DEG,
                          rate=np.array([s[1] for s in snaps]) * DEG,
                          status=tuple(int(s[3]) for s in snaps))  # type: ignore[arg-type]

    def check_value(self, angles: NDArray | None, rates: NDArray | None) -> None:
        self.limits.check(angles, rates)


__all__ = ["AclTable", "AclCounters", "LinkLost"]
