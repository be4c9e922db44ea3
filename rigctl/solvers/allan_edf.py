"""Confidence of Allan-family deviations: noise identification, EDF, chi-square intervals.

* Noise type per tau: :mod:`rigctl.solvers.allan_noise_id` (Stable32's rules: lag-1
  autocorrelation with >= 30 averages, B1 ratio / R(n) below, the previous tau's type once
  fewer than 2 x the stop ratio remain), re-exported here.
* Equivalent degrees of freedom: Greenhall's algorithm (C. A. Greenhall, W. J. Riley,
  "Uncertainty of stability variances based on finite differences", PTTI 2003), which covers
  overlapped / non-overlapped, modified / unmodified Allan (d = 2) and Hadamard (d = 3)
  variances; total variance: edf = b (T / tau) - c (NIST SP 1065 table 11).
* Strided estimators (fast mode: the overlapping Allan variance at factor m summed over every
  s-th term only, :func:`rigctl.solvers.allan.fast_stride`): Greenhall's algorithm already
  takes the term spacing as a parameter, S = tau / (spacing of the terms), S = m for the
  fully overlapping and S = 1 for the non-overlapped estimator. With stride s it is S = m/s
  and M = 1 + floor((N - L) / s) terms (L = m d + 1 phase points per term), and eq. 10-12 of
  the paper hold unchanged: edf = M sz(0)^2 / BasicSum(J, M, S, F), J = min(M, (d+1) S).
  Only the alpha = 2 closed form (eq. 13) assumes S = m; with a stride the basic sum is
  evaluated directly (J <= J_MAX whenever S <= 33, always so in fast mode, S = 8..16).
  This matters where the phase noise dominates (white / flicker PM: terms a few samples
  apart are nearly independent, so dropping 15 of 16 drops the EDF by about as much); for
  FM noise the strided EDF is within a few per cent of the fully overlapping one.
* Intervals: sigma * sqrt(edf / chi2.ppf(1 - p, edf)) .. sigma * sqrt(edf / chi2.ppf(p, edf)),
  p = (1 - confidence) / 2 (NIST SP 1065 eq. 45).
"""
from __future__ import annotations

import functools
import math

import numpy as np
from scipy.special import comb
from .distributions import chi2

from .allan_noise_id import (clamp_alpha, lag1_autocorrelation, noise_id, noise_id_b1,
                             noise_id_curve, noise_id_lag1)

__all__ = ["ONE_SIGMA", "chi2_interval", "clamp_alpha", "confidence", "edf", "edf_greenhall",
           "edf_totdev", "lag1_autocorrelation", "noise_id", "noise_id_b1", "noise_id_curve",
           "noise_id_lag1"]

ONE_SIGMA = 0.683  # Stable32's "Confidence Factor"
_J_MAX = 100

# Greenhall 2003, table 1 (modified variances, all alpha), rows alpha = 2..-4, cols d = 1..3
_TABLE1 = {2: [(2 / 3, 1 / 3), (7 / 9, 1 / 2), (22 / 25, 2 / 3)],
           1: [(0.840, 0.345), (0.997, 0.616), (1.141, 0.843)],
           0: [(1.079, 0.368), (1.033, 0.607), (1.184, 0.848)],
           -1: [None, (1.048, 0.534), (1.180, 0.816)],
           -2: [None, (1.302, 0.535), (1.175, 0.777)],
           -3: [None, None, (1.194, 0.703)],
           -4: [None, None, (1.489, 0.702)]}
# table 2 (unmodified variances, alpha <= 0 and alpha = 1 numerator)
_TABLE2 = {2: [(3 / 2, 1 / 2), (35 / 18, 1.0), (231 / 100, 3 / 2)],
           1: [(78.6, 25.2), (790.0, 410.0), (9950.0, 6520.0)],
           0: [(2 / 3, 1 / 6), (2 / 3, 1 / 3), (7 / 9, 1 / 2)],
           -1: [None, (0.852, 0.375), (0.997, 0.617)],
           -2: [None, (1.079, 0.368), (1.033, 0.607)],
           -3: [None, None, (1.053, 0.553)],
           -4: [None, None, (1.302, 0.535)]}
