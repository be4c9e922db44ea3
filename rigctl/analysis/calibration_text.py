"""Presentation of calibration results: parameter tables and noise summaries in field units.

Values are SI inside (parameter names carry their SI unit, e.g. ``accel_bias_x_m_s2``); the
one table of field units and spellings is :mod:`rigctl.display_units`.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..display_units import NOISE_UNITS, display, format_number, format_value, slug
from ..solvers.calibration_result import CalibrationResult



def param_table(res: CalibrationResult, title: str) -> str:
    """Each parameter with its field unit (rigctl.display_units), 1-sigma and 95 % interval,
    digits from the uncertainty; dof and chi2/dof."""
    trusted = res.status in ("ok", "poor_fit")
    lines = [f"{title}: status {res.status}{'' if trusted else '  (NOT TRUSTWORTHY)'}; dof {res.dof}, "
             f"chi2 {res.chi2:.4g}, chi2/dof {res.chi2_per_dof:.3g}, p {res.chi2_p_value:.3g}, "
             f"{'Student-t' if res.interval == 't' else 'normal'} intervals"]
    lines += [f"  WARNING: {w}" for w in res.warnings]
    lines.append(f"  {'parameter':<36} {'unit':<14} {'value':>12} {'1-sigma':>10} {'95% low':>12} {'95% high':>12}")
    for n, v, s, (lo, hi) in zip(res.names, res.values, res.sigma, res.ci95):
        d = display(n)
        u = d.sigma(s)
        val, sig = format_value(d.value(v), u)
        lines.append(f"  {d.base:<36} {d.unit:<14} {val:>12} {sig:>10} {format_value(d.value(lo), u)[0]:>12} "
                     f"{format_value(d.value(hi), u)[0]:>12}")
    return "\n".join(lines)


def noise_summary(models: list[Any], t0: float = 0.0) -> tuple[list[str], list[dict[str, Any]]]:
    """Text lines and JSON rows of the six channels' noise models (NoiseCoefficients; field units
    of rigctl.display_units.NOISE_UNITS, slugged into the keys: N_deg_per_sqrt_h, B_mg, ...);
    t0: the random walk's origin the covariance used, s."""
    from ..solvers.segments import CHANNELS

    lines, rows = [], []
    for ch, m in zip(CHANNELS, models):
        U = NOISE_UNITS[ch.split("_")[0]]
        (nu, nf), (bu, bf), (ku, kf) = U["N"], U["B"], U["K"]
        nper = {g: v * nf for g, v in (m.white_by_group or {"*": m.N.value}).items()}
        info = m.details
        row = {"channel": ch, "source": m.source, f"N_{slug(nu)}": nper, f"B_{slug(bu)}": m.B.value * bf,
               f"K_{slug(ku)}": m.K.value * kf, "flicker_tau_min_s": m.flicker_tau_min_s,
               "flicker_tau_max_s": m.flicker_tau_max_s, "rw_origin_s": t0,
               **{k: v for k, v in info.items() if k in ("residual_dof", "converged", "note")}}
        rows.append(row)
        ntxt = ", ".join(f"{v:.4g}" + ("" if g == "*" else f" ({g})") for g, v in nper.items())
        extra = f"; REML on {info['residual_dof']} residual dof" if "residual_dof" in info else ""
        lines.append(f"  {ch:<8} N {ntxt} {nu}, B {m.B.value * bf:.4g} {bu}, K {m.K.value * kf:.4g} {ku}{extra}")
    return lines, rows


def effect_parameter_line(p: dict[str, Any]) -> str:
    """One parameter of an effect the closed loop found ({name, value, sigma, ci95}, SI) in the
    field's units, as :func:`param_table` shows it: name, unit, value +- 1-sigma, 95 % interval."""
    d = display(p["name"])
    u = d.sigma(p["sigma"])
    v, us = format_value(d.value(p["value"]), u)
    lo, hi = (format_number(d.value(x), u) for x in p["ci95"])
    return f"{d.base:<32} {d.unit:<14} {v:>10} +- {us:<8} 95% [{lo}, {hi}]"
