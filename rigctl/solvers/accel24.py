"""Accelerometer calibration from static positions (24-position test, docs/methods.md A3).

Model (A2), axis i with true specific force a = (a_x, a_y, a_z) in the body frame:

    A_i = a_i0 + S_i a_i + sum_{j != i} K_ji a_j + K_ii a_i^2

Per axis the paper's five unknowns X_i = [S_i, K_ji, K_ki, a_i0, K_ii] (units: 1, 1, 1, m/s^2,
s^2/m). Stacking the K position means gives Z_i = A X_i + V, solved by weighted least squares
with the segments' uncertainties (see :func:`rigctl.solvers.calibration_result.fit_linear`):

    X_hat = (A^T W A)^-1 A^T W Z,   Cov = (A^T W A)^-1,   W = Sigma_i^-1

with Sigma_i the covariance of axis i's K position means: diag(s_k^2) when they are independent,
full under time-correlated noise (bias instability, rate random walk: the bias wanders between
positions; :mod:`rigctl.solvers.segment_cov`), then solved by Cholesky whitening.

The same numbers in matrix form ("full form"): f_meas = b + M a + diag(q) (a o a), with
M_ii = S_i, M_ij = K_ji (row i = output axis, column j = input axis), b_i = a_i0, q_i = K_ii.
The noise of different axes is independent, so the full covariance is block diagonal.

For segments whose specific force varies within the window, the quadratic regressor is the mean
of a_i^2 (SegmentTable.f_ref_outer), not the square of the mean.

Gyro biases come from the same static positions: W = w0 + M_g w_ref with w_ref the Earth rate in
the body frame, so w0 = weighted mean of (W - M_g w_ref) (M_g = I unless a rate test gave it).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .calibration_result import CalibrationResult, fit_linear
from .segments import SegmentTable

AXES = ("x", "y", "z")


def accel_axis_names(i: int, quadratic: bool = True) -> list[str]:
    """The paper's per-axis parameter names with units, for output axis i."""
    ax = AXES[i]
    others = [AXES[j] for j in range(3) if j != i]
    names = [f"accel_{ax}_S_ratio", f"accel_{ax}_K_{others[0]}{ax}_ratio",
             f"accel_{ax}_K_{others[1]}{ax}_ratio", f"accel_{ax}_a0_m_s2"]
    if quadratic:
        names.append(f"accel_{ax}_K_{ax}{ax}_s2_per_m")
    return names


def accel_full_names(quadratic: bool = True) -> list[str]:
    """Names of the full form: biases, the 3x3 matrix M (row-major), quadratic terms."""
    names = [f"accel_bias_{a}_m_s2" for a in AXES]
    names += [f"accel_M_{a}{b}_ratio" for a in AXES for b in AXES]
    if quadratic:
        names += [f"accel_quad_{a}_s2_per_m" for a in AXES]
    return names


def accel_axis_design(i: int, f_ref: ArrayLike, f_sq_i: ArrayLike | None = None,
                      quadratic: bool = True) -> NDArray[np.float64]:
    """(K, 5) design for output axis i: [a_i, a_j, a_k, 1, mean(a_i^2)] (paper order)."""
    f_ref = np.asarray(f_ref, dtype=np.float64)
    others = [j for j in range(3) if j != i]
    cols = [f_ref[:, i], f_ref[:, others[0]], f_ref[:, others[1]], np.ones(len(f_ref))]
    if quadratic:
        cols.append(f_ref[:, i] ** 2 if f_sq_i is None else np.asarray(f_sq_i, dtype=np.float64))
    return np.stack(cols, axis=1)


