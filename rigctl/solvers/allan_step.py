"""A step of the rate in a record too short for the excursion detector (pure functions of
arrays; docs/allan.md, "Detection limits: a rate step, a Gauss-Markov bump").

:mod:`rigctl.solvers.allan_excursions` judges window-mean differences against the record's own
robust Allan deviation, which needs 32 windows of 30 s: below 960 s it does not run, and the
self-check absorbs a step of any size into the terms (a single step adds an Allan variance
that grows with tau, as K's does). Here the noise's levels come from the fit instead.

**The statistic.** The generalized likelihood ratio for a step at an unknown time against a
Gaussian model of the record's ``N_COARSE`` group means y (covariance Sigma), the offset and a
ramp as nuisance (X; R is in the fitted model, so a ramp is no step)::

    z_k = s_k' P y / sqrt(s_k' P s_k),   P = Sigma^-1 - Sigma^-1 X (X' Sigma^-1 X)^-1 X' Sigma^-1

s_k the step at group k, k over ``EDGE`` .. 1 - ``EDGE`` of the record; the statistic is
max_k |z_k|, the step's estimate there z_k / sqrt(s_k' P s_k). Sigma: white rate noise
(N^2 / T_g on the diagonal, T_g the group length), flicker (one-sided PSD B^2 / (2 pi f),
stationary, its autocovariance from that spectrum on a circle ``CIRCLE`` times the record,
averaged over the groups), a rate random walk (K^2 min(t_a, t_b) from the record's start,
averaged) and white phase noise (Q^2: 2 Q^2 / T_g^2 on the diagonal, -Q^2 / T_g^2 beside it).

**The levels** are the fit's 95 % upper ends of Q, N, B and K (a term's bound where it is
one): levels estimated low would make noise look like a step; too high only costs power.
The step itself moves them (the fit's B and K grow with it), which is the test's main cost
against one that knows the noise: measured on 5-minute records with the default emulated
gyro's N and B, found in 94 of 100 at 12 B (B its bias instability), 28 at 8 B, none without
a step (the emulator's own records: 49 of 60 at 12 B, none of 60 without); the test that
knows N, B and K finds 6 B in 199 of 200 (benchmarks/allan_step_limit.py).

**Calibration.** The threshold is the 99 % point (``ALPHA``) of max_k |z_k| under no step,
from ``N_DRAWS`` draws of N(0, Sigma) with a fixed seed (the statistic's law depends on the
levels' ratios and the record's length, not on the data).

**The level must hold** (:func:`level_hold`). Under a large K or B the whitened weights of
z_k are local: z_k compares the few seconds either side of k, and an output that leaves its
level for a few seconds and comes back (a phone gyro dwelling on its quantized levels, a
short bump) reads as a step (a Galaxy S5's 5-minute windows: 21 of 207 beyond the threshold,
its two sides' means differing by 0-80 deg/h where the "step" was 240-600 deg/h). A step
found is therefore reported only when the least-squares step at that k, equal weights on
every group mean, offset and ramp beside it, is significant against the stationary part of
the noise (Sigma_0: Sigma without the random walk) at the same alpha, with z_k's sign::

    found = max_k |z_k| > threshold  and  |z_hold| > z_(1 - alpha/2)  and  z_hold z_k > 0

An intersection of two tests: under the model its false-alarm probability is at most that
of the first, alpha (the second only removes alarms), and a step that holds passes both
(measured: the same 0 / 4 / 28 / 94 of 100 at 3 / 6 / 8 / 12 B, z_hold 3.8 or more where
the first test fired).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_triangular
from .distributions import norm

#: the group means the test works on (a step's information is at low frequencies)
N_COARSE = 150
#: the step time is scanned over this share of the record (each end left out)
EDGE = 0.05
#: the flicker's autocovariance: its spectrum on a circle this many times the record
CIRCLE = 8
#: false-alarm probability per axis (as the excursion detector's)
ALPHA = 0.01
#: draws of the statistic under no step for its 1 - ALPHA point (fixed seed)
N_DRAWS = 2000
#: each group's blocks are averaged into sub-blocks, at least this many per group
SUB_PER_GROUP = 8
#: fewer blocks than this: no test (a group must hold at least one block)
MIN_BLOCKS = N_COARSE


def flicker_acov(nb: int, b_si: float, block_s: float, circle: int = CIRCLE) -> np.ndarray:
    """Autocovariance at block lags 0 .. circle nb - 1 of flicker rate noise of level ``b_si``
    (one-sided PSD B^2 / (2 pi f), no power at f = 0) sampled as means of ``block_s`` blocks,
    periodic over circle x nb blocks (SI^2). E|X_f|^2 = S(f) n / (2 dt) for the n-point DFT,
    the Nyquist bin half that (its real part only); the autocovariance is their inverse DFT / n."""
    nc = circle * nb
    f = np.fft.rfftfreq(nc, block_s)
    s = np.zeros(f.size)
    s[1:] = b_si ** 2 / (2.0 * math.pi * f[1:])
    p = s * nc / (2.0 * block_s)
    if nc % 2 == 0:
        p[-1] /= 2.0
    return np.fft.irfft(p, nc) / nc


def group_sigma(nb: int, block_s: float, n_si: float, b_si: float, k_si: float,
                q_si: float = 0.0, n_groups: int = N_COARSE, circle: int = CIRCLE) -> np.ndarray:
    """Covariance (SI^2) of the means of ``n_groups`` equal groups of ``nb`` // n_groups blocks
    of ``block_s`` s of white (N, u sqrt(s)) + flicker (B, u) + random-walk (K, u / sqrt(s))
    rate noise and white phase noise (Q, u s): the module docstring's Sigma."""
    m = nb // n_groups
    tg = m * block_s
    c = flicker_acov(nb, b_si, block_s, circle)
    lags = np.arange(-(m - 1), m)
    w = (m - np.abs(lags)) / m ** 2
    cb = (c[np.abs(np.arange(n_groups)[:, None] * m + lags[None, :])] * w).sum(axis=1)
    i = np.arange(n_groups)
    sig = cb[np.abs(i[:, None] - i[None, :])]
    sig = sig + np.eye(n_groups) * n_si ** 2 / tg
    # the random walk as block values r_a = sum_{j <= a} e_j, Var e = K^2 dt: Cov(r_a, r_b) =
    # K^2 dt (min(a, b) + 1); group means: K^2 dt (I m + (m + 1) / 2) across groups I < J,
    # K^2 dt (I m + (m + 1)(2m + 1) / (6m)) within group I
    base = i * m + (m + 1) / 2.0
    rw = np.minimum(base[:, None], base[None, :])
    rw[i, i] = i * m + (m + 1) * (2 * m + 1) / (6.0 * m)
    sig = sig + k_si ** 2 * block_s * rw
    if q_si > 0:  # white phase noise x (Var x = Q^2): group mean (x_end - x_start) / T_g
        sig = sig + (q_si / tg) ** 2 * (2.0 * np.eye(n_groups) - np.eye(n_groups, k=1)
                                         - np.eye(n_groups, k=-1))
    return sig


