"""Orientation-free multi-position calibration (Tedaldi, Pretto, Menegatti, ICRA 2014).

For data taken without a table (hand-held poses, imported logs). Three steps:

1. Static intervals (:func:`detect_static_intervals`). The variance magnitude of the
   accelerometer over a sliding window of t_w seconds,
       v(t) = || (var a_x, var a_y, var a_z) over [t - t_w/2, t + t_w/2] ||,
   is compared with k * v_init, v_init the same quantity over the initial static period
   T_init; runs of v < k v_init lasting at least t_min seconds are static.
2. Accelerometer (:func:`calibrate_accel_multipos`): a = T K (u - b), with u the raw means,
   T = [[1, -a_yz, a_zy], [0, 1, -a_zx], [0, 0, 1]] (misalignment, rad), K = diag(s)
   (scale, SI per raw unit), b the bias (raw units). At rest |a| = g, so the residual of pose p
   is r_p = (|a_p| - g) / s_p, s_p = || (a_p/|a_p|)^T T K diag(sigma_u,p) || the propagated
   uncertainty of |a_p| (sigma_u from the noise model at the pose's length). When the pose
   means share time-correlated noise (bias instability, random walk: ``pose_cov`` per axis,
   :func:`pose_cov` from IEEE 952 coefficients), the errors of |a_p| are correlated,
   Cov(|a_p|, |a_q|) = sum_c n_pc n_qc C_c[p, q] with n_p = d|a_p|/du, and the residual vector
   is whitened by its Cholesky factor instead. Solved with scipy.optimize.least_squares;
   Cov = (J^T J)^-1 (J of the normalised residuals); dof = P - 9.
3. Gyro (:func:`calibrate_gyro_multipos`): w = T_g K_g (u_g - b_g) (6 misalignments, 3 scales; b_g
   from the initial static period). The calibrated rate is integrated between consecutive poses
   into a rotation R (body k -> body k+1); the gravity direction of pose k propagated, R^T g_k,
   must match the measured direction of pose k+1. Residuals 3 per transition, 2 independent:
   dof = 2 (P - 1) - 9.

Too few poses: the fit is still computed, but with fewer than n_params + min_dof poses
(default min_dof = n_params, so 18 poses for 9 parameters; Tedaldi et al. recommend 36-50 poses;
the gyro step uses the same poses and the same rule) the result carries status
"insufficient_poses", the reason and the dof, and must not be reported as a confident fit: with
1 dof the residuals land below the noise floor whatever the truth, and the chi2 cannot test
anything.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import scipy.linalg
import scipy.optimize
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import uniform_filter1d
from scipy.spatial.transform import Rotation

from .calibration_result import STATUS_INSUFFICIENT, STATUS_POOR_FIT, CalibrationResult
from .noise_coefficients import NoiseCoefficients
from .segment_stats import SensorNoise, allan_curve_from_samples, mean_sigma_from_model

AXES = ("x", "y", "z")


def detect_static_intervals(acc: ArrayLike, fs_hz: float, t_init_s: float, k: float = 8.0,
                            window_s: float = 0.5, min_duration_s: float = 1.0
                            ) -> list[tuple[int, int]]:
    """Static intervals [start, end) in samples, the first being the initial static period.

    Args:
        acc: (n, 3) accelerometer samples (any unit).
        fs_hz: sample rate, Hz.
        t_init_s: length of the initial static period, s (sets the threshold).
        k: threshold multiplier on the initial variance magnitude.
        window_s: variance window t_w, s.
        min_duration_s: shortest static interval kept, s.
    """
    a = np.asarray(acc, dtype=np.float64)
    n_init = int(round(t_init_s * fs_hz))
    if n_init < 10 or n_init > len(a):
        raise ValueError("the initial static period must hold at least 10 samples of the record")
    v_init = np.linalg.norm(a[:n_init].var(axis=0))
    w = max(3, int(round(window_s * fs_hz)))
    mean = uniform_filter1d(a, w, axis=0, mode="nearest")
    mean2 = uniform_filter1d(a**2, w, axis=0, mode="nearest")
    v = np.linalg.norm(np.clip(mean2 - mean**2, 0, None), axis=1)
    static = v < k * v_init
    static[:n_init] = True
    edges = np.diff(np.concatenate([[0], static.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    n_min = int(round(min_duration_s * fs_hz))
    # shrink each interval by half a window at both ends (the window smears the motion)
    h = w // 2
    out = []
    for s, e in zip(starts, ends):
        s2, e2 = (s if s == 0 else s + h), (e if e == len(a) else e - h)
        if e2 - s2 >= n_min:
            out.append((int(s2), int(e2)))
    return out


def _tk(p: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.array([[1.0, -p[0], p[1]], [0.0, 1.0, -p[2]], [0.0, 0.0, 1.0]])
    return T @ np.diag(p[3:6])


ACC_NAMES_TEMPLATE = ["accel_misalign_yz_rad", "accel_misalign_zy_rad", "accel_misalign_zx_rad",
                      "accel_scale_x_m_s2_per_{u}", "accel_scale_y_m_s2_per_{u}",
                      "accel_scale_z_m_s2_per_{u}", "accel_bias_x_{u}", "accel_bias_y_{u}",
                      "accel_bias_z_{u}"]


def _sufficiency(res: CalibrationResult, n_poses: int, n_params: int, min_dof: int, what: str) -> None:
    """chi2 check (inflate by chi2/dof if improbable), then the pose-count rule."""
    if res.dof > 0 and res.chi2_p_value < 1e-3:
        birge = res.chi2_per_dof
        res.covariance = res.covariance * birge
        res.interval = "t"
        res.status = STATUS_POOR_FIT
        res.warnings.append(f"chi2/dof = {birge:.3g}: residuals exceed the noise model (motion during "
                            "'static' poses, unmodelled effects); covariance inflated by chi2/dof")
    if n_poses < n_params + min_dof:
        res.status = STATUS_INSUFFICIENT
        res.warnings.append(
            f"too few poses for a trustworthy {what} fit: {n_poses} poses for {n_params} parameters "
            f"(residual dof = {res.dof}; need >= {n_params + min_dof} poses, Tedaldi et al. "
            "recommend 36-50). With so few poses the fit can follow the errors of the data, so a "
            "small chi2 proves nothing, the parameters are poorly separated and the intervals "
            "below are not to be trusted; record more poses in varied orientations.")


def pose_means(data: ArrayLike, intervals: list[tuple[int, int]], fs_hz: float,
               noise: SensorNoise | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Means (P, 3) of each interval and their uncertainties from the noise model at T."""
    x = np.asarray(data, dtype=np.float64)
    means = np.array([x[s:e].mean(axis=0) for s, e in intervals])
    if noise is None:
        noise = allan_curve_from_samples(x[intervals[0][0]:intervals[0][1]], fs_hz)
    sig = np.array([mean_sigma_from_model((e - s) / fs_hz, noise) for s, e in intervals])
    return means, sig


