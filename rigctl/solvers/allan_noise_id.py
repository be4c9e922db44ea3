"""Power-law noise identification per tau, as Stable32 does it.

The exponent alpha of S_y(f) ~ f^alpha (2 white PM, 1 flicker PM, 0 white FM, -1 flicker FM,
-2 random-walk FM, -3 flicker-walk FM, -4 random-run FM) is identified at each averaging
factor m of a run, from the phase x (N points, tau = m tau0), by one of three rules, chosen
by the number of averages n = floor((N - 1) / m) available at that tau:

1. **n >= 30: lag-1 autocorrelation** (W. J. Riley, C. A. Greenhall, "Power law noise
   identification using the lag 1 autocorrelation", EFTF 2004; NIST SP 1065 sec. 5.5.6).
   z = x[::m] (the phase decimated by m, *not* averaged), differenced d = 0, 1, ... times
   until delta = r1 / (1 + r1) < 0.25 or d = dmax (2 for the Allan family and the total
   deviation, 3 for Hadamard); alpha = 2 - round(2 delta) - 2 d, with
   r1 = sum (z_t - zbar)(z_{t+1} - zbar) / sum (z_t - zbar)^2 (no detrending, no scaling).
2. **2 s <= n < 30: B1 ratio** (Barnes 1969; Howe, Beard, Greenhall, Riley, PTTI 2000;
   SP 1065 sec. 5.5.4-5.5.5). The m-averaged frequencies y_k = (x[(k+1)m] - x[km]) / (m tau0),
   k < n, give B1 = s^2(y) / AVAR(y) (sample variance with n - 1, over the *non-overlapped*
   Allan variance of the same averages). It is compared with its expected value for an
   Allan-variance tau exponent mu, B1(N, mu) = N (1 - N^mu) / (2 (N - 1) (1 - 2^mu))
   (mu = 0: N ln N / (2 (N - 1) ln 2)), where Stable32 takes **N = the number of terms of
   the estimator being run** (the "#" column of its tables: n - 1 for adev, N - 2m for oadev,
   N - 2 for totdev, ...), not the number of averages. The decision boundaries are the
   geometric means of the expected values of adjacent mu in 1, 0, -1, -2; mu = 1, 0, -1
   give alpha = -mu - 1.
   * mu = -2 (white or flicker PM, indistinguishable by B1): **R(n) = MVAR / AVAR** at m
     (both fully overlapping) against its expected values 1/m (white PM) and
     3 ln(256/27) / (2 (1.038 + 3 ln(pi m))) (flicker PM with f_h = 1/(2 tau0), IEEE 1139),
     boundary at their geometric mean: alpha = 2 below, 1 above.
   * Hadamard (hdev, ohdev) with mu = 1: **B1 of the frequency averages taken as phase**
     (the y_k differenced once more) with the same N and boundaries; mu* = 1 -> alpha = -4,
     mu* = 0 -> -3, otherwise -2 (Howe et al. 2000: "add 2 to the resulting mu").
3. **n < 2 s: the previous tau's alpha is kept** (s = Stable32's stop ratio of the estimator:
   5 adev/hdev, 4 oadev/mdev/tdev/ohdev, 2 totdev). Stable32 stops identifying there (the
   first tau of a run is always identified).

Rules 2 and 3 are not in the papers; they were established against every Stable32 reference
table shipped with allantools (PHASE.DAT, Cs 5071A, Keysight 53230A; tests in
tests/test_allan_stable32.py), where they reproduce every automatically identified row but
11 (reported there). The identified alpha selects the EDF (:mod:`rigctl.solvers.allan_edf`)
after clamping to the range the estimator's EDF supports (:func:`clamp_alpha`).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from . import allan_kernels as K
from .allan import STOP_RATIO

LAG1_MIN_POINTS = 30  # averages needed for the lag-1 method (Riley & Greenhall 2004)
#: from this many decimated points on the compiled kernel identifies (the reference tables'
#: series are shorter: they keep the numpy path, sum for sum)
LAG1_COMPILED_POINTS = 1 << 16
_HADAMARD = ("hdev", "ohdev")
_BLOCK = 1 << 20


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum a*b without BLAS (no thread pool: long vectors on a shared machine)."""
    return float(np.einsum("i,i->", a, b))


def n_terms(kind: str, n_phase: int, m: int) -> int:
    """Number of terms of estimator ``kind`` at factor m with ``n_phase`` phase points (the
    "#" column of Stable32's tables)."""
    n, m = int(n_phase), int(m)
    counts = {"adev": (n - 1) // m - 1, "hdev": (n - 1) // m - 2, "oadev": n - 2 * m,
              "mdev": n - 3 * m + 1, "tdev": n - 3 * m + 1, "ohdev": n - 3 * m,
              "totdev": n - 2}
    return counts[kind]


