"""Emulated turntable speaking the ACL-flavoured ASCII protocol over a pty and over TCP.

Table API (duck-typed; the physics table implements the same). Axes are numbered 1..n_axes as
on the wire; SI units (rad, rad/s, rad/s^2, s); ``mode`` is "off" | "position" | "rate";
refusals raise :class:`TableRefused` with an SCPI-like code (-221 settings conflict such as
interlock open or wrong mode, -222 out of range)::

    n_axes: int
    time() -> float                                   table clock, s
    interlock_close(axis) / interlock_open(axis) / interlock_reset()   (reset: all axes)
    interlock_state(axis) -> "CLOSED" | "OPEN" | "FAULT"
    set_mode(axis, mode) / get_mode(axis) -> mode
    move_to(axis, angle_rad)                          position demand (position mode)
    set_rate(axis, rate_rad_s)                        rate demand (rate mode)
    demand(axis) -> (angle_rad, rate_rad_s)
    set_limits(axis, mode, rate=None, accel=None) / get_limits(axis, mode) -> (rate, accel)
    set_window(axis, window_rad, dwell_s)             in-position window for TARGET_REACHED
    stop(axis=None)                                   controlled stop to rate 0, mode off
    trip(axis, fault_code)                            fault injection: interlock FAULT + stop
    reset()                                           *RST: all off, interlocks open, default limits
    read(axis) -> dict(angle, rate, accel, status, t, following_error, fault_code)

``status`` is the 16-bit word of :class:`rigctl.drivers.modbus_map.StatusBit`.
:class:`IdealTable` implements the API with instant moves (tests; the physics table comes later).
"""
from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from rigctl.drivers.acl import (AclCode, AclError, AclRequest, expect_args, format_error,
                                format_error_queue_entry, format_ok, format_read_all, format_replies,
                                format_status, format_value, parse_axis, parse_message, parse_number)
from rigctl.drivers.modbus_map import FaultCode, StatusBit, wrap_angle

from .links import PtyEndpoint, TcpEndpoint

DEG = math.pi / 180.0
MODES = ("off", "position", "rate")
MAX_LINE = 32768


class TableRefused(Exception):
    """The table refused a request; ``code`` is an SCPI-like code (see module docstring)."""

    def __init__(self, code: int, text: str) -> None:
        super().__init__(f"{code},{text}")
        self.code, self.text = int(code), text


@dataclass
class _Axis:
    mode: str = "off"
    interlock: str = "OPEN"
    angle0: float = 0.0
    t0: float = 0.0
    rate: float = 0.0
    demand_angle: float = 0.0
    demand_rate: float = 0.0
    limits: dict = field(default_factory=lambda: {"position": [100 * DEG, 100 * DEG],
                                                  "rate": [1000 * DEG, 500 * DEG]})
    window: float = 1e-3 * DEG
    dwell: float = 0.0
    t_in: float = 0.0
    fault_code: int = 0


