"""Confidence of Allan-family deviations: noise identification, EDF, chi-square intervals.

* Noise type per tau, as Stable32 does it (Riley & Greenhall, "Power law noise identification
  using the lag 1 autocorrelation", EFTF 2004; NIST SP 1065 sec. 5.6): the phase decimated by
  m (every m-th point) is differenced d = 0, 1, ... times until delta = r1 / (1 + r1) < 0.25
  (r1 the lag-1 autocorrelation) or d = dmax (2 for the Allan family, 3 for Hadamard); then
  alpha = 2 - round(2 delta) - 2 d (the power-law exponent of S_y(f) ~ f^alpha:
  2 white PM, 1 flicker PM, 0 white FM, -1 flicker FM, -2 random-walk FM).
  With fewer than 30 decimated points the B1 ratio (standard variance of the m-averaged
  frequencies over the non-overlapped Allan variance, compared with its expected value
  B1(N, mu) = N (1 - N^mu) / (2 (N - 1) (1 - 2^mu)), Barnes/Howe) is used instead, and R(n)
  = MVAR / AVAR separates white from flicker PM (both mu = -2).
* Equivalent degrees of freedom: Greenhall's algorithm (C. A. Greenhall, W. J. Riley,
  "Uncertainty of stability variances based on finite differences", PTTI 2003), which covers
  overlapped / non-overlapped, modified / unmodified Allan (d = 2) and Hadamard (d = 3)
  variances; total variance: edf = b (T / tau) - c (NIST SP 1065 table 11).
* Intervals: sigma * sqrt(edf / chi2.ppf(1 - p, edf)) .. sigma * sqrt(edf / chi2.ppf(p, edf)),
  p = (1 - confidence) / 2 (NIST SP 1065 eq. 45).
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
from scipy.special import comb
from scipy.stats import chi2

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


def edf_greenhall(alpha: int, d: int, m: int, n_phase: int, overlapping: bool,
                  modified: bool) -> float:
    """Equivalent degrees of freedom of a finite-difference variance (Greenhall 2003).

    alpha: noise exponent (2..-4, alpha + 2d > 1); d: 2 Allan, 3 Hadamard; m: averaging
    factor; n_phase: number of phase points; overlapping: stride 1 (else m); modified: the
    m-point phase average (MVAR) instead of point samples.
    """
    alpha, d, m = int(alpha), int(d), int(m)
    if alpha + 2 * d <= 1:
        raise ValueError(f"EDF undefined for alpha={alpha}, d={d} (need alpha + 2d > 1)")
    f = 1 if modified else m
    s = m if overlapping else 1
    length = m / f + m * d
    big_m = 1 + math.floor(s * (n_phase - length) / m)
    if big_m < 1:
        raise ValueError("too few phase points for this averaging factor")
    j_ = min(big_m, (d + 1) * s)
    r = big_m / s
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


def edf(kind: str, alpha: int, m: int, n_phase: int) -> float:
    """EDF of deviation ``kind`` (adev, oadev, mdev, tdev, hdev, ohdev, totdev)."""
    if kind == "totdev":
        return edf_totdev(alpha, m, n_phase)
    d, ov, mod = _GREENHALL_KIND[kind]
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


# --------------------------------------------------------------------------- noise ID
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum a*b without BLAS (no thread pool: long vectors on a shared machine)."""
    return float(np.einsum("i,i->", a, b))


def lag1_autocorrelation(z: np.ndarray) -> float:
    """r1 = sum (z_t - zbar)(z_{t+1} - zbar) / sum (z_t - zbar)^2 (Riley 2004 eq. 2)."""
    z = np.asarray(z, dtype=np.float64) - np.mean(z)
    den = _dot(z, z)
    return _dot(z[:-1], z[1:]) / den if den > 0 else 0.0


def noise_id_lag1(x: np.ndarray, m: int, dmax: int = 2) -> int:
    """Lag-1 autocorrelation noise ID on phase ``x`` at factor ``m`` (alpha, integer)."""
    z = np.asarray(x[:: int(m)], dtype=np.float64)
    d = 0
    while True:
        r1 = lag1_autocorrelation(z)
        delta = r1 / (1.0 + r1)
        if delta < 0.25 or d >= dmax:
            return 2 - int(round(2.0 * delta)) - 2 * d
        z = np.diff(z)
        d += 1


