"""Short excursions of a static capture's rate: level shifts and bumps lasting from
``MIN_S`` (30 s) to a quarter of the record (pure functions of arrays).

A disturbance of the sensor or its surroundings for a few minutes (a supply or temperature
event: the ADIS16405 capture in tests/data has two, ~300 s each, of +-2e-2 m/s^2 on its y
accelerometer) is not noise: folded into the Allan curve it makes a bump that no stationary
model explains, and the stationarity test (:mod:`rigctl.solvers.allan_stationarity`, windows
of ~1/8 of the record) cannot see it. This module finds such events before the fit.

**The statistic.** At a window length L and a time t, the difference of the adjacent
window means

    D(t, L) = ybar[t, t + L) - ybar[t - L, t)

has, for any noise with stationary increments, the variance

    Var D(t, L) = 2 sigma_A^2(L)

(the Allan variance at tau = L is half the expected square of exactly this difference). The
capture's own 2 sigma_A^2(L) is estimated robustly from the D's themselves: centre c(L) =
their median (a steady drift adds the same L x slope to every D and is taken out), spread
s(L) = 1.4826 x the median absolute deviation about it -- the robust Allan deviation at L,
times sqrt(2) -- so that the few D's an excursion makes do not inflate the scale they are
judged against (the plain Allan deviation would: masking). z(t, L) = (D - c) / s.

**Calibration (family-wise).** L runs over half-octaves from ``MIN_S`` to ``MAX_FRACTION``
of the record (at least 1/MAX_FRACTION independent windows, so that the scale is
estimated from enough of them); t over a grid of L/4. An excursion longer than the largest
L still shows its two edges as steps at the smaller L. The family-wise false-alarm
probability per axis, ``ALPHA``, is split equally over the scales; within a scale the
threshold z*(L) holds the M(L) positions' probability of any |z| > z* (Bonferroni over the
positions, conservative: neighbouring positions overlap) at that share, *allowing for the
scale's own estimation error*: s(L)^2 / (2 sigma_A^2) is taken as chi2(nu)/nu with nu =
:data:`MAD_EFFICIENCY` x the number of independent windows (T / L - 2), and z* solves

    E_r[ min(1, 2 M Phi(-z* r)) ] = ALPHA / n_scales,   r^2 ~ chi2(nu) / nu

(for Gaussian D; below for white phase noise).

**Non-Gaussian white PM.** Where the record's noise at L is white phase noise (a counter's
time-interval readings, an IMU's angle quantization), D is no average: with the phase X (the
running sum of the rate), D(t, L) = (X[t + L] - 2 X[t] + X[t - L]) / L combines three
readings, and is as non-Gaussian as they are. The Keysight 53230A's readings (skewed,
quantized to ~5 ps) put 24 times the Gaussian probability beyond z = 5.3 in one tail of D,
and the Gaussian threshold raised a false step on 6 of 100 shuffles of them. So the tail of
z is taken from the record's own readings wherever their white PM is a share a^2 >=
:data:`MIN_PM_SHARE` of Var D:

    z = a U + b G,   U = (p1 - 2 p2 + p3) / (sqrt 6 sd p),   a^2 = 6 sigma_p^2 / (L^2 s^2),

p1, p2, p3 independent draws from the readings' empirical law (the exact law of D under the
readings shuffled, which keeps their distribution and takes out any time structure: the null
of white PM; computed by FFT convolution of their histogram, not by drawing), G standard
normal for the rest of D (an average of many terms; b^2 = 1 - a^2, at least
:data:`MIN_GAUSS_SHARE`). sigma_p^2 is the lag-2 autocovariance of the rate's first
differences (sigma_p^2 for white PM, 0 for white FM, little for slower noise), the readings
the phase less the running median of its :data:`PM_WINDOW` - 1 neighbours (the slower noise
and a trend taken out, and a glitch kept to its own reading), without those beyond
:data:`PM_OUTLIER_SD` robust sd (one glitch is the spike screen's). The threshold then solves
E_r[min(1, M T(z* r))] = alpha / n_scales with T(z) = 2 max(P(z > z), P(z < -z)) of that
law (never below the Gaussian 2 Phi(-z): the empirical law does not see the tail beyond its
most extreme reading), and z at such a scale is judged against the mean absolute deviation
of the half of the D's nearest their median (:func:`trimmed_spread`; a quantized reading's
lattice holds a median absolute deviation on a few values), the same spread taken of the
model law. Where white PM carries less than :data:`MIN_PM_SHARE` of Var D (white FM, flicker, random
walk and Gauss-Markov noise, which D averages over many samples) nothing changes.

**Edges, then excursions.** The positions beyond z* at each scale form runs of one sign; the
largest |z| of a run is an edge (a step up or down at t). Edges of one sign closer than the
larger of their L's are one edge (the finest scale's time is kept). Consecutive edges of
opposite sign at most a quarter of the record apart make an excursion. An edge left alone is
looked for its return: the opposite step within a quarter of the record after it (and before
it), at the threshold of that smaller family of positions, one-sided -- a second stage that
runs only after a first-stage edge, so the family-wise false-alarm probability stays ALPHA. An
edge without a return is reported as a level shift; within a quarter of the record of its
start or end, as an excursion that runs to it where that window departs from its flank as a
bump must (in the step's direction, by at least half the step) -- else the step was a short
event whose return is too gradual to be found (the Galaxy S5 gyro's 30 s dip at 4060 s), and
not the whole window before it.

**Size.** The mean over the excursion less the mean of its flanks -- the stretches of its own
length before and after it, clipped to the record, without other excursions -- in units of y
(NaN when other excursions cover both flanks); a level shift's size is its step, D at the
scale it was found.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.optimize import brentq
from .distributions import chi2, norm

#: shortest window length tested (s) ...
MIN_S = 30.0
#: ... and at least this many of the sensor's samples (a window of a few samples is one
#: outlier's: spikes are the spike screen's, rigctl.solvers.allan_checks)
MIN_SAMPLES = 16
#: longest window length tested: this share of the record (at least 32 windows of it)
MAX_FRACTION = 1.0 / 32.0
#: an excursion lasts at most this share of the record
MAX_DURATION_FRACTION = 0.25
#: window lengths: half-octave steps
SCALE_STEP = math.sqrt(2.0)
#: positions every L / GRID of the window length
GRID = 4
#: family-wise false-alarm probability per axis (any excursion or level shift reported on a
#: record without one)
ALPHA = 0.01
#: the median absolute deviation's efficiency for a Gaussian scale (its EDF per sample)
MAD_EFFICIENCY = 0.37
#: quantile points of r for the threshold's expectation over the scale's error
_R_POINTS = 400
#: the readings of the white phase noise: the block phase less the running median of its
#: neighbours in a centred window of this many blocks (short: a slower process or an
#: excursion, a kink of the phase, stays out of the readings -- with a 65-block moving average
#: the OCXO's excursions raised the 30 s threshold 5.4 -> 6.3 and two were lost; a median: the
#: Cs5071A's first-point glitch, in a moving average, shifted 16 readings and raised its 30 s
#: threshold 5.9 -> 7.6)
PM_WINDOW = 17
#: below this share of Var D the white PM is not modelled (D taken as Gaussian)
MIN_PM_SHARE = 0.01
#: the Gaussian share of z is at least this (it smooths a quantized reading's lattice)
MIN_GAUSS_SHARE = 0.01
#: readings farther than this many robust sd from their median are not in the white PM's
#: law (a glitch of one reading is the spike screen's, and would set the tail by itself)
PM_OUTLIER_SD = 8.0
#: the spread used where the white PM is modelled: the mean absolute deviation of the D's
#: about their median over the TRIM share nearest it (half: as robust as their median absolute
#: deviation, which the OCXO's excursions need -- with 0.95 two of its excursions were lost) ...
TRIM = 0.5
#: ... divided by its value for a standard normal, E[|Z| ; |Z| <= z_(1+TRIM)/2] / TRIM
_TRIM_GAUSS = float(2.0 * (norm.pdf(0.0) - norm.pdf(norm.isf((1.0 - TRIM) / 2.0))) / TRIM)


@lru_cache(maxsize=4096)
def threshold(m: int, nu: float, alpha: float) -> float:
    """z* with E_r[min(1, 2 m Phi(-z* r))] = alpha, r^2 ~ chi2(nu)/nu (module docstring);
    nu = inf: the plain Bonferroni threshold Phi^-1(1 - alpha / (2 m))."""
    if not math.isfinite(nu) or nu > 1e6:
        return float(norm.isf(alpha / (2.0 * m)))
    return _solve(m, nu, alpha, lambda z: 2.0 * norm.sf(z))


def tail_threshold(m: int, nu: float, alpha: float, tail: "PhaseTail | None") -> float:
    """z* with E_r[min(1, m T(z* r))] = alpha, r^2 ~ chi2(nu)/nu, T(z) the probability of
    |z| > z at one position where white PM is part of D (:class:`PhaseTail`, module
    docstring "Non-Gaussian white PM"); :func:`threshold` when ``tail`` is None."""
    if tail is None:
        return threshold(m, nu, alpha)
    return _solve(m, nu, alpha, tail.sf)


def _solve(m: int, nu: float, alpha: float, sf) -> float:
    """The threshold's equation E_r[min(1, m sf(z* r))] = alpha solved for z*."""
    r = np.ones(1) if not math.isfinite(nu) or nu > 1e6 else \
        np.sqrt(chi2.ppf((np.arange(_R_POINTS) + 0.5) / _R_POINTS, nu) / nu)

    def excess(z: float) -> float:
        return float(np.mean(np.minimum(1.0, m * sf(z * r)))) - alpha

    lo = float(norm.isf(alpha / (2.0 * m)))
    hi = lo
    while excess(hi) > 0:
        hi *= 1.5
        if hi > 1e6:
            return math.inf
    return float(brentq(excess, lo * 0.5, hi, xtol=1e-4))


