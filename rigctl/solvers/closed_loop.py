"""The closed loop: fit the declared model, trace residual structure to a named effect, add it.

All segments and all six channels (accel x, y, z, gyro x, y, z) form one generalised linear
least-squares problem y = X beta + v, Cov(v) = Sigma: block diagonal over the channels, each
block the covariance of that channel's segment means (diag(s^2) for independent means, full
under bias instability / rate random walk, SegmentTable.cov). Everything below works on the
whitened problem L^-1 y = L^-1 X beta + L^-1 v (Sigma = L L^T): chi2, F, BIC, the
cross-validation and the residual scan. The declared model is A2 for both sensors (accel bias +
3x3 [+ quadratic], gyro drift + 3x3), with local gravity and Earth rate in the references.

Loop (every decision is recorded in ``explain``):

1. fit the current model; chi2_0, p_0 parameters, n observations.
2. for each library candidate not yet in the model: append its regressors (columns that the
   current model already spans are dropped as not identifiable), refit, and compute

       F = ((chi2_0 - chi2_c) / k) / (chi2_c / (n - p_c)),   p = P(F_{k, n-p_c} > F)
       BIC = n ln(chi2 / n) + p ln n,   dBIC = BIC_c - BIC_0

   (both are invariant to a common scale error of the noise model).
3. candidates with p * m < alpha (Bonferroni over the m candidates tested in the round; family-
   wise alpha = 0.01) and dBIC < 0 are ranked by dBIC; the best one is confirmed by
   leave-one-segment-out cross-validation. Under correlated errors the left-out segment's
   prediction uses the others' residuals too (best linear unbiased prediction); its error is
   (Dubrule 1983, universal kriging)

       e_g,loo = (P_gg)^-1 (P y)_g,   P = Sigma^-1 - Sigma^-1 X (X^T Sigma^-1 X)^-1 X^T Sigma^-1,

   and CV = sum_g e_g,loo^T (Sigma^-1)_gg e_g,loo (g: the rows of segment g). For a diagonal
   Sigma this is sum_g |(I - H_gg)^-1 e_g|^2 in whitened units (H the whitened hat matrix).
   The candidate is added only if CV drops; otherwise the next is tried. Repeat until none
   qualifies.
4. the whitened residuals of the final model are scanned for correlation with the physical
   variables (time, temperature, specific force, rate, |rate|, angular acceleration), each
   whitened and projected off the model's span (a partial correlation: the score test of adding
   the variable as a regressor), and for serial correlation in time; a significant correlation
   (Bonferroni-corrected p < alpha) or a chi2 with p < alpha that no candidate explained is
   reported as *unexplained*, naming the variable.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from . import distributions as _dist
from . import segment_cov as sc
from .accel24 import accel_columns
from ..jsonable import jsonable
from .calibration_result import CalibrationResult, fit_linear
from .effect_library import LIBRARY, Effect
from .gyro_rate import gyro_columns
from .gls_problem import (_chi2_drop, _cv_groups, _fit, _identifiable, _Problem, loso_cv, noise_floor,
                          satterthwaite_dof, variance_gradient)
from .segments import CHANNELS, SegmentTable

MG_PER_M_S2 = 1.0 / 9.80665e-3
DEG_H_PER_RAD_S = 180.0 / np.pi * 3600.0


def declared_design(seg: SegmentTable, quadratic: bool = True) -> tuple[NDArray[np.float64], list[str]]:
    """(K, 6, p) design of the declared A2 model for both sensors, and the names."""
    Xa, na = accel_columns(seg, quadratic)
    Xg, ng = gyro_columns(seg)
    K = len(seg)
    X = np.zeros((K, 6, len(na) + len(ng)))
    X[:, 0:3, : len(na)] = Xa
    X[:, 3:6, len(na):] = Xg
    return X, na + ng


VARIABLES = ("time", "temperature", "f_x", "f_y", "f_z", "w_x", "w_y", "w_z", "|w|", "|wdot|")


def _variables(seg: SegmentTable) -> dict[str, NDArray[np.float64]]:
    out: dict[str, NDArray[np.float64]] = {}
    if seg.time is not None:
        out["time"] = seg.time
    if seg.temperature is not None:
        out["temperature"] = seg.temperature
    for i, a in enumerate("xyz"):
        out[f"f_{a}"] = seg.f_ref[:, i]
    for i, a in enumerate("xyz"):
        out[f"w_{a}"] = seg.w_ref[:, i]
    out["|w|"] = np.linalg.norm(seg.w_ref, axis=1)
    if seg.ang_accel is not None:
        out["|wdot|"] = np.linalg.norm(seg.ang_accel, axis=1)
    return out


def residual_scan(seg: SegmentTable, prob: _Problem, fit: CalibrationResult,
                  q: NDArray[np.float64] | None = None) -> list[dict[str, Any]]:
    """Partial correlation of each channel's whitened residuals with each physical variable.

    The variable v (per segment) enters channel c as a candidate column x; its whitened form
    L^-1 x projected off the model's whitened span (orthonormal basis q) is correlated with the
    whitened residuals of channel c: r, t = r sqrt(df/(1 - r^2)), df = n_c - 2. A variable the
    model already holds (an accelerometer channel's f_x, f_y, f_z through its scale and
    misalignment, a constant temperature through the bias ...) is skipped: projected off, less
    than 1e-10 of its whitened norm is left, rounding whose "r" would be noise. Plus the lag-1
    serial correlation of channel c's whitened residuals in time order (one-sided).
    """
    var = _variables(seg)
    e_all = fit.normalized_residuals
    rows = []
    for c in range(6):
        m = prob.channel == c
        r = e_all[m]
        g = prob.group[m]
        nr = len(r)
        if nr < 4:
            continue
        for vn, v in var.items():
            x = np.zeros(prob.y.size)
            x[m] = v[g]
            xw = prob.white(x)
            n0 = float(xw @ xw)  # before the projection: a variable in the model's span has
            if q is not None:    # only rounding left after it (its "r" would be noise)
                xw = xw - q @ (q.T @ xw)
            else:
                xw[m] -= xw[m].mean()
            xc = xw[m]
            den = np.sqrt((xc @ xc) * (r @ r))
            if den == 0 or (xc @ xc) < 1e-20 * (n0 + 1e-300):
                continue
            rr = float(np.clip((xc @ r) / den, -1.0, 1.0))
            tstat = rr * np.sqrt((nr - 2) / max(1e-300, 1.0 - rr**2))
            rows.append({"channel": CHANNELS[c], "variable": vn, "r": rr, "t": abs(tstat), "df": nr - 2})
        if seg.time is not None and nr >= 8:
            order = np.argsort(seg.time[g], kind="stable")
            ro = r[order] - r.mean()
            r1 = float(ro[:-1] @ ro[1:] / (ro @ ro)) if ro @ ro > 0 else 0.0
            p = float(_dist.norm.sf(r1 * np.sqrt(nr)))  # one-sided: neighbours alike
            rows.append({"channel": CHANNELS[c], "variable": "time (serial correlation)", "r": r1, "p": p})
    tr = [row for row in rows if "t" in row]
    if tr:
        pv = 2.0 * _dist.t.sf(np.array([row.pop("t") for row in tr]), np.array([row.pop("df") for row in tr]))
        for row, p in zip(tr, pv):
            row["p"] = float(p)
    n_tests = max(1, len(rows))
    for row in rows:
        row["p_adj"] = min(1.0, row["p"] * n_tests)
    return sorted(rows, key=lambda d: d["p"])


def _pattern(seg: SegmentTable, prob: _Problem, fit: CalibrationResult, q: NDArray[np.float64]) -> str:
    rms = [float(np.sqrt(np.mean(fit.normalized_residuals[prob.channel == c] ** 2)))
           if np.any(prob.channel == c) else float("nan") for c in range(6)]
    c = int(np.nanargmax(rms))
    scan = [r for r in residual_scan(seg, prob, fit, q) if r["channel"] == CHANNELS[c]]
    top = f", follows {scan[0]['variable']} (r = {scan[0]['r']:+.2f})" if scan else ""
    return (f"chi2/dof = {fit.chi2_per_dof:.3g}; largest residual in {CHANNELS[c]} "
            f"({rms[c]:.2f} x its noise){top}")


@dataclass
class ClosedLoopResult:
    """Output of :func:`closed_loop` (see the module docstring). ``to_dict`` is JSON-able."""

    declared: CalibrationResult
    final: CalibrationResult
    effects: list[dict[str, Any]]
    explain: list[dict[str, Any]]
    rms_table: list[dict[str, Any]]
    unexplained: list[dict[str, Any]]
    not_available: dict[str, str]
    truth_errors: list[dict[str, Any]] = field(default_factory=list)

    @property
    def effect_names(self) -> list[str]:
        return [e["name"] for e in self.effects]

    def to_dict(self) -> dict[str, Any]:
        return jsonable({
            "declared": self.declared.to_dict(), "final": self.final.to_dict(),
            "effects": self.effects, "explain": self.explain, "rms_table": self.rms_table,
            "unexplained": self.unexplained, "not_available": self.not_available,
            "truth_errors": self.truth_errors})


def _rms_table(prob: _Problem, before: CalibrationResult, after: CalibrationResult,
               q: NDArray[np.float64], seg: SegmentTable | None = None) -> list[dict[str, Any]]:
    """RMS per channel: raw (the measurement against the table's reference with nominal scale
    and no calibration: y - f_ref, y - w_ref), declared model ("before"), final ("after"), and
    the noise floor."""
    rows = []
    floor = noise_floor(prob, q)
    raw = None if seg is None else prob.y - np.concatenate([seg.f_ref, seg.w_ref], axis=1).ravel()[prob.keep]
    for c, ch in enumerate(CHANNELS):
        m = prob.channel == c
        if not np.any(m):
            continue
        f, unit = (MG_PER_M_S2, "mg") if c < 3 else (DEG_H_PER_RAD_S, "deg_h")
        rows.append({"channel": ch, "unit": unit,
                     f"noise_floor_{unit}": float(floor[c] * f),
                     **({} if raw is None else {f"rms_raw_{unit}": float(np.sqrt(np.nanmean(raw[m] ** 2)) * f)}),
                     f"rms_before_{unit}": float(np.sqrt(np.mean(before.residuals[m] ** 2)) * f),
                     f"rms_after_{unit}": float(np.sqrt(np.mean(after.residuals[m] ** 2)) * f)})
    rows.append({"channel": "all", "unit": "1", "chi2_per_dof_before": before.chi2_per_dof,
                 "chi2_per_dof_after": after.chi2_per_dof})
    return rows


def closed_loop(
    seg: SegmentTable,
    quadratic: bool = True,
    alpha: float = 0.01,
    library: Sequence[Effect] = LIBRARY,
    truth: dict[str, float] | None = None,
    max_effects: int = 6,
) -> ClosedLoopResult:
    """Declared fit, then add library effects while one is significant and passes CV.

    Args:
        seg: per-segment means, uncertainties and references.
        quadratic: declare the accelerometer quadratic term (A2) or not.
        alpha: family-wise significance level (Bonferroni within each round).
        library: candidate effects (default :data:`~rigctl.solvers.effect_library.LIBRARY`).
        truth: optional {parameter name: true value} for before/after errors.
        max_effects: safety bound on the number of effects added.
    """
    prob = _Problem.from_table(seg)
    n = prob.y.size
    X3, names = declared_design(seg, quadratic)
    X = prob.rows(X3)
    declared = _fit(prob, X, names, "closed_loop_declared")
    current, cur_names, fit = X, list(names), declared
    effects: list[dict[str, Any]] = []
    explain: list[dict[str, Any]] = []
    not_available: dict[str, str] = {}
    built: dict[str, tuple[NDArray[np.float64], list[str]]] = {}
    for eff in library:
        if quadratic and eff.name == "accel_quadratic":
            not_available[eff.name] = "already in the declared model"
            continue
        b = eff.build(seg)
        if isinstance(b, str):
            not_available[eff.name] = b
            continue
        built[eff.name] = (prob.rows(b[0]), b[1])
    in_model: set[str] = set()
    step = 0
    while len(effects) < max_effects:
        step += 1
        q_cur = prob.qr(current)
        pattern = _pattern(seg, prob, fit, q_cur)
        cands = []
        for eff in library:
            if eff.name not in built or eff.name in in_model:
                continue
            Xc, cn = built[eff.name]
            keep, Bp = _identifiable(prob, q_cur, Xc)
            if not np.any(keep):
                explain.append({"step": step, "residual_pattern": pattern, "candidate": eff.name,
                                "statistic": "-", "decision": "not identifiable with these segments"})
                in_model.add(eff.name)
                continue
            k = int(keep.sum())
            p_c = current.shape[1] + k
            chi2_c = max(fit.chi2 - _chi2_drop(Bp[:, keep], fit.normalized_residuals), 1e-300)
            F = ((fit.chi2 - chi2_c) / k) / (chi2_c / (n - p_c)) if n > p_c else 0.0
            pv = float(_dist.f.sf(F, k, n - p_c)) if n > p_c else 1.0
            dbic = n * np.log(chi2_c / fit.chi2) + k * np.log(n)
            cands.append({"effect": eff, "X": np.hstack([current, Xc[:, keep]]),
                          "names": cur_names + [c for c, kk in zip(cn, keep) if kk],
                          "F": float(F), "p": pv, "k": k, "dBIC": float(dbic)})
        m = max(1, len(cands))
        for c in cands:
            c["p_adj"] = min(1.0, c["p"] * m)
        sig = sorted([c for c in cands if c["p_adj"] < alpha and c["dBIC"] < 0], key=lambda c: c["dBIC"])
        for c in sorted(cands, key=lambda c: c["p"]):
            if c not in sig:
                explain.append({"step": step, "residual_pattern": pattern, "candidate": c["effect"].name,
                                "statistic": _stat(c), "decision": "not significant"})
        added = None
        for c in sig:
            if added is not None:
                explain.append({"step": step, "residual_pattern": pattern, "candidate": c["effect"].name,
                                "statistic": _stat(c), "decision": f"deferred: {added['effect'].name} ranked first"})
                continue
            q_new = prob.qr(c["X"])
            groups = _cv_groups(prob, q_new)
            cv0 = loso_cv(prob, current, groups, q_cur)
            cv1 = loso_cv(prob, c["X"], groups, q_new)
            stat = _stat(c) + f", LOSO-CV {cv0:.4g} -> {cv1:.4g}"
            if cv1 < cv0:
                added = c
                c["fit"] = _fit(prob, c["X"], c["names"], "candidate")
                explain.append({"step": step, "residual_pattern": pattern, "candidate": c["effect"].name,
                                "statistic": stat, "decision": "added (significant, best BIC, CV improves)"})
                c["cv"] = (cv0, cv1)
            else:
                explain.append({"step": step, "residual_pattern": pattern, "candidate": c["effect"].name,
                                "statistic": stat, "decision": "rejected: fails cross-validation"})
        if added is None:
            break
        excess = fit.chi2 - fit.dof
        frac = (fit.chi2 - added["fit"].chi2) / excess if excess > 0 else float("nan")
        # rivals nearly as good (dBIC within 2: "not worth more than a bare mention")
        rivals = [c["effect"].name for c in sig if c is not added and c["dBIC"] - added["dBIC"] < 2.0]
        current, cur_names, fit = added["X"], list(added["names"]), added["fit"]
        in_model.add(added["effect"].name)
        effects.append({"name": added["effect"].name, "description": added["effect"].description,
                        "F": added["F"], "p": added["p"], "p_adj": added["p_adj"], "dBIC": added["dBIC"],
                        "cv_before": added["cv"][0], "cv_after": added["cv"][1], "step": step,
                        "excess_chi2_explained": float(frac),
                        "attribution": "ambiguous" if rivals else "confirmed", "alternatives": rivals})
        if rivals:
            explain.append({"step": step, "residual_pattern": pattern, "candidate": added["effect"].name,
                            "statistic": f"dBIC within 2 of {', '.join(rivals)}",
                            "decision": "added, but ambiguous: the data cannot tell these apart "
                                        "(e.g. time and temperature collinear during warm-up)"})
    final = fit_linear(current, prob.y, prob.s, cur_names, method="closed_loop_final", cov=prob.W)
    q_fin = prob.qr(current)
    if final.status == "ok":
        _carry_power_on(prob, current, final, seg)
    noise = seg.extra.get("noise_components")
    if final.status == "ok" and noise is not None and np.shape(noise["comps"])[1] == len(seg):
        nu = satterthwaite_dof(prob, current, final.covariance, noise)
        if nu is not None:  # the noise model was estimated from these data: t intervals
            # except the biases: their variance is dominated by the extrapolation of the slow
            # terms to power-on (a model statement the contrasts do not constrain; at K^2 ~ 0
            # the delta method breaks down), so they keep the normal interval of the model
            bias = np.array(["_bias_" in nm for nm in cur_names])
            final.interval, final.param_dof = "t", np.where(bias, np.inf, nu)
            final.extra["interval_dof"] = ("Student t with Satterthwaite dof for the estimated noise "
                                           "model (biases: normal)")
    for e in effects:
        idx = [i for i, nm in enumerate(final.names) if nm not in names and
               nm in built[e["name"]][1]]
        e["parameters"] = [{"name": final.names[i], "value": float(final.values[i]),
                            "sigma": float(final.sigma[i]), "ci95": final.ci95[i].tolist()} for i in idx]
    unexplained = _unexplained(seg, prob, final, alpha, q_fin)
    if unexplained:
        for e in effects:
            if not e["excess_chi2_explained"] >= 0.5:
                e["attribution"] = "uncertain"
                explain.append({"step": step, "residual_pattern": "structure remains after the loop",
                                "candidate": e["name"],
                                "statistic": f"explained {100 * e['excess_chi2_explained']:.0f} % of the excess chi2",
                                "decision": "kept, but attribution uncertain: it may stand in for an "
                                            "effect outside the library"})
    for u in unexplained:
        explain.append({"step": step, "residual_pattern": u["pattern"], "candidate": "(none)",
                        "statistic": u["statistic"], "decision": "unexplained"})
    res = ClosedLoopResult(declared=declared, final=final, effects=effects, explain=explain,
                           rms_table=_rms_table(prob, declared, final, q_fin, seg), unexplained=unexplained,
                           not_available=not_available)
    if truth:
        for nm in names:
            if nm in truth:
                t = truth[nm]
                res.truth_errors.append({
                    "name": nm, "truth": t,
                    "error_before": declared.value(nm) - t, "sigma_before": declared.sigma_of(nm),
                    "error_after": final.value(nm) - t, "sigma_after": final.sigma_of(nm)})
    return res


def _carry_power_on(prob: _Problem, X: NDArray[np.float64], fit: CalibrationResult, seg: SegmentTable) -> None:
    """Add to each bias's variance the power-on term of a random walk the covariance left at 0
    (:func:`rigctl.solvers.noise_coefficients.power_on_k2`): K_bound^2 (V X^T Sigma^-1 C_rw
    Sigma^-1 X V)_jj, the variance that a random walk of that size from t0 adds to this
    estimator's bias j (its extrapolation to power-on). The estimate, every other parameter's
    variance and the fit's chi2 stay as they are: only the biases' intervals widen."""
    po = seg.extra.get("power_on_k2")
    if not po or seg.t_start is None or seg.t_end is None or not any(po["k2"]):
        return
    rw = sc.cov_random_walk(np.asarray(seg.t_start, dtype=np.float64),
                            np.asarray(seg.t_end, dtype=np.float64), float(po["t0"]))[None]
    cov = fit.covariance.copy()
    Xn = np.nan_to_num(X)
    for j, nm in enumerate(fit.names):
        if "_bias_" not in nm:
            continue
        chans = np.unique(prob.channel[Xn[:, j] != 0])
        if chans.size != 1 or not po["k2"][int(chans[0])]:
            continue
        g = variance_gradient(prob, X, fit.covariance, int(chans[0]), rw)
        if g is not None:
            cov[j, j] += po["k2"][int(chans[0])] * float(g[0, j])
    fit.covariance = cov
    fit.extra["power_on_k2"] = [float(v) for v in po["k2"]]


def _stat(c: dict[str, Any]) -> str:
    return f"F({c['k']},.) = {c['F']:.3g}, p = {c['p']:.2g}, p_adj = {c['p_adj']:.2g}, dBIC = {c['dBIC']:.3g}"


def _unexplained(seg: SegmentTable, prob: _Problem, fit: CalibrationResult, alpha: float,
                 q: NDArray[np.float64]) -> list[dict[str, Any]]:
    out = []
    scan = residual_scan(seg, prob, fit, q)
    for row in scan:
        if row["p_adj"] < alpha:
            out.append({"channel": row["channel"], "variable": row["variable"],
                        "pattern": f"{row['channel']} residuals follow {row['variable']}",
                        "statistic": f"r = {row['r']:+.3f}, p_adj = {row['p_adj']:.2g}"})
    if fit.dof > 0 and fit.chi2_p_value < alpha and not out:
        top = scan[0] if scan else None
        out.append({"channel": top["channel"] if top else "all",
                    "variable": top["variable"] if top else "unknown",
                    "pattern": f"chi2/dof = {fit.chi2_per_dof:.3g} beyond the noise model",
                    "statistic": f"chi2 p = {fit.chi2_p_value:.2g}"
                                 + (f"; strongest: {top['channel']} vs {top['variable']} r = {top['r']:+.2f}" if top else "")})
    return out


def format_report(res: ClosedLoopResult, explain: bool = False,
                  effect_line: Callable[[dict[str, Any]], str] | None = None) -> str:
    """Human text: effects found, before/after RMS table, truth errors, and the explain chain.
    ``effect_line``: the text of one effect parameter ({name, value, sigma, ci95}, SI), e.g.
    in the field's units (rigctl.analysis.calibration_text.effect_parameter_line); default SI."""
    lines = ["Closed loop: effects found" if res.effects else "Closed loop: no undeclared effect found"]
    for e in res.effects:
        lines.append(f"  {e['name']}: {e['description']} (p_adj = {e['p_adj']:.2g}, dBIC = {e['dBIC']:.3g}, "
                     f"{100 * e['excess_chi2_explained']:.0f} % of excess chi2, {e['attribution']})")
        for p in e["parameters"]:
            lines.append("      " + (effect_line(p) if effect_line else
                                     f"{p['name']:<40} {p['value']:+.4g} +- {p['sigma']:.2g}  "
                                     f"95% [{p['ci95'][0]:+.4g}, {p['ci95'][1]:+.4g}]"))
    lines.append(f"  {'channel':<10} {'noise floor':>14} {'raw':>14} {'declared':>14} {'final':>14}")
    for r in res.rms_table:
        if r["channel"] == "all":
            lines.append(f"  chi2/dof   {'':>29} {r['chi2_per_dof_before']:>14.3g} {r['chi2_per_dof_after']:>14.3g}")
            continue
        u = r["unit"]
        shown = {"deg_h": "deg/h"}.get(u, u)
        lines.append(f"  {r['channel']:<10} {r[f'noise_floor_{u}']:>11.4g} {shown:<5} "
                     f"{r.get(f'rms_raw_{u}', float('nan')):>11.4g} {shown:<5} {r[f'rms_before_{u}']:>11.4g} "
                     f"{shown:<5} {r[f'rms_after_{u}']:>11.4g} {shown}")
    for u in res.unexplained:
        lines.append(f"  UNEXPLAINED: {u['pattern']} ({u['statistic']})")
    if res.truth_errors:
        lines.append(f"  {'parameter':<28} {'|err|/sigma before':>18} {'|err|/sigma after':>18}")
        for t in res.truth_errors:
            lines.append(f"  {t['name']:<28} {abs(t['error_before']) / t['sigma_before']:>18.2f} "
                         f"{abs(t['error_after']) / t['sigma_after']:>18.2f}")
    if explain:
        lines.append("  explain:")
        for x in res.explain:
            lines.append(f"    [{x['step']}] {x['residual_pattern']} | {x['candidate']} | {x['statistic']} | {x['decision']}")
    for k, v in res.not_available.items():
        lines.append(f"  not available: {k}: {v}")
    return "\n".join(lines)


