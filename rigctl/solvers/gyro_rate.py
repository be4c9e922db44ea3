"""Gyro rate test (docs/methods.md A4): forward/reverse pairs -> scale, misalignment and drift.

Model (A2): W = w0 + M_g w, with w the true body rate (Earth rate + table rate), M_g the
scale (diagonal) and misalignment (off-diagonal; row i = output axis, column j = input axis).

The table spins at +r and then -r about one axis. With w_+ = e + r, w_- = e - r (e: Earth rate
in the body, r: table rate in the body, both segment means):

    half-difference  d = (W_+ - W_-)/2 = M_g (w_+ - w_-)/2            -> scale, misalignment
    half-sum         s = (W_+ + W_-)/2 = w0 + M_g (w_+ + w_-)/2       -> drift w0 (Earth removed)

Per output axis i the 2P numbers [d_i; s_i] of the P pairs are one generalised least-squares
problem in (w0_i, M_i.):

    d_{p,i} = sum_j M_ij r_{p,j},    s_{p,i} = w0_i + sum_j M_ij e_{p,j},

with the covariance of [d; s] = T Sigma_i T^T, T the (2P, K) half-difference / half-sum matrix
and Sigma_i the covariance of axis i's K segment means (diag(s^2) for independent means:
Var(d_p) = Var(s_p) = (s_+^2 + s_-^2)/4, Cov(d_p, s_p) = (s_+^2 - s_-^2)/4; full under
time-correlated noise). dof = 2P - 4 per axis; the covariance of w0 and M_i. comes out of the
same fit.

Rate-dependent residuals of d and s (per pair and rate) are kept in ``extra["rate_residuals"]``:
even errors in the rate (scale asymmetry, rate^2) appear in s, odd ones (rate^3) in d.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..sensor_axes import axis_name
from .calibration_result import CalibrationResult, fit_linear
from .segments import SegmentTable

AXES = ("x", "y", "z")


def gyro_full_names() -> list[str]:
    """Names: drift w0 (rad/s) per axis, then M_g row-major (dimensionless)."""
    return [f"gyro_bias_{a}_rad_s" for a in AXES] + [f"gyro_M_{a}{b}_ratio" for a in AXES for b in AXES]


def gyro_columns(seg: SegmentTable) -> tuple[NDArray[np.float64], list[str]]:
    """(K, 3, 12) regressors of W = w0 + M_g w_ref for the gyro channels, and the names."""
    K = len(seg)
    X = np.zeros((K, 3, 12))
    for i in range(3):
        X[:, i, i] = 1.0
        X[:, i, 3 + 3 * i: 6 + 3 * i] = seg.w_ref
    return X, gyro_full_names()


def pair_forward_reverse(w_table: ArrayLike, rel_tol: float = 0.02) -> list[tuple[int, int]]:
    """Pairs (k_forward, k_reverse) of segments whose table rates are opposite.

    Args:
        w_table: (K, 3) table-induced body rate of each segment, rad/s (zero for static).
        rel_tol: |w_k + w_l| <= rel_tol * |w_k| to pair.

    The forward member is the one with the positive component along its dominant axis.
    """
    wt = np.asarray(w_table, dtype=np.float64)
    mag = np.linalg.norm(wt, axis=1)
    used: set[int] = set()
    pairs = []
    for k in np.argsort(-mag, kind="stable"):
        if mag[k] == 0 or k in used:
            continue
        cand = [l for l in range(len(wt)) if l != k and l not in used
                and np.linalg.norm(wt[k] + wt[l]) <= rel_tol * mag[k]]
        if not cand:
            continue
        l = min(cand, key=lambda m: np.linalg.norm(wt[k] + wt[m]))
        ax = int(np.argmax(np.abs(wt[k])))
        pairs.append((int(k), int(l)) if wt[k, ax] > 0 else (int(l), int(k)))
        used.update((int(k), int(l)))
    return sorted(pairs)


def calibrate_gyro_rate(w_meas: ArrayLike, w_sigma: ArrayLike, w_ref: ArrayLike,
                        w_table: ArrayLike, w_cov: ArrayLike | None = None) -> CalibrationResult:
    """Forward/reverse rate test: scale, misalignment and drift with the full covariance.

    Args:
        w_meas: (K, 3) measured mean rates of the rate segments, rad/s.
        w_sigma: (K, 3) their standard uncertainties, rad/s.
        w_ref: (K, 3) true mean body rates (Earth + table), rad/s.
        w_table: (K, 3) the table-induced part of w_ref, rad/s (used to pair segments).
        w_cov: (3, K, K) covariance of each axis' K means (default diag(w_sigma^2)).

    Returns:
        CalibrationResult with names :func:`gyro_full_names`; ``extra`` holds "M" (3x3),
        "drift_rad_s" (3,), "pairs" and "rate_residuals" (per pair: axis, rate, d and s residuals
        and their sigma, rad/s).
    """
    W = np.asarray(w_meas, dtype=np.float64)
    S = np.asarray(w_sigma, dtype=np.float64)
    wr = np.asarray(w_ref, dtype=np.float64)
    pairs = pair_forward_reverse(w_table)
    names = gyro_full_names()
    warnings = []
    if 2 * len(pairs) < len(W):
        warnings.append(f"{len(W) - 2 * len(pairs)} rate segments without an opposite partner were ignored")
    if not pairs:
        return CalibrationResult(method="gyro_rate", names=names, values=np.full(12, np.nan),
                                 covariance=np.full((12, 12), np.nan), dof=0, chi2=float("nan"),
                                 status="underdetermined", warnings=warnings + ["no forward/reverse pairs"])
    kp = np.array([p[0] for p in pairs])
    km = np.array([p[1] for p in pairs])
    P, K = len(pairs), len(W)
    Tm = np.zeros((2 * P, K))
    Tm[np.arange(P), kp], Tm[np.arange(P), km] = 0.5, -0.5
    Tm[P + np.arange(P), kp], Tm[P + np.arange(P), km] = 0.5, 0.5
    r = (wr[kp] - wr[km]) / 2.0
    e = (wr[kp] + wr[km]) / 2.0
    X = np.zeros((2 * P, 4))
    X[:P, 1:] = r
    X[P:, 0] = 1.0
    X[P:, 1:] = e
    values = np.full(12, np.nan)
    cov = np.zeros((12, 12))
    chi2, dof, status = 0.0, 0, "ok"
    d_res, s_res, sd = np.zeros((P, 3)), np.zeros((P, 3)), np.zeros((P, 3))
    nres = np.zeros((2 * P, 3))
    for i in range(3):
        Si = np.diag(S[:, i] ** 2) if w_cov is None else np.asarray(w_cov, dtype=np.float64)[i]
        C = Tm @ Si @ Tm.T
        sig = np.sqrt(np.diag(C))
        fit = fit_linear(X, Tm @ W[:, i], sig, [names[i]] + names[3 + 3 * i: 6 + 3 * i],
                         method="gyro_rate_axis", rescale_if_poor=False, cov=C)
        idx = [i, 3 + 3 * i, 4 + 3 * i, 5 + 3 * i]
        values[idx] = fit.values
        cov[np.ix_(idx, idx)] = fit.covariance
        d_res[:, i], s_res[:, i] = fit.residuals[:P], fit.residuals[P:]
        sd[:, i] = sig[:P]
        nres[:, i] = fit.normalized_residuals
        chi2 += fit.chi2
        dof += fit.dof
        if fit.status != "ok":
            status = fit.status
            warnings.append(f"{axis_name('gyro', i)}: " + "; ".join(fit.warnings))
    res = CalibrationResult(method="gyro_rate", names=names, values=values, covariance=cov, dof=dof,
                            chi2=chi2, residuals=np.concatenate([d_res.ravel(), s_res.ravel()]),
                            normalized_residuals=np.concatenate([nres[:P].ravel(), nres[P:].ravel()]),
                            status=status, warnings=warnings)
    rate_res = []
    for p, (a, b) in enumerate(pairs):
        ax = int(np.argmax(np.abs(r[p])))
        rate_res.append({"forward_segment": a, "reverse_segment": b, "axis": AXES[ax],
                         "rate_rad_s": float(r[p, ax]), "half_diff_residual_rad_s": d_res[p],
                         "half_sum_residual_rad_s": s_res[p], "sigma_rad_s": sd[p]})
    res.extra = {"M": values[3:].reshape(3, 3), "drift_rad_s": values[:3], "pairs": pairs,
                 "rate_residuals": rate_res}
    if status == "ok" and dof > 0 and res.chi2_p_value < 1e-3:
        res.status = "poor_fit"
        res.warnings.append(f"chi2/dof = {res.chi2_per_dof:.3g}: rate-dependent residuals exceed the noise "
                            "(see extra['rate_residuals']; scale asymmetry/nonlinearity or g-sensitivity?)")
    return res
