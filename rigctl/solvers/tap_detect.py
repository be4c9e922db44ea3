"""Tap detection in an accelerometer channel: first-difference detector and sub-sample onsets.

Pure functions of numpy arrays (SI units: m/s^2 and s). No I/O.

First-difference detector (Zhang et al. 2015): ``d_k = |a_{k+1} - a_k|`` on the tap-axis
accelerometer; an event is a cluster of ``d_k > k_sigma * sigma_d`` with ``sigma_d`` the
robust (1.4826 * MAD) standard deviation of the first difference. The tap sample is the first
sample of the rising edge: walking back from the first exceedance while the difference keeps
its sign and exceeds ``edge_sigma * sigma_d``, the first sample that differs from the quiet
baseline. Its time is 0..T after the tap (mean T/2; see ``tap_match.half_sample_correction``).

Sub-sample onset: around each event, fit ``y_k = b + A g(t_k - t0)`` over a window of samples
by variable projection (``b``, ``A`` linear least squares for each ``t0``; ``t0`` by a grid
then bounded Brent search), where ``g`` is the unit-peak sensor impulse response (zero for
negative argument): either configured (:class:`SecondOrderResponse`) or learned from the taps
themselves by stacking and aligning (:func:`learn_response`). Saturated samples are left out of the fit,
so clipped taps are timed from their unsaturated flanks.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

Template = Callable[[np.ndarray], np.ndarray]


@dataclass
class Detections:
    """First-difference detections (sample indices into the input arrays)."""

    index: np.ndarray  # (n,) int, first sample of the rising edge
    peak: np.ndarray  # (n,) m/s^2, signed peak deviation from the pre-tap baseline
    saturated: np.ndarray  # (n,) bool, any sample of the event at the saturation level
    sigma_diff: float  # m/s^2, robust std of the first difference
    threshold: float  # m/s^2


@dataclass
class Onsets:
    """Sub-sample onset fits: ``t0`` on the time axis given (s), with 1-sigma."""

    t0: np.ndarray  # (n,) s
    sigma_t0: np.ndarray  # (n,) s, from the fit's Jacobian and residual scale
    amplitude: np.ndarray  # (n,) m/s^2
    baseline: np.ndarray  # (n,) m/s^2
    rms_residual: np.ndarray  # (n,) m/s^2
    n_used: np.ndarray  # (n,) samples used (saturated ones excluded)


def robust_sigma(x: np.ndarray) -> float:
    """1.4826 * median absolute deviation (Gaussian-consistent std)."""
    x = np.asarray(x, dtype=float)
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def saturation_mask(a: np.ndarray, level: float | None = None) -> np.ndarray:
    """Samples at the saturation level. ``level`` (m/s^2) given, or auto: an extreme value
    (max or min) taken by at least two samples exactly, as clipping produces."""
    a = np.asarray(a, dtype=float)
    if level is not None:
        return np.abs(a) >= level * (1 - 1e-9)
    mask = np.zeros(a.shape, dtype=bool)
    for ext in (a.max(), a.min()):
        hit = a == ext
        if hit.sum() >= 2:
            mask |= hit
    return mask


def first_difference_detect(a: np.ndarray, *, k_sigma: float = 12.0, edge_sigma: float = 3.0,
                            min_separation: int = 30, threshold: float | None = None,
                            saturation_level: float | None = None) -> Detections:
    """Published first-difference tap detector on the tap-axis accelerometer ``a`` (m/s^2).

    ``threshold`` (m/s^2) overrides ``k_sigma * sigma_d``; exceedances closer than
    ``min_separation`` samples form one event.
    """
    a = np.asarray(a, dtype=float)
    diff = np.diff(a)
    sig = max(robust_sigma(diff), 1e-12)
    thr = threshold if threshold is not None else k_sigma * sig
    exceed = np.flatnonzero(np.abs(diff) > thr)
    sat = saturation_mask(a, saturation_level)
    if exceed.size == 0:
        z = np.zeros(0)
        return Detections(np.zeros(0, int), z, np.zeros(0, bool), sig, thr)
    starts = exceed[np.concatenate([[True], np.diff(exceed) > min_separation])]
    ends = np.append(exceed[np.flatnonzero(np.diff(exceed) > min_separation)], exceed[-1])
    idx, peak, satd = [], [], []
    for s, e in zip(starts, ends):
        sgn = np.sign(diff[s])
        k = s
        while k > 0 and np.sign(diff[k - 1]) == sgn and abs(diff[k - 1]) > edge_sigma * sig:
            k -= 1
        first = k + 1  # first sample that departs from the baseline
        base = np.median(a[max(0, k - 5):k + 1])
        seg = a[first:e + 2] - base
        j = int(np.argmax(np.abs(seg)))
        idx.append(first), peak.append(seg[j]), satd.append(bool(sat[first:e + 2].any()))
    return Detections(np.asarray(idx, int), np.asarray(peak), np.asarray(satd, bool), sig, thr)


@dataclass
class SecondOrderResponse:
    """Unit-peak impulse response of wn^2 / (s^2 + 2 zeta wn s + wn^2), 0 for t < 0."""

    natural_freq_hz: float
    damping: float

    def __call__(self, t: np.ndarray) -> np.ndarray:
        wn = 2 * np.pi * self.natural_freq_hz
        z = self.damping
        wd = wn * np.sqrt(1 - z * z)
        tp = np.arctan2(wd, z * wn) / wd
        peak = np.exp(-z * wn * tp) * np.sin(wd * tp)
        t = np.asarray(t, dtype=float)
        tt = np.maximum(t, 0.0)
        return np.where(t >= 0, np.exp(-z * wn * tt) * np.sin(wd * tt) / peak, 0.0)


def _windows(n: int, idx: np.ndarray, pre: int, post: int) -> list[np.ndarray]:
    return [np.arange(max(0, i - pre), min(n, i + post)) for i in idx]


def _profile(t: np.ndarray, y: np.ndarray, g: Template, t0: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each candidate t0: closed-form least squares of y = b + A g(t - t0); rss, A, b."""
    gm = g(t[None, :] - np.atleast_1d(t0)[:, None])
    n, sy, syy = t.size, y.sum(), y @ y
    sg, sgg, sgy = gm.sum(axis=1), (gm * gm).sum(axis=1), gm @ y
    det = n * sgg - sg * sg
    amp = np.where(det > 0, (n * sgy - sg * sy) / np.where(det > 0, det, 1.0), 0.0)
    b = (sy - amp * sg) / n
    rss = syy - b * sy - amp * sgy
    return rss, amp, b


