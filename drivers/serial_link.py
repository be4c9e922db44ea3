"""A serial link opened with ``serial.serial_for_url`` that reconnects with backoff.

Every serial-style driver (ACL table, Xsens IMU, NovAtel receiver) talks through
:class:`SerialLink`, so a config switches between ``/dev/ttyUSB0``, a pty path (or a symlink to
one) and ``socket://host:port`` (and any other pyserial URL: ``rfc2217://``, ``spy://``, ...)
without code changes.

Link loss (the port vanishes, a read fails, the peer closes the socket) closes the port, records
an event and raises :class:`rigctl.devices.LinkLost`. The next call reopens the port, at most once
per backoff interval (``first_s`` doubling up to ``max_s``, wall time), so a driver can simply call
:meth:`SerialLink.ensure` at the start of every operation. Reply timeouts raise
:class:`ReplyTimeout` and unparseable replies :class:`BadReply` (both are ``LinkLost``: the engine
pauses on them like on a pulled cable).
"""
from __future__ import annotations

import errno
import logging
import socket
import time
from dataclasses import dataclass, field

import serial

from rigctl.devices import LinkLost

log = logging.getLogger(__name__)

#: what to look at when a device path does not exist, per kind of port
_LOOK = {"serial": "is the adapter plugged in? ls /dev/serial/by-id",
         "gpio": "does the board have that chip? ls /dev/gpiochip*"}


def _errnos(exc: BaseException) -> list[int]:
    """errno values found along ``exc``'s chain (cause and context), outermost first."""
    out, seen, e = [], set(), exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, socket.gaierror):
            out.append(-1000)  # name resolution: its own (negative, platform) codes
        elif isinstance(e, OSError) and isinstance(e.errno, int):
            out.append(e.errno)
        elif isinstance(e, OSError) and e.args and isinstance(e.args[0], int):  # termios.error
            out.append(e.args[0])
        e = e.__cause__ or e.__context__
    return out


def explain_link_error(where: str, exc: BaseException, kind: str = "serial") -> str:
    """One line saying what is wrong with the port ``where`` (a pyserial URL, a TCP address, a
    GPIO chip) and what to do, from the errno ``exc`` (or an exception it chains) carries;
    ``kind`` is "serial", "tcp" or "gpio"."""
    codes = _errnos(exc)
    code = codes[0] if codes else None
    if code == errno.ENOENT:
        return f"{where}: no such device; {_LOOK.get(kind, _LOOK['serial'])}"
    if code in (errno.EACCES, errno.EPERM):
        group = "gpio" if kind == "gpio" else "dialout"
        return (f"{where}: permission denied; add the user to the {group} group (sudo adduser $USER {group}, "
                "then log in again)")
    if code == errno.EBUSY:
        return f"{where}: busy; another program holds the port (another rigctl? fuser {where})"
    if code == errno.ECONNREFUSED:
        return f"{where}: connection refused; is rigctl sim up / the device server running?"
    if code == -1000:
        return f"{where}: unknown host; check the host name in the config"
    if code in (errno.ETIMEDOUT, errno.EHOSTUNREACH, errno.ENETUNREACH, errno.EHOSTDOWN):
        return f"{where}: host unreachable ({errno.errorcode.get(code, code)}); check the address and the network"
    if code == errno.ENOTTY:
        return f"{where}: not a serial port; give the adapter's device (ls /dev/serial/by-id) or socket://HOST:PORT"
    if code == errno.EISDIR:
        return f"{where}: is a directory; give the device (ls /dev/serial/by-id)"
    if isinstance(exc, ReplyTimeout) or "no answer" in str(exc) or "no acknowledgement" in str(exc):
        return (f"{where}: opened, but the device does not answer; is it powered and is the right device "
                f"on this port, at the configured baud rate? ({exc})")
    return f"{where}: {exc}"


class ReplyTimeout(LinkLost):
    """No (complete) reply within the timeout."""


class BadReply(LinkLost):
    """A reply that could not be parsed (garbled, truncated, wrong checksum)."""


@dataclass
class Backoff:
    """Reconnect pacing: wait ``first_s``, then double up to ``max_s`` (wall seconds)."""

    first_s: float = 0.05
    max_s: float = 5.0
    _delay: float = 0.0
    _next: float = 0.0

    def ready(self) -> bool:
        return time.monotonic() >= self._next

    def wait_s(self) -> float:
        return max(0.0, self._next - time.monotonic())

    def failed(self) -> None:
        self._delay = min(self.max_s, self._delay * 2 if self._delay else self.first_s)
        self._next = time.monotonic() + self._delay

    def reset(self) -> None:
        self._delay, self._next = 0.0, 0.0


@dataclass
class LinkEvent:
    wall_time: float
    kind: str          # "lost" | "reconnected" | "open-failed"
    message: str