class IdealTable:
    """Instant-response table implementing the table API (see module docstring)."""

    def __init__(self, n_axes: int = 3, clock: Callable[[], float] = time.monotonic) -> None:
        self.n_axes = n_axes
        self._clock = clock
        self._t_start = clock()
        self._lock = threading.RLock()
        self._ax = {a: _Axis() for a in range(1, n_axes + 1)}

    def time(self) -> float:
        return self._clock() - self._t_start

    def _get(self, axis: int) -> _Axis:
        if axis not in self._ax:
            raise TableRefused(AclCode.OUT_OF_RANGE, f"axis {axis} out of range 1..{self.n_axes}")
        return self._ax[axis]

    def _freeze(self, a: _Axis, t: float) -> None:
        a.angle0 += a.rate * (t - a.t0)
        a.t0, a.rate = t, 0.0

    def interlock_close(self, axis: int) -> None:
        with self._lock:
            a = self._get(axis)
            if a.interlock == "FAULT":
                raise TableRefused(AclCode.SETTINGS_CONFLICT, f"axis {axis} interlock fault; reset first")
            a.interlock = "CLOSED"

    def interlock_open(self, axis: int) -> None:
        with self._lock:
            a = self._get(axis)
            self._freeze(a, self.time())
            a.mode = "off"
            if a.interlock != "FAULT":
                a.interlock = "OPEN"

    def interlock_reset(self) -> None:
        with self._lock:
            for a in self._ax.values():
                if a.interlock == "FAULT":
                    a.interlock, a.fault_code = "OPEN", 0

    def interlock_state(self, axis: int) -> str:
        with self._lock:
            return self._get(axis).interlock

    def set_mode(self, axis: int, mode: str) -> None:
        if mode not in MODES:
            raise TableRefused(AclCode.OUT_OF_RANGE, f"unknown mode {mode!r}")
        with self._lock:
            a = self._get(axis)
            if mode != "off" and a.interlock != "CLOSED":
                raise TableRefused(AclCode.SETTINGS_CONFLICT, f"axis {axis} interlock not closed")
            t = self.time()
            self._freeze(a, t)
            a.mode, a.demand_rate = mode, 0.0
            a.demand_angle, a.t_in = a.angle0, t

    def get_mode(self, axis: int) -> str:
        with self._lock:
            return self._get(axis).mode

    def _require(self, axis: int, mode: str) -> _Axis:
        a = self._get(axis)
        if a.interlock != "CLOSED":
            raise TableRefused(AclCode.SETTINGS_CONFLICT, f"axis {axis} interlock not closed")
        if a.mode != mode:
            raise TableRefused(AclCode.SETTINGS_CONFLICT, f"axis {axis} not in {mode} mode")
        return a

    def move_to(self, axis: int, angle_rad: float) -> None:
        with self._lock:
            a = self._require(axis, "position")
            t = self.time()
            a.angle0, a.t0, a.rate = float(angle_rad), t, 0.0
            a.demand_angle, a.t_in = float(angle_rad), t

    def set_rate(self, axis: int, rate_rad_s: float) -> None:
        with self._lock:
            a = self._require(axis, "rate")
            if abs(rate_rad_s) > a.limits["rate"][0]:
                raise TableRefused(AclCode.OUT_OF_RANGE, f"rate {rate_rad_s / DEG:g} deg/s above the "
                                   f"{a.limits['rate'][0] / DEG:g} deg/s limit")
            self._freeze(a, self.time())
            a.rate = a.demand_rate = float(rate_rad_s)

    def demand(self, axis: int) -> tuple[float, float]:
        with self._lock:
            a = self._get(axis)
            return a.demand_angle, a.demand_rate

    def set_limits(self, axis: int, mode: str, rate: float | None = None, accel: float | None = None) -> None:
        with self._lock:
            a = self._get(axis)
            if mode not in a.limits:
                raise TableRefused(AclCode.OUT_OF_RANGE, f"no limits for mode {mode!r}")
            for i, v in ((0, rate), (1, accel)):
                if v is not None:
                    if not v > 0:
                        raise TableRefused(AclCode.OUT_OF_RANGE, "limits must be positive")
                    a.limits[mode][i] = float(v)

    def get_limits(self, axis: int, mode: str) -> tuple[float, float]:
        with self._lock:
            a = self._get(axis)
            if mode not in a.limits:
                raise TableRefused(AclCode.OUT_OF_RANGE, f"no limits for mode {mode!r}")
            return tuple(a.limits[mode])  # type: ignore[return-value]

    def set_window(self, axis: int, window_rad: float, dwell_s: float) -> None:
        with self._lock:
            a = self._get(axis)
            a.window, a.dwell = abs(float(window_rad)), max(0.0, float(dwell_s))

    def stop(self, axis: int | None = None) -> None:
        with self._lock:
            t = self.time()
            for ax in ([axis] if axis is not None else list(self._ax)):
                a = self._get(ax)
                self._freeze(a, t)
                a.mode, a.demand_rate = "off", 0.0

    def trip(self, axis: int, fault_code: int = FaultCode.INTERLOCK_TRIP) -> None:
        with self._lock:
            a = self._get(axis)
            self._freeze(a, self.time())
            a.mode, a.interlock, a.fault_code = "off", "FAULT", int(fault_code)

    def reset(self) -> None:
        with self._lock:
            t = self.time()
            for ax, a in list(self._ax.items()):
                self._freeze(a, t)
                self._ax[ax] = _Axis(angle0=a.angle0, t0=t)

    def read(self, axis: int) -> dict:
        with self._lock:
            a = self._get(axis)
            t = self.time()
            angle = a.angle0 + a.rate * (t - a.t0)
            s = StatusBit.READY | StatusBit.PROFILE_COMPLETE
            if a.interlock == "CLOSED":
                s |= StatusBit.SERVO_ON
                if a.mode != "off":
                    s |= StatusBit.OPERATION_ENABLED
            else:
                s |= StatusBit.INTERLOCK_OPEN
            if a.interlock == "FAULT":
                s |= StatusBit.FAULT
            if a.mode == "rate":
                s |= StatusBit.AT_RATE
            ferr = wrap_angle(a.demand_angle - angle) if a.mode == "position" else 0.0
            if a.mode == "position" and abs(ferr) <= a.window and t - a.t_in >= a.dwell:
                s |= StatusBit.TARGET_REACHED
            if a.rate != 0.0:
                s |= StatusBit.MOVING
            return {"angle": angle, "rate": a.rate, "accel": 0.0, "status": int(s), "t": t,
                    "following_error": ferr, "fault_code": a.fault_code}


