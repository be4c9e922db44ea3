"""Physical-effect models of an IMU on a turntable: pure, vectorised numpy functions and small
stateful helpers (carried state only where an effect has memory). SI units throughout
(m/s^2, rad/s, s, K or degC); arrays of samples are (n, 3) with axes x, y, z.

Declared deterministic errors (docs/methods.md A2)::

    accelerometer  A = b_a + M_a a + k2_a * a**2          (M_a: diag = scale S_i, off-diag = K_ji)
    gyroscope      W = b_g + M_g w                         (diag = scale Sk_i, off-diag = K_ij)

Extra effects (each switchable in :mod:`rigctl.sim.error_model`):

* warm-up:            T(t) = T0 + dT (1 - exp(-t/tau));  bias += c_b (T - T_ref), scale += c_s (T - T_ref),
                      T_ref = T0 + dT (the settled temperature, so the declared values hold after warm-up)
* turn-on bias:       a constant drawn at every power-on (run-to-run repeatability), b_on ~ N(0, sigma^2)
                      per axis: the unit's first turn-on and every power cycle after it (:func:`turn_on_bias`)
* g-sensitivity:      W += G a + A_ae a**2           (G in rad/s per m/s^2, A_ae in rad/s per (m/s^2)^2)
* scale asymmetry:    A += 0.5 u |a|                 (scale S + u/2 for a > 0, S - u/2 for a < 0)
* gyro nonlinearity:  W += k2 w**2 + k3 w**3
* lever arm:          a += w x (w x r) + dw/dt x r   (IMU at r from the rotation centre)
* time delay:         the IMU sees the table's state at t - d (evaluate the table at t - d)
* vibration:          a += sum_k a_k sin(2 pi f_k t + phi_k), w likewise
* clock:              IMU sample-period error e(t) = drift_ppm + wander (first-order Gauss-Markov), so
                      sample k comes at t_k = t_{k-1} + tau0 (1 + 1e-6 e_k) (positive = IMU clock slow,
                      the convention of rigctl.sim.taps.ClockParams); dropped samples in bursts
* table geometry:     gimbal axes not orthogonal, base not level / not north-aligned
"""
from __future__ import annotations

from functools import lru_cache
from typing import Sequence

import numpy as np

from .iir import lfilter


