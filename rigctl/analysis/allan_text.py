"""Presentation of an Allan result as text: the per-axis table ``rigctl allan`` prints.

The pipeline is :mod:`rigctl.analysis.allan`; field units and their spellings come from
:mod:`rigctl.solvers.noise_coefficients` and :mod:`rigctl.display_units`.
"""
from __future__ import annotations

from typing import Any

from ..display_units import need_text, slug
from ..solvers import allan_fit as F
from ..solvers import noise_coefficients as NC
from . import allan_excursions as EXA
from .allan_drift import tc_interval
from .allan import chi2_carrier_text, check_notes, check_warnings, judged, screening_notes


def format_table(axis: str, r: dict[str, Any]) -> str:
    """Human-readable table of one axis plus its fitted terms."""
    unit = r["_unit"]
    lines = [f"== {axis} ({r['sensor']}, {r['n_samples']} samples, {r['mode']} mode)",
             f"{'tau_s':>12} {'adev_' + unit:>14} {'lo68':>12} {'hi68':>12} "
             f"{'alpha':>5} {'edf':>10}"]
    for i in range(len(r["tau_s"])):
        lines.append(f"{r['tau_s'][i]:12.5g} {r['adev_' + unit][i]:14.6g} "
                     f"{r['lo68_' + unit][i]:12.6g} {r['hi68_' + unit][i]:12.6g} "
                     f"{int(r['alpha'][i]):5d} {r['edf'][i]:10.4g}")
    lines.append("fitted terms (joint IEEE 952 fit over all taus"
                 + (" with a first-order Gauss-Markov term" if r["fit"].get("gm_term") else "")
                 + "; 95 % intervals or bounds):")
    lines += term_lines(r)
    pw = r["piecewise"]["terms"]
    parts = []
    for t in ("N", "B", "K"):
        unit_f = F.FIELD_UNITS[r["sensor"]][t][0]
        v = pw[t][f"value_{unit_f}"]
        parts.append(f"{t}={'n/a' if v is None else format(v, '.5g')} {unit_f}")
    lines.append("piecewise read-offs (for comparison): " + ", ".join(parts))
    warns, notes = screening_notes(r)
    lines += [f"note: {t}" for t in notes + check_notes(r)]
    for w in warns + check_warnings(r):
        lines.append(f"warning: {w}")
    lines += quiet_lines(r)
    return "\n".join(lines)


def term_lines(r: dict[str, Any]) -> list[str]:
    """The fitted terms of an axis (or of its quiet stretch) as the table's rows, with the
    Gauss-Markov term and the goodness of fit."""
    lines = []
    co = NC.as_coefficients(r["fit"]["coefficients"])
    for t, e in r["fit"]["terms"].items():
        c, unit_f = NC.in_field_units(co, t)
        if c.resolved:
            lo, hi = c.ci95
            more = capture_note(e, True)
            if e.get("held_at_curve_limit"):  # the fit wanted more than the curve allows
                more += " (held at the curve's own limit: the fit wanted more)"
            lines.append(f"  {e['name']:>26}: {c.value:.5g} {unit_f} [{lo:.5g}, {hi:.5g}]{more}")
        else:
            more = capture_note(e, False)
            if e.get("edf_below_estimate") is not None:  # held or kept, but with EDF < 1
                more += (f"; the fit's EDF there {e['edf_below_estimate']:.2g} < "
                         f"{F.MIN_ESTIMATE_EDF:g}: no estimate")
            what = NC.BOUND_SOURCES.get(c.bound_from or "fit", NC.BOUND_SOURCES["fit"])
            point = e.get(f"curve_limit_{unit_f}")
            if c.bound_from == "band" and point is not None:  # the point read beside the 95 % one
                what += f"; the curve's lowest point alone reads {point:.5g} {unit_f}"
            lines.append(f"  {e['name']:>26}: < {c.upper95:.5g} {unit_f} "
                         f"({what}; not supported by the data{more})")
    gm_line = gm_term_line(r["fit"])
    if gm_line:
        lines.append(gm_line)
    fit_line = goodness_line(r["fit"].get("check") or {}, bool(r["fit"].get("gm_term")))
    if fit_line:
        lines.append(fit_line)
    return lines