# table 3 (unmodified, alpha = 1): sz(0) ~ b0 + b1 ln m
_TABLE3 = [(6.0, 4.0), (15.23, 12.0), (47.8, 40.0)]
# NIST SP 1065 table 11, total variance: edf = b T/tau - c
_TOTDEV_BC = {0: (1.50, 0.0), -1: (1.17, 0.22), -2: (0.93, 0.36)}


# --------------------------------------------------------------------------- Greenhall EDF
def _sw(t: float, alpha: int) -> float:
    """Greenhall eq. 7: generalised autocovariance kernel of the power-law phase noise."""
    a = abs(t)
    if alpha % 2 == 0:  # 2, 0, -2, -4: -|t|, |t|^3, |t|^5, |t|^7
        return -a if alpha == 2 else a ** (3 - alpha)
    if a == 0.0:
        return 0.0
    return a ** (3 - alpha) * math.log(a)  # 1, -1, -3: t^2 ln|t|, t^4 ln|t|, t^6 ln|t|


def _sx(t: float, f: float, alpha: int) -> float:
    """Greenhall eq. 8: kernel after the F-point phase average (F = inf: no averaging)."""
    if math.isinf(f):
        return _sw(t, alpha + 2)
    return f * f * (2.0 * _sw(t, alpha) - _sw(t - 1.0 / f, alpha) - _sw(t + 1.0 / f, alpha))


def _sz(t: float, f: float, alpha: int, d: int) -> float:
    """Greenhall eq. 9: kernel of the d-th difference (binomial weights)."""
    total = 0.0
    for j in range(-d, d + 1):
        total += (-1) ** abs(j) * comb(2 * d, d + j, exact=True) * _sx(t + j, f, alpha)
    return total


def _basic_sum(j_: int, m_: float, s: float, f: float, alpha: int, d: int) -> float:
    """Greenhall eq. 10."""
    total = _sz(0.0, f, alpha, d) ** 2
    total += (1.0 - j_ / m_) * _sz(j_ / s, f, alpha, d) ** 2
    for j in range(1, int(j_)):
        total += 2.0 * (1.0 - j / m_) * _sz(j / s, f, alpha, d) ** 2
    return total


def _sz_many(t: np.ndarray, f: float, alpha: int, d: int) -> np.ndarray:
    """:func:`_sz` at many t at once (numpy; the same formulas, eq. 7-9)."""

    def sw(u: np.ndarray, al: int) -> np.ndarray:
        a = np.abs(u)
        if al % 2 == 0:
            return -a if al == 2 else a ** (3 - al)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(a == 0.0, 0.0, a ** (3 - al) * np.log(np.where(a == 0.0, 1.0, a)))

    def sx(u: np.ndarray) -> np.ndarray:
        if math.isinf(f):
            return sw(u, alpha + 2)
        if alpha == 1 and f >= 1e4:
            # flicker PM sampled at tau0 = tau / f: the second difference of t^2 ln|t| at step
            # 1/f cancels ~2 log10(f) digits; its limits instead: 2 ln f at t = 0 (exact) and
            # -(2 ln|t| + 3) elsewhere (error (6 f^2 t^2)^-1 <= 5e-7 for |t| >= 1/S >= 1/33)
            a = np.abs(u)
            with np.errstate(divide="ignore"):
                return np.where(a == 0.0, 2.0 * math.log(f),
                                -(2.0 * np.log(np.where(a == 0.0, 1.0, a)) + 3.0))
        return f * f * (2.0 * sw(u, alpha) - sw(u - 1.0 / f, alpha) - sw(u + 1.0 / f, alpha))

    js = np.arange(-d, d + 1)
    wts = np.array([(-1) ** abs(j) * comb(2 * d, d + j, exact=True) for j in js], dtype=float)
    return wts @ sx(np.asarray(t, dtype=float)[None, :] + js[:, None])


