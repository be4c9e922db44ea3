"""Library of candidate physical effects for the closed loop (issue 6 item 6).

Each candidate is a physically named set of regressors that the declared model (A2: accel
bias + 3x3 + quadratic, gyro drift + 3x3) does not contain. A builder returns, for a
:class:`~rigctl.solvers.segments.SegmentTable` with K segments, an array (K, 6, k): the
contribution of each of the k new parameters to the 6 channels (accel x, y, z, gyro x, y, z)
of each segment, plus the k parameter names (units in the names). When the table lacks what a
candidate needs (no temperature, no attitude, no angular acceleration), the builder returns a
string saying why the candidate is not available.

Effects and their regressors (a: true specific force, w: true rate, both body frame, SI):

* accel_warmup_temperature   A_i += c_i (T - T_ref)                          [m/s^2/K]
* gyro_warmup_temperature    W_i += c_i (T - T_ref)                          [rad/s/K]
* accel_thermal_scale        A_i += k_i (T - T_ref) a_i                      [1/K]
* gyro_thermal_scale         W_i += k_i (T - T_ref) w_i                      [1/K]
* accel_time_drift           A_i += d_i (t - t_ref)                          [m/s^3]
* gyro_time_drift            W_i += d_i (t - t_ref)                          [rad/s^2]
* gyro_g_sensitivity         W_i += sum_j G_ij a_j                           [rad/s per m/s^2]
* gyro_anisoelastic          W_i += sum_{j<=k} G_ijk mean(a_j a_k)           [rad/s per (m/s^2)^2]
* accel_quadratic            A_i += q_i mean(a_i^2)        (if not declared) [s^2/m]
* accel_cross_quadratic      A_i += sum over the other monomials mean(a_j a_k)[s^2/m]
* accel_scale_asymmetry      A_i += u_i mean(|a_i|)                          [1]
* gyro_scale_asymmetry       W_i += u_i mean(|w_i|)                          [1]
* gyro_scale_nonlinearity    W_i += n2_i mean(w_i^2) + n3_i mean(w_i^3)      [s/rad, s^2/rad^2]
* lever_arm                  A   += mean(w x (w x r)) + wdot x r             [m]
* time_delay                 W   -= tau wdot                                 [s]
* table_levelling            (A, W) += C_b^n^T (v^n x delta), v = g up, Omega  [rad], delta=(dE, dN, 0)
* table_gimbal_nonorthogonality  d(f, w)/d(delta) at the segment's gimbal angles and rates, for
                             middle axis (0, cos d0, sin d0), inner axis (1, d1, d2)/norm  [rad]
* table_north_alignment      W   += C_b^n^T (Omega^n x (0, 0, dU))            [rad]

(mean(.) is the segment mean of the reference moment; C_b^n is the segment mean of the
attitude matrix; T_ref defaults to the settled temperature of the last segment, t_ref to the
mean time; see SegmentTable.)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from .segments import SegmentTable

AXES = ("x", "y", "z")
Builder = Callable[[SegmentTable], "tuple[NDArray[np.float64], list[str]] | str"]


@dataclass(frozen=True)
class Effect:
    """A candidate effect: name, physical description, the variable it follows, its builder."""

    name: str
    description: str
    variable: str
    build: Builder


def _blank(seg: SegmentTable, k: int) -> NDArray[np.float64]:
    return np.zeros((len(seg), 6, k))


def _per_axis(seg: SegmentTable, values: NDArray[np.float64], offset: int, prefix: str, unit: str
              ) -> tuple[NDArray[np.float64], list[str]]:
    """Channel i of the sensor at ``offset`` gets values[:, i] (one parameter per axis)."""
    X = _blank(seg, 3)
    for i in range(3):
        X[:, offset + i, i] = values[:, i]
    return X, [f"{prefix}_{a}_{unit}" for a in AXES]


def _dtemp(seg: SegmentTable) -> "NDArray[np.float64] | str":
    """T - T_ref per segment (T_ref: given, else the settled temperature of the last segment)."""
    if seg.temperature is None:
        return "no temperature in the segment table"
    if seg.temperature_ref is not None:
        ref = seg.temperature_ref
    elif seg.time is not None:
        ref = float(seg.temperature[int(np.argmax(seg.time))])
    else:
        ref = float(seg.temperature[-1])
    t = seg.temperature - ref
    if np.ptp(t) == 0:
        return "temperature constant: warm-up drift not observable"
    return t


def _temperature(offset: int, prefix: str, unit: str) -> Builder:
    def build(seg: SegmentTable):
        t = _dtemp(seg)
        if isinstance(t, str):
            return t
        return _per_axis(seg, np.repeat(t[:, None], 3, axis=1), offset, prefix, unit)
    return build


def _thermal_scale(offset: int, prefix: str, unit: str) -> Builder:
    def build(seg: SegmentTable):
        t = _dtemp(seg)
        if isinstance(t, str):
            return t
        ref = seg.f_ref if offset == 0 else seg.w_ref
        return _per_axis(seg, t[:, None] * ref, offset, prefix, unit)
    return build


def _time(offset: int, prefix: str, unit: str) -> Builder:
    def build(seg: SegmentTable):
        if seg.time is None:
            return "no segment times in the segment table"
        t = seg.time - (np.mean(seg.time) if seg.time_ref is None else seg.time_ref)
        return _per_axis(seg, np.repeat(t[:, None], 3, axis=1), offset, prefix, unit)
    return build


def _g_sensitivity(seg: SegmentTable):
    X = _blank(seg, 9)
    for i in range(3):
        X[:, 3 + i, 3 * i: 3 * i + 3] = seg.f_ref
    return X, [f"gyro_g_sens_{a}{b}_rad_s_per_m_s2" for a in AXES for b in AXES]


_PAIRS = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]


def _anisoelastic(seg: SegmentTable):
    fo = seg.f_outer()
    X = _blank(seg, 18)
    names = []
    for i in range(3):
        for m, (j, k) in enumerate(_PAIRS):
            X[:, 3 + i, 6 * i + m] = fo[:, j, k]
            names.append(f"gyro_aniso_{AXES[i]}_{AXES[j]}{AXES[k]}_rad_s_per_m2_s4")
    return X, names


def _accel_quadratic(seg: SegmentTable):
    fo = seg.f_outer()
    return _per_axis(seg, np.stack([fo[:, i, i] for i in range(3)], axis=1), 0, "accel_quad", "s2_per_m")


def _accel_cross_quadratic(seg: SegmentTable):
    fo = seg.f_outer()
    X = _blank(seg, 15)
    names = []
    c = 0
    for i in range(3):
        for j, k in _PAIRS:
            if j == k == i:
                continue
            X[:, i, c] = fo[:, j, k]
            names.append(f"accel_xquad_{AXES[i]}_{AXES[j]}{AXES[k]}_s2_per_m")
            c += 1
    return X, names


def _accel_asym(seg: SegmentTable):
    return _per_axis(seg, seg.f_abs(), 0, "accel_scale_asym", "ratio")


def _gyro_asym(seg: SegmentTable):
    return _per_axis(seg, seg.w_abs(), 3, "gyro_scale_asym", "ratio")


def _gyro_nonlin(seg: SegmentTable):
    wo = seg.w_outer()
    X = _blank(seg, 6)
    names = []
    for i in range(3):
        X[:, 3 + i, 2 * i] = wo[:, i, i]
        X[:, 3 + i, 2 * i + 1] = seg.w_cube()[:, i]
        names += [f"gyro_nonlin2_{AXES[i]}_s_per_rad", f"gyro_nonlin3_{AXES[i]}_s2_per_rad2"]
    return X, names


def _lever_arm(seg: SegmentTable):
    wo = seg.w_outer()
    tr = np.trace(wo, axis1=1, axis2=2)
    wd = seg.ang_accel if seg.ang_accel is not None else np.zeros((len(seg), 3))
    X = _blank(seg, 3)
    for m in range(3):
        e = np.zeros(3)
        e[m] = 1.0
        X[:, 0:3, m] = wo[:, :, m] - tr[:, None] * e + np.cross(wd, e)
    if np.max(np.abs(X)) == 0:
        return "no rotating segments: lever arm not observable"
    return X, [f"lever_arm_{a}_m" for a in AXES]


def _time_delay(seg: SegmentTable):
    if seg.ang_accel is None or np.max(np.abs(seg.ang_accel)) == 0:
        return ("no segment with angular acceleration: a time delay does not change segment means "
                "(needs ramp segments)")
    X = _blank(seg, 1)
    X[:, 3:6, 0] = -seg.ang_accel
    return X, ["gyro_time_delay_s"]


def _levelling(seg: SegmentTable):
    if seg.attitude is None:
        return "no table attitude (C_b^n) in the segment table"
    g = seg.gravity_m_s2 if seg.gravity_m_s2 is not None else float(np.median(np.linalg.norm(seg.f_ref, axis=1)))
    om = seg.earth_rate_n if seg.earth_rate_n is not None else np.zeros(3)
    c_nb = np.swapaxes(seg.attitude, 1, 2)
    X = _blank(seg, 2)
    for m in range(2):
        d = np.zeros(3)
        d[m] = 1.0
        X[:, 0:3, m] = c_nb @ np.cross(np.array([0.0, 0.0, g]), d)
        X[:, 3:6, m] = c_nb @ np.cross(om, d)
    return X, ["table_tilt_east_rad", "table_tilt_north_rad"]


def _axis_rot(axis: NDArray[np.float64], angle: NDArray[np.float64]) -> NDArray[np.float64]:
    """(K, 3, 3) rotations by angle (K,) about the unit vector axis (3,) (Rodrigues' formula)."""
    k = axis / np.linalg.norm(axis)
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    a = angle[:, None, None]
    return np.eye(3) + np.sin(a) * Kx + (1.0 - np.cos(a)) * (Kx @ Kx)


def _gimbal_refs(seg: SegmentTable, d: NDArray[np.float64], g: float, om: NDArray[np.float64]
                 ) -> NDArray[np.float64]:
    """(K, 6) body [f, w] for gimbal axes middle = (0, cos d0, sin d0), inner = (1, d1, d2)/norm."""
    ang = seg.angles
    rates = seg.table_rate if seg.table_rate is not None else np.zeros_like(ang)
    ax_o = np.array([0.0, 0.0, 1.0])
    ax_m = np.array([0.0, np.cos(d[0]), np.sin(d[0])])
    ax_i = np.array([1.0, d[1], d[2]]) / np.linalg.norm([1.0, d[1], d[2]])
    Ro, Rm, Ri = _axis_rot(ax_o, ang[:, 0]), _axis_rot(ax_m, ang[:, 1]), _axis_rot(ax_i, ang[:, 2])
    CT = np.swapaxes(Ro @ Rm @ Ri, 1, 2)
    RiT, RmT = np.swapaxes(Ri, 1, 2), np.swapaxes(Rm, 1, 2)
    w_tab = (RiT @ (RmT @ (rates[:, :1] * ax_o)[..., None]))[..., 0] \
        + (RiT @ (rates[:, 1:2] * ax_m)[..., None])[..., 0] + rates[:, 2:3] * ax_i
    return np.concatenate([CT @ np.array([0.0, 0.0, g]), CT @ om + w_tab], axis=1)


def _nonorth(seg: SegmentTable):
    if seg.angles is None:
        return "no gimbal angles in the segment table"
    g = seg.gravity_m_s2 if seg.gravity_m_s2 is not None else float(np.median(np.linalg.norm(seg.f_ref, axis=1)))
    om = seg.earth_rate_n if seg.earth_rate_n is not None else np.zeros(3)
    X = _blank(seg, 3)
    h = 1e-6
    for m in range(3):
        d = np.zeros(3)
        d[m] = h
        X[:, :, m] = (_gimbal_refs(seg, d, g, om) - _gimbal_refs(seg, -d, g, om)) / (2 * h)
    return X, ["gimbal_nonorth_outer_middle_rad", "gimbal_nonorth_middle_inner_y_rad",
               "gimbal_nonorth_middle_inner_z_rad"]


def _north(seg: SegmentTable):
    if seg.attitude is None or seg.earth_rate_n is None:
        return "no table attitude or Earth rate in the segment table"
    c_nb = np.swapaxes(seg.attitude, 1, 2)
    X = _blank(seg, 1)
    X[:, 3:6, 0] = c_nb @ np.cross(seg.earth_rate_n, np.array([0.0, 0.0, 1.0]))
    return X, ["table_azimuth_error_rad"]


LIBRARY: tuple[Effect, ...] = (
    Effect("accel_warmup_temperature", "accelerometer bias follows temperature (warm-up drift)",
           "temperature", _temperature(0, "accel_temp_coef", "m_s2_per_K")),
    Effect("gyro_warmup_temperature", "gyro drift follows temperature (warm-up drift)",
           "temperature", _temperature(3, "gyro_temp_coef", "rad_s_per_K")),
    Effect("accel_thermal_scale", "accelerometer scale factor follows temperature", "temperature x input",
           _thermal_scale(0, "accel_scale_temp_coef", "per_K")),
    Effect("gyro_thermal_scale", "gyro scale factor follows temperature", "temperature x rate",
           _thermal_scale(3, "gyro_scale_temp_coef", "per_K")),
    Effect("accel_time_drift", "accelerometer bias drifts linearly in time", "time",
           _time(0, "accel_drift_rate", "m_s3")),
    Effect("gyro_time_drift", "gyro drift changes linearly in time", "time",
           _time(3, "gyro_drift_rate", "rad_s2")),
    Effect("gyro_g_sensitivity", "gyro output depends on specific force (g-sensitivity)",
           "specific force", _g_sensitivity),
    Effect("gyro_anisoelastic", "gyro output depends on products of specific force (anisoelastic)",
           "specific force products", _anisoelastic),
    Effect("accel_quadratic", "accelerometer second-order (quadratic) scale term",
           "specific force squared", _accel_quadratic),
    Effect("accel_cross_quadratic", "accelerometer cross-quadratic terms (a_j a_k, other axes squared)",
           "specific force products", _accel_cross_quadratic),
    Effect("accel_scale_asymmetry", "accelerometer scale differs for positive and negative input",
           "|specific force|", _accel_asym),
    Effect("gyro_scale_asymmetry", "gyro scale differs for positive and negative rate",
           "|rate|", _gyro_asym),
    Effect("gyro_scale_nonlinearity", "gyro scale nonlinearity (rate^2, rate^3)", "rate^2, rate^3",
           _gyro_nonlin),
    Effect("lever_arm", "accelerometers off the rotation centre: centripetal w x (w x r) and "
           "tangential wdot x r", "rate^2", _lever_arm),
    Effect("time_delay", "gyro samples delayed relative to the table (W = w(t - tau))",
           "angular acceleration", _time_delay),
    Effect("table_levelling", "table base not level: gravity and Earth rate tilted by (dE, dN)",
           "attitude", _levelling),
    Effect("table_gimbal_nonorthogonality", "table gimbal axes not orthogonal (middle tilted towards "
           "the outer axis, inner towards y and z)", "gimbal angles", _nonorth),
    Effect("table_north_alignment", "table not north-found: Earth rate rotated about up",
           "attitude", _north),
)


def effect_by_name(name: str) -> Effect:
    """Look up a library effect."""
    for e in LIBRARY:
        if e.name == name:
            return e
    raise KeyError(name)