def quiet_head(q: dict[str, Any]) -> str:
    """What the quiet stretch is and why it was taken (one sentence, no trailing colon)."""
    run = q["run"]
    a, b = q["t_s"]
    return (f"the record is not stationary at tau {run['tau_tested_s']:.3g} s (Bartlett p = "
            f"{run['p_value']:.2g} over {run['windows']} windows of {run['window_s']:.0f} s; the "
            f"self-check's run {run['tau_from_s']:.3g}-{run['tau_to_s']:.3g} s): quiet stretch t = "
            f"{a:.0f}-{b:.0f} s (samples {q['samples'][0]}-{q['samples'][1]} of the range analysed, "
            f"{100 * q['fraction']:.0f} % of it, {q['windows']} windows; its deviation there "
            f"x{q['deviation_ratio_at_run']:.2g} the record's)")


def quiet_check_text(check: dict[str, Any]) -> str:
    """The quiet stretch's own self-check in one clause."""
    if check.get("chi2_beyond_99"):  # never ok (rigctl.solvers.allan_fit): a finding
        carrier = chi2_carrier_text(check)
        st = judged(check)
        fw = ("every informative tau within the stretch's family-wise band, but "
              if st.get("n_outside_familywise", 1) == 0 else "")
        return (f"its self-check failed: {fw}the chi-square across taus is beyond its 99 % point "
                f"({st['chi2']:.4g} on {st['dof']} dof, p = {st['p_value']:.2g}): a "
                "finding, not a pass -- the terms do not describe the stretch's curve within its "
                "statistics" + (f"; carried by {carrier}" if carrier else ""))
    if check.get("ok"):
        return "its self-check passed"
    runs = check.get("outside") or []
    spans = ", ".join(f"{o['tau_from_s']:.3g}" if o["tau_from_s"] == o["tau_to_s"]
                      else f"{o['tau_from_s']:.3g}-{o['tau_to_s']:.3g}" for o in runs)
    causes = sorted({o.get("cause") or "" for o in runs} - {""})
    return (f"its self-check failed: the total leaves the stretch's 95 % band at "
            f"{check.get('n_outside', len(runs))} of {check.get('n_informative', '?')} informative taus"
            + (f" (tau {spans} s" + (f"; named: {', '.join(causes)}" if causes else "") + ")"
               if spans else ""))


def quiet_lines(r: dict[str, Any]) -> list[str]:
    """The quiet stretch's fit beside the whole record's (rigctl.analysis.allan_quiet): [] when
    the self-check named no run not stationary; a note when no stretch qualifies."""
    q = r.get("quiet_stretch")
    if not q:
        return []
    if not q.get("fitted"):
        run = q["run"]
        return [f"note: the record is not stationary at tau {run['tau_tested_s']:.3g} s (Bartlett "
                f"p = {run['p_value']:.2g}); {q.get('reason', 'no quiet stretch qualifies')}: the "
                "whole record's terms above are the only ones"]
    lines = [f"quiet stretch: {quiet_head(q)}. Fitted on its own, beside the whole record's "
             "terms above (which stay the record's; docs/allan.md, 'Non-stationary records'); "
             + quiet_check_text(q["fit"].get("check") or {}) + ":"]
    lines += term_lines(q)
    # its self-check's runs, each with its reason, as the record's (the chi-square sentence is
    # in the paragraph's head and the goodness-of-fit line above)
    lines += [f"warning: quiet stretch: {w}" for w in check_warnings(q)
              if not w.startswith("self-check failed:")]
    # its excursions: a warning while they are in its fit, a note once left out
    kind = "note" if q.get("excursions_excluded") else "warning"
    lines += [f"{kind}: {w}" for w in EXA.quiet_sentence(q, (r.get("excursions") or {}).get("unit", ""))]
    return lines