# ----------------------------------------------------------------------------- protocol

_MODE_WORDS = {"P": "position", "POS": "position", "POSITION": "position", "R": "rate", "RATE": "rate",
               "O": "off", "OFF": "off"}
_MODE_LETTER = {"position": "P", "rate": "R", "off": "O"}
_LIMIT_MODE = {"P": "position", "R": "rate"}


class AclServerCore:
    """Protocol logic: ``handle_line(str) -> reply line`` (no terminator), thread-safe.

    Side-channel faults (not on the wire): ``drop_replies`` (swallow the next n replies),
    ``delay_s`` (sleep before replying), ``garble_replies`` (corrupt the next n replies).
    ``answered`` counts the request lines done: reply written to the port (or swallowed);
    ``answered_bytes`` the bytes of those replies.
    """

    answered = 0
    answered_bytes = 0

    def __init__(self, table, serial: str = "SIM0001", version: str = "0.1") -> None:
        self.table = table
        self.idn = f"SIM,TT3-SIM,{serial},{version}"
        self.errors: deque[tuple[int, str]] = deque(maxlen=32)
        self.lock = threading.Lock()
        self.drop_replies = 0
        self.garble_replies = 0
        self.delay_s = 0.0

    def handle_line(self, line: str | bytes) -> str | None:
        with self.lock:
            try:
                reqs = parse_message(line)
            except AclError as e:
                self.errors.append((e.code, e.text))
                reply = format_error(e.code, e.text)
            else:
                out = []
                for r in reqs:
                    try:
                        out.append(self._exec(r))
                    except (AclError, TableRefused) as e:
                        self.errors.append((e.code, e.text))
                        out.append(format_error(e.code, e.text))
                reply = ";".join(out)
            if self.delay_s:
                time.sleep(self.delay_s)
            if self.drop_replies > 0:
                self.drop_replies -= 1
                return None
            if self.garble_replies > 0:
                self.garble_replies -= 1
                reply = reply[::-1].replace("O", "#") + "\x7f"
            return reply

    def _axes(self, arg: str, allow_all: bool = False) -> list[int]:
        return parse_axis(arg, self.table.n_axes, allow_all)

    def _exec(self, req: AclRequest) -> str:
        t, p, q = self.table, req.path, req.query
        if p == ("*IDN",):
            return self.idn
        if p == ("*RST",):
            t.reset()
            self.errors.clear()
            return format_ok()
        if p == ("*CLS",):
            self.errors.clear()
            return format_ok()
        if p == ("SYSTEM", "ERROR"):
            return format_error_queue_entry(*self.errors.popleft()) if self.errors else \
                format_error_queue_entry(0, "No error")
        if p == ("ABORT",):
            t.stop()
            return format_ok()
        if p == ("INTERLOCK", "RESET"):
            t.interlock_reset()
            return format_ok()
        if p[0] == "INTERLOCK":
            if q:
                return t.interlock_state(self._axes(expect_args(req, 1)[0])[0])
            for ax in self._axes(expect_args(req, 1)[0], allow_all=True):
                t.interlock_close(ax) if p[1] == "CLOSE" else t.interlock_open(ax)
            return format_ok()
        if p[0] == "MODE":
            if q:
                return _MODE_LETTER[t.get_mode(self._axes(expect_args(req, 1)[0])[0])]
            if len(p) == 1:
                ax_arg, mode_arg = expect_args(req, 2)
                mode = _MODE_WORDS.get(mode_arg.strip().upper())
                if mode is None:
                    raise AclError(AclCode.COMMAND_ERROR, f"Unknown mode {mode_arg!r}")
            else:
                ax_arg, mode = expect_args(req, 1)[0], p[1].lower()
            for ax in self._axes(ax_arg, allow_all=True):
                t.set_mode(ax, mode)
            return format_ok()
        if p[0] == "DEMAND":
            if q:
                ang, rate = t.demand(self._axes(expect_args(req, 1)[0])[0])
                return format_value((ang if p[1] == "POSITION" else rate) / DEG)
            ax_arg, v = expect_args(req, 2)
            ax, val = self._axes(ax_arg)[0], parse_number(v) * DEG
            t.move_to(ax, val) if p[1] == "POSITION" else t.set_rate(ax, val)
            return format_ok()
        if p[0] == "LIMIT":
            n = 2 if q else 3
            args = expect_args(req, n)
            mode = _LIMIT_MODE.get(args[0].strip().upper()[:1])
            if mode is None:
                raise AclError(AclCode.COMMAND_ERROR, f"Limit mode must be P or R, got {args[0]!r}")
            ax = self._axes(args[1])[0]
            i = 0 if p[1] == "RATE" else 1
            if q:
                return format_value(t.get_limits(ax, mode)[i] / DEG)
            v = parse_number(args[2]) * DEG
            t.set_limits(ax, mode, **({"rate": v} if i == 0 else {"accel": v}))
            return format_ok()
        if p[0] in ("READ", "STATUS"):
            r = t.read(self._axes(expect_args(req, 1)[0])[0])
            if p[1] == "POSITION":
                return format_value(wrap_angle(r["angle"]) / DEG)
            if p[1] == "RATE":
                return format_value(r["rate"] / DEG)
            if p[1] == "ACCELERATION":
                return format_value(r["accel"] / DEG)
            if p[1] == "AXIS":
                return format_status(r["status"])
            return format_read_all(wrap_angle(r["angle"]) / DEG, r["rate"] / DEG, r["accel"] / DEG,
                                   r["status"], int(round(r["t"] * 1e3)))
        raise AclError(AclCode.COMMAND_ERROR, f"Command not implemented: {req.name}")