def dmax_of(kind: str) -> int:
    """Maximum differencing order of the lag-1 method: 3 for Hadamard, else 2."""
    return 3 if kind in _HADAMARD else 2


# --------------------------------------------------------------------------- lag-1 ACF
def lag1_autocorrelation(z: np.ndarray) -> float:
    """r1 = sum (z_t - zbar)(z_{t+1} - zbar) / sum (z_t - zbar)^2 (Riley 2004 eq. 2)."""
    z = np.asarray(z, dtype=np.float64) - np.mean(z)
    den = _dot(z, z)
    return _dot(z[:-1], z[1:]) / den if den > 0 else 0.0


def noise_id_lag1(x: np.ndarray, m: int, dmax: int = 2) -> int:
    """Lag-1 autocorrelation noise ID on phase ``x`` decimated by ``m`` (alpha, integer)."""
    if K.HAVE_NUMBA and len(x) // int(m) >= LAG1_COMPILED_POINTS:  # the same, in one kernel
        return K.lag1_alpha(x, int(m), int(dmax))
    z = np.asarray(x[:: int(m)], dtype=np.float64)
    d = 0
    while True:
        r1 = lag1_autocorrelation(z)
        delta = r1 / (1.0 + r1)
        if delta < 0.25 or d >= dmax or z.size < 3:
            return 2 - int(round(2.0 * delta)) - 2 * d
        z = np.diff(z)
        d += 1


# --------------------------------------------------------------------------- B1 and R(n)
def b1_expected(n: float, mu: int) -> float:
    """Expected B1 for N = ``n`` and Allan tau exponent ``mu`` (Howe et al. 2000, table 3)."""
    n = float(n)
    if mu == -1:
        return 1.0
    if mu == 0:
        return n * math.log(n) / (2.0 * (n - 1.0) * math.log(2.0))
    return n * (1.0 - n ** mu) / (2.0 * (n - 1.0) * (1.0 - 2.0 ** mu))


def b1_mu(b1: float, n: float) -> int:
    """Allan tau exponent mu in (1, 0, -1, -2) whose expected B1 is nearest on a log scale
    (boundaries at geometric means of adjacent expected values)."""
    mus = (1, 0, -1, -2)
    exp = [b1_expected(n, mu) for mu in mus]
    for i in range(len(mus) - 1):
        if b1 > math.sqrt(exp[i] * exp[i + 1]):
            return mus[i]
    return mus[-1]


def _ratio_b1(y: np.ndarray) -> float:
    """Sample variance of y over its non-overlapped Allan variance (NaN if undefined)."""
    if y.size < 3:
        return math.nan
    dy = np.diff(y)
    avar = _dot(dy, dy) / (2.0 * (y.size - 1))
    return float(np.var(y, ddof=1)) / avar if avar > 0 else math.nan


def frequency_averages(x: np.ndarray, m: int) -> np.ndarray:
    """The n = floor((N - 1) / m) m-averaged frequencies of phase ``x`` (per tau0)."""
    n = (x.size - 1) // int(m)
    xs = np.asarray(x[: n * m + 1: m], dtype=np.float64)
    return np.diff(xs) / m


def b1_ratio(x: np.ndarray, m: int) -> float:
    """B1 = s^2 / AVAR of the m-averaged frequencies of phase ``x`` (both at tau = m tau0)."""
    return _ratio_b1(frequency_averages(x, m))


def rn_ratio(x: np.ndarray, m: int) -> float:
    """R(n) = MVAR(m) / AVAR(m), both fully overlapping, from phase ``x``; blockwise (memory
    O(block + m)). MVAR terms S_j = sum_{i=j}^{j+m-1} D[i], D[i] = x[i+2m] - 2x[i+m] + x[i]."""
    m = int(m)
    n = x.size
    n_a, n_m = n - 2 * m, n - 3 * m + 1
    if n_m < 1:
        return math.nan
    s_a = s_m = 0.0
    for a in range(0, n_a, _BLOCK):
        b = min(a + _BLOCK, n_a)
        e = min(b + m - 1, n_a)  # D[a:e] also feeds the MVAR terms j in [a, b)
        d = x[a + 2 * m: e + 2 * m] - 2.0 * x[a + m: e + m] + x[a: e]
        s_a += _dot(d[: b - a], d[: b - a])
        jb = min(b, n_m)
        if jb > a:
            c = np.concatenate(([0.0], np.cumsum(d)))
            s = c[m: m + jb - a] - c[: jb - a]
            s_m += _dot(s, s)
    if s_a <= 0:
        return math.nan
    return (s_m / (m * m * n_m)) / (s_a / n_a)