class PhaseTail:
    """The tail of z at one position where part of D is the record's white PM (docstring,
    "Non-Gaussian white PM"): z = a U + b G, U the white-PM combination (p_1 - 2 p_2 + p_3) /
    (sqrt 6 sd p) of three independent phase readings drawn from the record's own readings
    (:func:`white_pm_law`; the exact law of the shuffled readings), G standard normal (the
    rest of D, an average of many terms), a^2 the white PM's share of Var D, a^2 + b^2 = 1
    (b at least :data:`MIN_GAUSS_SHARE` ** 0.5). :meth:`sf` is T(z) = 2 max(P(z > z0),
    P(z < -z0)), the two-sided probability a symmetric law with the heavier of the two tails
    would have (one-sided tests use it as 2 x their tail), tabulated on a grid."""

    __slots__ = ("a", "_z", "_logt")
    _STEP = 0.005  # grid step (z units)

    def __init__(self, a: float, law: tuple[np.ndarray, np.ndarray]) -> None:
        u, g = law
        self.a = float(a)
        b = math.sqrt(max(1.0 - self.a ** 2, MIN_GAUSS_SHARE))
        h = self._STEP
        zmax = max(30.0, self.a * float(np.max(np.abs(u))) + 12.0 * b)
        n = int(math.ceil(2.0 * zmax / h)) + 1
        mass = np.bincount(np.clip(np.round((self.a * u + zmax) / h).astype(np.int64), 0, n - 1),
                           weights=g, minlength=n)
        k = int(math.ceil(12.0 * b / h))
        ker = norm.pdf(np.arange(-k, k + 1) * h / b)
        ker /= ker.sum()
        size = 1 << int(math.ceil(math.log2(n + ker.size)))
        conv = np.fft.irfft(np.fft.rfft(mass, size) * np.fft.rfft(ker, size), size)[k:k + n]
        conv = np.clip(conv, 0.0, None)
        conv /= conv.sum()
        grid = -zmax + np.arange(n) * h
        # z is judged in units of the D's spread about their median (:func:`trimmed_spread`):
        # the same of this law, so that T is in z's own units
        cdf = np.cumsum(conv)
        med = float(np.interp(0.5, cdf, grid))
        q = np.arange(0.0, zmax - abs(med), h)  # P(|Z - med| <= q), and its TRIM quantile
        inside = np.interp(med + q, grid, cdf) - np.interp(med - q, grid, cdf, left=0.0)
        qt = float(np.interp(TRIM, inside, q))
        sel = q <= qt
        # E[|Z - med| ; |Z - med| <= qt] / TRIM, from the increments of P(|Z - med| <= q)
        qs = q[sel]
        spread = float(np.sum(0.5 * (qs[1:] + qs[:-1]) * np.diff(inside[sel]))) / TRIM / _TRIM_GAUSS
        upper = np.cumsum(conv[::-1])[::-1]  # P(Z >= grid)
        zs = np.arange(0.0, 0.999 * (zmax - abs(med)) / spread, h)
        up = np.interp(med + zs * spread, grid, upper)
        low = np.interp(med - zs * spread, grid, cdf)
        self._z = zs
        self._logt = np.log(np.maximum(2.0 * np.maximum(up, low), 1e-300))

    def sf(self, z: np.ndarray) -> np.ndarray:
        """T(z) (class docstring), never below the Gaussian 2 Phi(-z): the readings' law is
        empirical, and its tail beyond the most extreme reading is not seen."""
        z = np.abs(z)
        return np.maximum(np.exp(np.interp(z, self._z, self._logt)), 2.0 * norm.sf(z))


