"""Pulse edges on a serial port's modem-status line (DCD, CTS, DSR or RI), behind
:class:`rigctl.devices.PulseSource`.

Mode ``wait`` (real UARTs): a thread blocks in ``ioctl(fd, TIOCMIWAIT, mask)`` until the line
changes, takes ``time.monotonic_ns()`` at once, reads the level with ``TIOCMGET`` and the kernel's
per-line transition counters with ``TIOCGICOUNT`` (``struct serial_icounter_struct``: cts, dsr,
rng, dcd, rx, tx, frame, overrun, parity, brk, buf_overrun, 9 reserved ints). A counter step of
more transitions between two wake-ups than the level change explains means edges were missed
(counted in ``missed``; never silently ignored). TIOCMIWAIT has no timeout and cannot be
interrupted portably: ``close`` closes the port and waits 0.5 s; a thread still blocked in the
ioctl (a daemon thread) ends at the next line change.

Mode ``poll``: reads the line through pyserial (``ser.cd`` / ``cts`` / ``dsr`` / ``ri``) every
``poll_interval_s`` -- coarser timestamps, but it works on any pyserial URL that reports modem
lines (``rfc2217://``, and ``loop://`` where CTS follows RTS, which the tests use).

Time base: host monotonic clock at wake-up (userspace latency: tens of us to ~1 ms; the kernel
PPS line discipline is better for DCD, see docs/hardware.md), mapped onto the run clock by the
offset taken at connect (scaled by the run clock's speed).

Untested without hardware: TIOCMIWAIT/TIOCGICOUNT on a real UART (ptys answer ENOTTY, which the
tests check produces a clear error), the latency of USB-serial adapters.
"""
from __future__ import annotations

import array
import fcntl
import logging
import termios
import time

import serial

from rigctl.devices import Clock

from .reader_thread import HostTimedPulses

log = logging.getLogger(__name__)
LINES = {"cd": termios.TIOCM_CD, "cts": termios.TIOCM_CTS, "dsr": termios.TIOCM_DSR, "ri": termios.TIOCM_RI}
#: index of each line's counter in struct serial_icounter_struct
ICOUNT_INDEX = {"cts": 0, "dsr": 1, "ri": 2, "cd": 3}
ICOUNT_INTS = 20


def parse_icount(buf: bytes | array.array) -> dict[str, int]:
    """Decode ``struct serial_icounter_struct`` (20 native ints) into the four line counters."""
    a = array.array("i")
    a.frombytes(bytes(buf)[:4 * ICOUNT_INTS])
    return {k: int(a[i]) for k, i in ICOUNT_INDEX.items()}


def read_icount(fd: int) -> dict[str, int]:
    buf = array.array("i", [0] * ICOUNT_INTS)
    fcntl.ioctl(fd, termios.TIOCGICOUNT, buf, True)
    return parse_icount(buf.tobytes())


def _level(fd: int, mask: int) -> bool:
    return bool(int.from_bytes(fcntl.ioctl(fd, termios.TIOCMGET, b"\0\0\0\0"), "little") & mask)


class ModemPulses(HostTimedPulses):
    """Edges on a modem-status line of ``url``; ``connect()``, ``read()``, ``close()``."""

    source, reader_what = "modem", "modem-line reader"

    def __init__(self, url: str, clock: Clock, *, baudrate: int = 9600, line: str = "cd", edge: str = "rising",
                 mode: str = "wait", poll_interval_s: float = 0.001, name: str = "pulses") -> None:
        if line not in LINES:
            raise ValueError(f"line must be one of {', '.join(LINES)}")
        self.url, self.clock, self.name = url, clock, name
        self.baudrate, self.line, self.edge, self.mode, self.poll_interval_s = baudrate, line, edge, mode, poll_interval_s
        self.ser: serial.SerialBase | None = None
        self.edges = 0
        self.missed = 0
        self._init_pulses()

    def identify(self) -> str:
        """Open the port and read the configured modem-status line's level; close it."""
        ser = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.1)
        try:
            level = self._poll_level(ser)
        finally:
            ser.close()
        return f"port open, {self.line.upper()} {'high' if level else 'low'}"

    def connect(self) -> None:
        self.ser = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.1)
        if self.mode == "wait":
            try:
                fd = self.ser.fileno()
                self._count = read_icount(fd)[self.line]
                self._level = _level(fd, LINES[self.line])
            except (OSError, AttributeError, serial.SerialException) as exc:
                self.ser.close()
                self.ser = None
                raise RuntimeError(f"{self.name}: {self.url} has no modem-status lines to wait on ({exc}); "
                                   "ptys and sockets cannot carry DCD/CTS edges -- use a real UART, or "
                                   "mode: poll on an rfc2217:// port") from exc
        else:
            self._level = self._poll_level(self.ser)
        self._start_pulses(self._run_wait if self.mode == "wait" else self._run_poll, time.monotonic_ns(), "modem")

    def _poll_level(self, ser: serial.SerialBase) -> bool:
        return bool(getattr(ser, self.line))

    def _wanted(self, rising: bool) -> bool:
        return self.edge == "both" or (self.edge == "rising") == rising

    def on_change(self, t_ns: int, level: bool, transitions: int) -> None:
        """Account for a wake-up: ``transitions`` counted by the kernel since the last one."""
        expected = int(level != self._level)
        if transitions > expected:               # whole pulses (or more) happened unseen
            self.missed += transitions - expected
            log.warning("%s: %d %s transitions missed", self.name, transitions - expected, self.line)
        if level != self._level and self._wanted(level):
            self.edges += 1
            self._add([self.to_run_time(t_ns)])
        self._level = level

    def _run_wait(self) -> None:
        fd, mask = self.ser.fileno(), LINES[self.line]
        try:
            while not self._stop.is_set():
                fcntl.ioctl(fd, termios.TIOCMIWAIT, mask)
                t_ns = time.monotonic_ns()
                level = _level(fd, mask)
                count = read_icount(fd)[self.line]
                self.on_change(t_ns, level, count - self._count)
                self._count = count
        except OSError as exc:
            if not self._stop.is_set():
                log.exception("%s: modem-line wait failed", self.name)
                self._fatal = exc

    def _run_poll(self) -> None:
        ser = self.ser  # close() sets self.ser to None, then closes it: this read then raises
        try:
            while not self._stop.wait(self.poll_interval_s):
                level = self._poll_level(ser)
                if level != self._level:
                    self.on_change(time.monotonic_ns(), level, 1)
        except (OSError, serial.SerialException) as exc:
            if not self._stop.is_set():
                self._fatal = exc

    def close(self) -> None:
        self._stop.set()
        ser, self.ser = self.ser, None
        if ser is not None:
            ser.close()
        if self._thread is not None:    # TIOCMIWAIT cannot be interrupted portably: a thread
            self._thread.join(timeout=0.5)  # blocked in it (daemon) ends at the next line change