def _fit_one(t: np.ndarray, y: np.ndarray, g: Template, t_lo: float, t_hi: float,
             period: float) -> tuple[float, float, float, float, float]:
    """Variable-projection fit of y = b + A g(t - t0); returns t0, sigma, A, b, rms."""
    from scipy.optimize import minimize_scalar  # here: the emulator imports this module (~0.17 s)

    grid = np.linspace(t_lo, t_hi, 41)
    j = int(np.argmin(_profile(t, y, g, grid)[0]))
    res = minimize_scalar(lambda x: float(_profile(t, y, g, np.array([x]))[0][0]),
                          bounds=(grid[max(j - 1, 0)], grid[min(j + 1, 40)]),
                          method="bounded", options={"xatol": period * 1e-6})
    t0 = float(res.x)
    rss0, amp, b = (float(v[0]) for v in _profile(t, y, g, np.array([t0])))
    dof = max(t.size - 3, 1)
    s2 = max(rss0, 0.0) / dof
    h = period * 1e-4  # Jacobian of the model by central differences in t0
    dg = (g(t - t0 - h) - g(t - t0 + h)) / (2 * h) * amp
    jac = np.column_stack([np.ones_like(t), g(t - t0), dg])
    try:
        cov = np.linalg.inv(jac.T @ jac) * s2
        sig = float(np.sqrt(max(cov[2, 2], 0.0)))
    except np.linalg.LinAlgError:
        sig = float("nan")
    return t0, sig, amp, b, float(np.sqrt(s2))


def fit_onsets(time_s: np.ndarray, a: np.ndarray, index: np.ndarray, template: Template, *,
               pre: int = 4, post: int = 20, saturated: np.ndarray | None = None,
               search: tuple[float, float] = (-2.5, 0.5)) -> Onsets:
    """Sub-sample tap onsets ``t0`` (s, on the ``time_s`` axis) around detections ``index``.

    ``time_s`` is each sample's time on the IMU's own timescale (counter / nominal rate, so
    dropped samples are handled); the fit uses samples ``index - pre .. index + post - 1``
    minus those in ``saturated``; ``t0`` is searched in ``time_s[index] + search * T``.
    """
    time_s = np.asarray(time_s, dtype=float)
    a = np.asarray(a, dtype=float)
    sat = np.zeros(a.shape, bool) if saturated is None else np.asarray(saturated, bool)
    period = float(np.median(np.diff(time_s)))
    out = np.full((6, len(index)), np.nan)
    for n, (i, w) in enumerate(zip(index, _windows(a.size, np.asarray(index), pre, post))):
        w = w[~sat[w]]
        if w.size < 5:
            continue
        ti = time_s[i]
        t0, sig, amp, b, rms = _fit_one(time_s[w], a[w], template, ti + search[0] * period,
                                        ti + search[1] * period, period)
        out[:, n] = (t0, sig, amp, b, rms, w.size)
    return Onsets(out[0], out[1], out[2], out[3], out[4], out[5])


