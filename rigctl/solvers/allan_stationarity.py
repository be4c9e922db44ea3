"""Is a bump of the Allan curve stationary noise? (pure functions of arrays)

The self-check (:func:`rigctl.solvers.allan_fit.self_check`) names a run of taus where the
data lie above the fitted IEEE 952 total "a bump". A stationary correlated process (a
first-order Gauss-Markov process: a hump near 1.9 x its correlation time; a periodic
disturbance of period T: near 0.37 T) makes one, and so do a few transient excursions of the
rate in part of the record (a disturbance of the source or of its environment: the record of a
10 MHz OCXO in tests/data has excursions of -4 .. -9e-11 lasting 30-300 s in its first 2.7 h and
none after; its curve's bump at 65-175 s is theirs). The two are told apart by where in the
record the Allan variance at the bump's tau comes from -- the dynamic Allan variance
(Galleani and Tavella, IEEE Trans. UFFC 56 (2009) 450): the record is cut into k windows of
equal length (at least ``WINDOW_TAUS`` taus each, at most ``MAX_WINDOWS``), the overlapping Allan
variance s_i^2 at the tau computed inside each, and Bartlett's test of equal variances applied
with each window's EDF nu_i:

    M = (sum nu_i) ln(s_p^2) - sum nu_i ln(s_i^2),   s_p^2 = sum nu_i s_i^2 / sum nu_i,
    C = 1 + (sum 1/nu_i - 1/sum nu_i) / (3 (k - 1)),  M / C ~ chi2(k - 1)

under stationarity (each s_i^2 a chi-square estimate of one sigma^2). nu_i is the smallest of
NIST SP 1065's simple EDF approximations over the power-law noises (white PM .. random-walk
FM) for the window: a nu too small shrinks M, so the test can only err on the safe side
whatever the noise (measured: false alarms on white + random-walk and white + flicker series in
tests/test_allan_stationarity.py). The windows' estimates are independent but for terms
spanning a window edge (none: each window's terms stay inside it). A bump is called
non-stationary when p < ``ALPHA``; the windows whose s_i^2 exceed the median window's by more
than a single window reaches with probability ALPHA / k are named (where the bump comes from).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from .distributions import chi2

from . import allan as AL
from . import allan_edf as E

#: false-alarm probability per bump tested
ALPHA = 1e-3
#: at most this many windows ...
MAX_WINDOWS = 8
#: ... each at least this many taus long (an EDF of ~15 or more per window)
WINDOW_TAUS = 10


def _nist_edfs(n_phase: int, m: int) -> list[float]:
    """NIST SP 1065 simple EDF approximations of the overlapping Allan variance (N phase points,
    factor m) for white PM, flicker PM, white FM, flicker FM and random-walk FM."""
    n = float(n_phase)
    out = [(n + 1) * (n - 2 * m) / (2 * (n - m))]
    if (n - 1) / (2 * m) > 1:
        out.append(math.exp(math.sqrt(math.log((n - 1) / (2 * m))
                                      * math.log((2 * m + 1) * (n - 1) / 4))))
    out.append((3 * (n - 1) / (2 * m) - 2 * (n - 2) / n) * 4 * m * m / (4 * m * m + 5))
    out.append(2 * (n - 2) ** 2 / (2.3 * n - 4.9) if m == 1 else 5 * n * n / (4 * m * (n + 3 * m)))
    out.append((n - 2) / m * ((n - 1) ** 2 - 3 * m * (n - 1) + 4 * m * m) / (n - 3) ** 2)
    return out


@lru_cache(maxsize=1024)
def window_edf(n_samples: int, m: int) -> float:
    """The EDF used for a window of ``n_samples`` rate samples at factor m: the smallest over
    the power-law noises of Greenhall's EDF (:func:`rigctl.solvers.allan_edf.edf`) and of
    the simple approximations (see the module docstring)."""
    g = [E.edf("oadev", a, m, n_samples + 1) for a in (2, 1, 0, -1, -2)]
    return max(1.0, min(min(g), min(_nist_edfs(n_samples + 1, m))))


def _oavar(y: np.ndarray, m: int) -> float:
    """The fully overlapping Allan variance of the rate samples ``y`` at factor m, in y^2
    units (tau0 cancels): the project's exact estimator (:func:`rigctl.solvers.allan.oadev`)."""
    return float(AL.oadev(y, 1.0, [m], mode="exact").dev[0]) ** 2


