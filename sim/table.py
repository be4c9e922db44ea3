"""Emulated three-axis turntable: motion profiles and servo dynamics, evaluated on a time grid.

Each axis runs a motion *profile* (piecewise constant acceleration, limited in rate and
acceleration) and a servo whose tracking error ``e`` obeys

    e'' + 2 zeta w_n e' + w_n^2 e = -a_profile(t)

(a position loop with velocity feed-forward: no error at constant rate, a lag under
acceleration, overshoot and ringing after each acceleration change). The actual motion is
``profile + e``. The error filter is discretised exactly for a zero-order-hold input with
scipy.signal and run with ``lfilter`` over whole blocks, carrying its state between blocks, so
a virtual-time run costs a few vectorised calls per block rather than a Python loop per tick.

Status bits follow :class:`rigctl.devices.AxisStatus`: *profile complete* comes as soon as the
profile ends, before the servo has physically settled; *target reached* needs the axis inside
the in-position window continuously for the dwell time, as real controllers do.
Angles in rad, rates rad/s, accelerations rad/s^2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from rigctl.devices import AxisStatus

OFF, POSITION, RATE = 0, 1, 2


@dataclass
class ServoParams:
    """Per-axis servo: natural frequency w_n (Hz), damping zeta, windows and encoder."""

    natural_hz: float = 4.0
    damping: float = 0.6
    in_position_window: float = math.radians(0.002)
    at_rate_window: float = math.radians(0.01)
    dwell_s: float = 0.2
    encoder_lsb: float = math.radians(1e-5)


def wrap_angle(a: NDArray[np.float64] | float) -> NDArray[np.float64] | float:
    """Wrap to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a), 2 * np.pi)


