"""Inertial-sensor noise with exact Allan signatures (IEEE Std 952 coefficients), chunked and seeded.

Terms (per axis: the three axes' :class:`rigctl.solvers.noise_coefficients.NoiseCoefficients`, whose
docstring gives the PSDs; all SI, for a gyro the "rate" unit is rad/s, for an accelerometer m/s^2):

==== ======================================= ================== ==========================
key  term                                    unit (gyro/accel)  Allan variance sigma^2(tau)
==== ======================================= ================== ==========================
Q    quantization of the integrated output   rad | m/s          3 Q^2 / tau^2
N    angle / velocity random walk            rad/s/sqrt(Hz)     N^2 / tau
B    bias instability (flicker, 1/f)         rad/s | m/s^2      (2 ln2 / pi) B^2 (plateau)
K    rate random walk                        rad/s^2/sqrt(Hz)   K^2 tau / 3
R    rate ramp                               rad/s^2 | m/s^3    R^2 tau^2 / 2
gm   first-order Gauss-Markov: sigma,        rad/s | m/s^2, s   sigma^2 x (the OU curve,
     correlation time Tc (each a list)                          rigctl.solvers.noise_coefficients)
==== ======================================= ================== ==========================

Realisation at output rate fs (tau0 = 1/fs), for output sample k, in per-sample terms
sn^2 = N^2 fs (white), sb^2 = (B c_B)^2 (flicker input):

* B alone is white noise through a cascade of matched-z pole/zero pairs H (``flicker_pairs_per_decade``
  pairs per decade, zero a half-step above each pole) whose |H|^2 follows 1/f between
  f_lo = 1/(2 pi tau_max) / 10 and f_hi = min(10/tau_min, fs/4); c_B is set so the Allan plateau equals
  (0.664 B)^2 on average over [flicker_tau_min_s, flicker_tau_max_s]. Not a single Gauss-Markov process
  (which gives a bump): the cascade gives a plateau flat to about +-1 % in deviation.
* N and B together are ONE white Gaussian sequence through ONE minimum-phase filter
  g G(z) = g prod_j (1 - zeta_j z^-1) / prod_k (1 - p_k z^-1) with g^2 |G|^2 = sn^2 + sb^2 |H|^2
  (spectral factorisation, :mod:`rigctl.sim.spectral_factor`): a stationary Gaussian process is fixed by its
  spectrum, so this has exactly the law of independent N + B, with one normal draw per sample instead of two.
  The stable states are drawn from their stationary distribution: sample 0 already has the full variance.
* K: random walk from 0 at power-on, y_k = y_{k-1} + K sqrt(tau0) w_k, with w_k uniform (on 2^16 levels in
  [-sqrt 3, sqrt 3], unit variance; its own stream). Any white increments give exactly K^2 tau/3 (1 + 1/(2 M^2));
  a 16-bit uniform draw costs a twelfth of a normal one, and the walk is Gaussian to a relative fourth cumulant
  of 1.2/n after n samples (K only shows at long tau, where n > 1e4). Not folded into G: a filter with a pole at
  z = 1 has exact increments but cannot give the power-on level of "stationary N + B plus a walk from 0".
* R: deterministic ramp R (k + 1) tau0 from power-on.
* gm: each Gauss-Markov term is its exact discretisation, the AR(1) sequence
  x_k = exp(-tau0/Tc) x_(k-1) + sigma sqrt(1 - exp(-2 tau0/Tc)) e_k from the stationary law
  (:class:`GaussMarkovNoise`, one more stream per axis spawned after the others, so the other
  terms draw the same numbers with or without it); added to the signal before Q.
* Q: the running integral theta of (signal + all other terms) is quantized with step
  q = sqrt(12) Q and differenced: y_k = (q round(theta_k/q) - q round(theta_{k-1}/q)) / tau0.
  The error is white and uniform (hence exactly 3 Q^2/tau^2) as long as the integral moves by
  about one step or more per sample. The N + B integral comes from the same filter with one more pole at
  z = 1 (gain tau0/q), the walk's and the ramp's in closed form per block, the signal's as a running sum.

Speed: the filter runs on a fixed grid of chunks (``FIRST_CHUNK``, doubling, then ``CHUNK`` samples). With numba
(the ``fast`` extra) the filter, the K walk and the ramp of a chunk are one compiled loop over the samples
(``_chunk_fused``: the cascade in parallel form as :func:`rigctl.sim.block_iir.run_direct`, then the walk and the
ramp), and the quantizer another (numpy's operations in numpy's order): about 15 ns per axis-sample on one core of
the shared test machine (load ~10), 8-10 of them numpy's normal draw. Without numba:
BLAS block recursion (:mod:`rigctl.sim.block_iir`), about 30 ns per axis-sample (benchmarks/emulator.py).

:func:`theoretical_avar` gives both the IEEE curve (``rate_hz=None``) and the *exact* expectation of
the overlapping Allan variance of what :class:`NoiseGenerator` produces (``rate_hz`` given): the
discrete-time random-walk term K^2 tau/3 (1 + 1/(2 M^2)) and the flicker cascade's own curve, obtained
from its autocovariance (a sum of exponentials, from partial fractions).

Chunking and seeding: each axis has two ``numpy.random.Generator`` (SFC64) streams (N + B, K) spawned from
one ``SeedSequence``; everything is computed on chunks aligned to a fixed grid of samples and every recursion
(filter state, walk, quantizer residual, signal integral) is carried, so the same seed gives bit-identical
output whether generated in one piece or in chunks. (Since the combined N + B filter, the same seed gives
other numbers than releases with separate N, B, K normal streams; the statistics are unchanged.)
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np

from rigctl.solvers.noise_coefficients import PLATEAU, TERMS, NoiseCoefficients, terms_of
from rigctl.solvers.segment_cov import ou_avar

from . import block_iir as _bi
from .block_iir import BlockCascade

if _bi.HAVE_NUMBA:
    from rigctl.jit import njit

    @njit(cache=True, nogil=True)
    def _walk(raw16, mean, s, kappa, quantized, state, row):  # pragma: no cover - compiled
        """row += the K random walk (quantized: its integral in steps q) sample by sample:
        W_t = W_{t-1} + s (v_t - mean), Theta_t = Theta_{t-1} + kappa W_t; state = (W, Theta)."""
        w = state[0]
        th = state[1]
        if quantized:
            for t in range(row.size):
                w += s * (raw16[t] - mean)
                th += kappa * w
                row[t] += th
        else:
            for t in range(row.size):
                w += s * (raw16[t] - mean)
                row[t] += w
        state[0] = w
        state[1] = th

    @njit(cache=True, nogil=True, fastmath=True)
    def _chunk_fused(eps, p, rp, c_int, gain, state, raw, k_on, k_s, kappa, quant, wstate,
                     r_on, r_coef, base, out):  # pragma: no cover - compiled
        """One chunk of every axis in one pass: the N + B cascade (block_iir._direct's
        arithmetic, fastmath for the pole sum), then the K walk (:func:`_walk`) and the R ramp
        (:func:`_ramp`) added in that order with their arithmetic (no reassociation across
        them: each is one dependent add)."""
        k_n, n = eps.shape
        n_st = p.size
        n_int = c_int.shape[1]
        s = np.empty(n_st)
        for k in range(k_n):
            for i in range(n_st):
                s[i] = state[k, i]
            g = gain[k]
            rk = rp[k]
            kon = k_on[k]
            q = quant[k]
            ks = k_s[k]
            kap = kappa[k]
            w = wstate[k, 0]
            th = wstate[k, 1]
            ron = r_on[k]
            rc = r_coef[k]
            for t in range(n):
                e = eps[k, t]
                x = 0.0
                for i in range(n_st):
                    x += rk[i] * s[i]
                    s[i] = p[i] * s[i] + e
                x += e
                for j in range(n_int):
                    wj = state[k, n_st + j]
                    state[k, n_st + j] = wj + x
                    x = x + c_int[k, j] * wj
                v = g * x
                if kon:
                    w += ks * (raw[k, t] - _U16_MEAN)
                    if q:
                        th += kap * w
                        v += th
                    else:
                        v += w
                if ron:
                    kk = float(t) + base
                    if q:
                        v += ((kk + 1.0) * kk) * rc
                    else:
                        v += kk * rc
                out[k, t] = v
            for i in range(n_st):
                state[k, i] = s[i]
            wstate[k, 0] = w
            wstate[k, 1] = th

    @njit(cache=True, nogil=True)
    def _ramp(row, base, coef, quantized):  # pragma: no cover - compiled
        """row += R (k+1) tau0 (coef = R tau0), or on a quantized axis its integral
        (k+1)(k+2) R tau0^2 / (2q) (coef = R tau0^2 / (2q)); k = base - 1 + j: numpy's
        operations of NoiseGenerator._next_chunk, in one pass."""
        for j in range(row.size):
            kk = float(j) + base
            if quantized:
                row[j] += ((kk + 1.0) * kk) * coef
            else:
                row[j] += kk * coef

    @njit(cache=True, nogil=True)
    def _quantize(row, sig, has_sig, k_sig, k_out, state):  # pragma: no cover - compiled
        """In place, as the numpy path of NoiseGenerator.next (same operations, same order):
        row (the integral in steps q) += running sum of sig * k_sig (carried in state[0]),
        rounded, differenced against the previous rounded value (state[1]), times k_out."""
        th_s = state[0]
        prev = state[1]
        for t in range(row.size):
            v = row[t]
            if has_sig:
                th_s += sig[t] * k_sig
                v += th_s
            r = np.rint(v)
            row[t] = (r - prev) * k_out
            prev = r
        state[0] = th_s
        state[1] = prev
from .spectral_factor import factor, residues



def arrays(axes: Sequence[NoiseCoefficients], flicker_pairs_per_decade: float = 2) -> dict:
    """The generator's working form of three axes' coefficients: every term a (3,) array, the flicker
    band (shared by the axes: one cascade) and the cascade's density as floats (axes with different
    flicker bands are a ValueError). Gauss-Markov terms are not part of it: :class:`GaussMarkovNoise`."""
    axes = list(axes)
    if len(axes) != 3:
        raise ValueError(f"the emulator's noise needs three axes, got {len(axes)}")
    band = {(m.flicker_tau_min_s, m.flicker_tau_max_s) for m in axes}
    if len(band) != 1:
        raise ValueError(f"the three axes need one flicker band, got {sorted(band)}")
    (lo, hi), = band
    out: dict = {t: terms_of(axes, t) for t in TERMS}
    out.update(flicker_tau_min_s=float(lo), flicker_tau_max_s=float(hi),
               flicker_pairs_per_decade=float(flicker_pairs_per_decade))
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
    r = residues(a_pole, a_zero)
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


def flicker_variance(axes: Sequence[NoiseCoefficients], rate_hz: float,
                     flicker_pairs_per_decade: float = 2) -> np.ndarray:
    """Stationary variance (3,) of the flicker term's samples, (rate unit)^2."""
    P = arrays(axes, flicker_pairs_per_decade)
    d = design_flicker(P["flicker_tau_min_s"], P["flicker_tau_max_s"], rate_hz, P["flicker_pairs_per_decade"])
    return _cascade_autocov(d.a_pole, d.a_zero)[2] * d.input_std_per_B**2 * P["B"] ** 2


