"""``rigctl history UNIT``: every parameter of a unit across its calibrations, with its drift.

Reads the results database (``--db``, default ``runs/results.sqlite``). Per parameter: each
analysis (recorded UTC, run, value +- standard uncertainty in the display unit, verdict) and
the drift: the weighted least-squares line value = a + d (t - t_mean), weights 1/u^2, t in
years (:func:`rigctl.solvers.calibration_result.fit_linear`; when the scatter exceeds the
uncertainties, chi2/dof > 1 with p < 0.001, the slope's uncertainty is scaled by the Birge ratio
and stated so). Two calibrations give a slope with no check of the scatter (dof 0).
A drift is stated as a number per year only when it is resolved: the calibrations span at least
:data:`MIN_DRIFT_SPAN_S` (one day; minutes apart, a slope per year extrapolates the noise of
two readings by 10^5) and the slope's 95 % interval excludes zero. Otherwise the line says
"not resolved" and why (with the slope +- u when only the interval is the reason).
Exit codes: 0 done, 2 invalid input (no such unit or database).
"""
from __future__ import annotations

import argparse
import datetime as _dt
from pathlib import Path
from typing import Any

import numpy as np

from ..display_units import format_value
from ..solvers.calibration_result import fit_linear
from ..errors import InputError
from ..units import format_duration

YEAR_S = 365.25 * 86400.0
#: shortest span of calibration times (first to last) over which a drift per year is stated, s
MIN_DRIFT_SPAN_S = 86400.0


def _t(s: str) -> float:
    return _dt.datetime.fromisoformat(s.replace("Z", "+00:00")).timestamp()


def drift(t_s: np.ndarray, v: np.ndarray, u: np.ndarray) -> dict[str, Any] | None:
    """Weighted linear drift of values ``v`` +- ``u`` at times ``t_s`` (s): slope per year, its
    standard uncertainty, dof, chi2/dof and whether the covariance was scaled (None for < 2
    points or a zero uncertainty)."""
    if t_s.size < 2 or not np.all(u > 0) or np.ptp(t_s) <= 0:
        return None
    ty = (t_s - t_s.mean()) / YEAR_S
    r = fit_linear(np.column_stack([np.ones_like(ty), ty]), v, u, ["offset", "slope_per_year"],
                   method="drift")
    lo, hi = r.ci95[1]
    return {"slope_per_year": float(r.values[1]), "u_slope_per_year": float(r.sigma[1]), "dof": int(r.dof),
            "chi2_per_dof": float(r.chi2_per_dof) if r.dof > 0 else None, "scaled": r.interval == "t",
            "ci95_per_year": (float(lo), float(hi)), "span_s": float(np.ptp(t_s))}


def unresolved_reason(d: dict[str, Any]) -> str | None:
    """Why the drift ``d`` (from :func:`drift`) is not resolved, or None when it is: the
    calibrations span less than MIN_DRIFT_SPAN_S, or the slope's 95 % interval contains zero."""
    if d["span_s"] < MIN_DRIFT_SPAN_S:
        return (f"the calibrations span only {format_duration(d['span_s'])}; a drift per year needs "
                f"them at least {format_duration(MIN_DRIFT_SPAN_S)} apart")
    lo, hi = d["ci95_per_year"]
    if lo <= 0.0 <= hi:
        return "its 95 % interval includes zero"
    return None


def history_text(unit: str, analyses: list[Any]) -> str:
    """The history table of one unit (analyses from rigctl.recording.results_db.unit_history)."""
    lines = [f"rigctl history: unit {unit}: {len(analyses)} analyses"]
    series: dict[tuple[str, str], list[tuple[Any, Any]]] = {}
    for a in analyses:
        for r in a.results:
            series.setdefault((a.kind, r.parameter), []).append((a, r))
    for (kind, param), rows in sorted(series.items()):
        unit_d = rows[0][1].unit
        lines.append(f"{param} [{unit_d}] ({kind})")
        for a, r in rows:
            v, u = format_value(r.value, r.u)
            lines.append(f"  {a.recorded_utc or a.analysed_utc:<26} {a.run:<40} {v:>12} +- {u:<9}"
                         f" {r.verdict or ''}")
        t = np.array([_t(a.recorded_utc or a.analysed_utc) for a, _ in rows])
        d = drift(t, np.array([r.value for _, r in rows]), np.array([r.u for _, r in rows]))
        if d is None:
            lines.append("  drift: n/a (fewer than two calibrations at different times)")
            continue
        why = unresolved_reason(d)
        if why is not None and d["span_s"] < MIN_DRIFT_SPAN_S:
            lines.append(f"  drift: not resolved yet: {why}")
            continue
        s, us = format_value(d["slope_per_year"], d["u_slope_per_year"])
        note = (f"dof {d['dof']}, chi2/dof {d['chi2_per_dof']:.3g}" if d["chi2_per_dof"] is not None
                else "2 points: the scatter is not checked")
        if d["scaled"]:
            note += ": scatter above the uncertainties, slope uncertainty scaled by sqrt(chi2/dof)"
        if why is not None:
            lines.append(f"  drift: not resolved: {s} +- {us} {unit_d}/year, {why} ({note})")
        else:
            lines.append(f"  drift: {s} +- {us} {unit_d}/year ({note})")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl history``."""
    from ..analysis.production import results_db_module

    db = results_db_module("rigctl history")

    target = args.db or str(Path(args.runs) / db.DEFAULT_NAME)
    if "://" not in target and not Path(target).is_file():
        raise InputError("no results database here", target,
                         hint="give --db FILE|URL or --runs DIR (the folder holding results.sqlite)")
    engine = db.open_db(target)
    try:
        analyses = db.unit_history(engine, args.unit, args.kind)
        if not analyses:
            known = sorted({r["unit_id"] for r in db.all_rows(engine)})
            raise InputError(f"no results for unit {args.unit!r} in the database", target,
                             hint="units in it: " + (", ".join(known) if known else "none"))
        print(history_text(args.unit, analyses))
    finally:
        engine.dispose()
    return 0


def register(subparsers: Any) -> None:
    """Add the ``history`` sub-command."""
    p = subparsers.add_parser("history", description=__doc__.split("\n\n")[0])
    p.add_argument("unit", help="unit ID (/meta imu_serial, else imu_device_id; `rigctl calibrate` prints it)")
    p.add_argument("--db", metavar="URL|FILE", help="results database (default RUNS/results.sqlite)")
    p.add_argument("--runs", default="runs", help="the runs directory whose results.sqlite to read (default runs)")
    p.add_argument("--kind", choices=("calibration", "allan"), help="only calibrations or only Allan results")
    p.set_defaults(func=run)