def _edf_strided(j_: int, big_m: int, s: float, f: float, alpha: int, d: int) -> float:
    """M sz(0)^2 / BasicSum(J, M, S, F) (Greenhall eq. 10-11), the basic sum in one numpy
    evaluation of sz at the lags j / S, j = 0..J."""
    z = _sz_many(np.arange(j_ + 1, dtype=float) / s, f, alpha, d) ** 2
    w = 2.0 * (1.0 - np.arange(1, j_) / big_m)
    basic = z[0] + (1.0 - j_ / big_m) * z[j_] + float(np.dot(w, z[1:j_]))
    return big_m * float(z[0]) / basic


@functools.lru_cache(maxsize=1 << 14)  # a pure function; the axes of a capture share m and N
def edf_greenhall(alpha: int, d: int, m: int, n_phase: int, overlapping: bool,
                  modified: bool, stride: int | None = None) -> float:
    """Equivalent degrees of freedom of a finite-difference variance (Greenhall 2003).

    alpha: noise exponent (2..-4, alpha + 2d > 1); d: 2 Allan, 3 Hadamard; m: averaging
    factor; n_phase: number of phase points; overlapping: stride 1 (else m); modified: the
    m-point phase average (MVAR) instead of point samples. ``stride`` (unmodified only):
    the spacing of the terms actually summed, in samples, overriding ``overlapping``
    (1 = overlapping, m = non-overlapped); Greenhall's S = m / stride (eq. 10-12; see the
    module docstring). Dimensionless.
    """
    alpha, d, m = int(alpha), int(d), int(m)
    if alpha + 2 * d <= 1:
        raise ValueError(f"EDF undefined for alpha={alpha}, d={d} (need alpha + 2d > 1)")
    f = 1 if modified else m
    step = 1 if overlapping else m  # term spacing in samples
    if stride is not None:
        if modified:
            raise ValueError("a stride is only defined here for the unmodified variances")
        step = int(stride)
        if not 1 <= step <= m:
            raise ValueError(f"stride must be 1..m, got {stride} for m = {m}")
    s = m / step if step != 1 else m  # Greenhall's S (terms per tau)
    length = m // f + m * d  # phase points spanned by one term, minus one
    big_m = 1 + math.floor((n_phase - length) / step)
    if big_m < 1:
        raise ValueError("too few phase points for this averaging factor")
    j_ = min(big_m, math.floor((d + 1) * s))
    r = big_m / s
    if step not in (1, m) and j_ <= _J_MAX:  # strided: the basic sum, directly (eq. 10-11)
        fp = m if (alpha > 0 or m * (d + 1) <= _J_MAX) else math.inf
        return _edf_strided(j_, big_m, s, fp, alpha, d)
    if modified:
        if j_ <= _J_MAX:
            return big_m * _sz(0, 1, alpha, d) ** 2 / _basic_sum(j_, big_m, s, 1, alpha, d)
        if r > d + 1:
            a0, a1 = _TABLE1[alpha][d - 1]
            return r / (a0 - a1 / r)
        mp = _J_MAX / r
        return _J_MAX * _sz(0, 1, alpha, d) ** 2 / _basic_sum(_J_MAX, _J_MAX, mp, 1, alpha, d)
    if alpha <= 0:
        if j_ <= _J_MAX:
            fp = m if m * (d + 1) <= _J_MAX else math.inf
            return big_m * _sz(0, fp, alpha, d) ** 2 / _basic_sum(j_, big_m, s, fp, alpha, d)
        if r > d + 1:
            a0, a1 = _TABLE2[alpha][d - 1]
            return r / (a0 - a1 / r)
        mp = _J_MAX / r
        return (_J_MAX * _sz(0, math.inf, alpha, d) ** 2
                / _basic_sum(_J_MAX, _J_MAX, mp, math.inf, alpha, d))
    if alpha == 1:
        if j_ <= _J_MAX:
            return big_m * _sz(0, m, 1, d) ** 2 / _basic_sum(j_, big_m, s, m, 1, d)
        b0, b1 = _TABLE3[d - 1]
        if r > d + 1:
            a0, a1 = _TABLE2[1][d - 1]
            return (b0 + b1 * math.log(m)) ** 2 * r / (a0 - a1 / r)
        mp = _J_MAX / r
        return ((b0 + b1 * math.log(m)) ** 2 * _J_MAX
                / _basic_sum(_J_MAX, _J_MAX, mp, mp, 1, d))
    # alpha == 2, unmodified
    k = math.ceil(r)
    if k > d:
        a0 = comb(4 * d, 2 * d, exact=True) / comb(2 * d, d, exact=True) ** 2
        return big_m / (a0 - (d / 2.0) / r)
    return big_m * _sz(0, m, alpha, d) ** 2 / _basic_sum(j_, big_m, s, m, alpha, d)


