"""Emulated three-axis turntable: motion profiles and servo dynamics, evaluated on a time grid.

Each axis runs a motion *profile* (piecewise constant acceleration, limited in rate and
acceleration) and a servo whose tracking error ``e`` obeys

    e'' + 2 zeta w_n e' + w_n^2 e = -a_profile(t)

(a position loop with velocity feed-forward: no error at constant rate, a lag under
acceleration, overshoot and ringing after each acceleration change). The actual motion is
``profile + e``. The error filter is discretised exactly for a zero-order-hold input
(scipy.signal's ``cont2discrete``) and run with ``lfilter`` over whole blocks, carrying its state
between blocks, so a virtual-time run costs a few compiled calls per block rather than a Python
loop per tick (both from :mod:`rigctl.sim.iir`: scipy's arithmetic, without importing
scipy.signal).

Optional imperfections (all off by default, SI in :class:`ServoParams`):

* encoder noise: the reported angle is ``round((x + N(0, sigma^2)) / lsb) * lsb``;
* rate ripple, as a fraction of the profile rate ``v``, once per revolution and/or at a fixed
  frequency: ``w_r = v (r_rev sin(p + phi_rev) + r_f sin(2 pi f_r t + phi_f))``; the actual
  rate is ``w + w_r`` and the angle gains ``x_r = integral w_r dt`` while the profile moves;
  at rest (``v = 0``) the position loop removes the residual, ``x_r' = -zeta w_n x_r``;
* wobble: the axis tilts by ``A`` (rad) about the two axes perpendicular to it, in the frame
  it rotates in, with the pattern ``A (cos(n theta + phi), sin(n theta + phi))`` fixed to the
  axis angle ``theta`` (``n`` = harmonic; ``n = 1`` is indistinguishable from a constant
  mounting tilt of the rotating part). :meth:`SimTurntable.wobble` gives the resulting small
  body-frame attitude error ``d`` (C_b^n -> C_b^n (I + [d x])) and its rate.

Status bits follow :class:`rigctl.devices.AxisStatus`: *profile complete* comes as soon as the
profile ends, before the servo has physically settled; *target reached* needs the axis inside
the in-position window continuously for the dwell time, as real controllers do.
Angles in rad, rates rad/s, accelerations rad/s^2.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from rigctl.devices import AxisStatus

from . import table_kernels as _tk
from .iir import cont2discrete_zoh, lfilter, lfilter_prepared, prepare

OFF, POSITION, RATE = 0, 1, 2
_READY, _FAULT, _SERVO_ON, _OPERATION_ENABLED = (int(AxisStatus.READY), int(AxisStatus.FAULT), int(AxisStatus.SERVO_ON),
                                                 int(AxisStatus.OPERATION_ENABLED))
_PROFILE_COMPLETE, _MOVING, _AT_RATE, _TARGET_REACHED = (int(AxisStatus.PROFILE_COMPLETE), int(AxisStatus.MOVING),
                                                         int(AxisStatus.AT_RATE), int(AxisStatus.TARGET_REACHED))


@dataclass
class ServoParams:
    """Per-axis servo: natural frequency w_n (Hz), damping zeta, windows and encoder."""

    natural_hz: float = 4.0
    damping: float = 0.6
    in_position_window: float = math.radians(0.002)
    at_rate_window: float = math.radians(0.01)
    dwell_s: float = 0.2
    encoder_lsb: float = math.radians(1e-5)
    encoder_noise: float = 0.0  # rad, 1-sigma, before quantisation
    ripple_per_rev: float = 0.0  # fraction of rate, once per revolution of the axis angle
    ripple_per_rev_phase: float = 0.0  # rad
    ripple_fraction: float = 0.0  # fraction of rate at ripple_hz
    ripple_hz: float = 0.0
    ripple_phase: float = 0.0  # rad
    wobble: float = 0.0  # rad, tilt amplitude of the axis
    wobble_harmonic: int = 2  # cycles per revolution
    wobble_phase: float = 0.0  # rad
    jerk_max: float = math.inf  # rad/s^3 (inf: acceleration steps, the plain trapezoid)


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
        self.prev: Profile | None = None  # the profile this one replaced (for times < t0)
        self._pieces: NDArray[np.float64] | None = None  # (t, p, v, a) as one (4, n) array

    def _arrays(self) -> NDArray[np.float64]:
        """The pieces as one (4, n) array, made at the first evaluation (the lists are final
        by then: only the constructors change them)."""
        if self._pieces is None:
            self._pieces = np.array([self.t, self.p, self.v, self.a], dtype=float)
        return self._pieces

    def _append(self, dt: float, a: float) -> None:
        t0, p0, v0, a0 = self.t[-1], self.p[-1], self.v[-1], self.a[-1]
        self._pieces = None
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
                    amax: float, t_jerk: float = 0.0) -> "Profile":
        """Stop if moving, then a trapezoid (or triangle) to ``target``. With ``t_jerk`` > 0
        (jerk-limited: the acceleration is later averaged over t_jerk) a triangle gets a coast
        of t_jerk at its peak, so acceleration never reverses within one averaging window."""
        prof = cls(t0, p0, v0)
        if v0 != 0.0:
            prof._append(abs(v0) / amax, -math.copysign(amax, v0))
            prof.v[-1] = 0.0
            if t_jerk > 0.0:
                prof._append(t_jerk, 0.0)
        d = target - prof.p[-1]
        dist = abs(d)
        if dist > 0.0:
            sgn = math.copysign(1.0, d)
            if dist > vmax * vmax / amax:
                t_acc = vmax / amax
                t_cruise = (dist - vmax * vmax / amax) / vmax
            elif t_jerk > 0.0:  # a t^2 + a t t_jerk = dist
                t_acc = 0.5 * (-t_jerk + math.sqrt(t_jerk * t_jerk + 4.0 * dist / amax))
                t_cruise = t_jerk
            else:
                t_acc = math.sqrt(dist / amax)
                t_cruise = 0.0
            prof._append(t_acc, sgn * amax)
            prof._append(t_cruise, 0.0)
            prof._append(t_acc, -sgn * amax)
        prof.p[-1], prof.v[-1] = target, 0.0
        return prof

    def evaluate_full(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Position, rate, acceleration and the position's integral P(t) = int_{t0}^t p (rad s)
        at ``t``; times before t0 come from the replaced profile (at rest at p0 if none)."""
        tt, aa = np.asarray(self.t), np.asarray(self.a)
        pp, vv = np.asarray(self.p), np.asarray(self.v)
        d = np.diff(tt)
        seg = pp[:-1] * d + vv[:-1] * d**2 / 2 + aa[:-1] * d**3 / 6
        big = np.concatenate([[0.0], np.cumsum(seg)])
        idx = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 1)
        dt = t - tt[idx]
        p, v, a = pp[idx], vv[idx], aa[idx]
        pos = p + v * dt + 0.5 * a * dt * dt
        vel = v + a * dt
        acc = a.copy()
        integ = big[idx] + p * dt + v * dt**2 / 2 + a * dt**3 / 6
        early = t < tt[0]
        if np.any(early):
            te = t[early]
            if self.prev is not None:
                p2, v2, a2, i2 = self.prev.evaluate_full(te)
                i0 = self.prev.evaluate_full(np.array([tt[0]]))[3][0]
                pos[early], vel[early], acc[early], integ[early] = p2, v2, a2, i2 - i0
            else:  # moving uniformly at (p0, v0) before the first command
                de = te - tt[0]
                pos[early], vel[early], acc[early] = pp[0] + vv[0] * de, vv[0], 0.0
                integ[early] = pp[0] * de + vv[0] * de**2 / 2
        return pos, vel, acc, integ

    def smoothed(self, t: NDArray[np.float64], t_jerk: float) -> tuple[NDArray, NDArray, NDArray]:
        """The profile averaged over the window [t - t_jerk, t]: acceleration steps of amax
        become ramps of jerk amax / t_jerk, and position, rate and acceleration stay
        consistent (each is the window mean of its own kind; the motion lags t_jerk / 2)."""
        p1, v1, a1, i1 = self.evaluate_full(t)
        p0, v0, _, i0 = self.evaluate_full(t - t_jerk)
        pos = (i1 - i0) / t_jerk
        # window inside one piece: the exact mean p - v T / 2 + a T^2 / 6 (no cancellation)
        tt = np.asarray(self.t)
        same = ((np.searchsorted(tt, t, side="right") == np.searchsorted(tt, t - t_jerk, side="right"))
                & (t - t_jerk >= tt[0]))
        pos[same] = (p1 - v1 * t_jerk / 2 + a1 * t_jerk**2 / 6)[same]
        return pos, (p1 - p0) / t_jerk, (v1 - v0) / t_jerk

    def prune(self, t_from: float) -> None:
        """Forget replaced profiles not needed for times >= t_from."""
        node = self.prev
        while node is not None and node.t[0] > t_from:
            node = node.prev
        if node is not None:
            node.prev = None

    def evaluate(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """Profile position, rate and acceleration at times ``t``. A time before this
        profile's start t0 is the replaced profile's (``prev``); without one the axis was at
        (p0, v0) moving uniformly. A piece is never run backwards from its start."""
        t = np.asarray(t, dtype=float)
        pieces = self._arrays()
        if t.size and t.min() >= self.t[-1]:  # all in the last piece (an axis at rest, mostly)
            tp, pp, vp, ap = pieces[:, -1].tolist()
            if vp == 0.0 and ap == 0.0:
                # at rest: with dt = t - tp >= 0 (never -0.0), vp dt and 0.5 ap dt dt are the
                # signed zeros vp and 0.5 ap, so the expressions below are these constants --
                # the same floats, signed zeros included, without the array arithmetic
                return (np.full(t.shape, pp + vp + 0.5 * ap), np.full(t.shape, vp + ap), np.full(t.shape, ap))
            dt = t - tp
            return pp + vp * dt + 0.5 * ap * dt * dt, vp + ap * dt, np.full(t.shape, ap)
        idx = np.searchsorted(pieces[0], t, side="right") - 1  # <= n - 1
        idx = np.maximum(idx, 0)
        tp, pp, vp, ap = pieces[:, idx]
        dt = t - tp
        pos, vel, acc = pp + vp * dt + 0.5 * ap * dt * dt, vp + ap * dt, ap
        early = t < self.t[0]
        if early.any():
            if self.prev is not None:
                p2, v2, a2 = self.prev.evaluate(t[early])
            else:
                de = t[early] - self.t[0]
                p2, v2, a2 = self.p[0] + self.v[0] * de, np.full(de.shape, self.v[0]), np.zeros(de.shape)
            pos, vel, acc = pos.copy(), vel.copy(), acc.copy()
            pos[early], vel[early], acc[early] = p2, v2, a2
        return pos, vel, acc


class TableAxis:
    """One gimbal axis: mode, profile and servo error state."""

    def __init__(self, servo: ServoParams, vmax: float, amax: float, continuous: bool, dt: float,
                 t0: float = 0.0) -> None:
        self.servo, self.vmax, self.amax, self.continuous, self.dt = servo, vmax, amax, continuous, dt
        #: jerk limit as an averaging window of the acceleration, s (0: no jerk limit)
        self.t_jerk = amax / servo.jerk_max if math.isfinite(servo.jerk_max) and servo.jerk_max > 0 else 0.0
        self.mode = OFF
        self.target = 0.0
        self.profile = Profile(t0, 0.0, 0.0)
        self.fault = False
        wn, z = 2 * math.pi * servo.natural_hz, servo.damping
        den = [1.0, 2 * z * wn, wn * wn]
        self._wn2, self._2zwn = wn * wn, 2 * z * wn
        self._b_e, self._a_e = cont2discrete_zoh([-1.0], den, dt)
        self._b_de, self._a_de = cont2discrete_zoh([-1.0, 0.0], den, dt)
        self._b_e, self._b_de = np.ravel(self._b_e), np.ravel(self._b_de)
        # the two filters in lfilter's normal form, once (advance() runs them at every poll)
        self._f_e, self._f_de = prepare(self._b_e, self._a_e), prepare(self._b_de, self._a_de)
        self._zi_e = np.zeros(2)
        self._zi_de = np.zeros(2)
        # load the compiled filter now, while the world is built before the run clock starts
        # (rigctl.engine.rig.open_rig), not at the first block (numba's set-up: ~0.1-0.3 s)
        lfilter(self._b_e, self._a_e, np.zeros(0), self._zi_e)
        self.last = (0.0, 0.0, 0.0)  # actual angle, rate, accel at the last grid point
        self.last_t = t0
        self.in_window_since: float | None = None
        self._ripple_angle = 0.0  # x_r at the last grid point, rad
        #: servo state at the recent grid points (time, e, e', the acceleration held over the
        #: following step, ripple angle), for :meth:`at`; trimmed by :meth:`forget_before`
        self._hist = np.empty((5, 0))
        self._hist_ripple = False  # a ripple angle was ever stored in _hist (else its row is 0)
        #: every kept grid point has e = e' = +0.0 and a = 0 (an axis that has rested long enough
        #: for its servo error to underflow to zero): at() has nothing to propagate
        self._hist_quiet = True
        self._t_first: float | None = None  # first grid time ever (at rest before it)

    @classmethod
    def probe(cls, natural_hz: float, damping: float, dt: float) -> "TableAxis":
        """A continuous axis (300 deg/s, 400 deg/s^2) for sim/table_kernels.py's comparison."""
        return cls(ServoParams(natural_hz=natural_hz, damping=damping), math.radians(300), math.radians(400), True, dt)

    def command(self, t: float, mode: int, value: float) -> None:
        """New demand at time ``t``: POSITION (angle rad), RATE (rad/s) or OFF (controlled stop)."""
        p0, v0, _ = (float(x[0]) for x in self.profile.evaluate(np.array([t])))
        old = self.profile
        self.in_window_since = None
        if mode == POSITION:
            target = value
            if self.continuous:  # shortest way round to the equivalent angle
                target = p0 + float(wrap_angle(value - p0))
            self.target = target
            self.profile = Profile.to_position(t, p0, v0, target, self.vmax, self.amax, self.t_jerk)
        elif mode == RATE:
            self.target = value
            self.profile = Profile.to_rate(t, p0, v0, value, self.amax)
        else:
            self.target = 0.0
            self.profile = Profile.to_rate(t, p0, v0, 0.0, self.amax)
        # times before t (the jerk window, or an IMU sample not produced yet whose instant
        # precedes the command) come from the replaced profile; forget_before() prunes the chain
        self.profile.prev = old
        self.profile.prune(min(t - self.t_jerk, self._keep_from))
        self.mode = mode

    _keep_from = -math.inf  # earliest time still needed by at() (set by forget_before)

    def forget_before(self, t: float) -> None:
        """Drop the grid history and replaced profiles not needed for times >= ``t``."""
        self._keep_from = float(t)
        self.profile.prune(t - self.t_jerk)
        h = self._hist
        if h.shape[1] > 1:
            j = int(np.searchsorted(h[0], t, side="right")) - 1
            if j > 0:
                self._hist = h[:, j:].copy()
                if not self._hist_quiet:
                    self._hist_quiet = _quiet(self._hist)

    @property
    def end(self) -> float:
        """Time the (jerk-limited) profile reaches its end, s."""
        return self.profile.end + self.t_jerk

    def advance(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """Actual angle, rate, acceleration on the grid ``t`` (uniform, step dt, after last_t)."""
        sv = self.servo
        if (t.size and not (self.t_jerk > 0 or sv.ripple_per_rev or sv.ripple_fraction or self._ripple_angle)
                and t[0] >= self.profile.t[0] and _tk.on(TableAxis)):
            # the common case compiled, the same floats (sim/table_kernels.py)
            x, w, acc, self._zi_e, self._zi_de, hist, last_out, inside, quiet = _tk.advance(self, t)
            self.last = (float(x[-1]), float(w[-1]), float(acc[-1]))
            self._set_window(t, bool(inside), int(last_out))
            self.last_t = float(t[-1])
            if self._t_first is None:
                self._t_first = float(t[0])
            self._hist = hist
            if self._hist_quiet:
                self._hist_quiet = quiet
            return x, w, acc
        if self.t_jerk > 0:
            p, v, a = self.profile.smoothed(t, self.t_jerk)
        else:
            p, v, a = self.profile.evaluate(t)
        e, self._zi_e = lfilter_prepared(*self._f_e, a, self._zi_e)
        de, self._zi_de = lfilter_prepared(*self._f_de, a, self._zi_de)
        x, w = p + e, v + de
        acc = -self._2zwn * de - self._wn2 * e
        sv = self.servo
        xr = None
        if t.size and (sv.ripple_per_rev or sv.ripple_fraction or self._ripple_angle):
            xr, wr = self._ripple(t, p, v)
            x, w = x + xr, w + wr
        if t.size:
            self.last = (float(x[-1]), float(w[-1]), float(acc[-1]))
            self._update_window(t, x, w)
            self.last_t = float(t[-1])
            if self._t_first is None:
                self._t_first = float(t[0])
            # one (5, m + n) array of the kept rows and the new ones (the same values as
            # hstack(hist, vstack(rows)), without the intermediate arrays)
            h = self._hist
            m = h.shape[1]
            hist = np.empty((5, m + t.size))
            hist[:, :m] = h
            hist[0, m:], hist[1, m:], hist[2, m:], hist[3, m:] = t, e, de, a
            hist[4, m:] = 0.0 if xr is None else xr
            self._hist_ripple = self._hist_ripple or xr is not None
            self._hist = hist
            if self._hist_quiet:
                self._hist_quiet = _quiet(hist[:, m:])
        return x, w, acc

    def at(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """Actual angle, rate and acceleration at any times ``t`` (increasing or not) from the
        last :meth:`forget_before` time to one grid step past the last grid point, s.

        The same physics as :meth:`advance`, evaluated off the grid: the profile exactly, the
        servo error propagated exactly from the grid point t_j <= t over d = t - t_j with the
        acceleration the discretised servo holds over that step (zero-order hold),

            s(d) = s* + exp(A d) (s_j - s*),  s = (e, e'),  s* = (-a_j / w_n^2, 0),
            exp(A d) = exp(-zeta w_n d) [C(d) I + S(d) (A + zeta w_n I)]

        (C, S = cos, sin(w d)/w with w = w_n sqrt(1 - zeta^2); cosh, sinh when zeta > 1), so
        ``at(t_j)`` and ``at(t_j + dt)`` are the grid values. Before the first grid point the
        axis is at rest."""
        t = np.asarray(t, dtype=float)
        h, sv = self._hist, self.servo
        if (t.ndim == 1 and t.size and h.shape[1] and self.t_jerk == 0
                and not (sv.ripple_per_rev or sv.ripple_fraction or self._hist_ripple) and _tk.on(TableAxis)):
            tmin = t.min()
            if not (tmin < self._t_first - 1e-9 * self.dt or tmin < self.profile.t[0]
                    or (h[0, 0] > self._t_first and tmin < h[0, 0] - 1e-9 * self.dt)):
                return _tk.at(self, t)  # the common case compiled, the same floats (sim/table_kernels.py)
        if self.t_jerk > 0:
            p, v, _ = self.profile.smoothed(t, self.t_jerk)
        else:
            p, v, _ = self.profile.evaluate(t)
        h = self._hist
        if not h.shape[1]:
            zero = np.zeros(t.shape)
            return p, v, zero
        tmin = t.min() if t.size else math.inf
        if h[0, 0] > self._t_first and tmin < h[0, 0] - 1e-9 * self.dt:
            raise RuntimeError(f"table state asked for t = {t.min():.6f} s, before the kept "
                               f"history ({h[0, 0]:.6f} s): forget_before() was called too late")
        sv = self.servo
        if (self._hist_quiet and not (sv.ripple_per_rev or sv.ripple_fraction or self._hist_ripple)
                and not tmin < self._t_first - 1e-9 * self.dt):
            # e0 = de0 = +0.0 and u = 0 at every grid point: nothing is live below, e = de = +0.0,
            # so x, w, acc are p + 0.0, v + 0.0 and the constant (-2 zeta w_n) 0.0 - w_n^2 0.0
            return p + 0.0, v + 0.0, np.full(t.shape, -self._2zwn * 0.0 - self._wn2 * 0.0)
        j = np.searchsorted(h[0], t + 1e-9 * self.dt, side="right") - 1  # <= h.shape[1] - 1
        j = np.maximum(j, 0)
        tj, e0, de0, u, xr0 = h[:, j]
        d = t - tj
        e, de = e0, de0
        live = (d != 0.0) & ((e0 != 0.0) | (de0 != 0.0) | (u != 0.0))  # at rest the error stays 0
        if live.all():
            e, de = self._propagate(e0, de0, u, d)
        elif live.any():
            e, de = e0.copy(), de0.copy()
            e[live], de[live] = self._propagate(e0[live], de0[live], u[live], d[live])
        before = None  # samples before the first grid point (at rest), only when there are any
        if tmin < self._t_first - 1e-9 * self.dt:
            before = t < self._t_first - 1e-9 * self.dt
            e, de = np.where(before, 0.0, e), np.where(before, 0.0, de)
        x, w = p + e, v + de
        acc = -self._2zwn * de - self._wn2 * e
        sv = self.servo
        if sv.ripple_per_rev or sv.ripple_fraction or (self._hist_ripple and np.any(xr0 != 0.0)):
            rr = v * (sv.ripple_per_rev * np.sin(p + sv.ripple_per_rev_phase)
                      + sv.ripple_fraction * np.sin(2 * np.pi * sv.ripple_hz * t + sv.ripple_phase))
            decay = 0.5 * self._2zwn
            rest = xr0 * np.exp(-decay * d)
            moving = v != 0.0
            xr = np.where(moving, xr0 + rr * d, rest)
            wr = np.where(moving, rr, -decay * rest)
            if before is not None:
                xr, wr = np.where(before, 0.0, xr), np.where(before, 0.0, wr)
            x, w = x + xr, w + wr
        return x, w, acc

    def at_one(self, t: float) -> tuple[float, float]:
        """(angle, rate) at one time ``t``: :meth:`at` of ``np.array([t])``, the same values. Its
        common case -- no jerk limit, no ripple ever stored, ``t`` inside the kept history, after
        the first grid point and in the current profile -- in scalar arithmetic (the same
        operations in the same order; the table is read at every poll, and the array path's
        per-call cost is most of a one-sample read); any other case through :meth:`at`."""
        t = float(t)
        h, sv, prof = self._hist, self.servo, self.profile
        eps = 1e-9 * self.dt
        if (self.t_jerk > 0 or not h.shape[1] or sv.ripple_per_rev or sv.ripple_fraction or self._hist_ripple
                or t < prof.t[0] or t < self._t_first - eps  # type: ignore[operator]
                or (h[0, 0] > self._t_first and t < h[0, 0] - eps)):
            x, w, _ = self.at(np.array([t]))
            return float(x[0]), float(w[0])
        # the profile (Profile.evaluate): the piece holding t, never one before the first
        i = max(bisect.bisect_right(prof.t, t) - 1, 0)
        tp, pp, vp, ap = prof.t[i], prof.p[i], prof.v[i], prof.a[i]
        dt = t - tp
        p, v = pp + vp * dt + 0.5 * ap * dt * dt, vp + ap * dt
        # the servo error from the grid point t_j <= t (as at())
        j = max(int(np.searchsorted(h[0], t + eps, side="right")) - 1, 0)
        tj, e0, de0, u = h[0, j].item(), h[1, j].item(), h[2, j].item(), h[3, j].item()
        d = t - tj
        e, de = e0, de0
        if d != 0.0 and (e0 != 0.0 or de0 != 0.0 or u != 0.0):
            e, de = self._propagate(e0, de0, u, d)  # type: ignore[arg-type]
        return float(p + e), float(v + de)

    def _propagate(self, e0: NDArray, de0: NDArray, u: NDArray, d: NDArray) -> tuple[NDArray, NDArray]:
        """Servo error state (e, e') after d seconds from (e0, de0) under constant input u
        (see :meth:`at`): exact for e'' + 2 zeta w_n e' + w_n^2 e = -u."""
        wn2 = self._wn2
        sig = 0.5 * self._2zwn
        z = self.servo.damping
        estar = -u / wn2
        E, D = e0 - estar, de0
        if z < 1.0:
            om = math.sqrt(wn2) * math.sqrt(1.0 - z * z)
            C, S = np.cos(om * d), np.sin(om * d) / om
        elif z > 1.0:
            om = math.sqrt(wn2) * math.sqrt(z * z - 1.0)
            C, S = np.cosh(om * d), np.sinh(om * d) / om
        else:
            C, S = np.ones_like(d), d
        ex = np.exp(-sig * d)
        return estar + ex * (C * E + S * (sig * E + D)), ex * (C * D - S * (wn2 * E + sig * D))

    def _ripple(self, t: NDArray, p: NDArray, v: NDArray) -> tuple[NDArray, NDArray]:
        """Ripple angle x_r and rate w_r on the grid (see the module docstring)."""
        sv = self.servo
        rr = v * (sv.ripple_per_rev * np.sin(p + sv.ripple_per_rev_phase)
                  + sv.ripple_fraction * np.sin(2 * np.pi * sv.ripple_hz * t + sv.ripple_phase))
        moving = v != 0.0
        xr, wr = np.empty_like(t), np.empty_like(t)
        decay = 0.5 * self._2zwn  # zeta w_n, 1/s
        edges = np.concatenate([[0], np.flatnonzero(np.diff(moving)) + 1, [t.size]])
        x0 = self._ripple_angle
        for i0, i1 in zip(edges[:-1], edges[1:]):
            if moving[i0]:
                xr[i0:i1] = x0 + np.cumsum(rr[i0:i1]) * self.dt
                wr[i0:i1] = rr[i0:i1]
            else:
                xr[i0:i1] = x0 * np.exp(-decay * self.dt * np.arange(1, i1 - i0 + 1))
                wr[i0:i1] = -decay * xr[i0:i1]
            x0 = float(xr[i1 - 1])
        self._ripple_angle = x0 if abs(x0) > 1e-15 else 0.0
        return xr, wr

    def _update_window(self, t: NDArray, x: NDArray, w: NDArray) -> None:
        if self.mode == POSITION:
            inside = np.abs(x - self.target) <= self.servo.in_position_window
        elif self.mode == RATE:
            inside = np.abs(w - self.target) <= self.servo.at_rate_window
        else:
            inside = np.abs(w) <= self.servo.at_rate_window
        outside = np.flatnonzero(~inside)
        self._set_window(t, bool(inside[-1]), int(outside[-1]) if outside.size else -1)

    def _set_window(self, t: NDArray, inside_last: bool, last_out: int) -> None:
        """in_window_since after the grid ``t``: whether its last point is inside the window and
        the index of its last point outside (-1: none)."""
        if inside_last:
            if last_out >= 0:
                self.in_window_since = float(t[last_out + 1])
            elif self.in_window_since is None:
                self.in_window_since = float(t[0])
        else:
            self.in_window_since = None

    def status(self, t: float) -> int:
        s = _READY  # plain ints: IntFlag arithmetic costs microseconds per operation
        if self.fault:
            return s | _FAULT
        if self.mode != OFF:
            s |= _SERVO_ON | _OPERATION_ENABLED
        if t >= self.end:
            s |= _PROFILE_COMPLETE
        if abs(self.last[1]) > self.servo.at_rate_window:
            s |= _MOVING
        held = self.in_window_since is not None and t - self.in_window_since >= self.servo.dwell_s
        if held and t >= self.end:
            s |= _AT_RATE if self.mode == RATE else _TARGET_REACHED
        return s


def _quiet(h: NDArray[np.float64]) -> bool:
    """Grid points h (5, m) all with servo error e = e' = +0.0 (not -0.0) and acceleration 0."""
    return not (h[1:4].any() or np.signbit(h[1:3]).any())


def _columns(cols: list[tuple[NDArray, NDArray, NDArray]], n: int) -> tuple[NDArray, NDArray, NDArray]:
    """The axes' (angle, rate, acceleration) as three (n, 3) arrays, axis k in column k (what
    np.stack(..., axis=1) makes, with fewer calls)."""
    out = np.empty((3, n, 3))
    for k, c in enumerate(cols):
        out[0, :, k], out[1, :, k], out[2, :, k] = c
    return out[0], out[1], out[2]


class SimTurntable:
    """Three axes [outer, middle, inner] on one uniform physics grid."""

    def __init__(self, servos: list[ServoParams], vmax: NDArray, amax: NDArray,
                 continuous: list[bool], dt: float, rng: np.random.Generator) -> None:
        self.axes = [TableAxis(s, float(vmax[i]), float(amax[i]), continuous[i], dt)
                     for i, s in enumerate(servos)]
        self.rng = rng
        self.dt = dt
        self.vmax, self.amax = np.asarray(vmax, float), np.asarray(amax, float)

    def command(self, t: float, modes: list[int], values: NDArray) -> None:
        for ax, m, v in zip(self.axes, modes, values):
            ax.command(t, m, float(v))

    def advance(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """(n, 3) actual angles, gimbal rates and gimbal accelerations on the grid ``t``."""
        return _columns([ax.advance(t) for ax in self.axes], np.shape(t)[0])

    def step(self, t: NDArray[np.float64]) -> None:
        """:meth:`advance` without assembling its (n, 3) arrays (for a caller that reads the
        state through :meth:`at` and :meth:`measured`)."""
        for ax in self.axes:
            ax.advance(t)

    def at(self, t: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """(n, 3) actual angles, gimbal rates and accelerations at any times ``t`` within the
        kept history (:meth:`TableAxis.at`): the table's state at the IMU's sample instants."""
        return _columns([ax.at(t) for ax in self.axes], np.shape(t)[0])

    def forget_before(self, t: float) -> None:
        """No :meth:`at` call will ask for times before ``t``: drop what only those needed."""
        for ax in self.axes:
            ax.forget_before(t)

    def measured(self, t: float) -> tuple[NDArray, NDArray, tuple[int, int, int]]:
        """Encoder reading (quantised, wrapped for continuous axes), rate and status at ``t``
        (the actual state at ``t`` when it lies after the last grid point, within one step)."""
        ang, rate = np.empty(3), np.empty(3)
        for i, ax in enumerate(self.axes):
            q, a = ax.servo.encoder_lsb, ax.last[0]
            r = ax.last[1]
            if t > ax.last_t and ax._hist.shape[1]:
                a, r = ax.at_one(t)
            if ax.servo.encoder_noise > 0:
                a += ax.servo.encoder_noise * float(self.rng.standard_normal())
            a = round(a / q) * q if q > 0 else a
            ang[i] = float(wrap_angle(a)) if ax.continuous else a
            rate[i] = r
        status = tuple(ax.status(t) for ax in self.axes)
        return ang, rate, status  # type: ignore[return-value]

    def wobble(self, ang: NDArray, rates: NDArray) -> tuple[NDArray, NDArray] | None:
        """Body-frame attitude error d (n, 3) rad and its rate d' (n, 3) rad/s from the axes'
        wobble, for actual angles / gimbal rates (n, 3); None when no axis wobbles.

        Axis k's tilt ``w_k`` acts in the frame it rotates in (the next-outer gimbal's), so in
        the body frame ``d_k = M_k^T w_k`` with ``M_k`` the rotation of axis k and all inner
        ones, and ``d_k' = M_k^T w_k' - r_k x d_k`` with ``r_k`` the body rate relative to that
        frame; ``d = sum d_k`` (first order in the tilt)."""
        if not any(ax.servo.wobble for ax in self.axes):
            return None
        from rigctl.frames import _rot, gimbal_rate_body

        n = ang.shape[0]
        d, dd = np.zeros((n, 3)), np.zeros((n, 3))
        perp = {0: (0, 1), 1: (2, 0), 2: (1, 2)}  # outer z: (x, y); middle y: (z, x); inner x: (y, z)
        names = ("z", "y", "x")
        for k, ax in enumerate(self.axes):
            sv = ax.servo
            if not sv.wobble:
                continue
            ph = sv.wobble_harmonic * ang[:, k] + sv.wobble_phase
            w, wd = np.zeros((n, 3)), np.zeros((n, 3))
            i, j = perp[k]
            w[:, i], w[:, j] = sv.wobble * np.cos(ph), sv.wobble * np.sin(ph)
            rate_ph = sv.wobble_harmonic * rates[:, k]
            wd[:, i], wd[:, j] = -w[:, j] * rate_ph, w[:, i] * rate_ph
            m = _rot(names[k], ang[:, k])
            for kk in range(k + 1, 3):
                m = m @ _rot(names[kk], ang[:, kk])
            dk = np.einsum("nji,nj->ni", m, w)
            sub_a, sub_r = np.zeros((n, 3)), np.zeros((n, 3))
            sub_a[:, k:], sub_r[:, k:] = ang[:, k:], rates[:, k:]
            rel = gimbal_rate_body(sub_a, sub_r)
            d += dk
            dd += np.einsum("nji,nj->ni", m, wd) - np.cross(rel, dk)
        return d, dd

    def truth(self) -> dict:
        """The table's true physical parameters, SI, units in the key names (JSON-serialisable).
        The controller's settings (in-position / at-rate windows, dwell) are not truth: a wired
        driver may set them over the link."""
        axes = []
        for ax in self.axes:
            sv = ax.servo
            axes.append({"natural_hz": sv.natural_hz, "damping": sv.damping,
                         "encoder_lsb_rad": sv.encoder_lsb, "encoder_noise_rad": sv.encoder_noise,
                         "rate_ripple_per_rev_fraction": sv.ripple_per_rev,
                         "rate_ripple_per_rev_phase_rad": sv.ripple_per_rev_phase,
                         "rate_ripple_fraction": sv.ripple_fraction, "rate_ripple_hz": sv.ripple_hz,
                         "rate_ripple_phase_rad": sv.ripple_phase, "wobble_rad": sv.wobble,
                         "wobble_harmonic": sv.wobble_harmonic, "wobble_phase_rad": sv.wobble_phase,
                         "jerk_limit_rad_s3": sv.jerk_max if math.isfinite(sv.jerk_max) else None,
                         "rate_limit_rad_s": ax.vmax, "accel_limit_rad_s2": ax.amax,
                         "continuous": ax.continuous})
        return {"axes": axes, "order": ["outer", "middle", "inner"]}
