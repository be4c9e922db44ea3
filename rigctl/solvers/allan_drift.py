"""Slow features of a static capture that are not IEEE 952 noise, found before the Allan fit
(pure functions of arrays; the application layer, :mod:`rigctl.analysis.allan_drift`, feeds
them the block means of the streamed record).

* **Start transient** (a warm-up after power-on): the mean settles exponentially,
  y(t) = c + A exp(-t / tau_w). :func:`start_transient_test` asks whether the first stretch of
  the record differs from the next one by more than the noise allows: at each scale T
  (octaves) the difference d0 = mean[0, T) - mean[T, 2T) is compared with the differences of
  later, non-overlapping pairs of T-means, d_k (k >= 2). Without a transient d0 and the d_k
  have one distribution whatever the noise (the Allan variance is half their mean square: white,
  flicker and random-walk rate alike), so t = d0 / rms(d_k) follows Student's t with M (the
  number of pairs) degrees of freedom; the smallest p over the scales, times their number
  (Bonferroni), is the test's p-value. :func:`fit_start_transient` then fits c, A, tau_w to the
  block means of the first stretch (variable projection: tau_w searched, c and A linear; the
  model integrates the exponential over each block), with a heteroscedasticity-and-
  autocorrelation-consistent (Newey-West) covariance for the intervals, since the residual
  is coloured noise. :func:`transient_avar` is the overlapping Allan variance of the fitted
  transient over a record of length T_rec (closed form, continuous time):

      sigma_w^2(tau) = A^2 tau_w^3 (1 - e^{-tau/tau_w})^4 (1 - e^{-2 (T_rec - 2 tau)/tau_w})
                       / (4 tau^2 (T_rec - 2 tau))

  and :func:`trim_for` the time to cut from the start so that what is left of it stays below a
  tenth of the curve's deviation at every tau.
* **Temperature** (:func:`temperature_regression`): the slow part of the signal (block means)
  regressed on the recorded temperature's block means, by least squares on the *differences*
  of consecutive block means (a bias that also wanders like a random walk leaves white
  differences), the coefficient with its Student-t interval and p-value; the temperature
  term's own Allan deviation (:func:`series_adev`) says at which taus it matters.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from . import distributions as stats

#: the start-transient test's false-alarm probability per axis (Bonferroni over the scales)
ALPHA = 1e-3
#: at least this many later pairs of T-means to compare the first pair with
MIN_PAIRS = 6
#: the first later pair starts at block 2 * SKIP_PAIRS (the pair right after the first is left
#: out: a long transient is still in it)
SKIP_PAIRS = 2
#: block means kept for the test (the record is averaged down to at most this many blocks)
MAX_BLOCKS = 1 << 17
#: the fit reads the first FIT_SPAN time constants (at most half the record) ...
FIT_SPAN = 8.0
#: ... in this many block means
FIT_BLOCKS = 256
#: what is left of a transient after trimming: its Allan deviation at most this share of the
#: curve's (without the transient) at every tau, i.e. 1 % of the variance
TRIM_SHARE = 0.1
#: a run of taus outside the band is put down to the transient (or the temperature) where
#: its Allan variance is at least this share of the curve's
NAME_SHARE = 0.1


def aggregate(y: np.ndarray, k: int) -> np.ndarray:
    """Means of k consecutive values (the last incomplete group dropped)."""
    n = (y.size // k) * k
    return y[:n].reshape(-1, k).mean(axis=1) if k > 1 else y[:n].copy()


def start_transient_test(ybar: np.ndarray, block_s: float, alpha: float = ALPHA) -> dict:
    """The start-transient test on block means ``ybar`` of length ``block_s`` each (see the
    module's doc). Returns {detected, p_value (Bonferroni), alpha, scales: [{T_s, t, dof, p}],
    best_T_s (the scale of the smallest p), sign}."""
    ybar = np.asarray(ybar, dtype=float)
    scales = []
    k = 1
    while True:
        z = aggregate(ybar, k)
        pairs = z.size // 2 - SKIP_PAIRS
        if pairs < MIN_PAIRS:
            break
        d0 = z[0] - z[1]
        late = z[2 * SKIP_PAIRS: 2 * (SKIP_PAIRS + pairs)].reshape(-1, 2)
        d = late[:, 0] - late[:, 1]
        s = math.sqrt(float(np.mean(d * d)))
        t = d0 / s if s > 0 else (0.0 if d0 == 0 else math.inf)
        p = float(2.0 * stats.t.sf(abs(t), pairs))
        scales.append({"T_s": k * block_s, "t": float(t), "dof": int(pairs), "p": p,
                       "d0": float(d0), "rms_later": s})
        k *= 2
    if not scales:
        return {"detected": False, "p_value": 1.0, "alpha": alpha, "scales": [],
                "skipped": f"too short: fewer than {MIN_PAIRS + SKIP_PAIRS} pairs of blocks"}
    best = min(scales, key=lambda s: s["p"])
    p_all = min(1.0, best["p"] * len(scales))
    return {"detected": bool(p_all < alpha), "p_value": p_all, "alpha": alpha,
            "scales": scales, "best_T_s": best["T_s"], "sign": int(np.sign(best["d0"]))}


def _block_exp(t0: np.ndarray, t1: np.ndarray, tau: float) -> np.ndarray:
    """Mean of exp(-t / tau) over each block [t0, t1)."""
    return tau / (t1 - t0) * (np.exp(-t0 / tau) - np.exp(-t1 / tau))


def _hac_cov(jac: np.ndarray, r: np.ndarray, lags: int) -> np.ndarray:
    """Newey-West covariance of least-squares parameters: (J'J)^-1 S (J'J)^-1, S the
    Bartlett-weighted sum of the autocovariances of J_t r_t up to ``lags``."""
    g = jac * r[:, None]
    s = g.T @ g
    for lag in range(1, lags + 1):
        w = 1.0 - lag / (lags + 1.0)
        c = g[lag:].T @ g[:-lag]
        s += w * (c + c.T)
    inv = np.linalg.pinv(jac.T @ jac)
    return inv @ s @ inv


def _fit_exp(z: np.ndarray, b: float, tau_max: float) -> tuple[float, float, float, np.ndarray]:
    """Least squares of c + A (block mean of exp(-t / tau_w)) on the block means ``z`` (block
    length b): tau_w searched on a log grid in [b/4, tau_max] and refined, c and A linear.
    Returns (c, A, tau_w, residuals)."""
    t0 = np.arange(z.size) * b
    t1 = t0 + b

    def solve(log_tw: float) -> tuple[np.ndarray, np.ndarray]:
        a = np.column_stack([np.ones(z.size), _block_exp(t0, t1, math.exp(log_tw))])
        coef = np.linalg.lstsq(a, z, rcond=None)[0]
        return coef, z - a @ coef

    def rss(log_tw: float) -> float:
        r = solve(log_tw)[1]
        return float(r @ r)

    grid = np.linspace(math.log(b / 4.0), math.log(tau_max), 60)
    i = int(np.argmin([rss(g) for g in grid]))
    res = optimize.minimize_scalar(rss, bounds=(grid[max(i - 1, 0)], grid[min(i + 1, 59)]),
                                   method="bounded", options={"xatol": 1e-6})
    (c, amp), r = solve(float(res.x))
    return float(c), float(amp), math.exp(float(res.x)), r


#: at least this many later stretches of the record for the intervals from the record's own
#: noise; fewer: Newey-West
MIN_REPLICATES = 4
#: overlapping stretches for a short record (hop = stretch / OVERLAP)
OVERLAP = 4


def fit_start_transient(ybar: np.ndarray, block_s: float, tau_guess: float,
                        record_s: float) -> dict:
    """Fit y = c + A exp(-t / tau_w) to the block means of the record's start (the first
    FIT_SPAN tau_w, at most half the record; FIT_BLOCKS blocks), twice (the span from the
    first fit's tau_w). The 95 % intervals come from the record's own noise: the fitted
    transient is added to each later stretch of the same length (where it has died away)
    and fitted again; the spread of those fits (Student t over their number) is the
    interval, since the noise is coloured (flicker, random walk) and a residual-based
    interval would be far too narrow. With fewer than MIN_REPLICATES later stretches that do
    not overlap, stretches overlapping by three quarters are used and the Student quantile
    has the independent stretches' count less one (at least 1) degrees of freedom: wide,
    honest intervals (2 h at 10 Hz, consumer_mems: 104 of 104 held 270 s, ~[70, 1000] s);
    with fewer than 2 stretches at all, Newey-West's (too narrow on coloured noise: 2 h at
    100 Hz, when they were used for every record with fewer than 4 stretches, 52 of 107 held
    270 s; now 107 of 107). ``interval_from`` says which. Returns {amp, tau_s, offset,
    amp_ci95, tau_ci95, span_s, blocks, block_s, replicates, interval_from, resid_rms}
    (units of y, s)."""
    ybar = np.asarray(ybar, dtype=float)
    tau = max(float(tau_guess), 2.0 * block_s)
    out: dict = {}
    for _ in range(2):
        span = min(record_s / 2.0, FIT_SPAN * tau)
        nb = int(span / block_s)
        k = max(1, nb // FIT_BLOCKS)
        nb = (nb // k) * k
        z = aggregate(ybar[:nb], k)
        if z.size < 8:
            return {"skipped": "too few blocks in the record's start"}
        b = k * block_s
        c, amp, tw, r = _fit_exp(z, b, span)
        tau = tw
    t0 = np.arange(z.size) * b
    shape = _block_exp(t0, t0 + b, tw)
    reps = []
    n_free = ybar.size // nb - 1  # later stretches that do not overlap
    # fewer than MIN_REPLICATES: stretches that overlap by three quarters (as many again
    # per stretch), the Student quantile still from the independent ones (at least 1 dof)
    hop = nb if n_free >= MIN_REPLICATES else max(1, nb // OVERLAP)
    for j0 in range(nb, ybar.size - nb + 1, hop):
        zj = aggregate(ybar[j0: j0 + nb], k) + amp * shape
        _, aj, twj, _ = _fit_exp(zj, b, span)
        reps.append((aj, math.log(twj)))
    q_n = len(reps)
    if q_n >= MIN_REPLICATES or (hop != nb and q_n >= 2):
        rep = np.array(reps)
        dof = q_n - 1 if hop == nb else max(1, n_free - 1) if n_free > 1 else 1
        q = float(stats.t.ppf(0.975, dof)) * math.sqrt(1.0 + 1.0 / max(n_free, 1))
        sd_amp, sd_log = float(np.std(rep[:, 0], ddof=1)), float(np.std(rep[:, 1], ddof=1))
        how = (f"the fit repeated on {q_n} later stretches of the record with the transient added"
               + ("" if hop == nb else f" (overlapping; {n_free} independent, t with {dof} dof)"))
    else:
        h = 1e-5
        dlog = (_block_exp(t0, t0 + b, tw * math.exp(h))
                - _block_exp(t0, t0 + b, tw * math.exp(-h))) / (2 * h)
        jac = np.column_stack([np.ones(z.size), shape, amp * dlog])
        lags = int(math.floor(4.0 * (z.size / 100.0) ** (2.0 / 9.0))) * 2
        cov = _hac_cov(jac, r, lags)
        q = float(stats.t.ppf(0.975, max(z.size - 3, 1)))
        sd_amp, sd_log = math.sqrt(max(cov[1, 1], 0.0)), math.sqrt(max(cov[2, 2], 0.0))
        how = (f"Newey-West ({lags} lags): the record has fewer than {MIN_REPLICATES} later "
               "stretches as long as the fitted one, so the interval may be too narrow for "
               "coloured noise")
    return {"amp": amp, "tau_s": tw, "offset": c,
            "amp_ci95": [amp - q * sd_amp, amp + q * sd_amp],
            "tau_ci95": [tw * math.exp(-q * sd_log), tw * math.exp(q * sd_log)],
            "span_s": float(z.size * b), "blocks": int(z.size), "block_s": float(b),
            "replicates": q_n, "interval_from": how,
            "resid_rms": float(np.sqrt(np.mean(r * r)))}


def transient_avar(tau: np.ndarray, amp: float, tau_w: float, record_s: float) -> np.ndarray:
    """Overlapping Allan variance of A exp(-t / tau_w) over a record of ``record_s`` (the
    module's closed form; 0 where 2 tau >= record_s)."""
    tau = np.asarray(tau, dtype=float)
    span = record_s - 2.0 * tau
    out = np.zeros(tau.shape)
    ok = span > 0
    tt, ss = tau[ok], span[ok]
    out[ok] = (amp * amp * tau_w ** 3 * (-np.expm1(-tt / tau_w)) ** 4
               * (-np.expm1(-2.0 * ss / tau_w)) / (4.0 * tt * tt * ss))
    return out


def trim_for(amp: float, tau_w: float, tau: np.ndarray, adev: np.ndarray, record_s: float,
             share: float = TRIM_SHARE) -> float:
    """Seconds to cut from the start so that what is left of the transient (A e^{-t/tau_w})
    has an Allan deviation of at most ``share`` of the curve's without it (the measured
    variance less the transient's own, at least a quarter of the measured) at every tau the
    shortened record still has. ``amp`` and ``tau_w``: take the upper ends of their intervals
    for a cut that is long enough."""
    tau = np.asarray(tau, dtype=float)
    dev2 = np.asarray(adev, dtype=float) ** 2
    clean = np.maximum(dev2 - transient_avar(tau, amp, tau_w, record_s), 0.0625 * dev2)
    cut = 0.0
    for _ in range(4):  # the shorter record gives the transient a larger share: iterate
        rest = record_s - cut
        ok = 2.0 * tau < rest
        if not ok.any():
            return cut
        unit = transient_avar(tau[ok], 1.0, tau_w, rest)
        with np.errstate(divide="ignore"):
            lim = np.min(share * np.sqrt(clean[ok]) / np.sqrt(np.maximum(unit, 1e-300)))
        new = tau_w * math.log(abs(amp) / lim) if abs(amp) > lim else 0.0
        if abs(new - cut) < 1e-3 * tau_w:
            return max(new, 0.0)
        cut = max(new, 0.0)
    return cut


def series_adev(z: np.ndarray, block_s: float, tau: np.ndarray) -> np.ndarray:
    """Overlapping Allan deviation of the series of block means ``z`` at ``tau`` (rounded to
    whole blocks; NaN below one block or beyond a third of the series)."""
    x = np.concatenate(([0.0], np.cumsum(np.asarray(z, dtype=float)))) * block_s
    out = np.full(np.shape(tau), np.nan)
    for i, t in enumerate(np.asarray(tau, dtype=float)):
        m = int(round(t / block_s))
        if m < 1 or 2 * m >= x.size - 1:
            continue
        d = x[2 * m:] - 2.0 * x[m:-m] + x[: -2 * m]
        out[i] = math.sqrt(float(np.mean(d * d)) / (2.0 * (m * block_s) ** 2))
    return out


def temperature_regression(ybar: np.ndarray, tbar: np.ndarray) -> dict:
    """The slow part of the signal against temperature: least squares of the differences of
    consecutive block means of the output on those of the temperature (no intercept), the
    coefficient (units of y per K) with its 95 % Student-t interval, t statistic and p-value,
    the temperature's span, and the share of the output's slow variance (its block means'
    variance about their mean) that the temperature term takes. ``ybar``, ``tbar``: block
    means of the same blocks (NaN blocks are left out)."""
    y = np.asarray(ybar, dtype=float)
    T = np.asarray(tbar, dtype=float)
    dy, dT = np.diff(y), np.diff(T)
    ok = np.isfinite(dy) & np.isfinite(dT)
    dy, dT = dy[ok], dT[ok]
    n = dy.size
    sxx = float(dT @ dT)
    if n < 4 or sxx <= 0:
        return {"skipped": "the temperature does not change" if n >= 4 else "too few blocks"}
    k = float(dT @ dy) / sxx
    r = dy - k * dT
    s2 = float(r @ r) / (n - 1)
    se = math.sqrt(s2 / sxx)
    q = float(stats.t.ppf(0.975, n - 1))
    tstat = k / se if se > 0 else math.inf
    p = float(2.0 * stats.t.sf(abs(tstat), n - 1))
    fin = np.isfinite(y) & np.isfinite(T)
    yc = y[fin] - np.mean(y[fin])
    Tc = T[fin] - np.mean(T[fin])
    var_y = float(np.mean(yc * yc))
    share = float(np.mean((k * Tc) ** 2) / var_y) if var_y > 0 else 0.0
    return {"coef": k, "coef_ci95": [k - q * se, k + q * se], "se": se, "t": tstat,
            "p_value": p, "dof": n - 1, "temp_span_K": float(np.ptp(T[np.isfinite(T)])),
            "slow_share": share}
