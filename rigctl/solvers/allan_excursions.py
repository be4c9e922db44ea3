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

    E_r[ min(1, 2 M Phi(-z* r)) ] = ALPHA / n_scales,   r^2 ~ chi2(nu) / nu.

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
from scipy.optimize import brentq
from scipy.stats import chi2, norm

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


@lru_cache(maxsize=4096)
def threshold(m: int, nu: float, alpha: float) -> float:
    """z* with E_r[min(1, 2 m Phi(-z* r))] = alpha, r^2 ~ chi2(nu)/nu (module docstring);
    nu = inf: the plain Bonferroni threshold Phi^-1(1 - alpha / (2 m))."""
    if not math.isfinite(nu) or nu > 1e6:
        return float(norm.isf(alpha / (2.0 * m)))
    q = (np.arange(_R_POINTS) + 0.5) / _R_POINTS
    r = np.sqrt(chi2.ppf(q, nu) / nu)

    def excess(z: float) -> float:
        return float(np.mean(np.minimum(1.0, 2.0 * m * norm.sf(z * r)))) - alpha

    lo = float(norm.isf(alpha / (2.0 * m)))
    hi = lo
    while excess(hi) > 0:
        hi *= 1.5
        if hi > 1e6:
            return math.inf
    return float(brentq(excess, lo * 0.5, hi, xtol=1e-4))


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
    "robust_adev_si" (s(L)/sqrt(2) per scale), "edges" [{"t_s", "z", "L_s", "threshold_z",
    "stage"}], "excursions" [{"start_s", "end_s", "duration_s", "size_si", "kind" ("bump",
    "to the start", "to the end", "level shift"), "z_start", "z_end"}]} in s from the first
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
                           "allowing for the spread's estimation error"}
    Ls = scales(n, block_s, min_s, max_fraction)
    if not Ls:
        out["skipped"] = (f"the record ({t_rec:.0f} s) is shorter than {min_s / max_fraction:.0f} s "
                          f"(windows of {min_s:g} s need at least {1 / max_fraction:g} of them)")
        return out
    scans = [step_scan(y, L) for L in Ls]
    a_scale = alpha / len(Ls)
    for sc in scans:
        sc["thr"] = threshold(int(sc["t"].size), round(sc["nu"], 3), a_scale) \
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
        thr = threshold(m, round(sc["nu"], 3), 2.0 * a_scale)  # one-sided: alpha, not alpha/2
        zz = np.where(sel, sign * z, 0.0)
        for t, v in _runs(zz, thr, ts, sc["L"]):
            if v > 0 and not any(abs(f["t"] - t) <= max(f["L"], sc["L"]) for f in found):
                found.append({"t": t, "z": float(sign * v), "L": sc["L"], "thr": thr,
                              "step": float(sign * v * sc["spread"])})
    return found
