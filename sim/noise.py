"""Inertial-sensor noise with exact Allan signatures (IEEE Std 952 coefficients), chunked and seeded.

Terms (per axis; all SI, for a gyro the "rate" unit is rad/s, for an accelerometer m/s^2):

==== ======================================= ================== ==========================
key  term                                    unit (gyro/accel)  Allan variance sigma^2(tau)
==== ======================================= ================== ==========================
Q    quantization of the integrated output   rad | m/s          3 Q^2 / tau^2
N    angle / velocity random walk            rad/s/sqrt(Hz)     N^2 / tau
B    bias instability (flicker, 1/f)         rad/s | m/s^2      (2 ln2 / pi) B^2 (plateau)
K    rate random walk                        rad/s^2/sqrt(Hz)   K^2 tau / 3
R    rate ramp                               rad/s^2 | m/s^3    R^2 tau^2 / 2
==== ======================================= ================== ==========================

Realisation at output rate fs (tau0 = 1/fs), for output sample k:

* N: white, y_k = N sqrt(fs) w_k (exact: sigma^2 = N^2/tau for every M).
* B: one white sequence through a cascade of matched-z pole/zero pairs (``flicker_pairs_per_decade``
  pairs per decade, zero a half-step above each pole) whose |H|^2 follows 1/f between
  f_lo = 1/(2 pi tau_max) / 10 and f_hi = min(10/tau_min, fs/4); the gain is set so the Allan
  plateau equals (0.664 B)^2 on average over [flicker_tau_min_s, flicker_tau_max_s].  This is a
  single IIR filter (one random number per sample), not a single Gauss-Markov process: a single
  GM gives a bump, the cascade gives a plateau flat to about +-1 % in deviation.
* K: random walk, y_k = y_{k-1} + K sqrt(tau0) w_k (starts at 0 at power-on).
* R: y_k = R k tau0 (deterministic ramp from power-on).
* Q: the running integral theta of (signal + all other terms) is quantized with step
  q = sqrt(12) Q and differenced: y_k = (q round(theta_k/q) - q round(theta_{k-1}/q)) / tau0.
  The error is white and uniform (hence exactly 3 Q^2/tau^2) as long as the integral moves by
  about one step or more per sample; the residual is carried between chunks.

:func:`theoretical_avar` gives both the IEEE curve (``rate_hz=None``) and the *exact* expectation of
the overlapping Allan variance of what :class:`NoiseGenerator` produces (``rate_hz`` given): the
discrete-time random-walk term K^2 tau/3 (1 + 1/(2 M^2)) and the flicker cascade's own curve, obtained
from its autocovariance (a sum of exponentials, from partial fractions).

Chunking and seeding: each (term, axis) has its own ``numpy.random.Generator`` (SFC64) spawned from one
``SeedSequence``; every recursion (filter state, cumulative sums, quantizer residual) is carried.
The same seed therefore gives bit-identical output whether generated in one piece or in chunks.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy import signal

TERMS = ("Q", "N", "B", "K", "R")
PLATEAU = 2.0 * np.log(2.0) / np.pi  # sigma^2 / B^2 on the flicker plateau (0.664^2)
_DEFAULT_FLICKER = {"flicker_tau_min_s": 1.0, "flicker_tau_max_s": 1.0e4, "flicker_pairs_per_decade": 2}


def _axis3(value: float | Sequence[float]) -> np.ndarray:
    """Broadcast a scalar or 3-sequence to a float64 (3,) array."""
    arr = np.asarray(value, dtype=np.float64)
    return np.broadcast_to(arr, (3,)).copy()


def normalise_params(params: Mapping[str, object]) -> dict:
    """Fill defaults: every term as a (3,) array (0 when absent), flicker band settings as floats."""
    out: dict = {t: _axis3(params.get(t, 0.0)) for t in TERMS}
    for key, default in _DEFAULT_FLICKER.items():
        out[key] = float(params.get(key, default))
    if out["flicker_tau_max_s"] <= out["flicker_tau_min_s"]:
        raise ValueError("flicker_tau_max_s must exceed flicker_tau_min_s")
    if np.any(np.concatenate([out[t] for t in TERMS]) < 0):
        raise ValueError("noise coefficients must be >= 0")
    return out


# ----------------------------------------------------------------------------------------------
# flicker cascade design and its exact Allan variance
@dataclass(frozen=True)
class FlickerDesign:
    """Pole/zero cascade for 1/f noise: p_k = exp(-a_pole[k]), z_k = exp(-a_zero[k]).

    ``input_std_per_B``: std of the white driving sequence divided by B (dimensionless), chosen so
    that the mean Allan variance over the configured tau range equals PLATEAU * B^2.
    """

    a_pole: np.ndarray
    a_zero: np.ndarray
    input_std_per_B: float

    def sos(self) -> np.ndarray:
        """Second-order sections (slowest pole paired with fastest, to keep roots well conditioned)."""
        p, z = np.exp(-self.a_pole), np.exp(-self.a_zero)
        n = len(p)
        half = (n + 1) // 2
        rows = []
        for i in range(half):
            j = n - 1 - i
            if j > i:
                b = np.poly([z[i], z[j]])
                a = np.poly([p[i], p[j]])
            else:
                b = np.array([1.0, -z[i], 0.0])
                a = np.array([1.0, -p[i], 0.0])
            rows.append(np.concatenate([b, a]))
        return np.array(rows)

    def stationary_state_cov(self) -> np.ndarray:
        """Covariance of the flattened sosfilt state (2 per section) in steady state, unit white input.

        The state update z' = A z + B x is probed from scipy's own sosfilt (so the state convention
        is scipy's), then Sigma = sum_j A^j B B^T A^jT by Smith's doubling (k squarings sum 2^k
        samples; it stops when A^(2^k) has decayed, well beyond the slowest time constant).
        """
        sos = self.sos()
        ns = 2 * sos.shape[0]
        A = np.empty((ns, ns))
        for i in range(ns):
            zi = np.zeros(ns)
            zi[i] = 1.0
            A[:, i] = signal.sosfilt(sos, [0.0], zi=zi.reshape(-1, 2))[1].ravel()
        B = signal.sosfilt(sos, [1.0], zi=np.zeros((ns // 2, 2)))[1].ravel()
        S = np.outer(B, B)
        Ak = A
        for _ in range(40):
            S = S + Ak @ S @ Ak.T
            Ak = Ak @ Ak
            if np.max(np.abs(Ak)) < 1e-18:
                break
        return 0.5 * (S + S.T)


def _exp_avar(M: np.ndarray, a: float) -> np.ndarray:
    """Allan variance (expected, overlapping) of a stationary sequence with autocovariance exp(-a|j|).

    Closed form M^2 sigma^2 = M(1+p)/(1-p) - p(1-p^M)(3-p^M)/(1-p)^2 when a*M is not tiny, otherwise
    the exact sum M^2 sigma^2 = sum_{j=1}^{2M-1} r(j) (p^j - 1) with the Allan filter's
    autocorrelation r(j) = 2M-3j (j<=M), -(2M-j) (M<j<2M), which avoids cancellation.
    """
    M = np.asarray(M, dtype=np.float64)
    out = np.empty_like(M)
    x = -np.expm1(-a)
    p = 1.0 - x
    for i, m in enumerate(M):
        if a * m >= 1e-3:
            pm = np.exp(-a * m)
            one_m_pm = -np.expm1(-a * m)
            out[i] = (m * (1 + p) / x - p * one_m_pm * (3 - pm) / x**2) / m**2
        else:
            mi = int(m)
            j = np.arange(1, 2 * mi, dtype=np.float64)
            r = np.where(j <= mi, 2 * mi - 3 * j, -(2 * mi - j))
            out[i] = np.sum(r * np.expm1(-a * j)) / mi**2
    return out


def _cascade_autocov(a_pole: np.ndarray, a_zero: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Autocovariance of unit white noise through prod (1 - z_k/z)/(1 - p_k/z) (gain 1).

    Partial fractions H = D + sum r_k/(1 - p_k z^-1); h_0 = 1, h_n = sum r_k p_k^n; then
    R(j) = sum_l c_l p_l^j (j >= 1) with c_l = r_l (1 + sum_k r_k p_k p_l/(1-p_k p_l)) and
    R(0) = 1 + sum_kl r_k r_l p_k p_l/(1 - p_k p_l) = sum_l c_l + d. Returns (c, d, R(0)).
    """
    p = np.exp(-a_pole)
    # differences computed from expm1 values to keep precision for poles near 1
    om_p = -np.expm1(-a_pole)  # 1 - p
    om_z = -np.expm1(-a_zero)  # 1 - z
    n = len(p)
    r = np.empty(n)
    for k in range(n):
        num = np.prod((om_z - om_p[k]) / p[k])  # 1 - z_j/p_k = (p_k - z_j)/p_k
        others = np.delete(np.arange(n), k)
        den = np.prod((om_p[others] - om_p[k]) / p[k])
        r[k] = num / den
    one_m_pp = -np.expm1(-(a_pole[:, None] + a_pole[None, :]))
    cross = (r[:, None] * p[:, None] * p[None, :] / one_m_pp)  # [k, l]
    c = r * (1.0 + cross.sum(axis=0))
    R0 = 1.0 + float(np.sum(cross * r[None, :]))
    return c, R0 - float(c.sum()), R0


def _cascade_avar(a_pole: np.ndarray, a_zero: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Exact Allan variance for unit white input through the cascade: sum_l c_l AVAR_exp + d/M."""
    c, d, _ = _cascade_autocov(a_pole, a_zero)
    total = d / np.asarray(M, dtype=np.float64)
    for cl, al in zip(c, a_pole):
        total = total + cl * _exp_avar(M, al)
    return total


def flicker_variance(params: Mapping[str, object], rate_hz: float) -> np.ndarray:
    """Stationary variance (3,) of the flicker term's samples, (rate unit)^2."""
    P = normalise_params(params)
    d = design_flicker(P["flicker_tau_min_s"], P["flicker_tau_max_s"], rate_hz, P["flicker_pairs_per_decade"])
    return _cascade_autocov(d.a_pole, d.a_zero)[2] * d.input_std_per_B**2 * P["B"] ** 2


def design_flicker(tau_min_s: float, tau_max_s: float, rate_hz: float, pairs_per_decade: float = 2) -> FlickerDesign:
    """Design the 1/f cascade for a plateau over [tau_min_s, tau_max_s] at output rate rate_hz."""
    tau0 = 1.0 / rate_hz
    f_lo = 1.0 / (2 * np.pi * tau_max_s) / 10.0
    f_hi = min(10.0 / tau_min_s, rate_hz / 4.0)
    step = 10.0 ** (1.0 / pairs_per_decade)
    n_pairs = max(1, int(np.floor(np.log10(f_hi / f_lo) * pairs_per_decade)))
    f_pole = f_lo * step ** np.arange(n_pairs)
    f_zero = f_pole * np.sqrt(step)
    a_pole, a_zero = 2 * np.pi * f_pole * tau0, 2 * np.pi * f_zero * tau0
    # one more pole half a step above the last zero, with its zero at z = 0: without it the
    # cascade's response goes flat above the band and adds white noise (biasing N by ~1 %)
    a_pole = np.append(a_pole, a_zero[-1] * np.sqrt(step))
    a_zero = np.append(a_zero, np.inf)
    taus = np.geomspace(tau_min_s, tau_max_s, 9)
    M = np.maximum(1, np.round(taus * rate_hz))
    mean_avar = float(np.mean(_cascade_avar(a_pole, a_zero, M)))
    return FlickerDesign(a_pole, a_zero, float(np.sqrt(PLATEAU / mean_avar)))


# ----------------------------------------------------------------------------------------------
def theoretical_avar(params: Mapping[str, object], tau: np.ndarray, rate_hz: float | None = None,
                     extra_white_var: np.ndarray | float = 0.0) -> np.ndarray:
    """Theoretical Allan variance, shape (len(tau), 3), in (rate unit)^2.

    rate_hz None: the IEEE 952 sum 3Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau/3 + R^2 tau^2/2.
    rate_hz given: the exact expectation for :class:`NoiseGenerator` at that rate (tau rounded to
    M = tau*fs samples), including the flicker cascade's real curve. ``extra_white_var`` adds white
    noise of that per-sample variance (e.g. ADC quantization LSB^2/12), sigma^2 = v tau0/tau.
    """
    P = normalise_params(params)
    tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
    if rate_hz is None:
        t = tau[:, None]
        return (3 * P["Q"] ** 2 / t**2 + P["N"] ** 2 / t + PLATEAU * P["B"] ** 2
                + P["K"] ** 2 * t / 3 + P["R"] ** 2 * t**2 / 2)
    tau0 = 1.0 / rate_hz
    M = np.maximum(1, np.round(tau * rate_hz))
    t = (M * tau0)[:, None]
    avar = (3 * P["Q"] ** 2 / t**2 + (P["N"] ** 2 + np.asarray(extra_white_var) * tau0) / t
            + P["K"] ** 2 * t / 3 * (1 + 1 / (2 * M[:, None] ** 2)) + P["R"] ** 2 * t**2 / 2)
    if np.any(P["B"] > 0):
        d = design_flicker(P["flicker_tau_min_s"], P["flicker_tau_max_s"], rate_hz, P["flicker_pairs_per_decade"])
        unit = _cascade_avar(d.a_pole, d.a_zero, M) * d.input_std_per_B**2
        avar = avar + unit[:, None] * P["B"] ** 2
    return avar


# ----------------------------------------------------------------------------------------------
class NoiseGenerator:
    """Chunked, seeded 3-axis noise: ``gen.next(n) -> (n, 3)`` float64 in the rate unit.

    ``gen.next(n, signal)`` adds a (n, 3) signal before quantization of the integral (Q acts on the
    integrated total output, as in a delta-angle / delta-velocity sensor).
    """

    def __init__(self, params: Mapping[str, object], rate_hz: float, seed: int | np.random.SeedSequence | None = 0):
        self.params = normalise_params(params)
        self.rate_hz = float(rate_hz)
        self.tau0 = 1.0 / self.rate_hz
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        children = ss.spawn(3 * 3)  # (N, B, K) x 3 axes
        self._rng = [np.random.Generator(np.random.SFC64(c)) for c in children]  # SFC64: fastest normals
        P = self.params
        self._n_scale = P["N"] * np.sqrt(self.rate_hz)
        self._k_scale = P["K"] * np.sqrt(self.tau0)
        self._q_step = np.sqrt(12.0) * P["Q"]
        self._flicker = None
        if np.any(P["B"] > 0):
            d = design_flicker(P["flicker_tau_min_s"], P["flicker_tau_max_s"], self.rate_hz, P["flicker_pairs_per_decade"])
            self._flicker = d
            self._sos = d.sos()
            self._b_scale = P["B"] * d.input_std_per_B
            # stationary start (no build-up of the slow components after power-on): draw the filter
            # state from its steady-state distribution, from the B streams, per axis
            cov = d.stationary_state_cov()
            lam, U = np.linalg.eigh(cov)
            root = U * np.sqrt(np.clip(lam, 0.0, None))
            zi = np.stack([root @ self._rng[3 + ax].standard_normal(len(lam)) * self._b_scale[ax]
                           for ax in range(3)])  # (3, 2*n_sec)
            self._zi = np.ascontiguousarray(zi.reshape(3, -1, 2).transpose(1, 0, 2))  # (n_sec, 3, 2)
        self._rrw = np.zeros(3)
        self._theta = np.zeros(3)  # running integral (rate unit * s)
        self._theta_q = np.zeros(3)  # quantized integral at the previous sample
        self._k = 0  # samples produced so far

    def _fill_normals(self, term: int, out: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """Fill out (3, n) with scaled standard normals of term 0=N, 1=B, 2=K from per-axis streams."""
        for ax in range(3):
            self._rng[3 * term + ax].standard_normal(out=out[ax])
        out *= scale[:, None]
        return out

    def next(self, n: int, signal_in: np.ndarray | None = None) -> np.ndarray:
        """Next n samples (n, 3); optional signal (n, 3) is added before quantization of the integral.

        The returned array is a transposed view of a (3, n) C-contiguous buffer.
        """
        P = self.params
        y = np.zeros((3, n)) if signal_in is None else np.array(np.asarray(signal_in, dtype=np.float64).T, order="C")
        buf = np.empty((3, n))
        if np.any(self._n_scale > 0):
            y += self._fill_normals(0, buf, self._n_scale)
        if self._flicker is not None:
            self._fill_normals(1, buf, self._b_scale)
            fl, self._zi = signal.sosfilt(self._sos, buf, axis=-1, zi=self._zi)
            y += fl
        if np.any(self._k_scale > 0):
            self._fill_normals(2, buf, self._k_scale)
            buf[:, 0] += self._rrw
            np.cumsum(buf, axis=-1, out=buf)
            self._rrw = buf[:, -1].copy()
            y += buf
        if np.any(P["R"] > 0):
            t = (self._k + 1 + np.arange(n)) * self.tau0
            y += P["R"][:, None] * t[None, :]
        if np.any(self._q_step > 0):
            self._quantize_integral(y, buf)
        self._k += n
        return y.T

    def _quantize_integral(self, y: np.ndarray, buf: np.ndarray) -> None:
        """In place: quantize the running integral with step q per axis and difference it."""
        np.multiply(y, self.tau0, out=buf)
        buf[:, 0] += self._theta
        np.cumsum(buf, axis=-1, out=buf)
        self._theta = buf[:, -1].copy()
        for ax in range(3):
            q = self._q_step[ax]
            if q <= 0:
                continue
            tq = buf[ax]
            tq /= q
            np.round(tq, out=tq)
            tq *= q
            y[ax, 1:] = tq[1:] - tq[:-1]
            y[ax, 0] = tq[0] - self._theta_q[ax]
            y[ax] *= self.rate_hz
            self._theta_q[ax] = tq[-1]