def capture_note(e: dict[str, Any], resolved: bool) -> str:
    """A term's Cramer-Rao capture figure as the table prints it after the value ('' when this
    capture determines it to +-25 %): for an estimate "(this capture: +-X % at best
    (Cramer-Rao); +-25 % needs about Y)", X the bound's sd; for a bound "; +-25 % would need at
    least Y of capture" inside the bound's parenthesis (:func:`rigctl.display_units.need_text`)."""
    need = need_text(e, resolved)
    if not need:
        return ""
    if resolved:
        return f" (this capture: +-{100 * e['crb_rel_sd']:.0f} % at best (Cramer-Rao); {need})"
    return f"; {need}"


def gm_term_line(fit: dict[str, Any]) -> str:
    """The fitted Gauss-Markov term as a row of the term table ('' when the fit has none):
    sigma_GM in the deviation's field unit (B's) and Tc in s, each with its 95 % interval and,
    where this capture cannot give it to +-25 %, its own Cramer-Rao capture figure (``crb``:
    :func:`rigctl.solvers.allan_fit._add_crb`) in the IEEE terms' words (:func:`capture_note`)."""
    t = fit.get("gm_term")
    if not t:
        return ""
    unit = t["sigma_unit"]
    s, (lo, hi) = t[f"sigma_{slug(unit)}"], t[f"sigma_ci95_{slug(unit)}"]
    tc = t["tc_s"]
    crb = t.get("crb") or {}
    name = "Gauss-Markov sigma_GM, Tc"
    sig_e, tc_e = crb.get("sigma") or {}, crb.get("tc") or {}
    if t.get("resolved"):
        val = f"{s:.5g} {unit} [{lo:.5g}, {hi:.5g}]{capture_note(sig_e, True)}"
    else:
        val = f"< {hi:.5g} {unit} (not resolved by the joint fit{capture_note(sig_e, False)})"
    tc_more = capture_note(tc_e, not tc_e.get("bounded"))
    if tc_e.get("bounded") and tc_more:  # Tc's lower limit, with sigma_GM at its bound
        tc_more = f" ({tc_more[2:]}, with sigma_GM at its bound)"
    more = " (held at the curve's own limit: the fit wanted more)" if t.get(
        "held_at_curve_limit") else ""
    return f"  {name:>26}: {val}, Tc {tc:.4g} s {tc_interval(t, 4)}{tc_more}{more}"


def goodness_line(check: dict[str, Any], with_gm: bool = False) -> str:
    """The joint fit's chi-square as one line: the reported terms against the deviations with
    their covariance across taus (that of the gap-free stretches when gaps were skipped),
    without the model error. Beyond its 99 % point it says so, whatever the self-check's
    verdict on the individual taus (the curve can stay within every tau's band while the taus
    together rule the model out)."""
    if "chi2" not in check:
        return ""
    p = check["p_value"]
    text = f"goodness of fit: chi-square {check['chi2']:.4g} on {check['dof']} dof (p = {p:.2g})"
    eps = check.get("model_error_rel", 0.0)
    if p < F.MODEL_ERROR_P and check.get("passes_on_bounds"):
        c = judged(check)
        return (text + "; beyond its 99 % point for the resolved terms alone; with the terms "
                f"known only as bounds taken within them, chi-square {c['chi2']:.4g} on "
                f"{c['dof']} dof (p = {c['p_value']:.2g}): the self-check passed on them (note)")
    if p < F.MODEL_ERROR_P:
        text += ("; beyond its 99 % point: the IEEE 952 terms"
                 + (" and the Gauss-Markov term" if with_gm else "")
                 + " do not describe this curve within its statistics")
        if eps > 0:
            text += f" (a model error of {100 * eps:.2g} % of sigma^2 was added to the weights)"
        text += ": a finding, not a pass"
        carrier = chi2_carrier_text(check)
        if carrier:
            text += f"; carried by {carrier}"
    return text