@lru_cache(maxsize=64)
def design_flicker(tau_min_s: float, tau_max_s: float, rate_hz: float, pairs_per_decade: float = 2) -> FlickerDesign:
    """Design the 1/f cascade for a plateau over [tau_min_s, tau_max_s] at output rate rate_hz (cached)."""
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
    a_pole.flags.writeable = a_zero.flags.writeable = False  # shared through the cache
    return FlickerDesign(a_pole, a_zero, float(np.sqrt(PLATEAU / mean_avar)))


# ----------------------------------------------------------------------------------------------
def theoretical_avar(axes: Sequence[NoiseCoefficients], tau: np.ndarray, rate_hz: float | None = None,
                     extra_white_var: np.ndarray | float = 0.0, flicker_pairs_per_decade: float = 2) -> np.ndarray:
    """Theoretical Allan variance, shape (len(tau), 3), in (rate unit)^2.

    rate_hz None: the IEEE 952 sum 3Q^2/tau^2 + N^2/tau + (2 ln2/pi) B^2 + K^2 tau/3 + R^2 tau^2/2
    (plus each Gauss-Markov term's continuous-time curve).
    rate_hz given: the exact expectation for :class:`NoiseGenerator` at that rate (tau rounded to
    M = tau*fs samples), including the flicker cascade's real curve. ``extra_white_var`` adds white
    noise of that per-sample variance (e.g. ADC quantization LSB^2/12), sigma^2 = v tau0/tau.
    """
    P = arrays(axes, flicker_pairs_per_decade)
    tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
    if rate_hz is None:
        t = tau[:, None]
        avar = (3 * P["Q"] ** 2 / t**2 + P["N"] ** 2 / t + PLATEAU * P["B"] ** 2
                + P["K"] ** 2 * t / 3 + P["R"] ** 2 * t**2 / 2)
        for ax, m in enumerate(axes):  # Gauss-Markov: the continuous-time curve
            for g in m.gm:
                avar[:, ax] = avar[:, ax] + g.sigma.value**2 * ou_avar(tau, g.tau_c_s)
        return avar
    tau0 = 1.0 / rate_hz
    M = np.maximum(1, np.round(tau * rate_hz))
    t = (M * tau0)[:, None]
    avar = (3 * P["Q"] ** 2 / t**2 + (P["N"] ** 2 + np.asarray(extra_white_var) * tau0) / t
            + P["K"] ** 2 * t / 3 * (1 + 1 / (2 * M[:, None] ** 2)) + P["R"] ** 2 * t**2 / 2)
    if np.any(P["B"] > 0):
        d = design_flicker(P["flicker_tau_min_s"], P["flicker_tau_max_s"], rate_hz, P["flicker_pairs_per_decade"])
        unit = _cascade_avar(d.a_pole, d.a_zero, M) * d.input_std_per_B**2
        avar = avar + unit[:, None] * P["B"] ** 2
    for ax, m in enumerate(axes):  # Gauss-Markov: autocovariance sigma^2 exp(-tau0 |j| / Tc)
        for g in m.gm:
            avar[:, ax] = avar[:, ax] + g.sigma.value**2 * _exp_avar(M, tau0 / g.tau_c_s)
    return avar