class StepGLR:
    """The generalized likelihood ratio for a step at an unknown time against N(X beta, sigma)
    (module docstring); ``trend``: the ramp in X beside the offset."""

    def __init__(self, sigma: np.ndarray, trend: bool = True, edge: float = EDGE):
        n = sigma.shape[0]
        self.n = n
        self.chol = np.linalg.cholesky(sigma)
        x = [np.ones(n)] + ([np.linspace(-1.0, 1.0, n)] if trend else [])
        xw = solve_triangular(self.chol, np.column_stack(x), lower=True)
        self.q = np.linalg.qr(xw)[0]
        self.ks = np.arange(int(edge * n), n - int(edge * n) + 1)
        s = (np.arange(n)[:, None] >= self.ks[None, :]).astype(float)
        w = solve_triangular(self.chol, s, lower=True)
        w -= self.q @ (self.q.T @ w)
        self.info = np.sum(w * w, axis=0)  # s_k' P s_k
        self.w = w / np.sqrt(self.info)

    def z(self, y: np.ndarray) -> np.ndarray:
        """z_k of each row of ``y`` (group means)."""
        yw = solve_triangular(self.chol, np.atleast_2d(y).T, lower=True)
        yw -= self.q @ (self.q.T @ yw)
        return (self.w.T @ yw).T

    def stat(self, y: np.ndarray) -> np.ndarray:
        """max_k |z_k| of each row of ``y``."""
        return np.max(np.abs(self.z(y)), axis=1)

    def null_point(self, alpha: float = ALPHA, draws: int = N_DRAWS, seed: int = 1) -> float:
        """The 1 - alpha point of :meth:`stat` under no step (draws of N(0, sigma))."""
        # y = L e under no step: the whitened, projected data are e less its part in X, and
        # the columns of w are orthogonal to X already, so z = w' e
        e = np.random.default_rng(seed).standard_normal((self.n, draws))
        return float(np.quantile(np.max(np.abs(self.w.T @ e), axis=0), 1.0 - alpha))

    def sd_at(self, k: int) -> float:
        """sd of the step's estimate at group k (known time; SI)."""
        return float(1.0 / math.sqrt(self.info[np.searchsorted(self.ks, k)]))


def group_means(y: np.ndarray, n_groups: int = N_COARSE) -> np.ndarray:
    """Means of n_groups equal groups of ``y`` (the last len(y) mod n_groups values left out)."""
    m = y.size // n_groups
    return np.asarray(y[: m * n_groups], dtype=float).reshape(n_groups, m).mean(axis=1)


