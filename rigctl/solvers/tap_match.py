"""Match detected taps (IMU timescale) to logged pulses (reference timescale).

Pure functions of numpy arrays; times in seconds. No I/O.

Neither side is assumed complete: pulses can be missed (hammer did not trigger, receiver dead
time) or extra (bounce, interference); taps can be missed (data loss) or extra (bumps with no
pulse). Equal counts are never assumed.

1. **Interval patterns.** Every (tap i, pulse j) pair proposes an offset ``d_ij = p_j - t_i``.
   Its support is the number of other taps within ``window_s`` of tap i that also find a
   pulse within ``pattern_tol_s`` after the same shift, i.e. how many of the local tap
   intervals the pulse intervals reproduce. Each tap keeps its best-supported pair if the
   support is at least ``min_support`` and unique.
2. **Time.** Each tap's predicted pulse time is ``t_i + L(t_i) + m(t_i)``: ``L`` a robust line
   through the offsets of the pattern-matched taps (``scipy.stats.siegelslopes``: the clock
   drift), ``m`` the median of those taps' deviations from the line within ``window_s`` (local
   wander; 0 where fewer than 3). The line comes first because a drift of D moves the offset
   by D * window_s across one window (2400 ppm x 120 s = 0.29 s on a real MPU-9150 pair,
   tests/data/mikov-mpu9150): a plain local median of the offsets would miss every tap near a
   window's edge by more than ``tolerance_s``. Pairs closer than ``tolerance_s`` are accepted
   one-to-one, nearest first.
3. **Outlier rule.** With local residual ``r_i`` = the offset less a robust line through all
   pairs and less the local median (within ``window_s``) of the deviations from that line, and
   ``sigma = 1.4826 MAD(r)``, a pair is an outlier if ``|r_i| > max(k sigma, floor_s)``
   (defaults k = 5, floor 1 ms).

Without sub-sample timing a tap's sample is 0..T after the tap (uniform), so its time is biased
late by T/2 with std T/sqrt(12); :func:`half_sample_correction` removes the bias.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def half_sample_correction(sample_time_s: np.ndarray, period_s: float) -> np.ndarray:
    """Tap time from its first-sample time: ``t = t_sample - T/2`` (mean of U(0, T) delay)."""
    return np.asarray(sample_time_s, dtype=float) - 0.5 * period_s


def robust_sigma(x: np.ndarray) -> float:
    """1.4826 * median absolute deviation."""
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def outlier_mask(residual_s: np.ndarray, k: float = 5.0, floor_s: float = 1e-3
                 ) -> tuple[np.ndarray, float]:
    """True where ``|r - median(r)| > max(k * 1.4826 MAD(r), floor_s)``; returns mask, limit."""
    r = np.asarray(residual_s, dtype=float)
    if r.size == 0:
        return np.zeros(0, bool), floor_s
    limit = max(k * robust_sigma(r), floor_s)
    return np.abs(r - np.median(r)) > limit, float(limit)


@dataclass
class MatchResult:
    """Matched pairs and what was left over (indices into the inputs)."""

    tap_index: np.ndarray  # (m,) int
    pulse_index: np.ndarray  # (m,) int
    offset_s: np.ndarray  # (m,) pulse - tap time, s
    local_residual_s: np.ndarray  # (m,) offset minus local median offset, s
    inlier: np.ndarray  # (m,) bool, passes the outlier rule
    outlier_limit_s: float
    unmatched_taps: np.ndarray  # taps with no pulse (spurious spikes, missed pulses)
    unmatched_pulses: np.ndarray  # pulses with no tap (extra pulses, taps lost)
    n_pattern_matched: int


def _pattern_candidates(t: np.ndarray, p: np.ndarray, window_s: float, tol_s: float,
                        min_support: int) -> tuple[np.ndarray, np.ndarray]:
    """Best pattern-supported pulse for each tap (-1 if none); returns pulse idx, support."""
    best = np.full(t.size, -1)
    support = np.zeros(t.size, int)
    for i, ti in enumerate(t):
        nb = t[(np.abs(t - ti) <= window_s) & (np.arange(t.size) != i)]
        if nb.size == 0:
            continue
        shifted = nb[None, :] + (p - ti)[:, None]  # (n_pulses, n_neighbours)
        pos = np.clip(np.searchsorted(p, shifted), 1, p.size - 1)
        dist = np.minimum(np.abs(p[pos] - shifted), np.abs(p[pos - 1] - shifted))
        score = (dist < tol_s).sum(axis=1)
        j = int(np.argmax(score))
        top = score[j]
        if top >= min(min_support, nb.size) and top >= 1 and (score == top).sum() == 1:
            best[i], support[i] = j, top
    return best, support


def _local_median(tq: np.ndarray, t: np.ndarray, d: np.ndarray, window_s: float
                  ) -> np.ndarray:
    out = np.full(tq.size, np.nan)
    for n, x in enumerate(tq):
        sel = np.abs(t - x) <= window_s
        if sel.sum() >= 3:
            out[n] = np.median(d[sel])
    return out


def match_taps(tap_time_s: np.ndarray, pulse_time_s: np.ndarray, *, tolerance_s: float = 0.05,
               window_s: float = 120.0, pattern_tol_s: float = 0.03, min_support: int = 3,
               outlier_k: float = 5.0, outlier_floor_s: float = 1e-3,
               debounce_s: float = 0.05) -> MatchResult:
    """Match taps (IMU seconds, after any half-sample correction) to pulses (reference s).

    Pulses less than ``debounce_s`` after the previous kept pulse are contact bounce (a
    software timeguard) and are left unmatched; the first edge of a burst is the tap's.
    """
    from scipy.stats import siegelslopes  # here, not at import: scipy.stats costs ~0.45 s of CPU

    t = np.asarray(tap_time_s, dtype=float)
    p_raw = np.asarray(pulse_time_s, dtype=float)
    order = np.argsort(p_raw, kind="stable")
    keep = np.ones(order.size, bool)
    last = -np.inf
    for n, x in enumerate(p_raw[order]):
        if x - last < debounce_s:
            keep[n] = False
        else:
            last = x
    order = order[keep]
    p = p_raw[order]
    empty = np.zeros(0, int)
    if t.size == 0 or p.size < 2:
        return MatchResult(empty, empty, np.zeros(0), np.zeros(0), np.zeros(0, bool),
                           outlier_floor_s, np.arange(t.size), np.arange(p.size), 0)
    def anchors(ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float] | None:
        """Pattern-matched taps (times, offsets) on the tap timescale ``ts`` and the robust
        line through their offsets; anchors that disagree with their neighbours by more than
        ``tolerance_s`` after the line is removed (an ambiguous pattern choice) are dropped."""
        best, _ = _pattern_candidates(ts, p, window_s, pattern_tol_s, min_support)
        idx = np.flatnonzero(best >= 0)
        if idx.size == 0:
            return None
        ta, da = t[idx], p[best[idx]] - t[idx]

        def line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
            if x.size >= 2 and np.ptp(x) > 0:
                s_, c_ = siegelslopes(y, x)
                return float(s_), float(c_)
            return 0.0, float(np.median(y))

        sl, ic = line(ta, da)
        dev = da - (ic + sl * ta)
        loc = _local_median(ta, ta, dev, window_s)
        ok = ~(np.abs(dev - np.where(np.isnan(loc), dev, loc)) > tolerance_s)
        sl, ic = line(ta[ok], da[ok])
        return ta[ok], da[ok], sl, ic

    first = anchors(t)
    if first is None:
        raise ValueError("no tap interval pattern matches the pulse intervals: check that "
                         "the recording holds tap groups and their pulses")
    ta, d_anchor, slope, intercept = first
    # a clock drift D stretches a tap interval L by D * L: beyond pattern_tol_s within one
    # window, the patterns are matched again on drift-corrected tap times
    if abs(slope) * window_s > pattern_tol_s:
        second = anchors(t * (1.0 + slope))
        if second is not None and second[0].size > ta.size:
            ta, d_anchor, slope, intercept = second
    loc = _local_median(t, ta, d_anchor - (intercept + slope * ta), window_s)
    pred = t + intercept + slope * t + np.where(np.isnan(loc), 0.0, loc)
    # one-to-one, nearest first
    ii, jj = np.nonzero(np.abs(p[None, :] - pred[:, None]) < tolerance_s)
    cost = np.abs(p[jj] - pred[ii])
    used_t, used_p = np.zeros(t.size, bool), np.zeros(p.size, bool)
    pairs = []
    for k in np.argsort(cost, kind="stable"):
        if not used_t[ii[k]] and not used_p[jj[k]]:
            used_t[ii[k]] = used_p[jj[k]] = True
            pairs.append((ii[k], jj[k]))
    pairs.sort()
    ti = np.array([a for a, _ in pairs], int)
    pj = np.array([b for _, b in pairs], int)
    d = p[pj] - t[ti]
    if ti.size >= 2 and np.ptp(t[ti]) > 0:
        s2, c2 = siegelslopes(d, t[ti])
    else:
        s2, c2 = 0.0, float(np.median(d)) if d.size else 0.0
    dev = d - (c2 + s2 * t[ti])
    loc = _local_median(t[ti], t[ti], dev, window_s)
    resid = dev - np.where(np.isnan(loc), 0.0, loc)
    out, limit = outlier_mask(resid, outlier_k, outlier_floor_s)
    return MatchResult(tap_index=ti, pulse_index=order[pj], offset_s=d, local_residual_s=resid,
                       inlier=~out, outlier_limit_s=limit,
                       unmatched_taps=np.flatnonzero(~used_t),
                       unmatched_pulses=np.setdiff1d(np.arange(p_raw.size), order[pj]),
                       n_pattern_matched=int(ta.size))


@dataclass
class VirtualTaps:
    """Group means of matched pairs ("virtual taps"), one row per group."""

    tap_time_s: np.ndarray
    pulse_time_s: np.ndarray
    offset_s: np.ndarray  # mean of (pulse - tap) in the group
    offset_sem_s: np.ndarray  # standard error of that mean
    count: np.ndarray


def virtual_taps(tap_time_s: np.ndarray, pulse_time_s: np.ndarray, gap_s: float = 30.0
                 ) -> VirtualTaps:
    """Average matched pairs in groups separated by more than ``gap_s``.

    The virtual tap time is the group's mean tap time, its pulse the mean pulse time; its error
    is the mean of the single errors (std / sqrt(n) for independent errors).
    """
    t = np.asarray(tap_time_s, float)
    p = np.asarray(pulse_time_s, float)
    o = np.argsort(t)
    t, p = t[o], p[o]
    cut = np.flatnonzero(np.diff(t) > gap_s) + 1
    rows = []
    for gt, gp in zip(np.split(t, cut), np.split(p, cut)):
        d = gp - gt
        sem = d.std(ddof=1) / np.sqrt(d.size) if d.size > 1 else np.nan
        rows.append((gt.mean(), gp.mean(), d.mean(), sem, d.size))
    arr = np.array(rows, dtype=float).reshape(-1, 5)
    return VirtualTaps(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4].astype(int))
