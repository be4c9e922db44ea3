"""IMU clock model: sample counter -> reference time, by robust regression on matched taps.

Pure functions of numpy arrays; times in s. No I/O.

Model, with ``x = (n - n_ref) / f_nom`` the IMU's own elapsed time (s) at counter ``n``::

    t_ref(n) = c0 + (1 + d) x + w(x) + T_nom * sum_k s_k H(n - b_k)

* ``c0``: reference time at the centring counter ``n_ref`` (s); offset at counter 0 is
  ``c0 - (1 + d) n_ref / f_nom``.
* ``d``: drift (reported in ppm, ``d * 1e6``); positive = the IMU clock is slow (its counts
  last longer than nominal, so fewer samples than nominal are recorded). With a wander
  term, ``d`` is the drift at the centring counter ``n_ref`` (mean of the matched taps).
* ``w(x)``: optional wander: ``"quadratic"`` ``q x^2``, or ``"piecewise"`` linear hinges
  ``sum_j r_j max(0, x - x_j)`` at given knots (rate changes, ppm-like).
* ``s_k``: whole-sample steps at counters ``b_k`` where samples were lost without the counter
  showing it (found from jumps in the timing residual). Counter gaps need no term: the
  counter itself carries them.

Fit: ``scipy.optimize.least_squares`` with a ``soft_l1`` (or ``huber``) loss, scale
``f_scale`` = robust residual sigma; outlier rule ``|r| > max(k sigma_MAD, floor)``; final
ordinary least squares on the inliers gives the covariance ``s^2 (X^T X)^-1`` with
``s^2 = RSS / (n - p)``; 95 % half-widths use Student t with ``n - p`` degrees of freedom.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from .distributions import t as student_t

from rigctl.solvers.tap_match import outlier_mask, robust_sigma


def counter_gaps(counter: np.ndarray) -> list[tuple[int, int, int]]:
    """Dropped samples visible in the counter: (row index after the gap, first missing
    counter value, number missing) for every step larger than 1."""
    c = np.asarray(counter, dtype=np.int64)
    step = np.diff(c)
    idx = np.flatnonzero(step != 1)
    return [(int(i + 1), int(c[i] + 1), int(step[i] - 1)) for i in idx]


@dataclass
class ClockFit:
    """Fitted IMU clock; see the module docstring for the model."""

    rate_hz: float
    n_ref: float
    coef: np.ndarray  # [c0 (s), d (-), wander terms...]; t = x + [1, x, ...] @ coef
    cov: np.ndarray
    wander: str | None
    knots_s: np.ndarray
    steps: list[tuple[float, int]]  # (counter after which samples were lost, n samples)
    step_brackets: list[tuple[float, float]]  # counter interval holding each step
    residual_s: np.ndarray  # per input pair, pulse minus model
    inlier: np.ndarray
    outlier_limit_s: float
    dof: int
    counter_gaps: list[tuple[int, int, int]] = field(default_factory=list)

    @property
    def drift_ppm(self) -> float:
        return float(self.coef[1] * 1e6)

    @property
    def drift_sigma_ppm(self) -> float:
        return float(np.sqrt(self.cov[1, 1]) * 1e6)

    @property
    def offset_s(self) -> float:
        """Reference time of counter 0 (s), linear part (wander terms excluded)."""
        return float(self.coef[0] - (1 + self.coef[1]) * self.n_ref / self.rate_hz)

    @property
    def offset_sigma_s(self) -> float:
        g = np.zeros(self.coef.size)
        g[0], g[1] = 1.0, -self.n_ref / self.rate_hz
        return float(np.sqrt(g @ self.cov @ g))

    @property
    def t95(self) -> float:
        """Student-t factor for 95 % two-sided intervals."""
        return float(student_t.ppf(0.975, max(self.dof, 1)))

    @property
    def residual_std_s(self) -> float:
        return float(np.std(self.residual_s[self.inlier], ddof=1)) if self.inlier.sum() > 1 else 0.0

    def corrected_counter(self, counter: np.ndarray) -> np.ndarray:
        """Counter with the whole-sample steps found from the residual added in."""
        n = np.asarray(counter, dtype=float).copy()
        for b, k in self.steps:
            n = n + k * (n > b)
        return n

    def time_of_counter(self, counter: np.ndarray) -> np.ndarray:
        """Reference time (s) of IMU counter value(s), fractional allowed."""
        n = self.corrected_counter(counter)
        x = (n - self.n_ref) / self.rate_hz
        return x + _design(x, self.wander, self.knots_s) @ self.coef


def _design(x: np.ndarray, wander: str | None, knots_s: np.ndarray) -> np.ndarray:
    cols = [np.ones_like(x), x]
    if wander == "quadratic":
        cols.append(x * x)
    elif wander == "piecewise":
        cols += [np.maximum(0.0, x - k) for k in knots_s]
    elif wander is not None:
        raise ValueError(f"unknown wander model {wander!r}")
    return np.column_stack(cols)


def _robust_fit(x: np.ndarray, y: np.ndarray, wander: str | None, knots: np.ndarray, loss: str,
                k: float, floor_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Robust fit of z = y - x = c0 + d x + w(x) (small numbers); returns coef, resid, inl."""
    a = _design(x, wander, knots)
    z = y - x
    c_ols, *_ = np.linalg.lstsq(a, z, rcond=None)
    scale = max(robust_sigma(z - a @ c_ols), floor_s / 5)
    from scipy.optimize import least_squares  # here: importing scipy.optimize costs ~0.5 s of CPU,
    # which every command that imports rigctl.analysis.sync (``rigctl --help`` too) paid before

    res = least_squares(lambda c: a @ c - z, c_ols, loss=loss, f_scale=scale)
    r = z - a @ res.x
    out, limit = outlier_mask(r, k, floor_s)
    inl = ~out
    c, *_ = np.linalg.lstsq(a[inl], z[inl], rcond=None)
    return c, z - a @ c, inl, limit


