"""Adapters from the physics emulator (:mod:`rigctl.sim.world`) to the wire servers.

* :class:`PhysicsTable` implements the duck-typed table API of :mod:`rigctl.sim.acl_server`
  (used by the ACL and the Modbus servers) on the world's :class:`~rigctl.sim.table.SimTurntable`:
  profiles, servo dynamics and status bits are the in-process emulator's, so a procedure run over
  the wire sees the same table as an in-process run. Added on top: per-axis interlocks (open at
  power-up; closing one is required before a mode other than off), trips (interlock or following
  error: FAULT bit, fault code, controlled stop, refusal until an interlock reset) and per-mode
  rate/acceleration limits.
* :class:`ImuTap` keeps the world's IMU samples with their true times so the Xsens emulator can
  stream them: a frame for time ``t`` carries the world sample whose true time is nearest ``t``
  (sample ``round(t * world_rate)`` when the IMU's clock is perfect; exact when the Xsens output
  rate divides the world rate; otherwise sample-and-hold). With a drifting IMU clock the stream
  stays on the run clock: a sample now and then repeats (slow clock) or is skipped (fast).

Reads never advance the world (the hardware loop does, every tick), so they are cheap and see
the state at the last tick; commands advance it first and act at the world's current time.
All values SI (rad, rad/s, rad/s^2, s); axes 1..3 = outer, middle, inner.
"""
from __future__ import annotations

import math
import threading

import numpy as np

from rigctl.config.config import TableLimits
from rigctl.devices import AxisStatus
from rigctl.drivers.acl import AclCode
from rigctl.drivers.modbus_map import FaultCode

from .acl_server import TableRefused
from .table import OFF, POSITION, RATE
from .world import SimWorld

MODE_NAME = {OFF: "off", POSITION: "position", RATE: "rate"}