@dataclass
class SerialLink:
    """One pyserial URL with reconnect-with-backoff; see the module docstring."""

    url: str
    name: str
    baudrate: int = 115200
    timeout_s: float = 0.5
    backoff: Backoff = field(default_factory=Backoff)
    ser: serial.SerialBase | None = field(default=None, repr=False)
    opens: int = 0
    losses: int = 0
    events: list[LinkEvent] = field(default_factory=list)

    @property
    def is_open(self) -> bool:
        return self.ser is not None

    @property
    def reconnects(self) -> int:
        """Successful opens after the first."""
        return max(0, self.opens - 1)

    def _event(self, kind: str, message: str) -> None:
        self.events.append(LinkEvent(time.monotonic(), kind, message))
        (log.warning if kind != "reconnected" else log.info)("%s (%s): %s", self.name, self.url, message)

    def open(self) -> serial.SerialBase:
        """Open the port now (raises LinkLost naming the URL on failure)."""
        try:
            ser = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.timeout_s,
                                        write_timeout=max(self.timeout_s, 1.0))
        except (serial.SerialException, OSError, ValueError) as exc:
            self.backoff.failed()
            if self.opens:
                self._event("open-failed", f"reopen failed: {exc}")
            raise LinkLost(self.name, f"cannot open {self.url}: {exc}") from exc
        self.ser = ser
        self.opens += 1
        self.backoff.reset()
        if self.opens > 1:
            self._event("reconnected", f"link re-established (reconnect #{self.opens - 1})")
        return ser

    def ensure(self) -> serial.SerialBase:
        """The open port; reopens a lost one when the backoff allows, else raises LinkLost."""
        if self.ser is not None:
            return self.ser
        if not self.backoff.ready():
            raise LinkLost(self.name, f"link to {self.url} down; next reconnect attempt in "
                                      f"{self.backoff.wait_s():.2f} s")
        return self.open()

    def lost(self, exc: BaseException | str) -> LinkLost:
        """Close the port after a failure and return the LinkLost to raise."""
        self.close()
        self.losses += 1
        self.backoff.failed()
        self._event("lost", f"link lost: {exc}")
        return LinkLost(self.name, f"link to {self.url} lost: {exc}")

    def write(self, data: bytes) -> None:
        ser = self.ensure()
        try:
            ser.write(data)
        except (serial.SerialException, OSError) as exc:
            raise self.lost(exc) from exc

    def read_some(self, timeout_s: float | None = None, max_bytes: int = 1 << 16) -> bytes:
        """Whatever arrives within ``timeout_s`` (returns as soon as any byte is there)."""
        ser = self.ensure()
        try:
            t = self.timeout_s if timeout_s is None else timeout_s
            if ser.timeout != t:  # pyserial's setter reconfigures the port (tcgetattr +
                ser.timeout = t   # tcsetattr) even for the same value: ~9 % of a stream reader
            n = ser.in_waiting
            return ser.read(min(max(n, 1), max_bytes))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # pyserial raises TypeError/AttributeError when another thread closed the port
            raise self.lost(exc) from exc

    def drain_input(self) -> int:
        """Discard buffered input (after a timeout, so a late reply cannot be misread)."""
        if self.ser is None:
            return 0
        try:
            n = self.ser.in_waiting
            self.ser.reset_input_buffer()
            return n
        except (serial.SerialException, OSError) as exc:
            raise self.lost(exc) from exc

    def close(self) -> None:
        ser, self.ser = self.ser, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass


class LineReader:
    """Assembles lines (LF-terminated, CR stripped) from a :class:`SerialLink`."""

    def __init__(self, link: SerialLink, max_line: int = 32768) -> None:
        self.link, self.max_line = link, max_line
        self._buf = bytearray()

    def clear(self) -> None:
        self._buf.clear()

    def take(self) -> bytes:
        """The buffered bytes not yet returned as lines (and forget them)."""
        out = bytes(self._buf)
        self._buf.clear()
        return out

    def readline(self, timeout_s: float) -> bytes:
        """One line without its terminator; raises ReplyTimeout or LinkLost."""
        deadline = time.monotonic() + timeout_s
        while True:
            i = self._buf.find(b"\n")
            if i >= 0:
                line = bytes(self._buf[:i]).rstrip(b"\r")
                del self._buf[:i + 1]
                return line
            if len(self._buf) > self.max_line:
                self._buf.clear()
                raise BadReply(self.link.name, f"reply longer than {self.max_line} bytes without a line end")
            left = deadline - time.monotonic()
            if left <= 0:
                raise ReplyTimeout(self.link.name, f"no complete reply from {self.link.url} within "
                                                   f"{timeout_s:g} s")
            self._buf += self.link.read_some(left)
