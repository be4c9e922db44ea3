"""Covariance of segment means under time-correlated noise, and the whitening every fit uses.

A calibration compares the means of K windows [a_i, b_i] (s, run time; T_i = b_i - a_i) taken
over 30-60 minutes. White noise makes their errors independent; bias instability (flicker) and
rate random walk do not: the bias wanders over the run, so the errors of different segments'
means are correlated and scatter more than each window's own noise says. For a noise process
e(t) with autocovariance r(s, t), the covariance of two window means is

    C_ij = 1/(T_i T_j) int_{a_i}^{b_i} int_{a_j}^{b_j} r(s, t) ds dt.

For a stationary r(s - t) with an even twice-integrable kernel k and F'' = k, F(0) = F'(0) = 0:

    int int k(s - t) ds dt = F(b_i - a_j) - F(a_i - a_j) - F(b_i - b_j) + F(a_i - b_j)     (*)

Per IEEE Std 952 term (coefficients as in :class:`~rigctl.solvers.noise_coefficients.NoiseCoefficients`):

* white (N):  C_ij = N^2 / T_i  if i == j else 0 (sigma_A^2 = N^2/tau: two-sided PSD N^2).
* quantization (Q) of the integrated output: a window mean is (theta_q(b) - theta_q(a))/T with
  independent rounding errors of variance Q^2 at both ends: C_ii = 2 Q^2 / T_i^2 (diagonal).
* rate random walk (K): Brownian motion from t0 (power-on), r(s, t) = K^2 min(s - t0, t - t0).
  With min(s, t) = (s + t - |s - t|)/2 and (*) for |x| (F = |x|^3/6):

      C_ij = K^2 [ (m_i + m_j)/2 - t0 - D_ij / (2 T_i T_j) ],   m = window mid time,
      D_ij = H(b_i - a_j) - H(a_i - a_j) - H(b_i - b_j) + H(a_i - b_j),   H(x) = |x|^3/6

  (so C_ii = K^2 (a_i - t0 + T_i/3)).
* bias instability (B): a 1/f PSD cannot be written with one exponential. It is represented by
  a bank of first-order Gauss-Markov (Ornstein-Uhlenbeck) processes with time constants tau_k
  log-spaced over the 1/f band, each with variance c_k; one-sided PSD of OU k:
  4 c_k tau_k / (1 + (2 pi f tau_k)^2). With ratio rho between neighbours, equal c_k =
  B^2 ln(rho)/pi sum to (B^2/pi)/f, the IEEE flicker PSD (sigma_A^2 = (2 ln 2/pi) B^2); the
  common scale is then set so that the bank's Allan variance averaged over [tau_min, tau_max]
  equals (2 ln 2/pi) B^2 exactly (:func:`flicker_bank`). The 1/f band runs from
  f_lo = 1/(2 pi tau_max)/10 to f_hi = 10/tau_min (a decade beyond the plateau on both sides,
  the emulator's convention). For one OU (k(u) = c e^{-|u|/tau}) (*) gives

      C_ij = c [1 + tau^2/(T_i T_j) Delta2 R],  R(x) = e^{-u} - 1 + u - u^2/2,  u = |x|/tau

  where Delta2 R is the four-term combination of (*) and the "1" is the x^2/2 part of F,
  integrated exactly (so that slow components lose no precision to cancellation).
* rate ramp (R): deterministic, not noise: left to the closed loop's time-drift effect.

**A constant added to every segment** (the slow flicker components, the random-walk value at
the reference time) changes C by c 1 1^T. Every calibration model has a bias per channel, i.e.
the column 1 is in the design, and for Sigma' = Sigma + X G X^T generalised least squares gives
the same estimate, the same residuals and the same chi2 (the residuals are Sigma^-1-orthogonal
to X), while Cov(beta) grows by G: only the bias parameters' intervals see the constant. This is
why the random walk's reference time t0 is arbitrary for everything except the biases (moving
t0 adds K^2 (t0 - t0') 1 1^T); t0 = power-on (run start) makes the bias the power-on bias, the
emulator's /truth.

:class:`Whitener` factors a covariance once (Cholesky, Sigma = L L^T, ``scipy.linalg.
cho_factor``) and whitens designs and observations (L^-1 A, ``solve_triangular``); with a
diagonal covariance it divides by the standard uncertainties (the weighted least squares of
before, bit for bit).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

_PLATEAU = 2.0 * np.log(2.0) / np.pi


# ------------------------------------------------------------------------------ kernels
def _window_pair(a: ArrayLike, b: ArrayLike, a2: ArrayLike | None, b2: ArrayLike | None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Window starts/ends as float64 arrays (the second set defaults to the first); each window
    must have t_end > t_start."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a2 = a if a2 is None else np.asarray(a2, dtype=np.float64)
    b2 = b if b2 is None else np.asarray(b2, dtype=np.float64)
    if np.any(b - a <= 0) or np.any(b2 - a2 <= 0):
        raise ValueError("every window needs t_end > t_start")
    return a, b, a2, b2


def _second_diff(fun, a: NDArray[np.float64], b: NDArray[np.float64],
                 a2: NDArray[np.float64], b2: NDArray[np.float64]) -> NDArray[np.float64]:
    """F(b_i - a_j) - F(a_i - a_j) - F(b_i - b_j) + F(a_i - b_j) for all (i, j).

    a, b: (..., K); a2, b2: (..., K2); result (..., K, K2) (plus any trailing axes ``fun`` adds).
    ``fun`` is even, elementwise a function of |x| (every caller's is): for one set of windows
    (a2 is a, b2 is b) a_i - b_j = -(b_j - a_i) exactly, so F(a_i - b_j) is F(b_j - a_i), the
    first term transposed, taken from it instead of evaluated again (the same values).
    """
    def d(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        return x[..., :, None] - y[..., None, :]

    first = fun(d(b, a2))
    if a2 is a and b2 is b:
        last = np.swapaxes(first, a.ndim - 1, a.ndim)
    else:
        last = fun(d(a, b2))
    return first - fun(d(a, a2)) - fun(d(b, b2)) + last


def _windows(a: ArrayLike, b: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    a = np.atleast_1d(np.asarray(a, dtype=np.float64))
    b = np.atleast_1d(np.asarray(b, dtype=np.float64))
    T = b - a
    if np.any(T <= 0):
        raise ValueError("every window needs t_end > t_start")
    return a, b, T


def cov_white(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """(K, K) covariance of window means of unit white noise (N = 1): diag(1/T)."""
    _, _, T = _windows(a, b)
    return np.diag(1.0 / T)


def cov_quantization(a: ArrayLike, b: ArrayLike) -> NDArray[np.float64]:
    """(K, K) for Q = 1 (quantized integrated output): diag(2/T^2)."""
    _, _, T = _windows(a, b)
    return np.diag(2.0 / T**2)


def cov_random_walk(a: ArrayLike, b: ArrayLike, t0: float = 0.0,
                    a2: ArrayLike | None = None, b2: ArrayLike | None = None) -> NDArray[np.float64]:
    """Covariance of window means of a unit rate random walk (K = 1) started at t0.

    Windows [a, b] (..., K) against [a2, b2] (..., K2) (default: the same); see the module
    docstring. Returns (..., K, K2).
    """
    a, b, a2, b2 = _window_pair(a, b, a2, b2)
    D = _second_diff(lambda x: np.abs(x) ** 3 / 6.0, a, b, a2, b2)
    m, m2 = (a + b) / 2.0, (a2 + b2) / 2.0
    TT = (b - a)[..., :, None] * (b2 - a2)[..., None, :]
    return (m[..., :, None] + m2[..., None, :]) / 2.0 - t0 - D / (2.0 * TT)


def _ou_r(x: NDArray[np.float64], tau: float | NDArray[np.float64]) -> NDArray[np.float64]:
    """tau^2 R(|x|/tau), R(u) = e^-u - 1 + u - u^2/2 (series below u = 0.05)."""
    u = np.abs(x) / tau
    out = np.expm1(-u)  # the direct form everywhere, in place (one pass per operation) ...
    out += u
    out -= u * u / 2.0
    small = u < 0.05
    if small.any():  # ... and the series where it cancels
        us = u[small]
        out[small] = -us**3 / 6.0 + us**4 / 24.0 - us**5 / 120.0 + us**6 / 720.0 - us**7 / 5040.0
    out *= tau**2
    return out


def cov_ou(a: ArrayLike, b: ArrayLike, tau: float, a2: ArrayLike | None = None,
           b2: ArrayLike | None = None) -> NDArray[np.float64]:
    """(K, K2) covariance of window means of a unit-variance OU process, time constant tau (s)."""
    a, b, T = _windows(a, b)
    a2, b2, T2 = (a, b, T) if a2 is None else _windows(a2, b2)
    d2 = _second_diff(lambda x: _ou_r(x, tau), a, b, a2, b2)
    return 1.0 + d2 / (T[:, None] * T2[None, :])


def ou_avar(tau_s: ArrayLike, tc_s: float) -> NDArray[np.float64]:
    """Allan variance of a unit-variance OU process (time constant tc) at cluster times tau:

        sigma_A^2 = (2 tc/tau) [1 - tc/(2 tau) (3 - 4 e^{-tau/tc} + e^{-2 tau/tc})]
    """
    r = np.asarray(tau_s, dtype=np.float64) / tc_s
    return 2.0 / r * (1.0 - (3.0 - 4.0 * np.exp(-r) + np.exp(-2.0 * r)) / (2.0 * r))


@dataclass(frozen=True)
class FlickerBank:
    """OU bank standing for 1/f noise: time constants tau_c (s) and variances per unit B^2."""

    tau_c: NDArray[np.float64]
    var_per_b2: NDArray[np.float64]
    tau_min_s: float
    tau_max_s: float

    @property
    def stationary_var_per_b2(self) -> float:
        """Total variance of the bank per unit B^2 (~ ln(f_hi/f_lo)/pi)."""
        return float(self.var_per_b2.sum())

    def avar(self, tau_s: ArrayLike) -> NDArray[np.float64]:
        """Allan variance of the bank per unit B^2 at tau (s)."""
        t = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
        return sum(c * ou_avar(t, tc) for c, tc in zip(self.var_per_b2, self.tau_c))


_BANKS: dict[tuple[float, float, int], FlickerBank] = {}


def flicker_bank(tau_min_s: float = 1.0, tau_max_s: float = 1.0e4, per_decade: int = 3) -> FlickerBank:
    """OU bank for bias instability with the Allan plateau (2 ln2/pi) B^2 over [tau_min, tau_max].

    Time constants tau_k = 1/(2 pi f_k), f_k log-spaced over [f_lo, f_hi] = [1/(2 pi tau_max)/10,
    10/tau_min] with ``per_decade`` per decade; equal variances B^2 ln(rho)/pi (the 1/f sum),
    rescaled so that the mean Allan variance over 9 log-spaced taus in [tau_min, tau_max] is
    exactly the plateau (the bank's plateau is flat to about 1 %).
    """
    key = (float(tau_min_s), float(tau_max_s), int(per_decade))
    if key in _BANKS:
        return _BANKS[key]
    if not tau_max_s > tau_min_s > 0:
        raise ValueError("flicker band needs 0 < tau_min < tau_max")
    f_lo, f_hi = 1.0 / (2.0 * np.pi * tau_max_s) / 10.0, 10.0 / tau_min_s
    n = max(2, int(np.ceil(np.log10(f_hi / f_lo) * per_decade)) + 1)
    f = np.geomspace(f_lo, f_hi, n)
    rho = f[1] / f[0]
    tau_c = 1.0 / (2.0 * np.pi * f)
    var = np.full(n, np.log(rho) / np.pi)
    probe = np.geomspace(tau_min_s, tau_max_s, 9)
    bank = FlickerBank(tau_c, var, float(tau_min_s), float(tau_max_s))
    scale = _PLATEAU / float(np.mean(bank.avar(probe)))
    bank = FlickerBank(tau_c, var * scale, float(tau_min_s), float(tau_max_s))
    _BANKS[key] = bank
    return bank


def cov_flicker(a: ArrayLike, b: ArrayLike, bank: FlickerBank | None = None,
                a2: ArrayLike | None = None, b2: ArrayLike | None = None) -> NDArray[np.float64]:
    """Covariance of window means of bias instability with B = 1 (sum over the OU bank).

    a, b: (..., K) window starts/ends (leading axes broadcast: blocks of windows at once);
    a2, b2 likewise (default: the same windows). Returns (..., K, K2).
    """
    bank = flicker_bank() if bank is None else bank
    a, b, a2, b2 = _window_pair(a, b, a2, b2)
    tau = bank.tau_c
    d2 = _second_diff(lambda x: _ou_r(x[..., None], tau), a, b, a2, b2)  # (..., K, K2, m)
    TT = (b - a)[..., :, None] * (b2 - a2)[..., None, :]
    return float(bank.var_per_b2.sum()) + (d2 @ bank.var_per_b2) / TT


def batch_windows(a: ArrayLike, b: ArrayLike, n_batches: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Start and end times (..., n_batches) of equal batches of the windows [a, b] (...)."""
    a = np.asarray(a, dtype=np.float64)[..., None]
    b = np.asarray(b, dtype=np.float64)[..., None]
    edges = a + (b - a) * np.arange(n_batches + 1) / n_batches
    return edges[..., :-1], edges[..., 1:]


def expected_batch_var(cov_batches: NDArray[np.float64]) -> NDArray[np.float64]:
    """E[var(batch means, ddof=1)/B] for batch means with covariance cov_batches (B, B):

        E = (tr C - 1^T C 1 / B) / (B (B - 1))

    (for white noise C = diag(B/T) and E = 1/T, the variance of the window mean).
    """
    n = cov_batches.shape[-1]
    tr = np.trace(cov_batches, axis1=-2, axis2=-1)
    return (tr - cov_batches.sum(axis=(-2, -1)) / n) / (n * (n - 1))


# ------------------------------------------------------------------------------ whitening
class Whitener:
    """Sigma = L L^T factored once; ``apply(A)`` returns L^-1 A (the whitened rows).

    ``Whitener(sigma=s)``: diagonal, L = diag(s) (weighted least squares).
    ``Whitener(cov=C)``: full covariance by Cholesky (scipy.linalg.cho_factor, lower).
    """

    def __init__(self, cov: ArrayLike | None = None, sigma: ArrayLike | None = None) -> None:
        if (cov is None) == (sigma is None):
            raise ValueError("give either cov or sigma")
        if sigma is not None:
            self.s = np.asarray(sigma, dtype=np.float64)
            self.L: NDArray[np.float64] | None = None
            self.n = self.s.size
        else:
            C = np.asarray(cov, dtype=np.float64)
            if C.ndim != 2 or C.shape[0] != C.shape[1]:
                raise ValueError("cov must be square")
            d = np.sqrt(np.diag(C))
            if np.count_nonzero(C - np.diag(np.diag(C))) == 0:
                self.s, self.L, self.n = d, None, d.size
            else:
                c, _ = scipy.linalg.cho_factor(C, lower=True, check_finite=True)
                self.L = np.tril(c)
                self.s = d
                self.n = d.size

    @property
    def diagonal(self) -> bool:
        """True when the covariance is diagonal."""
        return self.L is None

    def apply(self, A: ArrayLike) -> NDArray[np.float64]:
        """L^-1 A for A (n,) or (n, m)."""
        A = np.asarray(A, dtype=np.float64)
        if self.L is None:
            return A / (self.s if A.ndim == 1 else self.s[:, None])
        return scipy.linalg.solve_triangular(self.L, A, lower=True, check_finite=False)

    def inverse_factor(self) -> NDArray[np.float64]:
        """L^-1 as a dense (n, n) matrix."""
        return self.apply(np.eye(self.n))

    def cov(self) -> NDArray[np.float64]:
        """The covariance L L^T."""
        return np.diag(self.s**2) if self.L is None else self.L @ self.L.T

    def subset(self, idx: ArrayLike) -> "Whitener":
        """Whitener of the rows/columns idx."""
        idx = np.asarray(idx)
        if self.L is None:
            return Whitener(sigma=self.s[idx])
        return Whitener(cov=self.cov()[np.ix_(idx, idx)])