def learn_response(time_s: np.ndarray, a: np.ndarray, index: np.ndarray, *,
                   saturated: np.ndarray | None = None, max_taps: int = 40,
                   natural_freq_hz: tuple[float, ...] = (6.0, 9.0, 13.0, 18.0, 25.0, 35.0, 45.0),
                   damping: tuple[float, ...] = (0.3, 0.5, 0.7, 0.9), pre: int = 4,
                   post: int = 20, rounds: int = 3) -> SecondOrderResponse:
    """Learn the sensor's response from the taps themselves (stacking and aligning).

    All taps share one unit-peak second-order response ``g`` (``natural_freq_hz``, ``damping``);
    each tap has its own ``t0``, ``A``, ``b``. Start from the best of a small grid of
    (fn, zeta) with each tap aligned by :func:`fit_onsets`, then refine every parameter jointly
    with ``scipy.optimize.least_squares`` on the stacked residuals of the ``max_taps``
    largest unsaturated taps. A free-form (spline) template is not used: with samples only
    once per T, any time warp periodic in T fits stacked taps equally well, so a free-form
    stack cannot fix sub-sample timing; a parametric response can.
    """
    time_s = np.asarray(time_s, dtype=float)
    a = np.asarray(a, dtype=float)
    index = np.asarray(index)
    sat = np.zeros(a.shape, bool) if saturated is None else np.asarray(saturated, bool)
    wins = [w for w in _windows(a.size, index, pre, post)]
    clean = np.array([not sat[w].any() for w in wins])
    amp = np.array([np.ptp(a[w]) for w in wins])
    order = np.argsort(-np.where(clean, amp, -np.inf))[:max_taps]
    order = order[clean[order]] if clean[order].sum() >= 3 else order
    sel = index[order]
    best = (np.inf, None, None)
    for fn in natural_freq_hz:
        for z in damping:
            on = fit_onsets(time_s, a, sel, SecondOrderResponse(fn, z), pre=pre, post=post,
                            saturated=sat)
            rss = np.nansum(on.rms_residual**2 * (on.n_used - 3))
            if rss < best[0]:
                best = (rss, (fn, z), on)
    _, (fn, z), on = best
    period = float(np.median(np.diff(time_s)))
    for _ in range(rounds):
        good = np.isfinite(on.t0)
        fn, z, done = _joint_fit(time_s, a, sat, sel[good], on.t0[good], on.amplitude[good],
                                 on.baseline[good], fn, z, pre, post, period)
        if done:
            break
        on = fit_onsets(time_s, a, sel, SecondOrderResponse(fn, z), pre=pre, post=post,
                        saturated=sat)
    return SecondOrderResponse(fn, z)


def _joint_fit(time_s: np.ndarray, a: np.ndarray, sat: np.ndarray, sel: np.ndarray,
               t0: np.ndarray, amp0: np.ndarray, b0: np.ndarray, fn0: float, z0: float,
               pre: int, post: int, period: float) -> tuple[float, float, bool]:
    """Joint least squares of (fn, zeta) and every tap's (t0, A, b); returns fn, zeta, converged."""
    from scipy.optimize import least_squares  # here: the emulator imports this module (~0.17 s)
    from scipy.sparse import lil_matrix

    m = sel.size
    ws = [w[~sat[w]] for w in _windows(a.size, sel, pre, post)]
    tcat = np.concatenate([time_s[w] for w in ws])
    ycat = np.concatenate([a[w] for w in ws])
    owner = np.concatenate([np.full(w.size, i) for i, w in enumerate(ws)])

    def resid(p: np.ndarray) -> np.ndarray:
        g = SecondOrderResponse(p[0], p[1])
        return ycat - p[2 + 2 * m + owner] - p[2 + m + owner] * g(tcat - p[2 + owner])

    x0 = np.concatenate([[fn0, z0], t0, amp0, b0])
    lo = np.concatenate([[0.5, 0.05], t0 - 2 * period, np.full(2 * m, -np.inf)])
    hi = np.concatenate([[1.0 / period, 0.99], t0 + 2 * period, np.full(2 * m, np.inf)])
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
    sparsity = lil_matrix((owner.size, x0.size), dtype=int)
    sparsity[:, :2] = 1
    rows = np.arange(owner.size)
    for k in range(3):
        sparsity[rows, 2 + k * m + owner] = 1
    res = least_squares(resid, x0, bounds=(lo, hi), x_scale="jac", jac_sparsity=sparsity,
                        xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=100)
    return float(res.x[0]), float(res.x[1]), bool(res.status > 0)
