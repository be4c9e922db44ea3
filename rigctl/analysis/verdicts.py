"""Verdicts of a unit's results against a spec: one row per specified parameter, an overall.

:func:`evaluate` applies a :class:`rigctl.config.spec.Spec` to :class:`~rigctl.analysis.results.
Measured` parameters with the pure decision rule of :mod:`rigctl.solvers.conformity` and
returns a JSON-able dict, stored with the results (``payload["verdicts"]`` of
/results/calibration and /results/allan) and read by the report, the certificate and the
results database. :func:`format_verdicts` is the text the commands print.
"""
from __future__ import annotations

import math
from typing import Any

from ..display_units import format_value
from ..solvers.conformity import INDETERMINATE, decide, overall
from ..config.spec import Spec
from .results import Measured

RULE_TEXT = {
    "guarded": ("guarded acceptance and rejection (JCGM 106:2012 8.3, ISO 14253-1:2017): guard band "
                "= the expanded uncertainty U (95 % interval); PASS when the whole interval is inside "
                "the tolerance, FAIL when it is wholly outside, INDETERMINATE otherwise; a PASS carries "
                "at most 2.5 % probability of false accept at a one-sided limit"),
    "simple": ("simple acceptance (JCGM 106:2012 8.2, shared risk): PASS when the measured value is "
               "inside the tolerance, FAIL otherwise, whatever its uncertainty; the risk column gives "
               "each verdict's probability of being wrong (false accept for a PASS, false reject for a "
               "FAIL) from the normal / Student-t / chi-square distribution of the result"),
}


def _num(x: float) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def evaluate(spec: Spec, measured: list[Measured], kinds: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Decide every specified parameter present in ``measured``.

    ``kinds`` limits the spec's entries to what this evaluation measures ("calibration",
    "allan"): an entry matching no measured parameter is listed under ``not_measured`` and does
    not enter the overall verdict of a command that cannot measure it; it does when ``kinds``
    is None (the certificate: everything the spec asks must be decided).
    """
    rows, used = [], set()
    for m in measured:
        d = m.display
        lim = spec.limit_for(d.base)
        if lim is None:
            continue
        used.add(lim.pattern)
        lo, hi = lim.si(d)
        if not (math.isfinite(m.value) and math.isfinite(m.u)):
            dec_v, lo_i, hi_i, pc, risk = INDETERMINATE, math.nan, math.nan, math.nan, math.nan
        else:
            dec = decide(m.estimate, lo, hi, spec.rule)
            dec_v, lo_i, hi_i, pc, risk = dec.verdict, dec.lo, dec.hi, dec.p_conform, dec.risk
        rows.append({"parameter": d.base, "name_si": m.name, "unit": d.unit, "source": m.source,
                     "value": d.value(m.value), "u": d.sigma(m.u), "ci95": [_num(d.value(lo_i)), _num(d.value(hi_i))],
                     "k": _num(m.coverage_factor), "dof": _num(m.dof),
                     "lower": None if lo is None else d.value(lo), "upper": None if hi is None else d.value(hi),
                     "tolerance": lim.text(d), "verdict": dec_v, "p_conform": _num(pc), "risk": _num(risk),
                     "spec_line": lim.line})
    not_measured = [lim.pattern for lim in spec.limits if lim.pattern not in used]
    verdicts = [r["verdict"] for r in rows]
    if kinds is None and not_measured:
        verdicts.append(INDETERMINATE)
    return {"spec": spec.name, "spec_file": spec.path, "rule": spec.rule, "rule_text": RULE_TEXT[spec.rule],
            "overall": overall(verdicts), "parameters": rows, "not_measured": not_measured}


def format_verdicts(v: dict[str, Any]) -> str:
    """The verdict table the commands print (display units, digits from the uncertainty)."""
    lines = [f"Verdicts against {v['spec']} ({v['spec_file']}): decision rule: {v['rule_text']}",
             f"  {'parameter':<32} {'unit':<14} {'value':>12} {'u':>9} {'95% interval':>24} "
             f"{'tolerance':>22} {'p(conform)':>10}  verdict"]
    for r in v["parameters"]:
        val, u = format_value(r["value"], r["u"])
        lo, hi = r["ci95"]
        ci = "n/a" if lo is None else f"[{format_value(lo, r['u'])[0]}, {format_value(hi, r['u'])[0]}]"
        pc = "n/a" if r["p_conform"] is None else f"{r['p_conform']:.3f}"
        risk = ""
        if v["rule"] == "simple" and r["risk"] is not None:
            risk = f" (risk of false {'accept' if r['verdict'] == 'PASS' else 'reject'} {100 * r['risk']:.2g} %)"
        lines.append(f"  {r['parameter']:<32} {r['unit']:<14} {val:>12} {u:>9} {ci:>24} "
                     f"{r['tolerance']:>22} {pc:>10}  {r['verdict']}{risk}")
    if v["not_measured"]:
        lines.append("  not measured here: " + ", ".join(v["not_measured"]))
    lines.append(f"OVERALL: {v['overall']}")
    return "\n".join(lines)