def calibrate_accel_axis(i: int, f_meas_i: ArrayLike, sigma_i: ArrayLike, f_ref: ArrayLike,
                         f_sq_i: ArrayLike | None = None, quadratic: bool = True,
                         cov_i: ArrayLike | None = None) -> CalibrationResult:
    """Per-axis five-term fit (A3) for output axis i (0, 1, 2).

    Args:
        f_meas_i: (K,) measured means of accelerometer i, m/s^2.
        sigma_i: (K,) their standard uncertainties, m/s^2.
        f_ref: (K, 3) true specific force in the body frame, m/s^2.
        f_sq_i: (K,) mean of a_i^2 over each segment (default f_ref[:, i]^2).
        quadratic: include K_ii (the paper's model) or not.
        cov_i: (K, K) covariance of the K means (default diag(sigma_i^2)).
    """
    X = accel_axis_design(i, f_ref, f_sq_i, quadratic)
    return fit_linear(X, np.asarray(f_meas_i, float), np.asarray(sigma_i, float),
                      accel_axis_names(i, quadratic), method=f"accel24_axis_{AXES[i]}",
                      cov=None if cov_i is None else np.asarray(cov_i, float))


def accel_columns(seg: SegmentTable, quadratic: bool = True) -> tuple[NDArray[np.float64], list[str]]:
    """Regressors of the full form for the accelerometer channels.

    Returns:
        (K, 3, p) array: [k, i, :] is the design row of accelerometer i in segment k, and the
        p parameter names (:func:`accel_full_names`).
    """
    K = len(seg)
    names = accel_full_names(quadratic)
    p = len(names)
    X = np.zeros((K, 3, p))
    fo = seg.f_outer()
    for i in range(3):
        X[:, i, i] = 1.0
        X[:, i, 3 + 3 * i: 6 + 3 * i] = seg.f_ref
        if quadratic:
            X[:, i, 12 + i] = fo[:, i, i]
    return X, names


def calibrate_accel(f_meas: ArrayLike, f_sigma: ArrayLike, f_ref: ArrayLike,
                    f_ref_outer: ArrayLike | None = None, quadratic: bool = True,
                    f_cov: ArrayLike | None = None) -> CalibrationResult:
    """Full form f = b + M a + q o a^2 by weighted least squares over K static positions.

    Args:
        f_meas: (K, 3) measured means, m/s^2.
        f_sigma: (K, 3) their standard uncertainties, m/s^2.
        f_ref: (K, 3) true body specific force (gravity along up rotated into the body), m/s^2.
        f_ref_outer: (K, 3, 3) mean of a a^T per segment (default from f_ref).
        quadratic: include the quadratic terms q_i = K_ii.
        f_cov: (3, K, K) covariance of each axis' K means (default diag(f_sigma^2)).

    Returns:
        CalibrationResult with names :func:`accel_full_names`, block-diagonal covariance,
        dof = 3 K - p, chi2 summed over the axes, residuals (3K,) in axis-major order and
        ``extra`` = {"M": 3x3, "bias_m_s2": 3, "quad_s2_per_m": 3, "per_axis": [dict, ...]}.
    """
    f_meas = np.asarray(f_meas, dtype=np.float64)
    f_sigma = np.asarray(f_sigma, dtype=np.float64)
    f_ref = np.asarray(f_ref, dtype=np.float64)
    fo = None if f_ref_outer is None else np.asarray(f_ref_outer, dtype=np.float64)
    names = accel_full_names(quadratic)
    p = len(names)
    values = np.full(p, np.nan)
    cov = np.zeros((p, p))
    axis_results = []
    for i in range(3):
        r = calibrate_accel_axis(i, f_meas[:, i], f_sigma[:, i], f_ref,
                                 None if fo is None else fo[:, i, i], quadratic,
                                 None if f_cov is None else np.asarray(f_cov)[i])
        axis_results.append(r)
        # paper order [S_i, K_ji, K_ki, a0, K_ii] -> full-form indices
        others = [j for j in range(3) if j != i]
        idx = [3 + 3 * i + i, 3 + 3 * i + others[0], 3 + 3 * i + others[1], i]
        if quadratic:
            idx.append(12 + i)
        values[idx] = r.values
        cov[np.ix_(idx, idx)] = r.covariance
    pdof = np.zeros(p)
    for i, r in enumerate(axis_results):
        pdof[[k for k, nm in enumerate(names) if _axis_of(nm) == i]] = r.dof
    chi2 = float(sum(r.chi2 for r in axis_results))
    dof = int(sum(r.dof for r in axis_results))
    res = CalibrationResult(
        method="accel24", names=names, values=values, covariance=cov, dof=dof, chi2=chi2,
        residuals=np.concatenate([r.residuals for r in axis_results]),
        normalized_residuals=np.concatenate([r.normalized_residuals for r in axis_results]),
        interval="t" if any(r.interval == "t" for r in axis_results) else "normal",
        param_dof=pdof,
    )
    for r in axis_results:
        if r.status != "ok":
            res.status = r.status
            res.warnings.extend(f"{r.method}: {w}" for w in r.warnings)
    res.extra = {
        "M": values[3:12].reshape(3, 3),
        "bias_m_s2": values[0:3],
        "quad_s2_per_m": values[12:15] if quadratic else np.zeros(3),
        "per_axis": [r.to_dict() for r in axis_results],
    }
    return res