def dynamic_avar(y: np.ndarray, m: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan variance at factor m in each of k equal windows of the rate samples
    ``y``: (s2 per window, EDF per window, window start indices and the end)."""
    y = np.asarray(y, dtype=float)
    edges = np.linspace(0, y.size, k + 1).round().astype(int)
    s2 = np.array([_oavar(y[a:b], m) for a, b in zip(edges[:-1], edges[1:])])
    nu = np.array([window_edf(int(b - a), m) for a, b in zip(edges[:-1], edges[1:])])
    return s2, nu, edges


def _bartlett_stat(s2: np.ndarray, nu: np.ndarray) -> float:
    k = s2.size
    n = float(nu.sum())
    sp = float((nu * s2).sum()) / n
    m = n * math.log(sp) - float((nu * np.log(s2)).sum())
    c = 1.0 + (float((1.0 / nu).sum()) - 1.0 / n) / (3.0 * (k - 1))
    return max(m / c, 0.0)


def bartlett(s2: np.ndarray, nu: np.ndarray) -> tuple[float, float]:
    """Bartlett's statistic M / C for equal variances from estimates s2 with EDFs nu, and its
    p-value from chi2(k - 1)."""
    s2, nu = np.asarray(s2, dtype=float), np.asarray(nu, dtype=float)
    stat = _bartlett_stat(s2, nu)
    return stat, float(chi2.sf(stat, s2.size - 1))


def quiet_stretch(s2: np.ndarray, nu: np.ndarray, alpha: float = ALPHA) -> tuple[int, int]:
    """The longest run of consecutive windows [a, b) whose variances agree (Bartlett p >=
    alpha; one window always does), the lowest pooled variance among runs of that length:
    the stretch of the record least touched by a disturbance that adds variance."""
    k = len(s2)
    s2, nu = np.asarray(s2, dtype=float), np.asarray(nu, dtype=float)
    crit = chi2.isf(alpha, np.arange(1, k))  # the statistic's limit for b - a windows
    best = (1, -float(s2.min()), int(np.argmin(s2)), int(np.argmin(s2)) + 1)
    for a in range(k):
        for b in range(a + 2, k + 1):
            if _bartlett_stat(s2[a:b], nu[a:b]) <= crit[b - a - 2]:
                pooled = float((nu[a:b] * s2[a:b]).sum() / nu[a:b].sum())
                best = max(best, (b - a, -pooled, a, b))
    return best[2], best[3]


def bump_stationarity(y: np.ndarray, tau0: float, tau: float, alpha: float = ALPHA) -> dict:
    """Bartlett's test (module docstring) of the Allan variance at ``tau`` across windows of
    the rate samples ``y`` (``tau0`` apart: block means will do). Returns {"tested", "tau_s",
    "windows", "p_value", "stationary", "window_s", "ratio_to_median" per window, "loud": the
    windows (start, end s) whose variance exceeds the median window's beyond chance, "quiet":
    :func:`quiet_stretch` as (start s, end s, its deviation over the whole record's)}; tested
    False (with "skipped") when the record holds fewer than two windows of WINDOW_TAUS taus."""
    y = np.asarray(y, dtype=float)
    y = y[np.isfinite(y)]
    m = max(1, int(round(tau / tau0)))
    k = min(MAX_WINDOWS, y.size // (WINDOW_TAUS * m))
    out = {"tested": False, "tau_s": m * tau0, "alpha": alpha,
           "method": "dynamic Allan variance in equal windows, Bartlett's test (EDF: the "
                     "smallest NIST SP 1065 simple approximation)"}
    if abs(m * tau0 / tau - 1.0) > 0.25:  # block means too coarse for this tau
        out["skipped"] = f"the samples given are {tau0:g} s apart: no Allan variance at {tau:g} s"
        return out
    if k < 2:
        out["skipped"] = f"fewer than 2 windows of {WINDOW_TAUS} taus in the record"
        return out
    s2, nu, edges = dynamic_avar(y, m, k)
    if not np.all(s2 > 0):
        out["skipped"] = "a window without variance"
        return out
    stat, p = bartlett(s2, nu)
    med = float(np.median(s2))
    thr = chi2.isf(alpha / k, nu) / nu  # what one window of a stationary process reaches
    ratio = s2 / med
    loud = [(float(edges[i] * tau0), float(edges[i + 1] * tau0), float(ratio[i]))
            for i in range(k) if ratio[i] > thr[i]]
    whole = _oavar(y, m)
    q = quiet_stretch(s2, nu)  # at ALPHA whatever the test's own alpha: a smaller one lengthens it
    out["quiet"] = [float(edges[q[0]] * tau0), float(edges[q[1]] * tau0),
                    math.sqrt(float((nu[q[0]:q[1]] * s2[q[0]:q[1]]).sum() / nu[q[0]:q[1]].sum())
                              / whole)]
    out.update({"tested": True, "windows": int(k), "window_s": float(edges[1] - edges[0]) * tau0,
                "adev_whole_si": math.sqrt(whole),
                "adev_median_window_si": math.sqrt(med),
                "edf": nu.tolist(), "adev_si": np.sqrt(s2).tolist(),
                "ratio_to_median": ratio.tolist(), "statistic": stat, "dof": k - 1,
                "p_value": p, "stationary": bool(p >= alpha), "loud": loud})
    return out