def trimmed_spread(d: np.ndarray, centre: float) -> float:
    """The D's spread where the white PM is modelled: mean |d - centre| over the :data:`TRIM`
    share of them nearest the centre, over its standard-normal value (as robust as the median
    absolute deviation, but an average of half the D's: a quantized reading's lattice of D
    values holds the median absolute deviation itself on a few values, +-5 % on the Keysight
    53230A's)."""
    a = np.sort(np.abs(np.asarray(d, dtype=float) - centre))
    k = max(1, int(TRIM * a.size))
    return float(np.mean(a[:k])) / _TRIM_GAUSS


def white_pm_variance(ybar: np.ndarray) -> float:
    """sigma_p^2 of :func:`white_pm_law`: the lag-2 autocovariance of the first differences
    of ybar, clipped at 0 (0 for fewer than 4 blocks)."""
    y = np.asarray(ybar, dtype=float)
    if y.size < 4:
        return 0.0
    dy = np.diff(y)
    dy = dy - dy.mean()
    return max(0.0, float(np.mean(dy[2:] * dy[:-2])))


def white_pm_law(ybar: np.ndarray,
                 bins_per_sd: int = 50) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    """The record's white phase noise: its variance sigma_p^2 in units of the block phase
    X = cumsum(ybar) (blocks x units of ybar) and the law of U = (p_1 - 2 p_2 + p_3) /
    (sqrt 6 sd p) for three independent readings drawn from its own readings p
    (values, probabilities; module docstring, "Non-Gaussian white PM").

    sigma_p^2 is the lag-2 autocovariance of the first differences of ybar (X's second
    differences at lag 1): p_{i+1} - 2 p_i + p_{i-1} for white PM, whose lag-2 autocovariance
    is sigma_p^2, while white FM's y_{i+1} - y_i has none (and slower noise little); clipped
    at 0. The readings: X less the median of its neighbours in :data:`PM_WINDOW` blocks (which
    takes out the record's slower noise and a linear trend), their empirical law binned at
    sd / bins_per_sd, combined three times by FFT convolution."""
    y = np.asarray(ybar, dtype=float)
    var_p = white_pm_variance(y)
    if y.size < 4 * PM_WINDOW:
        return var_p, (np.zeros(1), np.ones(1))
    x = np.concatenate(([0.0], np.cumsum(y - np.median(y))))
    half = PM_WINDOW // 2
    # the median of the reading's neighbours, not of itself too (which pulls the median
    # towards it and makes Gaussian readings' residuals heavy-tailed: kurtosis 3.25)
    around = np.delete(sliding_window_view(x, PM_WINDOW), half, axis=1)
    p = x[half:x.size - half] - np.median(around, axis=1)
    centre = float(np.median(p))
    rsd = 1.4826 * float(np.median(np.abs(p - centre)))
    if rsd > 0:
        p = p[np.abs(p - centre) <= PM_OUTLIER_SD * rsd]
    sd = float(np.std(p))
    if not sd > 0:
        return var_p, (np.zeros(1), np.ones(1))
    h = sd / bins_per_sd
    lo = float(p.min())
    idx = np.round((p - lo) / h).astype(np.int64)
    f = np.bincount(idx) / p.size
    nb = f.size
    f2 = np.zeros(2 * nb - 1)
    f2[::2] = f[::-1]  # -2 p on the same grid
    size = 1 << int(math.ceil(math.log2(4 * nb)))
    g = np.fft.irfft(np.fft.rfft(f, size) ** 2 * np.fft.rfft(f2, size), size)[:4 * nb - 3]
    g = np.clip(g, 0.0, None)
    g /= g.sum()
    # grid value of index k: 2 lo - 2 (lo + (nb - 1) h) + k h
    vals = -2.0 * (nb - 1) * h + np.arange(g.size) * h
    keep = g > 1e-18
    vals, g = vals[keep], g[keep] / g[keep].sum()
    mu = float(np.sum(g * vals))
    return var_p, ((vals - mu) / (math.sqrt(6.0) * sd), g)