# ---------------------------------------------------------------------------- declared errors
def matvec(x: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Rows of x (n,3) times M^T, i.e. y_i = sum_j M[i,j] x_j, column by column without BLAS
    (multi-threaded BLAS on n x 3 products stalls badly when the cores are busy)."""
    M = np.asarray(M, dtype=float)
    out = np.empty((x.shape[0], 3))
    c0, c1, c2 = x[:, 0], x[:, 1], x[:, 2]
    for i in range(3):
        out[:, i] = M[i, 0] * c0 + M[i, 1] * c1 + M[i, 2] * c2
    return out


def accel_declared(f: np.ndarray, bias: np.ndarray, M: np.ndarray, k2: np.ndarray) -> np.ndarray:
    """A = b + M f + k2 f^2 (m/s^2); M (3,3) dimensionless, k2 (3,) in 1/(m/s^2)."""
    return matvec(f, M) + np.asarray(k2) * f * f + bias


def gyro_declared(w: np.ndarray, bias: np.ndarray, M: np.ndarray) -> np.ndarray:
    """W = b + M w (rad/s); M (3,3) dimensionless."""
    return matvec(w, M) + bias


def turn_on_bias(rng: np.random.Generator, gyro_sigma_rad_s: float,
                 accel_sigma_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """A turn-on bias of each sensor, b_on ~ N(0, sigma^2) per axis: the bias repeatability
    from turn-on to turn-on (run-to-run; a datasheet's "bias repeatability"). Returns (gyro (3,)
    rad/s, accel (3,) m/s^2), drawn in that order from ``rng`` (one seeded stream per unit, so a
    unit's sequence of turn-ons is reproducible)."""
    g = rng.standard_normal(3) * float(gyro_sigma_rad_s)
    return g, rng.standard_normal(3) * float(accel_sigma_m_s2)


# ---------------------------------------------------------------------------- thermal
def warmup_temperature(t: np.ndarray, T0_degC: float, dT_degC: float, tau_s: float) -> np.ndarray:
    """T(t) = T0 + dT (1 - exp(-t/tau)) in degC, t in s since power-on (t < 0 -> T0)."""
    t = np.maximum(np.asarray(t, dtype=float), 0.0)
    return T0_degC + dT_degC * -np.expm1(-t / tau_s)


def thermal_error(x: np.ndarray, dT: np.ndarray, bias_tc: np.ndarray, scale_tc: np.ndarray) -> np.ndarray:
    """Error c_b dT + c_s dT x for input x (n,3) and temperature offset dT (n,) from T_ref.

    bias_tc in (signal unit)/K, scale_tc in 1/K.
    """
    dT = np.asarray(dT, dtype=float)[:, None]
    return dT * (np.asarray(bias_tc) + np.asarray(scale_tc) * x)


# ---------------------------------------------------------------------------- sensor effects
def g_sensitivity_error(f: np.ndarray, G: np.ndarray, A_ae: np.ndarray | None = None) -> np.ndarray:
    """Gyro error G f + A_ae f^2 (rad/s) for specific force f (n,3)."""
    err = matvec(f, G)
    if A_ae is not None:
        err += matvec(f * f, A_ae)
    return err


def scale_asymmetry_error(f: np.ndarray, asym: np.ndarray) -> np.ndarray:
    """Accelerometer error 0.5 u |f| (positive-input scale minus negative-input scale = u)."""
    return 0.5 * np.asarray(asym) * np.abs(f)


def gyro_nonlinearity_error(w: np.ndarray, k2: np.ndarray, k3: np.ndarray) -> np.ndarray:
    """Gyro error k2 w^2 + k3 w^3; k2 in 1/(rad/s), k3 in 1/(rad/s)^2."""
    return w * w * (np.asarray(k2) + np.asarray(k3) * w)


def lever_arm_specific_force(w: np.ndarray, dw: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Specific force at offset r (m) from the rotation centre: w x (w x r) + dw/dt x r (m/s^2).

    The centripetal part has magnitude |w|^2 |r_perp| (3.05e-2 m/s^2 = 3.1 mg at 100 deg/s, r = 1 cm).
    """
    r = np.asarray(r, dtype=float)
    w0, w1, w2 = w[:, 0], w[:, 1], w[:, 2]
    d0, d1, d2 = dw[:, 0], dw[:, 1], dw[:, 2]
    wr = w0 * r[0] + w1 * r[1] + w2 * r[2]
    ww = w0 * w0 + w1 * w1 + w2 * w2
    out = np.empty_like(w, dtype=float)
    # w x (w x r) = w (w.r) - r |w|^2 ;  dw x r
    out[:, 0] = w0 * wr - r[0] * ww + (d1 * r[2] - d2 * r[1])
    out[:, 1] = w1 * wr - r[1] * ww + (d2 * r[0] - d0 * r[2])
    out[:, 2] = w2 * wr - r[2] * ww + (d0 * r[1] - d1 * r[0])
    return out


class AngularAcceleration:
    """dw/dt by backward differences over the sample times, carrying the previous sample."""

    def __init__(self) -> None:
        self._t: float | None = None
        self._w: np.ndarray | None = None

    def __call__(self, t: np.ndarray, w: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        if self._t is None:
            tt, ww = np.concatenate([[t[0] - 1.0], t]), np.vstack([w[:1], w])
        else:
            tt, ww = np.concatenate([[self._t], t]), np.vstack([self._w, w])
        self._t, self._w = float(t[-1]), w[-1:].copy()
        return np.diff(ww, axis=0) / np.diff(tt)[:, None]


def vibration_many(t: np.ndarray, freqs_hz: Sequence[float], amps: Sequence[np.ndarray],
                   phase_rad: np.ndarray) -> list[np.ndarray]:
    """Several signals sharing the same sinusoids: for each amp (k,3) in amps, the (n,3) sum
    sum_k amp[k] sin(2 pi f_k t + phase[k]) = sin(wt) (a cos p) + cos(wt) (a sin p).

    The phase 2 pi f t is reduced to [0, 2 pi) in cycles first (exact for long runs); one sin and
    one cos per frequency serve every signal.
    """
    t = np.asarray(t, dtype=float)
    outs = [np.zeros((len(t), 3)) for _ in amps]
    phase = np.asarray(phase_rad, dtype=float)
    for k, f in enumerate(freqs_hz):
        cyc = f * t
        cyc -= np.floor(cyc)
        cyc *= 2 * np.pi
        s, c = np.sin(cyc), np.cos(cyc)
        for out, amp in zip(outs, amps):
            a = np.asarray(amp, dtype=float)[k]
            for i in range(3):
                if a[i] != 0.0:
                    out[:, i] += s * (a[i] * np.cos(phase[k, i])) + c * (a[i] * np.sin(phase[k, i]))
    return outs


def vibration(t: np.ndarray, freqs_hz: Sequence[float], amp: np.ndarray, phase_rad: np.ndarray) -> np.ndarray:
    """Sum of sinusoids: sum_k amp[k] sin(2 pi f_k t + phase[k]); amp, phase (k,3); returns (n,3)."""
    return vibration_many(t, freqs_hz, [amp], phase_rad)[0]


# ---------------------------------------------------------------------------- clock and drops
class ClockModel:
    """IMU sample clock: true time of each output sample, and dropped samples.

    e_k = drift_ppm + g_k with g a stationary first-order Gauss-Markov process (std wander_ppm,
    correlation time wander_tau_s); dt_k = tau0 (1 + 1e-6 e_k) (positive: the IMU clock is slow, each
    count lasts longer, fewer samples per reference second; as rigctl.sim.taps.ClockParams);
    t_k = t0 + sum dt. Drops: each sample starts a
    burst of 1..drop_max_burst lost samples with probability drop_probability. Carried across blocks.
    """

    def __init__(self, rate_hz: float, drift_ppm: float = 0.0, wander_ppm: float = 0.0, wander_tau_s: float = 600.0,
                 drop_probability: float = 0.0, drop_max_burst: int = 1, t0_s: float = 0.0,
                 seed: int | np.random.SeedSequence | None = 0):
        self.tau0 = 1.0 / rate_hz
        self.drift_ppm, self.wander_ppm, self.wander_tau_s = float(drift_ppm), float(wander_ppm), float(wander_tau_s)
        self.drop_probability, self.drop_max_burst = float(drop_probability), int(drop_max_burst)
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        a, b, c = (np.random.default_rng(s) for s in ss.spawn(3))
        self._rng_w, self._rng_d, self._rng_l = a, b, c
        self._phi = float(np.exp(-self.tau0 / self.wander_tau_s))
        self._g = np.array([self._rng_w.standard_normal() * self.wander_ppm])  # stationary start
        self._t = float(t0_s) - self.tau0  # time of the previous sample
        self._burst_left = 0
        self.counter = 0

    def next(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t_true (n,), keep (n,) bool, period error e (n,) ppm) for the next n output samples."""
        if self.wander_ppm > 0:
            w = self._rng_w.standard_normal(n) * (self.wander_ppm * np.sqrt(1 - self._phi**2))
            g, zf = lfilter([1.0], [1.0, -self._phi], w, self._phi * self._g)
            self._g = g[-1:].copy()
            del zf
        else:
            g = np.zeros(n)
        e = self.drift_ppm + g
        dt = self.tau0 * (1.0 + 1e-6 * e)
        dt[0] += self._t
        t = np.cumsum(dt)
        self._t = float(t[-1])
        keep = np.ones(n, dtype=bool)
        if self.drop_probability > 0:
            starts = np.flatnonzero(self._rng_d.random(n) < self.drop_probability)
            lengths = self._rng_l.integers(1, self.drop_max_burst + 1, size=len(starts))
            if self._burst_left:
                keep[: self._burst_left] = False
            ends = starts + lengths
            for s, e_ in zip(starts, ends):  # loop over bursts only (rare events)
                keep[s:e_] = False
            tail = max([self._burst_left - n] + [int(x) - n for x in ends])
            self._burst_left = max(0, tail)
        self.counter += n
        return t, keep, e


# ---------------------------------------------------------------------------- table geometry
_EYE3 = np.eye(3)
_EYE3.setflags(write=False)


@lru_cache(maxsize=64)
def _rodrigues_terms(axis_bytes: bytes) -> tuple[np.ndarray, np.ndarray]:
    """K = [k x] and K @ K of the unit vector along the axis whose float64 bytes are given
    (read-only; a table's axes are the same at every poll, so they are made once)."""
    k = np.frombuffer(axis_bytes, dtype=float)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    KK = K @ K
    K.setflags(write=False)
    KK.setflags(write=False)
    return K, KK


def rotation_matrices(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: (n,3,3) rotations by angle (n,) rad about the unit vector axis (3,)."""
    K, KK = _rodrigues_terms(np.ascontiguousarray(axis, dtype=float).tobytes())
    a = np.asarray(angle, dtype=float)[:, None, None]
    return _EYE3 + np.sin(a) * K + (1 - np.cos(a)) * KK


def gimbal_axes(nonorth_rad: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Actual rotation axes (3,3): rows outer, middle, inner, each in its parent frame at zero.

    Nominal outer = z (base up), middle = y, inner = x (docs/methods.md A3: x, y, z accelerometer axes
    parallel to inner, middle, outer). nonorth_rad = (d_om, d_mi_y, d_mi_z): middle axis tilted by d_om
    towards z (outer/middle angle 90 deg - d_om), inner axis tilted by d_mi_y towards y (middle/inner
    non-orthogonality) and by d_mi_z towards z.
    """
    d_om, d_y, d_z = (float(v) for v in nonorth_rad)
    outer = np.array([0.0, 0.0, 1.0])
    middle = np.array([0.0, np.cos(d_om), np.sin(d_om)])
    inner = np.array([1.0, d_y, d_z])
    return np.vstack([outer, middle, inner / np.linalg.norm(inner)])


def base_to_local(level_x_rad: float = 0.0, level_y_rad: float = 0.0, north_rad: float = 0.0) -> np.ndarray:
    """(3,3) rotation from the table base frame to local ENU: levelling errors about x and y, and the
    north-alignment (azimuth) error about up: C = R_z(north) R_y(level_y) R_x(level_x)."""
    rz = rotation_matrices([0, 0, 1], [north_rad])[0]
    ry = rotation_matrices([0, 1, 0], [level_y_rad])[0]
    rx = rotation_matrices([1, 0, 0], [level_x_rad])[0]
    return rz @ ry @ rx


@lru_cache(maxsize=16)
def _table_frames(geometry_bytes: bytes) -> tuple[np.ndarray, np.ndarray]:
    """(:func:`gimbal_axes`, :func:`base_to_local`) of one table geometry (the float64 bytes of
    nonorth_rad (3), level_x_rad, level_y_rad, north_rad), read-only: the same for every poll of
    a run, so made once."""
    g = np.frombuffer(geometry_bytes, dtype=float)
    ax, base = gimbal_axes(g[:3].tolist()), base_to_local(*g[3:].tolist())
    ax.setflags(write=False)
    base.setflags(write=False)
    return ax, base


def table_attitude_and_rate(angles: np.ndarray, rates: np.ndarray, nonorth_rad: Sequence[float] = (0, 0, 0),
                            level_x_rad: float = 0.0, level_y_rad: float = 0.0,
                            north_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Body-to-ENU DCM (n,3,3) and table-induced body rate (n,3) rad/s from gimbal angles/rates
    (n,3) [outer, middle, inner] with non-orthogonal axes and a misaligned base.

    C_b^n = C_base^n R(a_o, th_o) R(a_m, th_m) R(a_i, th_i);
    w_b = R_i^T R_m^T (th_o' a_o) + R_i^T (th_m' a_m) + th_i' a_i.
    """
    angles, rates = np.atleast_2d(angles), np.atleast_2d(rates)
    ax, base = _table_frames(np.array([*nonorth_rad, level_x_rad, level_y_rad, north_rad], dtype=float).tobytes())
    Ro = rotation_matrices(ax[0], angles[:, 0])
    Rm = rotation_matrices(ax[1], angles[:, 1])
    Ri = rotation_matrices(ax[2], angles[:, 2])
    C = base @ Ro @ Rm @ Ri
    RiT, RmT = np.swapaxes(Ri, 1, 2), np.swapaxes(Rm, 1, 2)
    w = (np.einsum("nij,nj->ni", RiT, np.einsum("nij,nj->ni", RmT, rates[:, :1] * ax[0]))
         + np.einsum("nij,nj->ni", RiT, rates[:, 1:2] * ax[1]) + rates[:, 2:3] * ax[2])
    return C, w


def table_body_references(angles: np.ndarray, rates: np.ndarray | None, latitude_rad: float, g: float,
                          nonorth_rad: Sequence[float] = (0, 0, 0), level_x_rad: float = 0.0,
                          level_y_rad: float = 0.0, north_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """True body specific force and rate (n,3) for a table with geometry errors (same convention as
    rigctl.frames.body_references, which it equals when every error is zero):
    f^b = (C_b^n)^T (0, 0, g),  w^b = (C_b^n)^T Omega_E (0, cos L, sin L) + w_table^b."""
    from rigctl.frames import earth_rate_enu

    angles = np.atleast_2d(np.asarray(angles, dtype=float))
    rates = np.zeros_like(angles) if rates is None else np.atleast_2d(np.asarray(rates, dtype=float))
    C, w_tab = table_attitude_and_rate(angles, rates, nonorth_rad, level_x_rad, level_y_rad, north_rad)
    CT = np.swapaxes(C, 1, 2)
    f_b = CT @ np.array([0.0, 0.0, float(g)])
    w_b = CT @ earth_rate_enu(latitude_rad) + w_tab
    return f_b, w_b