def calibrate_session(seg: SegmentTable, quadratic: bool = True, truth: dict[str, float] | None = None,
                      alpha: float = 0.01) -> dict[str, Any]:
    """Everything `rigctl calibrate` needs from one SegmentTable.

    Runs the separate published solvers on their segments -- accel24 and the static gyro biases
    on kind "orientation", the forward/reverse rate test on kind "rate" -- and the joint closed
    loop on all segments. Returns {"accel24", "gyro_bias_static", "gyro_rate": CalibrationResult
    or None when the session has no such segments, "closed_loop": ClosedLoopResult}; use
    :func:`session_to_dict` for JSON and :func:`format_report` for the text.
    """
    from .accel24 import calibrate_accel, calibrate_gyro_bias_static
    from .gyro_rate import calibrate_gyro_rate

    static = seg.kind == "orientation"
    rate = seg.kind == "rate"

    def covs(mask: NDArray[np.bool_], sensor: slice) -> NDArray[np.float64] | None:
        return None if seg.cov is None else seg.cov[sensor][:, mask][:, :, mask]

    out: dict[str, Any] = {"accel24": None, "gyro_bias_static": None, "gyro_rate": None}
    if static.sum() >= 6:
        out["accel24"] = calibrate_accel(seg.f[static], seg.f_sigma[static], seg.f_ref[static],
                                         seg.f_outer()[static], quadratic, covs(static, slice(0, 3)))
        out["gyro_bias_static"] = calibrate_gyro_bias_static(seg.w[static], seg.w_sigma[static],
                                                             seg.w_ref[static], None, covs(static, slice(3, 6)))
    if rate.sum() >= 2:
        # pairing on the full reference rate is safe: the Earth rate is < 1e-4 of any table rate
        out["gyro_rate"] = calibrate_gyro_rate(seg.w[rate], seg.w_sigma[rate], seg.w_ref[rate],
                                               seg.w_ref[rate], covs(rate, slice(3, 6)))
    out["closed_loop"] = closed_loop(seg, quadratic=quadratic, alpha=alpha, truth=truth)
    return out


def session_to_dict(results: dict[str, Any]) -> dict[str, Any]:
    """JSON-serialisable form of :func:`calibrate_session`'s output."""
    return {k: (None if v is None else v.to_dict()) for k, v in results.items()}