def scales(n_blocks: int, block_s: float, min_s: float = MIN_S,
           max_fraction: float = MAX_FRACTION) -> list[int]:
    """The window lengths tested, in blocks (module docstring): half-octaves from min_s to
    max_fraction of the record, at least 2 blocks each."""
    out: list[int] = []
    length = min_s
    t_rec = n_blocks * block_s
    while length <= max_fraction * t_rec * (1 + 1e-9):
        k = max(2, int(round(length / block_s)))
        if not out or k > out[-1]:
            out.append(k)
        length *= SCALE_STEP
    return out


def step_scan(ybar: np.ndarray, L: int, grid: int = GRID) -> dict:
    """D(t, L) on the grid t = L, L + L/grid, ... (blocks), its median, robust spread (the
    robust sqrt(2) sigma_A(L)) and z; the cumulative sum makes each window mean exact."""
    y = np.asarray(ybar, dtype=float)
    c = np.concatenate(([0.0], np.cumsum(y - (y[0] if y.size else 0.0))))
    h = max(1, L // grid)
    ts = np.arange(L, y.size - L + 1, h)
    d = (c[ts + L] - 2.0 * c[ts] + c[ts - L]) / L
    med = float(np.median(d)) if d.size else 0.0
    s = 1.4826 * float(np.median(np.abs(d - med))) if d.size else 0.0
    z = (d - med) / s if s > 0 else np.zeros_like(d)
    return {"L": int(L), "t": ts, "d": d, "centre": med, "spread": s, "z": z,
            "nu": MAD_EFFICIENCY * max(y.size / L - 2.0, 1.0)}


def _runs(z: np.ndarray, thr: float, ts: np.ndarray, L: int) -> list[tuple[int, float]]:
    """(t, z) of the largest |z| of each run of positions beyond thr of one sign (positions
    within L of each other join a run)."""
    idx = np.flatnonzero(np.abs(z) > thr)
    out: list[tuple[int, float]] = []
    run: list[int] = []
    for i in idx.tolist():
        if run and (ts[i] - ts[run[-1]] > L or np.sign(z[i]) != np.sign(z[run[-1]])):
            k = max(run, key=lambda j: abs(z[j]))
            out.append((int(ts[k]), float(z[k])))
            run = []
        run.append(i)
    if run:
        k = max(run, key=lambda j: abs(z[j]))
        out.append((int(ts[k]), float(z[k])))
    return out


def window_size(ybar: np.ndarray, a: int, b: int, others: list[tuple[int, int]] = ()) -> float:
    """Mean of ybar[a:b) less the mean of its flanks of the same length (clipped to the
    record, without the blocks of ``others``)."""
    y = np.asarray(ybar, dtype=float)
    n = y.size
    d = b - a
    keep = np.zeros(n, dtype=bool)
    keep[max(0, a - d):a] = True
    keep[b:min(n, b + d)] = True
    flanks = keep.copy()
    for oa, ob in others:
        keep[max(0, oa):min(n, ob)] = False
    if not keep.any():  # other excursions cover both flanks: against them, as they are
        keep = flanks
    if not keep.any():
        return float("nan")
    return float(np.mean(y[a:b]) - np.mean(y[keep]))


def find_excursions(ybar: np.ndarray, block_s: float, alpha: float = ALPHA,
                    min_s: float = MIN_S, max_fraction: float = MAX_FRACTION) -> dict:
    """The excursions of the rate's block means ``ybar`` (``block_s`` s each), by the test of
    the module docstring. Returns {"tested", "alpha", "method", "scales_s", "thresholds_z",
    "robust_adev_si" (s(L)/sqrt(2) per scale), "white_pm_share" (a^2 per scale), "edges"
    [{"t_s", "z", "L_s", "threshold_z", "stage"}], "excursions" [{"start_s", "end_s",
    "duration_s", "size_si", "kind" ("bump", "to the start", "to the end", "level shift"),
    "z_start", "z_end"}]} in s from the first
    block and the units of ybar; tested False (with "skipped") when the record is shorter
    than min_s / max_fraction."""
    y = np.asarray(ybar, dtype=float)
    y = y[np.isfinite(y)]
    n = y.size
    t_rec = n * block_s
    out: dict = {"tested": False, "alpha": alpha, "min_s": min_s,
                 "max_duration_s": MAX_DURATION_FRACTION * t_rec,
                 "method": "adjacent window-mean differences over half-octave windows of "
                           f"{min_s:g} s to 1/{1 / max_fraction:g} of the record, judged against "
                           "their robust spread (the robust Allan deviation at that window "
                           "times sqrt 2), family-wise Bonferroni over positions and scales "
                           "allowing for the spread's estimation error; where white phase noise "
                           "is part of them, the tail of the record's own phase readings"}
    Ls = scales(n, block_s, min_s, max_fraction)
    if not Ls:
        out["skipped"] = (f"the record ({t_rec:.0f} s) is shorter than {min_s / max_fraction:.0f} s "
                          f"(windows of {min_s:g} s need at least {1 / max_fraction:g} of them)")
        return out
    scans = [step_scan(y, L) for L in Ls]
    a_scale = alpha / len(Ls)
    var_p = white_pm_variance(y)
    law = None  # the readings' law: only where some scale needs it
    tails: dict[float, PhaseTail] = {}
    for sc in scans:
        share = min(1.0, 6.0 * var_p / (sc["L"] ** 2 * sc["spread"] ** 2)) \
            if sc["spread"] > 0 else 0.0
        sc["pm_share"] = share
        sc["tail"] = None
        if share >= MIN_PM_SHARE:
            a = round(math.sqrt(share), 3)  # the same share at several scales: one table
            if a not in tails:
                if law is None:
                    law = white_pm_law(y)[1]
                tails[a] = PhaseTail(a, law)
            sc["tail"] = tails[a]
            sc["spread"] = trimmed_spread(sc["d"], sc["centre"])
            sc["z"] = (sc["d"] - sc["centre"]) / sc["spread"]
        sc["thr"] = tail_threshold(int(sc["t"].size), round(sc["nu"], 3), a_scale, sc["tail"]) \
            if sc["spread"] > 0 else math.inf
    edges = []
    for sc in scans:
        for t, z in _runs(sc["z"], sc["thr"], sc["t"], sc["L"]):
            edges.append({"t": t, "z": z, "L": sc["L"], "thr": sc["thr"], "stage": 1,
                          "step": z * sc["spread"]})
    # one edge per step: of one sign within the larger L, the most significant (relative to
    # its threshold) kept, at the finest scale's time
    edges.sort(key=lambda e: -abs(e["z"]) / e["thr"])
    kept: list[dict] = []
    for e in edges:
        same = [k for k in kept if np.sign(k["z"]) == np.sign(e["z"])
                and abs(k["t"] - e["t"]) <= max(k["L"], e["L"])]
        if same:
            k = same[0]
            if e["L"] < k.get("L_time", k["L"]):
                k["t_fine"], k["L_time"] = e["t"], e["L"]
            continue
        kept.append({**e, "t_fine": e["t"], "L_time": e["L"]})
    kept.sort(key=lambda e: e["t_fine"])
    max_d = int(MAX_DURATION_FRACTION * n)
    exc: list[tuple[int, int, str, float, float]] = []
    used = [False] * len(kept)
    for i, e in enumerate(kept):
        if used[i]:
            continue
        used[i] = True
        te, sg = e["t_fine"], np.sign(e["z"])
        # its return: the opposite steps after it (first-stage edges, and second-stage ones
        # beyond the threshold of that smaller family), up to max_d and the next edge of its
        # own sign; else before it (an excursion whose start was not seen)
        got = None
        for direction in (1, -1):
            others = [(j, k) for j, k in enumerate(kept) if not used[j]
                      and 0 < direction * (k["t_fine"] - te) <= max_d]
            same = [k["t_fine"] for _, k in others if np.sign(k["z"]) == sg]
            bound = (min(same) if direction > 0 else max(same)) if same else \
                (min(n, te + max_d) if direction > 0 else max(0, te - max_d))
            cands = [(k["t_fine"], k["z"], j, k["step"]) for j, k in others
                     if np.sign(k["z"]) != sg and direction * (k["t_fine"] - bound) < 0]
            lo, hi = (te, bound) if direction > 0 else (bound, te)
            cands += [(r["t"], r["z"], None, r["step"])
                      for r in _opposite_steps(scans, e, lo, hi, a_scale)
                      if not any(abs(r["t"] - k["t_fine"]) <= max(r["L"], k["L"]) for k in kept)]
            best = None
            for t, z, j, step in cands:
                a, b = sorted((te, t))
                if b - a < 1:
                    continue
                size = window_size(y, a, b)
                # a bump: the window departs from its flanks, in the direction of its
                # edges, by at least half the smaller of its two steps
                if not (np.sign(size) == sg * direction
                        and abs(size) >= 0.5 * min(abs(e["step"]), abs(step))):
                    continue
                score = abs(size) * math.sqrt(b - a)
                if best is None or score > best[0]:
                    best = (score, t, z, j)
            if best is not None:
                got = best
                break
        if got is not None:
            _, t, z, j = got
            if j is not None:
                used[j] = True
            else:
                edges.append({"t": t, "z": z, "L": 0, "thr": float("nan"), "stage": 2})
            a, b = sorted((te, t))
            za, zb = (e["z"], z) if a == te else (z, e["z"])
            exc.append((a, b, "bump", za, zb))
            for j, k in enumerate(kept):  # steps inside it are its own shape
                if a < k["t_fine"] < b:
                    used[j] = True
        elif te >= n - max_d and _runs_to_edge(y, te, n, sg, e["step"]):
            exc.append((te, n, "to the end", e["z"], float("nan")))
            for j in range(i + 1, len(kept)):  # the steps after it are its own shape
                used[j] = True
        elif te <= max_d and _runs_to_edge(y, 0, te, -sg, e["step"]):
            exc.append((0, te, "to the start", float("nan"), e["z"]))
        else:
            exc.append((te, te, "level shift", e["z"], e["step"]))
    exc.sort()
    # an excursion inside another (a step before the edge of one that runs to the start)
    # is part of the outer one's shape
    exc = [x for x in exc if not any(o is not x and o[0] <= x[0] and x[1] <= o[1]
                                     and (o[1] - o[0]) > (x[1] - x[0]) for o in exc)]
    windows = [(a, b) for a, b, kind, _, _ in exc if b > a]
    items = []
    for a, b, kind, za, zb in exc:
        # a level shift: its step (the adjacent window means' difference at the scale found)
        size = window_size(y, a, b, [w for w in windows if w != (a, b)]) if b > a else zb
        if b == a:
            zb = float("nan")
        items.append({"start_s": a * block_s, "end_s": b * block_s,
                      "duration_s": (b - a) * block_s, "size_si": size, "kind": kind,
                      "z_start": za, "z_end": zb, "blocks": [int(a), int(b)]})
    out.update({"tested": True, "block_s": block_s, "record_s": t_rec,
                "scales_s": [L * block_s for L in Ls],
                "thresholds_z": [sc["thr"] for sc in scans],
                "white_pm_share": [sc["pm_share"] for sc in scans],
                "robust_adev_si": [sc["spread"] / math.sqrt(2.0) for sc in scans],
                "edges": [{"t_s": e["t"] * block_s, "z": e["z"], "L_s": e["L"] * block_s,
                           "threshold_z": e["thr"], "stage": e["stage"]} for e in edges],
                "excursions": items})
    return out


def _runs_to_edge(y: np.ndarray, a: int, b: int, sign: float, step: float) -> bool:
    """Whether the window [a, b) between an unreturned step and the record's start or end
    departs from its flank as a bump must (in the step's direction, ``sign``, by at least
    half the step): else the step was a short event whose return is too gradual to be
    found, and the window is no excursion (the step is reported as a level shift)."""
    size = window_size(y, a, b)
    return bool(np.sign(size) == sign and abs(size) >= 0.5 * abs(step))


def _opposite_steps(scans: list[dict], e: dict, lo: int, hi: int, a_scale: float) -> list[dict]:
    """The steps of the opposite sign to edge ``e`` in (lo, hi) blocks (not within e's own L)
    beyond the one-sided threshold of that family of positions (per scale: the positions in
    the range), one per run (:func:`_runs`), each at the finest scale that has it."""
    sign = -np.sign(e["z"])
    found: list[dict] = []
    for sc in scans:
        ts, z = sc["t"], sc["z"]
        if sc["spread"] <= 0:
            continue
        sel = (ts > lo) & (ts < hi) & (np.abs(ts - e["t_fine"]) > sc["L"])
        m = int(sel.sum())
        if m == 0:
            continue
        thr = tail_threshold(m, round(sc["nu"], 3), 2.0 * a_scale, sc.get("tail"))  # one-sided
        zz = np.where(sel, sign * z, 0.0)
        for t, v in _runs(zz, thr, ts, sc["L"]):
            if v > 0 and not any(abs(f["t"] - t) <= max(f["L"], sc["L"]) for f in found):
                found.append({"t": t, "z": float(sign * v), "L": sc["L"], "thr": thr,
                              "step": float(sign * v * sc["spread"])})
    return found