def _axis_of(name: str) -> int:
    """Output axis of a full-form accelerometer parameter name."""
    tag = name.split("_")[2]  # bias_<a>, M_<ab>, quad_<a>
    return AXES.index(tag[0])


def calibrate_gyro_bias_static(w_meas: ArrayLike, w_sigma: ArrayLike, w_ref: ArrayLike,
                               M_g: ArrayLike | None = None, w_cov: ArrayLike | None = None
                               ) -> CalibrationResult:
    """Gyro biases from static positions with the Earth rate in the reference.

        W_k = w0 + M_g w_ref_k + v_k   =>   w0_hat = 1^T S^-1 z / 1^T S^-1 1,  z = W - M_g w_ref

    (S = diag(s^2) for independent means: the weighted mean; full S under time-correlated noise.)

    Args:
        w_meas: (K, 3) measured mean rates, rad/s.
        w_sigma: (K, 3) their standard uncertainties, rad/s.
        w_ref: (K, 3) true body rate (Earth rate rotated into the body), rad/s.
        M_g: (3, 3) gyro scale/misalignment matrix if known (default identity).
        w_cov: (3, K, K) covariance of each axis' K means (default diag(w_sigma^2)).

    The chi2 of the K - 1 residual dof per axis tests the constant-bias assumption (a large
    value points to g-sensitivity or drift, which the closed loop then looks for).
    """
    w_meas = np.asarray(w_meas, dtype=np.float64)
    w_sigma = np.asarray(w_sigma, dtype=np.float64)
    w_ref = np.asarray(w_ref, dtype=np.float64)
    M = np.eye(3) if M_g is None else np.asarray(M_g, dtype=np.float64)
    z = w_meas - w_ref @ M.T
    names = [f"gyro_bias_{a}_rad_s" for a in AXES]
    vals, cov, chi2, dof, res_all, nres_all, warn = [], np.zeros((3, 3)), 0.0, 0, [], [], []
    results = []
    for i in range(3):
        r = fit_linear(np.ones((len(z), 1)), z[:, i], w_sigma[:, i], [names[i]],
                       method=f"gyro_bias_{AXES[i]}",
                       cov=None if w_cov is None else np.asarray(w_cov, float)[i])
        results.append(r)
        vals.append(r.values[0])
        cov[i, i] = r.covariance[0, 0]
        chi2 += r.chi2
        dof += r.dof
        res_all.append(r.residuals)
        nres_all.append(r.normalized_residuals)
        warn.extend(r.warnings)
    out = CalibrationResult(method="gyro_bias_static", names=names, values=np.array(vals),
                            covariance=cov, dof=dof, chi2=chi2,
                            residuals=np.concatenate(res_all),
                            normalized_residuals=np.concatenate(nres_all),
                            interval="t" if any(r.interval == "t" for r in results) else "normal")
    if warn:
        out.status = "poor_fit"
        out.warnings = warn
    return out