def rn_expected(m: int, alpha: int) -> float:
    """Expected R(n) for white (alpha = 2) or flicker PM (alpha = 1, f_h = 1/(2 tau0))."""
    if alpha == 2:
        return 1.0 / m
    avar = (1.038 + 3.0 * math.log(math.pi * m)) / (4.0 * math.pi ** 2)
    mvar = 3.0 * math.log(256.0 / 27.0) / (8.0 * math.pi ** 2)
    return mvar / avar


def noise_id_b1(x: np.ndarray, m: int, kind: str = "oadev", n: int | None = None) -> int:
    """B1 / R(n) / Hadamard-B1 noise ID at factor ``m`` (rule 2 of the module docstring).

    ``n``: the N of the expected B1 values, by default the term count of ``kind`` for
    ``x`` (Stable32's choice; pass the full series' count when ``x`` is a decimated copy).
    """
    m = int(m)
    x = np.asarray(x, dtype=np.float64)
    y = frequency_averages(x, m)
    n_exp = float(n if n is not None else n_terms(kind, x.size, m))
    b1 = _ratio_b1(y)
    if not math.isfinite(b1) or n_exp < 2:
        return 0
    mu = b1_mu(b1, n_exp)
    if mu == -2:
        rn = rn_ratio(x, m)
        if not math.isfinite(rn):
            return 2
        return 1 if rn > math.sqrt(rn_expected(m, 1) * rn_expected(m, 2)) else 2
    if mu == 1 and kind in _HADAMARD:
        b1s = _ratio_b1(np.diff(y))  # the frequency averages taken as phase
        if math.isfinite(b1s):
            mu_s = b1_mu(b1s, n_exp)
            if mu_s >= 0:
                return -mu_s - 3
    return -mu - 1


# --------------------------------------------------------------------------- per tau / run
def noise_id(x: np.ndarray, m: int, kind: str = "oadev", n: int | None = None) -> int:
    """Stable32's noise ID at one factor (lag-1 with >= 30 averages, else B1 / R(n)), no
    hold. ``n``: N of the B1 expectation (see :func:`noise_id_b1`)."""
    x = np.asarray(x)
    if (x.size - 1) // int(m) >= LAG1_MIN_POINTS:
        return noise_id_lag1(x, m, dmax_of(kind))
    return noise_id_b1(x, m, kind, n)


def held(kind: str, n_phase: int, m: int) -> bool:
    """True where Stable32 keeps the previous tau's alpha (fewer than 2 x stop-ratio
    averages)."""
    return (int(n_phase) - 1) // int(m) < 2 * STOP_RATIO[kind]


def noise_id_curve(x: np.ndarray, ms: Sequence[int], kind: str = "oadev") -> np.ndarray:
    """Noise IDs of a whole run (factors ``ms``) as Stable32 reports them: rules 1-3 of the
    module docstring, the hold applied in increasing order of m."""
    x = np.asarray(x)
    ms = np.asarray(ms, dtype=np.int64)
    order = np.argsort(ms, kind="stable")
    out = np.zeros(ms.size, dtype=np.int64)
    prev: int | None = None
    for i in order:
        m = int(ms[i])
        if prev is not None and held(kind, x.size, m):
            out[i] = prev
            continue
        out[i] = prev = noise_id(x, m, kind)
    return out


def apply_hold(ms: Sequence[int], alphas: Sequence[int], n_phase: int, kind: str = "oadev"
               ) -> np.ndarray:
    """Stable32's hold (rule 3) applied to per-tau IDs computed elsewhere (e.g. from a
    decimated copy of the phase): in increasing m, a held tau takes the previous alpha."""
    ms = np.asarray(ms, dtype=np.int64)
    out = np.array(alphas, dtype=np.int64)
    order = np.argsort(ms, kind="stable")
    for k in range(1, order.size):
        if held(kind, n_phase, int(ms[order[k]])):
            out[order[k]] = out[order[k - 1]]
    return out


def clamp_alpha(alpha: int, kind: str) -> int:
    """Alpha inside the range the estimator's EDF supports: alpha + 2d > 1, i.e. -2..2 for
    the Allan family and the total deviation (d = 2), -4..2 for Hadamard (d = 3)."""
    lo = -4 if kind in _HADAMARD else -2
    return int(min(2, max(lo, alpha)))