class PhysicsTable:
    """Table API (see :mod:`rigctl.sim.acl_server`) over a :class:`SimWorld`'s turntable."""

    n_axes = 3

    def __init__(self, world: SimWorld, lock: threading.RLock, limits: TableLimits) -> None:
        self.world, self.lock, self.cfg_limits = world, lock, limits
        self._defaults = [(float(limits.rate[i]), float(limits.accel[i])) for i in range(3)]
        self.interlock: dict[int, str] = {}
        self.fault_code: dict[int, int] = {}
        self.limits: dict[int, dict[str, list[float]]] = {}
        self._init_axes()

    def _init_axes(self) -> None:
        for a in (1, 2, 3):
            self.interlock[a], self.fault_code[a] = "OPEN", 0
            r, acc = self._defaults[a - 1]
            self.limits[a] = {"position": [r, acc], "rate": [r, acc]}

    # -------------------------------------------------------------------------- helpers
    def _ax(self, axis: int):
        if axis not in (1, 2, 3):
            raise TableRefused(AclCode.OUT_OF_RANGE, f"axis {axis} out of range 1..3")
        return self.world.table.axes[axis - 1]

    def _t(self) -> float:
        """The run time the world has been advanced to, s."""
        return self.world.t

    def _now(self) -> float:
        """Advance the world to the clock and return its time (for commands)."""
        self.world.advance()
        return self._t()

    def _use_limits(self, axis: int, mode: str) -> None:
        ax = self._ax(axis)
        ax.vmax, ax.amax = self.limits[axis][mode]

    def _require(self, axis: int, mode: str):
        ax = self._ax(axis)
        if self.interlock[axis] != "CLOSED":
            raise TableRefused(AclCode.SETTINGS_CONFLICT, f"axis {axis} interlock {self.interlock[axis].lower()}"
                               + ("; reset the fault first" if self.interlock[axis] == "FAULT" else ""))
        if MODE_NAME[ax.mode] != mode:
            raise TableRefused(AclCode.SETTINGS_CONFLICT, f"axis {axis} not in {mode} mode")
        return ax

    # ------------------------------------------------------------------------ table API
    def time(self) -> float:
        with self.lock:
            return self._t()

    def interlock_close(self, axis: int) -> None:
        with self.lock:
            self._ax(axis)
            if self.interlock[axis] == "FAULT":
                raise TableRefused(AclCode.SETTINGS_CONFLICT, f"axis {axis} interlock fault; reset first")
            self.interlock[axis] = "CLOSED"

    def interlock_open(self, axis: int) -> None:
        with self.lock:
            ax = self._ax(axis)
            ax.command(self._now(), OFF, 0.0)
            if self.interlock[axis] != "FAULT":
                self.interlock[axis] = "OPEN"

    def interlock_reset(self) -> None:
        with self.lock:
            for a in (1, 2, 3):
                if self.interlock[a] == "FAULT":
                    self.interlock[a], self.fault_code[a] = "OPEN", 0

    def interlock_state(self, axis: int) -> str:
        with self.lock:
            self._ax(axis)
            return self.interlock[axis]

    def set_mode(self, axis: int, mode: str) -> None:
        if mode not in ("off", "position", "rate"):
            raise TableRefused(AclCode.OUT_OF_RANGE, f"unknown mode {mode!r}")
        with self.lock:
            ax = self._ax(axis)
            if mode != "off" and self.interlock[axis] != "CLOSED":
                raise TableRefused(AclCode.SETTINGS_CONFLICT, f"axis {axis} interlock not closed")
            if MODE_NAME[ax.mode] == mode:
                return
            t = self._now()
            if mode == "off":
                ax.command(t, OFF, 0.0)
                return
            self._use_limits(axis, mode)
            ax.command(t, RATE, 0.0)            # come to rest (rate mode: hold zero rate)
            if mode == "position":              # ... and hold where the stop ends
                ax.mode, ax.target = POSITION, float(ax.profile.p[-1])

    def get_mode(self, axis: int) -> str:
        with self.lock:
            return MODE_NAME[self._ax(axis).mode]

    def move_to(self, axis: int, angle_rad: float) -> None:
        with self.lock:
            ax = self._require(axis, "position")
            lo, hi = self.cfg_limits.angle_min[axis - 1], self.cfg_limits.angle_max[axis - 1]
            if not lo <= angle_rad <= hi:
                raise TableRefused(AclCode.OUT_OF_RANGE, f"axis {axis} angle {math.degrees(angle_rad):g} deg "
                                   f"outside [{math.degrees(lo):g}, {math.degrees(hi):g}] deg")
            self._use_limits(axis, "position")
            ax.command(self._now(), POSITION, float(angle_rad))

    def set_rate(self, axis: int, rate_rad_s: float) -> None:
        with self.lock:
            ax = self._require(axis, "rate")
            vmax = self.limits[axis]["rate"][0]
            if abs(rate_rad_s) > vmax * (1 + 1e-9):
                raise TableRefused(AclCode.OUT_OF_RANGE, f"rate {math.degrees(rate_rad_s):g} deg/s above the "
                                   f"{math.degrees(vmax):g} deg/s limit")
            self._use_limits(axis, "rate")
            ax.command(self._now(), RATE, float(rate_rad_s))

    def demand(self, axis: int) -> tuple[float, float]:
        with self.lock:
            ax = self._ax(axis)
            return (ax.target if ax.mode == POSITION else float(ax.last[0]),
                    ax.target if ax.mode == RATE else 0.0)

    def set_limits(self, axis: int, mode: str, rate: float | None = None, accel: float | None = None) -> None:
        with self.lock:
            self._ax(axis)
            if mode not in ("position", "rate"):
                raise TableRefused(AclCode.OUT_OF_RANGE, f"no limits for mode {mode!r}")
            for i, v in ((0, rate), (1, accel)):
                if v is not None:
                    if not v > 0:
                        raise TableRefused(AclCode.OUT_OF_RANGE, "limits must be positive")
                    if v > self._defaults[axis - 1][i] * (1 + 1e-9):
                        raise TableRefused(AclCode.OUT_OF_RANGE, "limit above the table's capability")
                    self.limits[axis][mode][i] = float(v)

    def get_limits(self, axis: int, mode: str) -> tuple[float, float]:
        with self.lock:
            self._ax(axis)
            if mode not in ("position", "rate"):
                raise TableRefused(AclCode.OUT_OF_RANGE, f"no limits for mode {mode!r}")
            return tuple(self.limits[axis][mode])  # type: ignore[return-value]

    def set_window(self, axis: int, window_rad: float, dwell_s: float) -> None:
        with self.lock:
            servo = self._ax(axis).servo
            servo.in_position_window, servo.dwell_s = abs(float(window_rad)), max(0.0, float(dwell_s))

    def stop(self, axis: int | None = None) -> None:
        with self.lock:
            t = self._now()
            for a in ([axis] if axis is not None else [1, 2, 3]):
                self._ax(a).command(t, OFF, 0.0)

    def trip(self, axis: int, fault_code: int = FaultCode.INTERLOCK_TRIP) -> None:
        """Fault injection: interlock FAULT, fault code, controlled stop."""
        with self.lock:
            self._ax(axis).command(self._now(), OFF, 0.0)
            self.interlock[axis], self.fault_code[axis] = "FAULT", int(fault_code)

    def reset(self) -> None:
        with self.lock:
            t = self._now()
            for ax in self.world.table.axes:
                ax.command(t, OFF, 0.0)
            self._init_axes()

    def read(self, axis: int) -> dict:
        with self.lock:
            ax = self._ax(axis)
            t = self._t()
            ang, rate, status = self.world.table.measured(t)
            i = axis - 1
            s = int(status[i])
            if self.interlock[axis] != "CLOSED":
                s |= AxisStatus.INTERLOCK_OPEN
                s &= ~int(AxisStatus.SERVO_ON)
            if self.interlock[axis] == "FAULT":
                s |= AxisStatus.FAULT
                if self.fault_code[axis] == FaultCode.FOLLOWING_ERROR:
                    s |= AxisStatus.FOLLOWING_ERROR
            ferr = ax.target - ax.last[0] if ax.mode == POSITION else 0.0
            return {"angle": float(ang[i]), "rate": float(rate[i]), "accel": float(ax.last[2]), "status": s,
                    "t": t, "following_error": float(ferr), "fault_code": self.fault_code[axis]}


