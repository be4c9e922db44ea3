"""Presentation of calibration results: parameter tables and noise summaries in field units.

Values are SI inside (parameter names carry their SI unit, e.g. ``accel_bias_x_m_s2``); the
one table of field units and spellings is :mod:`rigctl.display_units`.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..display_units import NOISE_UNITS, display, format_number, format_value, slug
from ..solvers.calibration_result import CalibrationResult
from ..solvers.noise_coefficients import Coefficient, coefficient_from



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


def coefficient_text(c: Coefficient, factor: float, unit: str) -> str:
    """One noise coefficient (SI; ``factor`` to the field ``unit``) as a noise-model line prints it:
    ``value [lo, hi] unit`` (95 %) for a resolved term; for one the data support only as a bound,
    ``< bound unit (95 %; covariance uses the estimate v)``: the covariance of the segment means
    takes the unconstrained estimate below the bound (docs/calibration.md section 10); a given
    value without an interval says so."""
    if not c.resolved:
        return (f"< {c.upper95 * factor:.4g} {unit} (95 %; covariance uses the estimate "
                f"{c.value * factor:.4g})")
    if c.ci95 is None:
        return f"{c.value * factor:.4g} {unit} (no interval)"
    lo, hi = c.ci95
    return f"{c.value * factor:.4g} [{lo * factor:.4g}, {hi * factor:.4g}] {unit}"


def _coefficient_row(c: Coefficient, factor: float) -> dict[str, Any]:
    """JSON form of :func:`coefficient_text` (field units)."""
    if not c.resolved:
        return {"upper95": c.upper95 * factor, "covariance_uses": c.value * factor}
    return {} if c.ci95 is None else {"ci95": [c.ci95[0] * factor, c.ci95[1] * factor]}


def noise_summary(models: list[Any], t0: float = 0.0) -> tuple[list[str], list[dict[str, Any]]]:
    """Text lines and JSON rows of the six channels' noise models (NoiseCoefficients; field units
    of rigctl.display_units.NOISE_UNITS, slugged into the keys: N_deg_per_sqrt_h, B_mg, ...),
    each term with its 95 % interval or, where the data support only that, its 95 % upper bound
    (:func:`coefficient_text`); t0: the random walk's origin the covariance used, s."""
    from ..sensor_axes import SENSOR
    from ..solvers.segments import CHANNELS

    lines, rows = [], []
    for ch, m in zip(CHANNELS, models):
        U = NOISE_UNITS[SENSOR[ch]]
        (nu, nf), (bu, bf), (ku, kf) = U["N"], U["B"], U["K"]
        info = m.details
        ngroup = {g: coefficient_from(c) for g, c in info.get("N_by_group", {}).items()}
        if m.white_by_group is None:
            ntxt = coefficient_text(m.N, nf, nu)
        else:
            ntxt = ", ".join(coefficient_text(ngroup.get(g, Coefficient(v)), nf, "").replace("  ", " ").rstrip()
                             + f" ({g})"
                             for g, v in m.white_by_group.items()) + f" {nu}"
        nper = {g: v * nf for g, v in (m.white_by_group or {"*": m.N.value}).items()}
        row = {"channel": ch, "source": m.source, f"N_{slug(nu)}": nper, f"B_{slug(bu)}": m.B.value * bf,
               f"K_{slug(ku)}": m.K.value * kf, f"B_{slug(bu)}_interval": _coefficient_row(m.B, bf),
               f"K_{slug(ku)}_interval": _coefficient_row(m.K, kf),
               f"N_{slug(nu)}_interval": {g: _coefficient_row(c, nf) for g, c in ngroup.items()},
               "flicker_tau_min_s": m.flicker_tau_min_s,
               "flicker_tau_max_s": m.flicker_tau_max_s, "rw_origin_s": t0,
               **{k: v for k, v in info.items() if k in ("residual_dof", "converged", "note")}}
        rows.append(row)
        extra = f"; REML on {info['residual_dof']} residual dof" if "residual_dof" in info else ""
        lines.append(f"  {ch:<8} N {ntxt}, B {coefficient_text(m.B, bf, bu)}, "
                     f"K {coefficient_text(m.K, kf, ku)}{extra}")
    return lines, rows


def effect_parameter_line(p: dict[str, Any]) -> str:
    """One parameter of an effect the closed loop found ({name, value, sigma, ci95}, SI) in the
    field's units, as :func:`param_table` shows it: name, unit, value +- 1-sigma, 95 % interval."""
    d = display(p["name"])
    u = d.sigma(p["sigma"])
    v, us = format_value(d.value(p["value"]), u)
    lo, hi = (format_number(d.value(x), u) for x in p["ci95"])
    return f"{d.base:<32} {d.unit:<14} {v:>10} +- {us:<8} 95% [{lo}, {hi}]"