class _LineHandler:
    """Assembles lines from a byte stream and writes one reply line per request line."""

    def __init__(self, core: AclServerCore) -> None:
        self.core, self.buf = core, b""

    def __call__(self, data: bytes, write: Callable[[bytes], None]) -> None:
        self.buf += data
        *lines, self.buf = self.buf.split(b"\n")
        if len(self.buf) > MAX_LINE:
            self.buf = b""
            write(format_replies([format_error(AclCode.COMMAND_ERROR, "Line too long")]))
        for line in lines:
            line = line.rstrip(b"\r")
            if not line.strip():
                continue
            reply = self.core.handle_line(line)
            out = b"" if reply is None else reply.encode("ascii", "replace") + b"\n"
            if out:
                write(out)
            with self.core.lock:
                self.core.answered += 1
                self.core.answered_bytes += len(out)


class AclServer:
    """Serves one table over any number of ptys and TCP listeners; ``close()`` tears all down."""

    def __init__(self, table=None, serial: str = "SIM0001") -> None:
        self.table = table if table is not None else IdealTable()
        self.core = AclServerCore(self.table, serial=serial)
        self._endpoints: list = []

    def open_pty(self) -> str:
        """Start a pty endpoint; returns the path the client opens (``/dev/pts/N``)."""
        ep = PtyEndpoint(_LineHandler(self.core), name="acl-pty")
        self._endpoints.append(ep)
        return ep.path

    def open_tcp(self, host: str = "127.0.0.1", port: int = 0) -> tuple[str, int]:
        """Start a TCP listener (port 0 = OS-picked); returns (host, port)."""
        ep = TcpEndpoint(lambda: _LineHandler(self.core), host=host, port=port, name="acl-tcp")
        self._endpoints.append(ep)
        return ep.address

    def close(self) -> None:
        while self._endpoints:
            self._endpoints.pop().close()

    def __enter__(self) -> AclServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
