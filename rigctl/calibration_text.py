"""Presentation of calibration results: parameter tables and noise summaries in field units.

Values are SI inside (parameter names carry their SI unit, e.g. ``accel_bias_x_m_s2``);
:func:`field_unit` maps a name to its display name and factor (mg, ug, ppm, urad, deg/h, ...).
"""
from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from .solvers.calibration_result import CalibrationResult

G0 = 9.80665
DEG_H = 180.0 / math.pi * 3600.0
DEG = math.pi / 180.0
# (name suffix, replacement, factor, offset-on-diagonal): first match wins (longest first)
_UNITS: tuple[tuple[str, str, float], ...] = (
    ("_rad_s_per_m2_s4", "_deg_h_per_g2", DEG_H * G0**2),
    ("_rad_s_per_m_s2", "_deg_h_per_g", DEG_H * G0),
    ("_m_s2_per_K", "_mg_per_K", 1.0 / (G0 * 1e-3)),
    ("_rad_s_per_K", "_deg_h_per_K", DEG_H),
    ("_s2_per_rad2", "_ppm_per_dps2", DEG**2 * 1e6),
    ("_s_per_rad", "_ppm_per_dps", DEG * 1e6),
    ("_s2_per_m", "_ug_per_g2", G0 * 1e6),
    ("_per_K", "_ppm_per_K", 1e6),
    ("_m_s3", "_mg_per_h", 3600.0 / (G0 * 1e-3)),
    ("_rad_s2", "_deg_h_per_h", DEG_H * 3600.0),
    ("_m_s2", "_mg", 1.0 / (G0 * 1e-3)),
    ("_rad_s", "_deg_h", DEG_H),
    ("_time_delay_s", "_time_delay_ms", 1e3),
    ("_rad", "_urad", 1e6),
    ("_m", "_mm", 1e3),
    ("_ratio", "_ppm", 1e6),
)


def field_unit(name: str) -> tuple[str, float, float]:
    """(display name, factor, offset) so that display = (value - offset) * factor.

    Diagonal elements of a scale/misalignment matrix (``*_M_xx_ratio``, multipos scales) are
    shown as scale errors in ppm (offset 1); off-diagonal ratios as urad.
    """
    m = re.match(r"^(accel|gyro)_M_([xyz])([xyz])_ratio$", name)
    if m:
        if m.group(2) == m.group(3):
            return f"{m.group(1)}_scale_error_{m.group(2)}_ppm", 1e6, 1.0
        return f"{m.group(1)}_misalignment_{m.group(2)}{m.group(3)}_urad", 1e6, 0.0
    m = re.match(r"^(accel|gyro)_scale_([xyz])_(m_s2_per_m_s2|rad_s_per_rad_s)$", name)
    if m:
        return f"{m.group(1)}_scale_error_{m.group(2)}_ppm", 1e6, 1.0
    for suf, rep, fac in _UNITS:
        if name.endswith(suf):
            return name[: -len(suf)] + rep, fac, 0.0
    return name, 1.0, 0.0


def param_table(res: CalibrationResult, title: str) -> str:
    """Each parameter with 1-sigma and 95 % interval in field units; dof and chi2/dof."""
    trusted = res.status in ("ok", "poor_fit")
    lines = [f"{title}: status {res.status}{'' if trusted else '  (NOT TRUSTWORTHY)'}; dof {res.dof}, "
             f"chi2 {res.chi2:.4g}, chi2/dof {res.chi2_per_dof:.3g}, p {res.chi2_p_value:.3g}, "
             f"{'Student-t' if res.interval == 't' else 'normal'} intervals"]
    lines += [f"  WARNING: {w}" for w in res.warnings]
    lines.append(f"  {'parameter':<38} {'value':>12} {'1-sigma':>10} {'95% low':>12} {'95% high':>12}")
    for n, v, s, (lo, hi) in zip(res.names, res.values, res.sigma, res.ci95):
        disp, f, off = field_unit(n)
        lines.append(f"  {disp:<38} {(v - off) * f:>12.5g} {s * f:>10.3g} {(lo - off) * f:>12.5g} "
                     f"{(hi - off) * f:>12.5g}")
    return "\n".join(lines)


#: field units of the noise coefficients: (name, factor from SI) for accel and gyro
_NOISE_UNITS = {"accel": (("N", "ug_per_rtHz", 1e6 / G0), ("B", "ug", 1e6 / G0), ("K", "ug_per_rts", 1e6 / G0)),
                "gyro": (("N", "deg_per_rth", 180.0 / math.pi * 60.0), ("B", "deg_h", DEG_H),
                         ("K", "deg_h_per_rth", DEG_H * 60.0))}


def noise_summary(models: list[Any]) -> tuple[list[str], list[dict[str, Any]]]:
    """Text lines and JSON rows of the six channels' noise models (field units in the keys)."""
    from .solvers.segments import CHANNELS

    lines, rows = [], []
    for ch, m in zip(CHANNELS, models):
        sensor = ch.split("_")[0]
        (nn, nu, nf), (bn, bu, bf), (kn, ku, kf) = _NOISE_UNITS[sensor]
        nper = {g: float(np.sqrt(v)) * nf for g, v in m.white_var.items()}
        row = {"channel": ch, "source": m.source, f"N_{nu}": nper, f"B_{bu}": m.B * bf, f"K_{ku}": m.K * kf,
               "flicker_tau_min_s": m.tau_min_s, "flicker_tau_max_s": m.tau_max_s, "rw_origin_s": m.t0,
               **{k: v for k, v in m.info.items() if k in ("residual_dof", "converged", "note")}}
        rows.append(row)
        ntxt = ", ".join(f"{v:.4g}" + ("" if g == "*" else f" ({g})") for g, v in nper.items())
        extra = f"; REML on {m.info['residual_dof']} residual dof" if "residual_dof" in m.info else ""
        lines.append(f"  {ch:<8} N {ntxt} {nu.replace('_per_', '/')}, B {m.B * bf:.4g} {bu}, "
                     f"K {m.K * kf:.4g} {ku.replace('_per_', '/')}{extra}")
    return lines, rows