# ----------------------------------------------------------------------------------------------
_KB = 16  # sub-block of the K random walk's running sums
_J1 = np.arange(1.0, _KB + 1.0)
_U16_MEAN, _U16_STD = 32767.5, np.sqrt((65536.0**2 - 1.0) / 12.0)  # uniform on the 16-bit integers
_RW_T1 = np.triu(np.ones((_KB, _KB)))  # [m, j] = 1 for m <= j: running sum within a sub-block
_RW_T2 = np.triu(_J1[None, :] - np.arange(_KB)[:, None])  # [m, j] = j - m + 1 for m <= j: double running sum


class GaussMarkovNoise:
    """First-order Gauss-Markov terms of three axes (each axis' ``gm``), sampled exactly.

    A term of stationary standard deviation sigma and correlation time Tc, sampled every tau0,
    is the AR(1) sequence x_k = phi x_(k-1) + sigma sqrt(1 - phi^2) e_k with phi = exp(-tau0/Tc)
    (the continuous process' exact discretisation: autocovariance sigma^2 phi^|k|), started from
    its stationary law. Each axis draws from its own stream, one normal per term and sample
    (row-major: the same numbers however the output is sliced), and the recursion's state is
    carried: bit-identical in one piece or in chunks.
    """

    def __init__(self, axes: Sequence[NoiseCoefficients], rate_hz: float,
                 seeds: Sequence[np.random.SeedSequence]) -> None:
        from scipy.signal import lfilter

        self._lfilter = lfilter
        tau0 = 1.0 / float(rate_hz)
        self.terms = [[(math.exp(-tau0 / g.tau_c_s), g.sigma.value * math.sqrt(-math.expm1(-2.0 * tau0 / g.tau_c_s)))
                       for g in m.gm] for m in axes]
        self._rng = [np.random.Generator(np.random.SFC64(s)) for s in seeds]
        # x_(-1) from the stationary law N(0, sigma^2)
        self._x = [np.array([g.sigma.value for g in m.gm]) * r.standard_normal(len(m.gm))
                   for m, r in zip(axes, self._rng)]

    def next(self, n: int) -> np.ndarray:
        """The next n samples (n, 3), rate unit."""
        out = np.zeros((n, 3))
        for ax, terms in enumerate(self.terms):
            if not terms:
                continue
            e = self._rng[ax].standard_normal((n, len(terms)))
            for j, (phi, c) in enumerate(terms):
                y, zf = self._lfilter([c], [1.0, -phi], e[:, j], zi=[phi * self._x[ax][j]])
                if n:
                    self._x[ax][j] = y[-1]
                out[:, ax] += y
        return out