def fit_clock(counter: np.ndarray, ref_time_s: np.ndarray, rate_hz: float, *,
              wander: str | None = None, knots_s: np.ndarray | None = None,
              loss: str = "soft_l1", outlier_k: float = 5.0, outlier_floor_s: float = 1e-3,
              detect_steps: bool = True, max_steps: int = 3, step_min_sigma: float = 8.0,
              gap_counter: np.ndarray | None = None, sigma_floor_s: float = 0.0) -> ClockFit:
    """Fit the IMU clock to matched (fractional counter, reference time) pairs.

    ``counter``: each matched tap's position in IMU samples (fractional, on the recorded
    counter); ``ref_time_s``: its pulse time. ``gap_counter``: the recording's full counter
    array, only to report counter gaps. With ``detect_steps``, a step in the residual between
    two consecutive taps, of at least ``step_min_sigma`` standard errors and within 0.3 sample
    of a whole number of samples, is taken as lost samples the counter did not show
    (greedy, at most ``max_steps``); the step is placed mid-way between the two taps and the
    counter interval between them reported as its bracket. ``sigma_floor_s``: the smallest
    timing error per pair the data can have (e.g. T / sqrt(12) for whole-sample tap times);
    the residual scale ``s`` is never taken below it, so pairs that happen to agree exactly
    (whole-sample times on both sides: two real MPU-9150s of tests/data/mikov-mpu9150 gave 22
    identical offsets) do not give a drift of 0 +- 0 ppm.
    """
    n = np.asarray(counter, dtype=float)
    y = np.asarray(ref_time_s, dtype=float)
    o = np.argsort(n)
    n, y = n[o], y[o]
    knots = np.asarray(knots_s if knots_s is not None else [], dtype=float)
    n_ref = float(np.round(np.mean(n)))
    period = 1.0 / rate_hz
    steps: list[tuple[float, int]] = []
    brackets: list[tuple[float, float]] = []

    def corrected(nn: np.ndarray) -> np.ndarray:
        out = nn.copy()
        for b, k in steps:
            out = out + k * (nn > b)
        return out

    if n.size < 3:
        raise ValueError("need at least 3 matched taps to fit a clock")
    coef, r, inl, limit = _robust_fit((corrected(n) - n_ref) / rate_hz, y, wander, knots, loss,
                                      outlier_k, outlier_floor_s)
    while detect_steps and len(steps) < max_steps:
        cand = _best_step(n, r, period)
        if cand is None:
            break
        n_lo, n_hi, step_s, sig = cand
        k = int(np.round(step_s / period))
        if k == 0 or abs(step_s - k * period) > 0.3 * period or abs(step_s) < step_min_sigma * sig:
            break
        steps.append((0.5 * (n_lo + n_hi), k))
        brackets.append((n_lo, n_hi))
        coef, r, inl, limit = _robust_fit((corrected(n) - n_ref) / rate_hz, y, wander, knots,
                                          loss, outlier_k, outlier_floor_s)
    a = _design((corrected(n) - n_ref) / rate_hz, wander, knots)[inl]
    dof = int(a.shape[0] - a.shape[1])
    s2 = max(float(r[inl] @ r[inl]) / max(dof, 1), float(sigma_floor_s) ** 2)
    cov = np.linalg.inv(a.T @ a) * s2
    resid = np.empty_like(r)
    inlier = np.empty_like(inl)
    resid[o], inlier[o] = r, inl
    gaps = counter_gaps(gap_counter) if gap_counter is not None else []
    return ClockFit(rate_hz, n_ref, coef, cov, wander, knots, steps, brackets, resid, inlier,
                    limit, dof, gaps)


def _best_step(n: np.ndarray, r: np.ndarray, period: float
               ) -> tuple[float, float, float, float] | None:
    """Best single step (between consecutive taps) in residuals r(n) with a refitted line."""
    best = None
    x = (n - n.mean()) * period
    for i in range(2, n.size - 2):  # at least 2 taps on each side
        if n[i] == n[i - 1]:
            continue
        a = np.column_stack([np.ones_like(x), x, (np.arange(n.size) >= i).astype(float)])
        c, *_ = np.linalg.lstsq(a, r, rcond=None)
        rss = float(np.sum((r - a @ c) ** 2))
        if best is None or rss < best[0]:
            dof = max(n.size - 3, 1)
            sig = np.sqrt(np.linalg.inv(a.T @ a)[2, 2] * rss / dof)
            best = (rss, n[i - 1], n[i], float(c[2]), float(sig))
    return None if best is None else best[1:]


def sample_count_check(counter_start: float, counter_end: float, ref_start_s: float,
                       ref_end_s: float, rate_hz: float, lost_between: int = 0) -> dict:
    """Expected vs recorded sample count between two (virtual) taps, as the paper's check.

    expected = (t_end - t_start) * f_nom; counted = counter difference (samples the IMU
    clock produced); recorded = counted - samples lost in between.
    """
    expected = (ref_end_s - ref_start_s) * rate_hz
    counted = counter_end - counter_start
    return {"span_s": ref_end_s - ref_start_s, "expected_samples": expected,
            "counted_samples": counted, "recorded_samples": counted - lost_between,
            "expected_minus_counted": expected - counted,
            "implied_drift_ppm": (expected / counted - 1.0) * 1e6 if counted else float("nan")}