def step_test(ybar: np.ndarray, block_s: float, levels: dict[str, float],
              alpha: float = ALPHA) -> dict:
    """The step test of the module docstring on the block means ``ybar`` (``block_s`` s each,
    SI) with the noise ``levels`` {Q, N, B, K} (SI; missing terms 0). Returns {"tested",
    "found", "z", "threshold_z", "t_s" (the step's time from the first block), "size_si" (its
    estimate there), "sd_si" (that estimate's sd), "beyond" (max |z| beyond its threshold),
    "hold" (:func:`level_hold` at that time: "size_si", "sd_si", "z", "threshold_z", "holds"),
    "alpha", "levels_si", "method"}; "found" is "beyond" and "holds" together. tested False
    (with "skipped") when there are fewer than MIN_BLOCKS blocks."""
    y = np.asarray(ybar, dtype=float)
    y = y[np.isfinite(y)]
    out: dict = {"tested": False, "found": False, "alpha": alpha,
                 "levels_si": {t: float(levels.get(t, 0.0)) for t in ("Q", "N", "B", "K")},
                 "method": "likelihood ratio for a step at an unknown time against the fit's "
                           "noise (its 95 % upper ends of Q, N, B, K), the offset and a ramp "
                           f"as nuisance, on {N_COARSE} group means; its {1 - alpha:.0%} point "
                           "under no step by simulation; found only where the level holds: "
                           "the least-squares step there (equal weights, offset and ramp "
                           "beside it) significant at the same alpha against the noise "
                           "without its random walk"}
    if y.size < MIN_BLOCKS:
        out["skipped"] = f"{y.size} blocks: fewer than {MIN_BLOCKS}"
        return out
    lv = out["levels_si"]
    # N_COARSE groups of m blocks (fewer than N_COARSE blocks left out at the end), each
    # averaged into sub-blocks of k blocks, k the largest divisor of m that leaves at least
    # SUB_PER_GROUP of them: the flicker's autocovariance on a circle of CIRCLE x the
    # sub-blocks, not of every sample (what that leaves out, the flicker inside a sub-block,
    # is about 0.1 % of a group mean's variance)
    m = y.size // N_COARSE
    y = y[: m * N_COARSE]
    k = next(d for d in range(max(1, m // SUB_PER_GROUP), 0, -1) if m % d == 0)
    sub = y.reshape(-1, k).mean(axis=1)
    sub_s = block_s * k
    glr = StepGLR(group_sigma(sub.size, sub_s, lv["N"], lv["B"], lv["K"], lv["Q"]))
    thr = glr.null_point(alpha)
    g = group_means(sub)
    z = glr.z(g)[0]
    i = int(np.argmax(np.abs(z)))
    beyond = bool(abs(z[i]) > thr)
    k = int(glr.ks[i])
    sd = 1.0 / math.sqrt(glr.info[i])
    tg = m * block_s
    hold = level_hold(g, k, group_sigma(sub.size, sub_s, lv["N"], lv["B"], 0.0, lv["Q"]),
                      alpha)
    holds = bool(abs(hold["z"]) > hold["threshold_z"] and hold["z"] * z[i] > 0)
    hold.update({"holds": holds, "size_si": hold.pop("d_si")})
    out.update({"tested": True, "found": beyond and holds, "z": float(z[i]),
                "threshold_z": thr, "beyond": beyond, "t_s": k * tg,
                "size_si": float(z[i]) * sd, "sd_si": sd, "hold": hold})
    return out


def level_hold(g: np.ndarray, k: int, sigma0: np.ndarray, alpha: float = ALPHA,
               trend: bool = True) -> dict:
    """Does the level hold on both sides of group k? The least-squares step at k with equal
    weights on every group mean g (SI), the offset and (``trend``) a ramp t beside it::

        d = c' g,  c' the step's row of (X_k' X_k)^-1 X_k',  X_k = [1, s_k, t]

        z_hold = d / sqrt(c' Sigma_0 c)

    Sigma_0 the stationary part of the noise (white, flicker, white phase: the random walk
    left out). Equal weights make d the difference of the two sides' means: a level that
    moves for a few seconds and comes back shifts it by its size x its duration / the side's
    length, where the GLR's whitened weights, local under a large K or B, read it as a step.
    Returns {"d_si", "sd_si", "z", "threshold_z"} (threshold: the two-sided 1 - alpha point
    of N(0, 1), the step's time taken as known)."""
    n = g.size
    cols = [np.ones(n), (np.arange(n) >= k).astype(float)]
    if trend:
        cols.append(np.linspace(-1.0, 1.0, n))
    c = np.linalg.pinv(np.column_stack(cols))[1]
    d = float(c @ g)
    sd = math.sqrt(float(c @ sigma0 @ c))
    return {"d_si": d, "sd_si": sd, "z": d / sd, "threshold_z": float(norm.isf(alpha / 2.0))}