class NoiseGenerator:
    """Chunked, seeded 3-axis noise: ``gen.next(n) -> (n, 3)`` float64 in the rate unit.

    ``gen.next(n, signal)`` adds a (n, 3) signal before quantization of the integral (Q acts on the
    integrated total output, as in a delta-angle / delta-velocity sensor).
    """

    # the filter's chunks follow a fixed grid (FIRST_CHUNK, 2 FIRST_CHUNK, ... then CHUNK samples each), so the
    # output is bit-identical however next() is sliced, and a short first call stays cheap
    CHUNK = 1 << 16
    FIRST_CHUNK = 1 << 12
    BLOCK = 64  # block length L of the BLAS block recursion

    def __init__(self, axes: Sequence[NoiseCoefficients], rate_hz: float,
                 seed: int | np.random.SeedSequence | None = 0, flicker_pairs_per_decade: float = 2):
        self.axes = tuple(axes)
        self.params = P = arrays(self.axes, flicker_pairs_per_decade)
        self.rate_hz = float(rate_hz)
        self.tau0 = 1.0 / self.rate_hz
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        streams = [np.random.Generator(np.random.SFC64(c)) for c in ss.spawn(6)]
        self._rng, self._rng_k = streams[:3], streams[3:]  # per axis: N + B, K
        self._q_step = np.sqrt(12.0) * P["Q"]
        self._quantized = self._q_step > 0
        q_safe = np.where(self._quantized, self._q_step, 1.0)
        # K: increments uniform with variance K^2 tau0 (see _add_random_walk); on quantized axes the running
        # sum is integrated once more, in steps q
        self._k_step = np.sqrt(self.tau0) * P["K"]
        self._k_scale = np.where(self._quantized, self.tau0 / q_safe, 1.0)
        self._k_level = np.zeros(3)  # random walk at the previous sample (rate unit)
        self._k_theta = np.zeros(3)  # its integral, in steps q (quantized axes)
        sn2 = P["N"] ** 2 * self.rate_hz
        a_pole, a_zero, sb2 = np.zeros(0), np.zeros(0), np.zeros(3)
        if np.any(P["B"] > 0):
            d = design_flicker(P["flicker_tau_min_s"], P["flicker_tau_max_s"], self.rate_hz, P["flicker_pairs_per_decade"])
            a_pole, a_zero, sb2 = d.a_pole, d.a_zero, (P["B"] * d.input_std_per_B) ** 2
        self.filters = [factor(sn2[ax], sb2[ax], 0.0, a_pole, a_zero) for ax in range(3)]
        res = np.array([residues(a_pole, f.b_stable) if sb2[ax] > 0 else np.zeros(len(a_pole))
                        for ax, f in enumerate(self.filters)]).reshape(3, len(a_pole))
        # quantized axes: the filter gives the noise's integral in steps q (one more pole at z = 1, gain tau0/q)
        c_int = self._quantized.astype(float)[:, None] if np.any(self._quantized) else np.zeros((3, 0))
        gain = np.array([f.gain for f in self.filters]) * self._k_scale
        self._active = gain > 0
        self._filter = None
        if np.any(self._active):
            self._filter = BlockCascade(a_pole, res, c_int, gain, self.BLOCK)
            if len(a_pole):  # stationary start: s_i = eps / (1 - p_i z^-1), Cov(s_i, s_j) = 1 / (1 - p_i p_j)
                lam, U = np.linalg.eigh(1.0 / -np.expm1(-(a_pole[:, None] + a_pole[None, :])))
                root = U * np.sqrt(np.clip(lam, 0.0, None))
                for ax in np.flatnonzero(self._active & (sb2 > 0)):
                    self._filter.state[ax, : len(a_pole)] = root @ self._rng[ax].standard_normal(len(a_pole))
        self._eps: dict[int, np.ndarray] = {}
        self._out: dict[int, np.ndarray] = {}
        self._raw: dict[int, np.ndarray] = {}
        self._kbuf: dict[int, np.ndarray] = {}
        self._kwork: dict[int, tuple] = {}  # K: (W_b, Theta_b, 1) per sub-block, two products
        self._ramp: dict[int, np.ndarray] = {}
        self._chunk = np.zeros((3, 0))
        self._n_chunks = 0
        self._k_chunk = 0  # index of the first sample of the next chunk
        self._pos = 0  # next unread sample of the current chunk
        self._sig_theta = np.zeros(3)  # running integral of the signal, in steps q
        self._theta_q = np.zeros(3)  # quantized integral at the previous sample, in steps q
        self._work = np.empty(0)
        # Gauss-Markov terms: their own streams (spawned after the six above, so the other terms'
        # numbers are the same with or without them), added to the signal before Q
        self._gm = GaussMarkovNoise(self.axes, self.rate_hz, ss.spawn(3)) \
            if any(m.gm for m in self.axes) else None

    def _next_chunk(self) -> None:
        m = min(self.CHUNK, self.FIRST_CHUNK << min(self._n_chunks, 30))
        self._n_chunks += 1
        if m not in self._eps:
            self._eps[m] = np.zeros((3, m))
            self._kbuf[m] = np.empty(m)
        if self._filter is None:
            self._chunk = np.zeros((3, m))
        else:
            eps = self._eps[m]
            for ax in np.flatnonzero(self._active):
                self._rng[ax].standard_normal(out=eps[ax])
            if _bi.HAVE_NUMBA:  # sample by sample, compiled (~4x faster than the BLAS blocks)
                if m not in self._out:
                    self._out[m] = np.empty((3, m))
                self._chunk = self._fused_chunk(eps, m)
                self._k_chunk += m
                self._pos = 0
                return
            self._chunk = self._filter.run(eps)
        for ax in np.flatnonzero(self._k_step > 0):
            if _bi.HAVE_NUMBA:
                self._walk_compiled(ax, self._chunk[ax], m)
            else:
                self._add_random_walk(ax, self._chunk[ax], self._kbuf[m])
        R = self.params["R"]
        if np.any(R > 0) and _bi.HAVE_NUMBA:
            base = float(self._k_chunk + 1)
            for ax in np.flatnonzero(R > 0):
                q = bool(self._quantized[ax])
                coef = 0.5 * R[ax] * self.tau0**2 / self._q_step[ax] if q else R[ax] * self.tau0
                _ramp(self._chunk[ax], base, coef, q)
        elif np.any(R > 0):  # ramp R (k+1) tau0; on quantized axes its integral R tau0^2 (k+1)(k+2)/2, steps q
            if m not in self._ramp:
                self._ramp[m] = np.empty((2, m))
            kk, (kk2, tmp) = self._kbuf[m], self._ramp[m]
            np.add(np.arange(m, dtype=np.float64), float(self._k_chunk + 1), out=kk)
            if np.any(self._quantized):
                np.add(kk, 1.0, out=kk2)
                kk2 *= kk
            for ax in np.flatnonzero(R > 0):
                if self._quantized[ax]:
                    self._chunk[ax] += np.multiply(kk2, 0.5 * R[ax] * self.tau0**2 / self._q_step[ax], out=tmp)
                else:
                    self._chunk[ax] += np.multiply(kk, R[ax] * self.tau0, out=tmp)
        self._k_chunk += m
        self._pos = 0

    def _fused_chunk(self, eps: np.ndarray, m: int) -> np.ndarray:
        """Filter, K walk and R ramp of one chunk in one compiled pass (the same draws and the
        same arithmetic as the separate passes: bit-identical to them)."""
        if m not in self._raw:
            self._raw[m] = np.zeros((3, m), dtype=np.uint16)
        raw = self._raw[m]
        k_on = self._k_step > 0
        for ax in np.flatnonzero(k_on):
            raw[ax] = self._rng_k[ax].bit_generator.random_raw(m // 4).view(np.uint16)
        f = self._filter
        if not hasattr(f, "_rp"):
            _bi.run_direct(f, eps[:, :0], self._out[m][:, :0])  # builds f._p, f._rp
        R = self.params["R"]
        q = self._quantized
        safe_q = np.where(q, self._q_step, 1.0)
        r_coef = np.where(q, 0.5 * R * self.tau0**2 / safe_q, R * self.tau0)
        wstate = np.stack([self._k_level, self._k_theta], axis=1)
        _chunk_fused(eps, f._p, f._rp, f.c_int, f.gain, f.state, raw, k_on,
                     self._k_step / _U16_STD, np.where(q, self._k_scale, 1.0), q, wstate,
                     R > 0, r_coef, float(self._k_chunk + 1), self._out[m])
        self._k_level[:] = wstate[:, 0]
        self._k_theta[:] = wstate[:, 1]
        return self._out[m]

    def _walk_compiled(self, ax: int, row: np.ndarray, m: int) -> None:
        """:meth:`_add_random_walk` sample by sample (the same draws, same walk; rounding
        differs in the last bits from the sub-block products)."""
        raw = self._rng_k[ax].bit_generator.random_raw(m // 4).view(np.uint16)
        quantized = bool(self._quantized[ax])
        state = np.array([self._k_level[ax], self._k_theta[ax]])
        _walk(raw, _U16_MEAN, self._k_step[ax] / _U16_STD,
              float(self._k_scale[ax]) if quantized else 1.0, quantized, state, row)
        self._k_level[ax], self._k_theta[ax] = state[0], state[1]

    def _add_random_walk(self, ax: int, row: np.ndarray, buf: np.ndarray) -> None:
        """row += the K random walk W over one chunk (on quantized axes its integral, in steps q), carried.

        Increments delta = K sqrt(tau0) (v - mean) / std, v uniform on the 16-bit integers (4 per 64-bit draw of
        the axis's K stream: a quarter of the cost of a float draw), so Var delta = K^2 tau0. In sub-blocks b of _KB samples
        (j = 0.._KB-1), with W_b and Theta_b the values before the sub-block (short cumulative sums):
        W = W_b + sum_{m<=j} delta_m;  Theta = Theta_b + kappa ((j+1) W_b + sum_{m<=j} (j-m+1) delta_m),
        kappa = tau0/q. The in-block sums are one matrix product C = V T (its last column, and for the double
        sum the difference of the last two, give the sub-block totals); the W_b, Theta_b, -mean terms another.
        """
        kb, s, quantized = _KB, self._k_step[ax] / _U16_STD, self._quantized[ax]
        raw = self._rng_k[ax].bit_generator.random_raw(len(buf) // 4)  # 4 x 16 bits per 64-bit draw
        np.copyto(buf, raw.view(np.uint16), casting="unsafe")
        U = buf.reshape(-1, kb)
        nbk = len(U)
        if nbk not in self._kwork:
            self._kwork[nbk] = (np.ones((nbk, 3)), np.empty((nbk, kb)), np.empty((nbk, kb)))
        Bm, C, C2 = self._kwork[nbk]
        kappa = self._k_scale[ax] if quantized else 1.0
        T = _RW_T2 if quantized else _RW_T1
        np.matmul(U, T, out=C)  # unscaled, u not yet centred
        if quantized:  # per sub-block: sum of delta, and sum of (kb - m) delta_m
            d_sum = (C[:, -1] - C[:, -2] - _U16_MEAN * kb) * s
            d_dbl = (C[:, -1] - _U16_MEAN * kb * (kb + 1) / 2) * s
        else:
            d_sum = (C[:, -1] - _U16_MEAN * kb) * s
        Bm[0, 0] = 0.0
        np.cumsum(d_sum[:-1], out=Bm[1:, 0])
        Bm[:, 0] += self._k_level[ax]  # W_b
        self._k_level[ax] = Bm[-1, 0] + d_sum[-1]
        if quantized:
            G = Bm[:, 0] * float(kb) + d_dbl  # sum of W over the sub-block
            Bm[0, 1] = 0.0
            np.cumsum(G[:-1], out=Bm[1:, 1])
            Bm[:, 1] *= kappa
            Bm[:, 1] += self._k_theta[ax]  # Theta_b
            self._k_theta[ax] = Bm[-1, 1] + kappa * G[-1]
            Mb = np.stack([kappa * _J1, np.ones(kb), -_U16_MEAN * (kappa * s) * T.sum(axis=0)])
        else:
            Mb = np.stack([np.ones(kb), np.zeros(kb), -_U16_MEAN * s * T.sum(axis=0)])
        np.matmul(Bm, Mb, out=C2)
        C *= kappa * s
        C += C2
        row += C.reshape(-1)

    def next(self, n: int, signal_in: np.ndarray | None = None) -> np.ndarray:
        """Next n samples (n, 3); optional signal (n, 3) is added before quantization of the integral.

        The returned array is a transposed view of a (3, n) C-contiguous buffer.
        """
        n = int(n)
        y = np.empty((3, n))
        i = 0
        while i < n:
            if self._pos == self._chunk.shape[1]:
                self._next_chunk()
            m = min(n - i, self._chunk.shape[1] - self._pos)
            y[:, i:i + m] = self._chunk[:, self._pos:self._pos + m]
            i += m
            self._pos += m
        sig = None if signal_in is None else np.asarray(signal_in, dtype=np.float64)
        if self._gm is not None:
            g = self._gm.next(n)
            sig = g if sig is None else sig + g
        if n == 0:
            return y.T
        if len(self._work) < n:
            self._work = np.empty(n)
        work = self._work[:n]
        for ax in range(3):
            row = y[ax]
            if not self._quantized[ax]:
                if sig is not None:
                    row += sig[:, ax]
                continue
            q = self._q_step[ax]  # row holds the noise integral in steps q
            if _bi.HAVE_NUMBA:  # the same operations in one compiled pass
                st = np.array([self._sig_theta[ax], self._theta_q[ax]])
                _quantize(row, sig[:, ax] if sig is not None else work, sig is not None,
                          self.tau0 / q, q * self.rate_hz, st)
                self._sig_theta[ax], self._theta_q[ax] = st[0], st[1]
                continue
            if sig is not None:
                np.multiply(sig[:, ax], self.tau0 / q, out=work)
                work[0] += self._sig_theta[ax]
                np.cumsum(work, out=work)
                self._sig_theta[ax] = work[-1]
                row += work
            np.rint(row, out=row)
            work[0] = row[0] - self._theta_q[ax]
            np.subtract(row[1:], row[:-1], out=work[1:])
            self._theta_q[ax] = row[-1]
            np.multiply(work, q * self.rate_hz, out=row)
        return y.T