class ImuTap:
    """The world's IMU samples by index, as a ``source(t)`` for the Xsens emulator."""

    def __init__(self, world: SimWorld, lock: threading.RLock) -> None:
        self.world, self.lock = world, lock
        self.base = 0                                  # index of the first buffered sample
        self._tt = np.empty(0)                         # true times of the buffered samples, s
        self._f = np.empty((0, 3))
        self._w = np.empty((0, 3))
        self._temp = np.empty(0)
        self.clamped = 0                               # requests for samples no longer buffered

    def pull(self) -> None:
        """Move newly generated samples from the world into the buffer (hold the lock)."""
        b, tt = self.world.take_imu(advance=False, true_time=True)
        if len(b):
            if not self._temp.size:
                self.base = int(b.counter[0])
            self._tt = np.concatenate((self._tt, tt))
            self._f = np.concatenate((self._f, b.specific_force))
            self._w = np.concatenate((self._w, b.angular_rate))
            self._temp = np.concatenate((self._temp, b.temperature))

    def trim(self, keep_from: int) -> None:
        """Forget samples no longer needed for frames at times >= ``keep_from / rate_hz``."""
        with self.lock:
            t_keep = (keep_from - 0.5) / self.world.rate_hz
            cut = int(np.searchsorted(self._tt, t_keep, side="left"))
            if cut:
                self._f, self._w, self._temp = self._f[cut:], self._w[cut:], self._temp[cut:]
                self._tt = self._tt[cut:]
                self.base += cut

    def __call__(self, t: np.ndarray) -> dict[str, np.ndarray]:
        t = np.asarray(t, dtype=float)
        with self.lock:
            if t.size and (not self._tt.size or t[-1] > self._tt[-1]):
                self.world.advance()
            self.pull()
            # the sample whose true time is nearest t (ties: the earlier)
            half = 0.5 / self.world.rate_hz
            j = np.searchsorted(self._tt, t + half, side="left") - 1
            if not self._temp.size:       # nothing generated yet: a still sensor
                n = t.size
                return {"acceleration": np.zeros((n, 3)), "rate_of_turn": np.zeros((n, 3)),
                        "temperature": np.full(n, 25.0), "status_word": np.zeros(n, np.int64)}
            self.clamped += int((j < 0).sum())  # nearest sample no longer buffered
            j = np.clip(j, 0, self._temp.size - 1)
            return {"acceleration": self._f[j], "rate_of_turn": self._w[j], "temperature": self._temp[j],
                    "status_word": np.zeros(t.size, np.int64)}