def pose_cov(intervals: list[tuple[int, int]], fs_hz: float, model: Sequence[NoiseCoefficients], t0_s: float = 0.0
             ) -> NDArray[np.float64]:
    """(3, P, P) covariance of the pose means per axis from IEEE 952 coefficients (time-correlated
    terms included, :mod:`rigctl.solvers.segment_cov`); intervals in samples, time from sample 0."""
    a = np.array([s for s, _ in intervals], dtype=np.float64) / fs_hz
    b = np.array([e for _, e in intervals], dtype=np.float64) / fs_hz
    return np.stack([m.cov(a, b, t0=t0_s) for m in model])


def calibrate_accel_multipos(means: ArrayLike, sigma: ArrayLike, g: float, unit: str = "count",
                             min_dof: int | None = None, pose_cov: ArrayLike | None = None
                             ) -> CalibrationResult:
    """Accelerometer from P static poses with the gravity-magnitude constraint (module doc).

    Args:
        means: (P, 3) raw means of the poses.
        sigma: (P, 3) their standard uncertainties (raw units).
        g: local gravity, m/s^2.
        unit: name of the raw unit, used in the parameter names.
        min_dof: minimum degrees of freedom for a trustworthy fit (default: 9, the parameter count).
        pose_cov: (3, P, P) covariance of the pose means per axis (raw units^2), when they share
            time-correlated noise; default: independent with the given sigma.
    """
    u = np.asarray(means, dtype=np.float64)
    pc = None if pose_cov is None else np.asarray(pose_cov, dtype=np.float64)
    su = np.asarray(sigma, dtype=np.float64)
    P = len(u)
    names = [n.format(u=unit) for n in ACC_NAMES_TEMPLATE]
    n_par = 9
    min_dof = n_par if min_dof is None else min_dof

    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        M = _tk(p)
        a = (u - p[6:9]) @ M.T
        na = np.linalg.norm(a, axis=1)
        dn = (a / na[:, None]) @ M  # d|a|/du
        if pc is not None:  # correlated pose means: whiten the residual vector
            C = sum(np.outer(dn[:, c], dn[:, c]) * pc[c] for c in range(3))
            return scipy.linalg.solve_triangular(np.linalg.cholesky(C), na - g, lower=True)
        s = np.sqrt(np.sum((dn * su) ** 2, axis=1))
        return (na - g) / s

    s0 = g / np.median(np.linalg.norm(u - u.mean(axis=0) * 0, axis=1))
    p0 = np.array([0, 0, 0, s0, s0, s0, 0, 0, 0], dtype=np.float64)
    p0[6:9] = 0.5 * (u.max(axis=0) + u.min(axis=0)) if P >= 6 else 0.0
    sol = scipy.optimize.least_squares(resid, p0, method="lm" if P >= n_par else "trf",
                                       x_scale=np.array([1e-2] * 3 + [s0] * 3 + [g / s0 * 0.05] * 3))
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((n_par, n_par), np.nan)
    r = sol.fun
    res = CalibrationResult(method="multipos_accel", names=names, values=sol.x, covariance=cov,
                            dof=P - n_par, chi2=float(r @ r), residuals=r * 0 + (np.linalg.norm(
                                (u - sol.x[6:9]) @ _tk(sol.x).T, axis=1) - g), normalized_residuals=r)
    res.extra = {"n_poses": P, "T_times_K": _tk(sol.x), "optimizer_status": int(sol.status)}
    _sufficiency(res, P, n_par, min_dof, "accelerometer")
    return res