class Profile:
    """Piecewise-constant-acceleration motion: pieces (t0, p0, v0, a) valid from t0 on."""

    def __init__(self, t0: float, p0: float, v0: float) -> None:
        self.t = [t0]
        self.p = [p0]
        self.v = [v0]
        self.a = [0.0]
        self.end = t0

    def _append(self, dt: float, a: float) -> None:
        t0, p0, v0, a0 = self.t[-1], self.p[-1], self.v[-1], self.a[-1]
        self.a[-1] = a
        if dt <= 0:
            return
        self.t.append(t0 + dt)
        self.p.append(p0 + v0 * dt + 0.5 * a * dt * dt)
        self.v.append(v0 + a * dt)
        self.a.append(0.0)
        self.end = t0 + dt
        del a0

    @classmethod
    def to_rate(cls, t0: float, p0: float, v0: float, rate: float, amax: float) -> "Profile":
        prof = cls(t0, p0, v0)
        dv = rate - v0
        if dv != 0.0:
            prof._append(abs(dv) / amax, math.copysign(amax, dv))
        prof.v[-1] = rate  # exact end rate
        return prof

    @classmethod
    def to_position(cls, t0: float, p0: float, v0: float, target: float, vmax: float,
                    amax: float) -> "Profile":
        """Stop if moving, then a trapezoid (or triangle) to ``target``."""
        prof = cls(t0, p0, v0)
        if v0 != 0.0:
            prof._append(abs(v0) / amax, -math.copysign(amax, v0))
            prof.v[-1] = 0.0
        d = target - prof.p[-1]
        dist = abs(d)
        if dist > 0.0:
            sgn = math.copysign(1.0, d)
            if dist > vmax * vmax / amax:
                t_acc = vmax / amax
                t_cruise = (dist - vmax * vmax / amax) / vmax
            else:
                t_acc = math.sqrt(dist / amax)
                t_cruise = 0.0
            prof._append(t_acc, sgn * amax)
            prof._append(t_cruise, 0.0)
            prof._append(t_acc, -sgn * amax)
        prof.p[-1], prof.v[-1] = target, 0.0
        return prof

    def evaluate(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """Profile position, rate and acceleration at times ``t``."""
        idx = np.searchsorted(np.asarray(self.t), t, side="right") - 1
        idx = np.clip(idx, 0, len(self.t) - 1)
        tp = np.asarray(self.t)[idx]
        pp, vp, ap = (np.asarray(x)[idx] for x in (self.p, self.v, self.a))
        dt = t - tp
        return pp + vp * dt + 0.5 * ap * dt * dt, vp + ap * dt, ap


class TableAxis:
    """One gimbal axis: mode, profile and servo error state."""

    def __init__(self, servo: ServoParams, vmax: float, amax: float, continuous: bool, dt: float,
                 t0: float = 0.0) -> None:
        self.servo, self.vmax, self.amax, self.continuous, self.dt = servo, vmax, amax, continuous, dt
        self.mode = OFF
        self.target = 0.0
        self.profile = Profile(t0, 0.0, 0.0)
        self.fault = False
        wn, z = 2 * math.pi * servo.natural_hz, servo.damping
        den = [1.0, 2 * z * wn, wn * wn]
        self._wn2, self._2zwn = wn * wn, 2 * z * wn
        self._b_e, self._a_e, _ = signal.cont2discrete(([-1.0], den), dt, method="zoh")
        self._b_de, self._a_de, _ = signal.cont2discrete(([-1.0, 0.0], den), dt, method="zoh")
        self._b_e, self._b_de = np.ravel(self._b_e), np.ravel(self._b_de)
        self._zi_e = np.zeros(2)
        self._zi_de = np.zeros(2)
        self.last = (0.0, 0.0, 0.0)  # actual angle, rate, accel at the last grid point
        self.last_t = t0
        self.in_window_since: float | None = None

    def command(self, t: float, mode: int, value: float) -> None:
        """New demand at time ``t``: POSITION (angle rad), RATE (rad/s) or OFF (controlled stop)."""
        p0, v0, _ = (float(x[0]) for x in self.profile.evaluate(np.array([t])))
        self.in_window_since = None
        if mode == POSITION:
            target = value
            if self.continuous:  # shortest way round to the equivalent angle
                target = p0 + float(wrap_angle(value - p0))
            self.target = target
            self.profile = Profile.to_position(t, p0, v0, target, self.vmax, self.amax)
        elif mode == RATE:
            self.target = value
            self.profile = Profile.to_rate(t, p0, v0, value, self.amax)
        else:
            self.target = 0.0
            self.profile = Profile.to_rate(t, p0, v0, 0.0, self.amax)
        self.mode = mode

    def advance(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """Actual angle, rate, acceleration on the grid ``t`` (uniform, step dt, after last_t)."""
        p, v, a = self.profile.evaluate(t)
        e, self._zi_e = signal.lfilter(self._b_e, self._a_e, a, zi=self._zi_e)
        de, self._zi_de = signal.lfilter(self._b_de, self._a_de, a, zi=self._zi_de)
        x, w = p + e, v + de
        acc = -self._2zwn * de - self._wn2 * e
        if t.size:
            self.last = (float(x[-1]), float(w[-1]), float(acc[-1]))
            self._update_window(t, x, w)
            self.last_t = float(t[-1])
        return x, w, acc

    def _update_window(self, t: NDArray, x: NDArray, w: NDArray) -> None:
        if self.mode == POSITION:
            inside = np.abs(x - self.target) <= self.servo.in_position_window
        elif self.mode == RATE:
            inside = np.abs(w - self.target) <= self.servo.at_rate_window
        else:
            inside = np.abs(w) <= self.servo.at_rate_window
        if inside[-1]:
            outside = np.flatnonzero(~inside)
            if outside.size:
                self.in_window_since = float(t[outside[-1] + 1])
            elif self.in_window_since is None:
                self.in_window_since = float(t[0])
        else:
            self.in_window_since = None

    def status(self, t: float) -> int:
        s = AxisStatus.READY
        if self.fault:
            return int(s | AxisStatus.FAULT)
        if self.mode != OFF:
            s |= AxisStatus.SERVO_ON | AxisStatus.OPERATION_ENABLED
        if t >= self.profile.end:
            s |= AxisStatus.PROFILE_COMPLETE
        if abs(self.last[1]) > self.servo.at_rate_window:
            s |= AxisStatus.MOVING
        held = self.in_window_since is not None and t - self.in_window_since >= self.servo.dwell_s
        if held and t >= self.profile.end:
            s |= AxisStatus.AT_RATE if self.mode == RATE else AxisStatus.TARGET_REACHED
        return int(s)


class SimTurntable:
    """Three axes [outer, middle, inner] on one uniform physics grid."""

    def __init__(self, servos: list[ServoParams], vmax: NDArray, amax: NDArray,
                 continuous: list[bool], dt: float, rng: np.random.Generator) -> None:
        self.axes = [TableAxis(s, float(vmax[i]), float(amax[i]), continuous[i], dt)
                     for i, s in enumerate(servos)]
        self.rng = rng
        self.dt = dt

    def command(self, t: float, modes: list[int], values: NDArray) -> None:
        for ax, m, v in zip(self.axes, modes, values):
            ax.command(t, m, float(v))

    def advance(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """(n, 3) actual angles, gimbal rates and gimbal accelerations on the grid ``t``."""
        cols = [ax.advance(t) for ax in self.axes]
        return (np.stack([c[0] for c in cols], axis=1), np.stack([c[1] for c in cols], axis=1),
                np.stack([c[2] for c in cols], axis=1))

    def measured(self, t: float) -> tuple[NDArray, NDArray, tuple[int, int, int]]:
        """Encoder reading (quantised, wrapped for continuous axes), rate and status at ``t``."""
        ang, rate = np.empty(3), np.empty(3)
        for i, ax in enumerate(self.axes):
            q = ax.servo.encoder_lsb
            a = round(ax.last[0] / q) * q if q > 0 else ax.last[0]
            ang[i] = float(wrap_angle(a)) if ax.continuous else a
            rate[i] = ax.last[1]
        status = tuple(ax.status(t) for ax in self.axes)
        return ang, rate, status  # type: ignore[return-value]