def edf_totdev(alpha: int, m: int, n_phase: int) -> float:
    """EDF of the total variance: b T/tau - c (SP 1065 table 11), T/tau = (N - 1) / m, for
    white, flicker and random-walk FM; white and flicker PM use the simple Allan-variance
    forms of SP 1065 table 5, as Stable32 does."""
    if alpha in _TOTDEV_BC:
        b, c = _TOTDEV_BC[alpha]
        return b * (n_phase - 1) / m - c
    n = float(n_phase)
    if alpha == 2:  # SP 1065 table 5 (Allan variance, white PM)
        return (n + 1.0) * (n - 2.0 * m) / (2.0 * (n - m))
    # flicker PM (SP 1065 table 5)
    return math.exp(math.sqrt(math.log((n - 1.0) / (2.0 * m))
                              * math.log((2.0 * m + 1.0) * (n - 1.0) / 4.0)))


#: (d, overlapping, modified) of each deviation for Greenhall's EDF
_GREENHALL_KIND = {"adev": (2, False, False), "oadev": (2, True, False),
                   "mdev": (2, True, True), "tdev": (2, True, True),
                   "hdev": (3, False, False), "ohdev": (3, True, False)}


def edf(kind: str, alpha: int, m: int, n_phase: int, stride: int = 1) -> float:
    """EDF of deviation ``kind`` (adev, oadev, mdev, tdev, hdev, ohdev, totdev); ``stride``
    (oadev, ohdev): the spacing of the terms actually summed (fast mode's strided sums)."""
    if kind == "totdev":
        return edf_totdev(alpha, m, n_phase)
    d, ov, mod = _GREENHALL_KIND[kind]
    if int(stride) != 1 and ov and not mod:
        return edf_greenhall(alpha, d, m, n_phase, ov, mod, int(stride))
    return edf_greenhall(alpha, d, m, n_phase, ov, mod)


def chi2_interval(dev: np.ndarray | float, edf_: np.ndarray | float,
                  confidence: float = ONE_SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided chi-square interval of a deviation (NIST SP 1065 eq. 45)."""
    p = (1.0 - confidence) / 2.0
    dev = np.asarray(dev, dtype=float)
    e = np.asarray(edf_, dtype=float)
    lo = dev * np.sqrt(e / chi2.ppf(1.0 - p, e))
    hi = dev * np.sqrt(e / chi2.ppf(p, e))
    return lo, hi


def confidence(kind: str, x: np.ndarray, ms: np.ndarray, devs: np.ndarray,
               alphas: np.ndarray | None = None, strides: np.ndarray | None = None) -> dict:
    """Noise ID (Stable32's, :func:`noise_id_curve`, unless ``alphas`` are given), EDF and
    68.3 % / 95 % intervals for a deviation curve from phase ``x``. ``alpha`` is the
    identified (or given) exponent, ``alpha_edf`` the one the EDF used (clamped).
    ``strides``: the term spacing of each deviation (``DevResult.stride``; fast mode)."""
    ms = np.asarray(ms, dtype=np.int64)
    st = np.ones_like(ms) if strides is None else np.asarray(strides, dtype=np.int64)
    if alphas is None:
        alphas = noise_id_curve(x, ms, kind)
    alphas = np.asarray(alphas, dtype=np.int64)
    used = np.array([clamp_alpha(a, kind) for a in alphas], dtype=np.int64)
    edfs = np.array([edf(kind, int(a), int(m), x.size, int(k)) for a, m, k in zip(used, ms, st)])
    lo68, hi68 = chi2_interval(devs, edfs, ONE_SIGMA)
    lo95, hi95 = chi2_interval(devs, edfs, 0.95)
    return {"alpha": alphas, "alpha_edf": used, "edf": edfs, "lo68": lo68, "hi68": hi68,
            "lo95": lo95, "hi95": hi95}