def calibrate_accel_apply(params: ArrayLike, raw: ArrayLike) -> NDArray[np.float64]:
    """Calibrated specific force a = T K (u - b) for raw samples (n, 3), m/s^2."""
    p = np.asarray(params, dtype=np.float64)
    return (np.asarray(raw, dtype=np.float64) - p[6:9]) @ _tk(p).T


def _tg(p: NDArray[np.float64]) -> NDArray[np.float64]:
    T = np.array([[1.0, p[0], p[1]], [p[2], 1.0, p[3]], [p[4], p[5], 1.0]])
    return T @ np.diag(p[6:9])


GYRO_NAMES_TEMPLATE = ["gyro_misalign_yz_rad", "gyro_misalign_zy_rad", "gyro_misalign_xz_rad",
                       "gyro_misalign_zx_rad", "gyro_misalign_xy_rad", "gyro_misalign_yx_rad",
                       "gyro_scale_x_rad_s_per_{u}", "gyro_scale_y_rad_s_per_{u}",
                       "gyro_scale_z_rad_s_per_{u}"]


def _integrate(w: NDArray[np.float64], dt: float) -> NDArray[np.float64]:
    """Rotation matrix body_start -> body_end, product of exp([w dt]x) (tree reduction)."""
    r = Rotation.from_rotvec(w * dt)
    while len(r) > 1:
        if len(r) % 2:
            r = Rotation.concatenate([r, Rotation.identity(1)])
        r = r[0::2] * r[1::2]
    return r[0].as_matrix()


def calibrate_gyro_multipos(gyro: ArrayLike, acc_cal: ArrayLike, intervals: list[tuple[int, int]],
                            fs_hz: float, scale_guess: float, unit: str = "count",
                            gyro_noise_rad_sqrt_s: float | None = None, min_dof: int | None = None
                            ) -> CalibrationResult:
    """Gyro scale and misalignment from rotations between static poses (module doc, step 3).

    Args:
        gyro: (n, 3) raw gyro samples.
        acc_cal: (n, 3) calibrated accelerometer samples, m/s^2.
        intervals: static intervals [start, end), the first is the initial static period.
        fs_hz: sample rate, Hz.
        scale_guess: nominal gyro scale, rad/s per raw unit (start value).
        unit: raw unit name for the parameter names.
        gyro_noise_rad_sqrt_s: angle random walk N (rad/sqrt(s)) for the direction uncertainty;
            default: estimated from the initial static period.
    """
    g_raw = np.asarray(gyro, dtype=np.float64)
    a = np.asarray(acc_cal, dtype=np.float64)
    s0, e0 = intervals[0]
    bias = g_raw[s0:e0].mean(axis=0)
    dt = 1.0 / fs_hz
    if gyro_noise_rad_sqrt_s is None:
        gyro_noise_rad_sqrt_s = float(np.mean(g_raw[s0:e0].std(axis=0)) * scale_guess * np.sqrt(dt))
    dirs, dsig = [], []
    for s, e in intervals:
        m = a[s:e].mean(axis=0)
        gn = np.linalg.norm(m)
        dirs.append(m / gn)
        dsig.append(np.mean(a[s:e].std(axis=0)) / np.sqrt(e - s) / gn)
    segs = [g_raw[intervals[k][1] - 1: intervals[k + 1][0] + 1] - bias for k in range(len(intervals) - 1)]
    sig = np.array([np.sqrt(dsig[k] ** 2 + dsig[k + 1] ** 2 + gyro_noise_rad_sqrt_s**2 * len(segs[k]) * dt)
                    for k in range(len(segs))])

    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        M = _tg(p)
        out = []
        for k, gs in enumerate(segs):
            R = _integrate(gs @ M.T, dt)
            out.append((dirs[k + 1] - R.T @ dirs[k]) / sig[k])
        return np.concatenate(out)

    p0 = np.array([0.0] * 6 + [scale_guess] * 3)
    sol = scipy.optimize.least_squares(resid, p0, x_scale=np.array([1e-2] * 6 + [scale_guess] * 3),
                                       method="trf")
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((9, 9), np.nan)
    names = [n.format(u=unit) for n in GYRO_NAMES_TEMPLATE]
    n_tr = len(segs)
    res = CalibrationResult(method="multipos_gyro", names=names, values=sol.x, covariance=cov,
                            dof=2 * n_tr - 9, chi2=float(sol.fun @ sol.fun), residuals=sol.fun * np.repeat(sig, 3),
                            normalized_residuals=sol.fun)
    res.extra = {"bias_" + unit: bias, "n_transitions": n_tr}
    _sufficiency(res, len(intervals), 9, 9 if min_dof is None else min_dof, "gyro")
    return res