def _b1_expected(n: int, mu: int) -> float:
    """Expected B1 ratio for n frequency averages and Allan tau-exponent mu (Howe 2000)."""
    if mu == -1:
        return 1.0
    if mu == 0:
        return n * math.log(n) / (2.0 * (n - 1.0) * math.log(2.0))
    return n * (1.0 - n ** mu) / (2.0 * (n - 1.0) * (1.0 - 2.0 ** mu))


def _rn_flicker_pm(m: int) -> float:
    """Expected MVAR/AVAR for flicker PM with f_h = 1/(2 tau0) (IEEE 1139 forms)."""
    avar = (1.038 + 3.0 * math.log(2.0 * math.pi * 0.5 * m)) / (4.0 * math.pi ** 2)
    mvar = 3.0 * math.log(256.0 / 27.0) / (8.0 * math.pi ** 2)
    return mvar / avar


def noise_id_b1(x: np.ndarray, m: int, dmax: int = 2) -> int:
    """B1 / R(n) noise ID on phase ``x`` at factor ``m`` (for few points)."""
    m = int(m)
    n = (x.size - 1) // m
    if n < 3:
        return 0
    xs = x[: n * m + 1: m]
    y = np.diff(xs) / m
    avar = float(np.sum(np.diff(y) ** 2)) / (2.0 * (n - 1))
    if avar <= 0:
        return 2
    b1 = float(np.var(y, ddof=1)) / avar
    mus = [-2, -1, 0, 1] + ([2] if dmax >= 3 else [])
    exp = [_b1_expected(n, mu) if mu != -2 else (n * n - 1.0) / (1.5 * n * (n - 1.0))
           for mu in mus]
    mu_sel = mus[0]
    for i in range(len(mus) - 1):
        if b1 > math.sqrt(exp[i] * exp[i + 1]):
            mu_sel = mus[i + 1]
    if mu_sel > -2:
        return -mu_sel - 1
    # white vs flicker PM: R(n) = MVAR / AVAR
    d2 = x[2 * m:] - 2.0 * x[m:-m] + x[: x.size - 2 * m]
    if d2.size < m:
        return 2
    c = np.concatenate(([0.0], np.cumsum(d2)))
    s = c[m:] - c[:-m]
    mvar = _dot(s, s) / (m * m * s.size)
    ovar = _dot(d2, d2) / d2.size
    rn = mvar / ovar if ovar > 0 else 1.0
    boundary = math.sqrt((1.0 / m) * _rn_flicker_pm(m))
    return 2 if rn < boundary else 1


def noise_id(x: np.ndarray, m: int, kind: str = "oadev") -> int:
    """Stable32's per-tau noise ID: lag-1 ACF with >= 30 decimated points (>= 30
    non-overlapped intervals for adev/hdev), else B1/R(n)."""
    dmax = 3 if kind in ("hdev", "ohdev") else 2
    n_dec = (np.asarray(x).size - 1) // int(m)  # non-overlapped intervals
    if kind not in ("adev", "hdev"):
        n_dec += 1  # decimated phase points
    if n_dec >= 30:
        return noise_id_lag1(x, m, dmax)
    return noise_id_b1(x, m, dmax)


def clamp_alpha(alpha: int, kind: str) -> int:
    """Keep alpha inside the range the EDF supports (alpha + 2d > 1; >= -2 for totdev)."""
    lo = -3 if kind in ("hdev", "ohdev") else -2
    return int(min(2, max(lo, alpha)))


def confidence(kind: str, x: np.ndarray, ms: np.ndarray, devs: np.ndarray,
               alphas: np.ndarray | None = None,
               id_fn: Callable[[np.ndarray, int, str], int] = noise_id) -> dict:
    """Noise ID, EDF and 68.3 % / 95 % intervals for a deviation curve from phase ``x``."""
    ms = np.asarray(ms, dtype=np.int64)
    if alphas is None:
        alphas = np.array([id_fn(x, int(m), kind) for m in ms], dtype=np.int64)
    alphas = np.array([clamp_alpha(a, kind) for a in alphas], dtype=np.int64)
    edfs = np.array([edf(kind, int(a), int(m), x.size) for a, m in zip(alphas, ms)])
    lo68, hi68 = chi2_interval(devs, edfs, ONE_SIGMA)
    lo95, hi95 = chi2_interval(devs, edfs, 0.95)
    return {"alpha": alphas, "edf": edfs, "lo68": lo68, "hi68": hi68,
            "lo95": lo95, "hi95": hi95}
