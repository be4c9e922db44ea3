"""The report page: one self-contained HTML file (inline CSS, PNGs as base64 data URIs).

Sections (element ids): ``verdicts`` (first: the verdicts stored with the results), ``summary``, ``table``, ``calibration``, ``closed-loop``, ``allan``,
``sync``, ``events`` (faults and suspender events), ``provenance``. A section whose results group is absent says "Not run".
Every plot is an ``<img id="plot-<plot id>">`` with a ``data:image/png;base64,`` source.
Numbers are shown in field units (mg, deg/h, ppm, ms) with the unit in the column header.
"""
from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path
from typing import Any

from .report import FAULT_KINDS, RunData, find_session
from ..analysis.allan_drift import tc_interval
from ..display_units import display, format_value
from ..sensor_axes import axis_name
from .report_allan import allan_curves
from ..analysis.allan import over_fit_text

G0 = 9.80665
SECTIONS = (("verdicts", "Verdicts"), ("summary", "Summary"), ("table", "Table orientation and rate"),
            ("calibration", "Calibration"), ("closed-loop", "Closed loop"),
            ("thermal", "Thermal calibration"),
            ("allan", "Allan deviation"), ("sync", "Time synchronisation"),
            ("events", "Faults and suspender events"), ("provenance", "Provenance"))
CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:0;color:#1d2330;
background:#f4f6f9}
header{background:#1f3b5a;color:#fff;padding:18px 28px}header h1{margin:0 0 4px;font-size:22px}
header p{margin:0;opacity:.85}
nav{background:#fff;border-bottom:1px solid #d5dbe3;padding:8px 28px}
nav a{margin-right:16px;color:#1f5fa8;text-decoration:none;font-size:14px}
main{padding:8px 28px 40px;max-width:1180px}
section{background:#fff;border:1px solid #d5dbe3;border-radius:6px;margin:16px 0;padding:6px 18px 14px}
h2{font-size:18px;color:#1f3b5a;border-bottom:2px solid #e3e8ef;padding-bottom:4px}
h3{font-size:15px;color:#33475b;margin-bottom:6px}
table{border-collapse:collapse;font-size:12.5px;margin:6px 0 10px}
th,td{border:1px solid #dde3ea;padding:3px 7px;text-align:left;vertical-align:top}
th{background:#eef2f7}td.num{text-align:right;font-family:Menlo,Consolas,monospace}
pre{background:#f6f8fa;border:1px solid #e1e4e8;padding:8px;font-size:12px;overflow-x:auto;
max-height:420px}
img.plot{max-width:100%;border:1px solid #e3e8ef;background:#fff}
figure{margin:8px 0}figcaption{font-size:12px;color:#5b6b7b}
.not-run{background:#fff7e0;border-left:4px solid #e0a800;padding:8px 12px;color:#6b5300}
.status-complete{color:#137333;font-weight:bold}.status-bad{color:#b3261e;font-weight:bold}
.warn{color:#b3261e}.ok{color:#137333}.muted{color:#6b7785;font-size:12px}
.PASS{color:#137333;font-weight:bold}.FAIL{color:#b3261e;font-weight:bold}
.INDETERMINATE{color:#8a5a00;font-weight:bold}
@media print{nav{display:none}body{background:#fff}main{max-width:none;padding:0}
section{border:none;page-break-inside:auto;margin:6mm 0}details{display:block}pre{max-height:none;overflow:visible;
white-space:pre-wrap}details>summary{list-style:none}figure,tr{page-break-inside:avoid}}
"""


def esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def fmt(v: Any, digits: int = 5) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int):  # a count is shown whole (360000 IMU samples, not 3.6e+05)
        return str(v)
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            return "n/a"
        return f"{v:.{digits}g}"
    return str(v)


def table(headers: list[str], rows: list[list[Any]], num_from: int = 1) -> str:
    """HTML table; cells from column ``num_from`` on that are numbers are right-aligned."""
    out = ["<table><tr>" + "".join(f"<th>{esc(h)}</th>" for h in headers) + "</tr>"]
    for r in rows:
        cells = []
        for j, c in enumerate(r):
            num = j >= num_from and isinstance(c, (int, float)) and not isinstance(c, bool)
            cells.append(f"<td class=\"num\">{esc(fmt(c))}</td>" if num else f"<td>{esc(fmt(c))}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def img(plots: dict[str, Path], pid: str, alt: str) -> str:
    p = plots.get(pid)
    if p is None:
        return f"<p class=\"muted\">(no data for the plot {esc(pid)})</p>"
    b64 = base64.b64encode(Path(p).read_bytes()).decode("ascii")
    return (f"<figure><img id=\"plot-{esc(pid)}\" class=\"plot\" alt=\"{esc(alt)}\" "
            f"src=\"data:image/png;base64,{b64}\"><figcaption>{esc(alt)} "
            f"({esc(Path(p).name)})</figcaption></figure>")


def not_run(what: str, how: str) -> str:
    return f"<p class=\"not-run\">Not run: {esc(what)}. {esc(how)}</p>"


def section(sid: str, body: str) -> str:
    title = dict(SECTIONS)[sid]
    return f"<section id=\"{sid}\"><h2>{esc(title)}</h2>\n{body}\n</section>"


# -- parameters in display units (rigctl.display_units: one table for every command) ----------
def param_rows(result: dict[str, Any]) -> list[list[Any]]:
    """parameter, unit, value, 1-sigma, 95 % interval (digits from the uncertainty), k, dof."""
    rows = []
    for p in result.get("parameters") or []:
        d = display(p["name"])
        v, sd = p.get("value"), p.get("sigma")
        u = d.sigma(sd)
        val, us = format_value(d.value(v), u)
        lo, hi = (format_value(d.value(p.get(k)), u)[0] if p.get(k) is not None else "n/a"
                  for k in ("ci95_low", "ci95_high"))
        k = (p["ci95_high"] - v) / sd if v is not None and sd and p.get("ci95_high") is not None else None
        dof = p.get("dof")
        rows.append([d.base, d.unit, val, us, f"[{lo}, {hi}]", None if k is None else round(k, 2),
                     "inf" if dof is None and k is not None and abs(k - 1.96) < 0.01 else dof])
    return rows


PARAM_HEAD = ["parameter", "unit", "value", "1-sigma", "95 % interval", "coverage k", "dof"]
K_NOTE = ("<p class=\"muted\">Coverage factor k: 1.96 for a normal interval; above it, the Student-t "
          "factor for the parameter's effective degrees of freedom (Satterthwaite). Small dof (k up to "
          "12.7 at 1 dof) arise when the noise model was estimated from this session's own segments (REML "
          "on a few residual dof): the uncertainty is then itself uncertain. Calibrate with the noise "
          "model of the unit's overnight capture (<code>rigctl calibrate --noise OVERNIGHT.h5</code>) for "
          "normal intervals.</p>")


def fit_line(r: dict[str, Any]) -> str:
    cls = "ok" if r.get("status") == "ok" else "warn"
    w = "".join(f"<li class=\"warn\">{esc(x)}</li>" for x in r.get("warnings") or [])
    return (f"<p>method <b>{esc(r.get('method'))}</b>, status <span class=\"{cls}\">"
            f"{esc(r.get('status'))}</span>, dof {esc(r.get('dof'))}, chi2/dof "
            f"{esc(fmt(r.get('chi2_per_dof'), 4))}, p {esc(fmt(r.get('chi2_p_value'), 3))}, "
            f"intervals {esc(r.get('interval'))}</p>" + (f"<ul>{w}</ul>" if w else ""))


# -- sections --------------------------------------------------------------------------------
def s_summary(d: RunData) -> str:
    m = d.meta
    cls = "status-complete" if d.status == "complete" else "status-bad"
    t0, t1 = d.imu.get("t_first"), d.imu.get("t_last")
    segs = d.segments or {}
    n_inc = int(sum(1 for s in segs.get("status", []) if s != "complete"))
    res = ", ".join(sorted(d.results)) or "none"
    # an imported log without wall-clock stamps: its capture time is unknown (/meta capture_time)
    unknown = str(m.get("capture_time", "")).startswith("unknown")
    started = (f"unknown (imported {m.get('import_utc', '?')}: the file has no wall-clock time stamps)"
               if unknown else m.get("started_utc", "?"))
    rows = [["status", f"{d.status}"], ["procedure", m.get("procedure_name", "?")],
            ["recording", str(d.recording)], ["started (UTC)", started],
            ["ended (UTC)", "unknown" if unknown else m.get("ended_utc", "?")],
            ["recorded span [s]", None if t0 is None else round(t1 - t0, 3)],
            ["IMU samples", d.imu.get("n")], ["IMU rate [Hz]", d.imu.get("rate_hz")],
            ["dropped samples (counter gaps)", f"{d.imu.get('dropped', 0)} in {d.imu.get('gaps', 0)} gaps"],
            ["segments", f"{len(segs.get('kind', []))} ({n_inc} incomplete)"],
            ["results groups", res]]
    return (f"<p>Run status: <span class=\"{cls}\">{esc(d.status)}</span></p>"
            + table(["item", "value"], rows))


def s_verdicts(d: RunData) -> str:
    """The verdicts stored with the results (``--spec``), first thing on the page."""
    got = [(k, (r.get("json") or {}).get("verdicts")) for k, r in sorted(d.results.items())]
    got = [(k, v) for k, v in got if v]
    if not got:
        return not_run("no verdicts: the results were computed without a spec",
                       "Run `rigctl calibrate RECORDING --spec SPEC.yaml` (and `rigctl allan ... --spec`).")
    out = []
    for kind, v in got:
        out.append(f"<p>{esc(kind)}: overall <span class=\"{esc(v['overall'])}\">{esc(v['overall'])}</span> "
                   f"against {esc(v['spec'])}</p>")
        rows = []
        for r in v["parameters"]:
            val, u = format_value(r["value"], r["u"])
            lo, hi = r["ci95"]
            ci = "n/a" if lo is None else f"[{format_value(lo, r['u'])[0]}, {format_value(hi, r['u'])[0]}]"
            rows.append([r["parameter"], r["unit"], val, u, ci, r["tolerance"], r["verdict"]])
        out.append(table(["parameter", "unit", "value", "u", "95 % interval", "tolerance", "verdict"], rows,
                         num_from=2).replace("<td>PASS</td>", "<td class=\"PASS\">PASS</td>")
                   .replace("<td>FAIL</td>", "<td class=\"FAIL\">FAIL</td>")
                   .replace("<td>INDETERMINATE</td>", "<td class=\"INDETERMINATE\">INDETERMINATE</td>"))
        out.append(f"<p class=\"muted\">Decision rule: {esc(v['rule_text'])}</p>")
    return "\n".join(out)


def s_provenance(d: RunData) -> str:
    m = d.meta
    keys = ["procedure_name", "procedure_path", "parameters_json", "config_path", "rig",
            "latitude_deg", "height_m", "gravity_m_s2", "started_utc", "ended_utc",
            "clock_zero_unix_s"]
    rows = [[k, m[k]] for k in keys if k in m]
    rows += [[f"file attribute {k}", v] for k, v in d.root_attrs.items()]
    rows.append(["run status", d.status])
    out = ["<h3>Run</h3>", table(["item", "value"], rows)]
    try:
        versions = json.loads(m.get("versions_json") or "{}")
    except json.JSONDecodeError:
        versions = {}
    out += ["<h3>Versions</h3>",
            table(["package", "version"], [[k, v] for k, v in versions.items()])
            if versions else "<p class=\"muted\">no versions recorded</p>"]
    out += ["<h3>Procedure</h3>", f"<pre>{esc(m.get('procedure_text', '(not recorded)'))}</pre>",
            "<h3>Rig configuration</h3>", f"<pre>{esc(m.get('config_yaml', '(not recorded)'))}</pre>"]
    for name, r in sorted(d.results.items()):
        out.append(f"<p class=\"muted\">/results/{esc(name)}: created {esc(r.get('created_utc'))}, "
                   f"schema_version {esc(r.get('schema_version'))}</p>")
    return "\n".join(out)


def s_events(d: RunData) -> str:
    faults = [[t, k, msg] for t, k, msg in d.events if k in FAULT_KINDS]
    out = [f"<p>{len(faults)} fault / suspender events, {d.imu.get('dropped', 0)} IMU samples "
           f"dropped (counter gaps).</p>"]
    if faults:
        out.append(table(["run time [s]", "kind", "message"], faults, num_from=0))
    out.append("<h3>All events</h3>")
    out.append(table(["run time [s]", "kind", "message"], [list(e) for e in d.events], num_from=0)
               if d.events else "<p class=\"muted\">no events recorded</p>")
    if d.run_log:
        out.append("<h3>Warnings and errors in the run log</h3>")
        out.append(table(["UTC", "kind", "message"],
                         [[r.get("utc", ""), r.get("kind"), r.get("message")] for r in d.run_log]))
    return "\n".join(out)


def s_table(d: RunData, plots: dict[str, Path]) -> str:
    if d.table is None:
        return not_run("the recording has no /table data", "Record a procedure with table motion.")
    out = [img(plots, "table_timeline", "Table orientation (deg) and rate (deg/s) against run time (s)")]
    s = d.segments
    if s:
        import numpy as np

        rows = []
        for k in sorted(set(s["kind"])):
            m = s["kind"] == k
            st = s.get("settle_time", np.full(m.size, np.nan))[m]
            dur = (s["t_end"] - s["t_start"])[m]
            rows.append([k, int(m.sum()), float(np.nanmean(dur)) if np.isfinite(dur).any() else None,
                         float(np.nanmax(st)) if np.isfinite(st).any() else None])
        out.append(table(["segment kind", "count", "mean window [s]", "max settle time [s]"], rows,
                         num_from=1))
    return "\n".join(out)


def _fit_results(payload: Any) -> list[tuple[str, dict[str, Any]]]:
    """(name, CalibrationResult dict) pairs of a calibration payload (any nesting)."""
    out: list[tuple[str, dict[str, Any]]] = []
    if isinstance(payload, dict):
        for k, v in payload.items():
            if isinstance(v, dict) and isinstance(v.get("parameters"), list) and "method" in v:
                out.append((str(k), v))
            elif isinstance(v, dict) and k != "closed_loop":
                out += _fit_results(v)
    return out


def _cal_status(payload: dict[str, Any]) -> str:
    bits = []
    if "trustworthy" in payload:
        ok = bool(payload["trustworthy"])
        bits.append(f"<p>Calibration status: <span class=\"{'ok' if ok else 'warn'}\">"
                    f"{esc(payload.get('status', 'ok' if ok else 'NOT TRUSTWORTHY'))}</span>"
                    f"{'' if ok else ' (NOT TRUSTWORTHY)'}</p>")
    for key in ("mode", "noise_model"):
        if payload.get(key):
            bits.append(f"<p class=\"muted\">{esc(key.replace('_', ' '))}: {esc(payload[key])}</p>")
    bits += [f"<p class=\"warn\">{esc(r)}</p>" for r in payload.get("reasons") or []]
    return "\n".join(bits)


def s_calibration(d: RunData, plots: dict[str, Path]) -> str:
    r = d.results.get("calibration")
    if not r:
        return not_run("no /results/calibration in the recording",
                       "Run `rigctl calibrate RECORDING` (or a procedure with a calibration solve step).")
    payload = r.get("json") or {}
    sess = find_session(payload)
    out = [_cal_status(payload)]
    if sess is None:  # e.g. an orientation-free (multi-position) calibration: no closed loop
        fits = _fit_results(payload)
        if not fits:
            return out[0] + not_run("/results/calibration holds no parameter table",
                                    "Re-run `rigctl calibrate RECORDING`.")
        for name, res in fits:
            out += [f"<h3>{esc(name)}</h3>", fit_line(res), table(PARAM_HEAD, param_rows(res), num_from=2)]
        return "\n".join(out)
    cl = sess.get("closed_loop") or {}
    fin = cl.get("final")
    if fin:
        out += ["<h3>Parameters (closed-loop model, 1-sigma and 95 % intervals)</h3>", fit_line(fin),
                table(PARAM_HEAD, param_rows(fin), num_from=2), K_NOTE]
    out += ["<h3>Residuals per orientation</h3>",
            img(plots, "cal_residuals_orientation",
                "Residuals per orientation before/after (accel mg, gyro deg/h)"),
            "<h3>Residuals per rate</h3>",
            img(plots, "cal_residuals_rate",
                "Residuals per rate before/after (gyro deg/h, accel mg) against rate (deg/s)")]
    for key, title in (("accel24", "24-position accelerometer fit (A3)"),
                       ("gyro_bias_static", "Gyro biases from the static positions"),
                       ("gyro_rate", "Rate test (A4)")):
        res = sess.get(key)
        if not res:
            continue
        out.append(f"<details open><summary>{esc(title)}</summary>{fit_line(res)}"
                   f"{table(PARAM_HEAD, param_rows(res), num_from=2)}</details>")
    return "\n".join(out)


def s_pose_loop(payload: dict[str, Any]) -> str:
    """The closed loop of an orientation-free calibration: each sub-model's chi2/dof against its
    band, the effects claimed and the findings; before/after with raw, declared and final."""
    rows = []
    for name, lp in payload["closed_loop"].items():
        band = lp.get("band_chi2_per_dof") or [None, None]
        rows.append([name, lp.get("status"), lp["declared"].get("chi2_per_dof"), lp["final"].get("chi2_per_dof"),
                     lp["final"].get("dof"), band[0], band[1], ", ".join(lp.get("effects_claimed") or []) or "none"])
    out = [f"<p>STATUS: <b>{esc(payload.get('status'))}</b></p>", "<h3>Sub-models</h3>",
           table(["sub-model", "status", "chi2/dof declared", "chi2/dof final", "dof", "band low", "band high",
                  "effects claimed"], rows, num_from=2)]
    for name, lp in payload["closed_loop"].items():
        for f in lp.get("findings") or []:
            out.append(f"<p class=\"warn\">{esc(name)}: {esc(f)}</p>")
    out.append("<h3>Before / after (RMS over the poses; raw: nominal scale, no calibration)</h3>")
    out.append(table(["channel", "unit", "raw", "declared model", "final model", "noise floor"],
                     [[r["channel"], r["unit"], r["raw"], r["declared"], r["final"], r["noise_floor"]]
                      for r in payload.get("before_after") or []], num_from=2))
    out.append("<h3>The chain: sub-model, round, candidate, statistic, decision</h3>")
    out.append(table(["sub-model", "round", "candidate", "statistic", "decision"],
                     [[name, x.get("step"), x.get("candidate"), x.get("statistic"), x.get("decision")]
                      for name, lp in payload["closed_loop"].items() for x in lp.get("explain") or []], num_from=0))
    return "\n".join(out)


def s_closed_loop(d: RunData, plots: dict[str, Path]) -> str:
    r = d.results.get("calibration")
    payload = r.get("json") if r else None
    if isinstance(payload, dict) and payload.get("mode") == "orientation_free" and payload.get("closed_loop"):
        return s_pose_loop(payload)
    sess = find_session(payload) if r else None
    cl = (sess or {}).get("closed_loop")
    if not cl:
        if r:
            return not_run("the calibration in /results/calibration has no closed loop (an "
                           "orientation-free calibration has none)",
                           "Record on a turntable (procedures/full-calibration.yaml) for the closed loop.")
        return not_run("the closed loop needs /results/calibration", "Run `rigctl calibrate RECORDING`.")
    out = ["<h3>Effects found</h3>"]
    effects = cl.get("effects") or []
    if effects:
        rows = []
        for e in effects:
            for p in e.get("parameters") or [{}]:
                d = display(p.get("name", ""))
                ci = p.get("ci95") or [None, None]
                u = d.sigma(p.get("sigma"))
                rows.append([e["name"], e.get("attribution"), e.get("p_adj"), e.get("dBIC"), d.base, d.unit,
                             *format_value(d.value(p.get("value")), u),
                             format_value(d.value(ci[0]), u)[0], format_value(d.value(ci[1]), u)[0]])
        out.append(table(["effect", "attribution", "p (adjusted)", "dBIC", "parameter", "unit", "value",
                          "1-sigma", "95 % low", "95 % high"], rows, num_from=2))
    else:
        out.append("<p>No undeclared effect found: the declared model explains the residuals.</p>")
    out.append("<h3>Before / after</h3>")
    rows = []
    for t in cl.get("rms_table") or []:
        if t.get("channel") == "all":
            rows.append(["chi2 per dof (all)", "1", None, t.get("chi2_per_dof_before"),
                         t.get("chi2_per_dof_after"), None])
            continue
        u = t.get("unit", "")
        rows.append([t["channel"], {"deg_h": "deg/h"}.get(u, u), t.get(f"rms_raw_{u}"),
                     t.get(f"rms_before_{u}"), t.get(f"rms_after_{u}"), t.get(f"noise_floor_{u}")])
    out.append(table(["channel", "unit", "raw", "declared model", "final model", "noise floor"], rows, num_from=2))
    out.append(img(plots, "cal_rms", "Residual RMS before/after against the noise floor (mg, deg/h)"))
    for u in cl.get("unexplained") or []:
        out.append(f"<p class=\"warn\">UNEXPLAINED: {esc(u.get('pattern'))} ({esc(u.get('statistic'))})</p>")
    if cl.get("truth_errors"):
        rows = [[t["name"], abs(t["error_before"]) / t["sigma_before"] if t.get("sigma_before") else None,
                 abs(t["error_after"]) / t["sigma_after"] if t.get("sigma_after") else None]
                for t in cl["truth_errors"] if t.get("error_before") is not None]
        out += ["<h3>Parameter errors against the emulator's truth</h3>",
                table(["parameter", "|error|/sigma before", "|error|/sigma after"], rows)]
    out.append("<h3>The chain: residual pattern, candidate, statistic, decision</h3>")
    out.append(table(["round", "residual pattern", "candidate", "statistic", "decision"],
                     [[x.get("step"), x.get("residual_pattern"), x.get("candidate"),
                       x.get("statistic"), x.get("decision")] for x in cl.get("explain") or []],
                     num_from=0))
    na = cl.get("not_available") or {}
    if na:
        out.append(table(["candidate not testable", "why"], [[k, v] for k, v in na.items()]))
    return "\n".join(out)


def _term_cell(c: Any) -> str:
    """A coefficient (in the unit of its column): value [95 % interval], or its bound."""
    if c.resolved:
        lo, hi = c.ci95 or (None, None)
        return f"{fmt(c.value)} [{fmt(lo)}, {fmt(hi)}]"
    from ..solvers.noise_coefficients import BOUND_SOURCES

    what = BOUND_SOURCES.get(c.bound_from or "fit", BOUND_SOURCES["fit"])
    return f"< {fmt(c.upper95)} ({what})"


def _need_cell(e: dict[str, Any], resolved: bool) -> str:
    """Capture length (h) that would resolve the term to +-25 %, or "" when this one does."""
    need = e.get("capture_h_for_25pct")
    if need is None:
        return ""
    from ..display_units import capture_text

    have = e.get("capture_h")
    if not resolved and have is not None and need <= 1.05 * have:
        return f"> {capture_text(have)} (this capture)"
    return (">= " if not resolved else "") + capture_text(need)


def s_allan(d: RunData, plots: dict[str, Path]) -> str:
    if "allan" not in d.results:
        return not_run("no /results/allan in the recording",
                       "Run `rigctl allan RECORDING` (or procedures/allan-overnight.yaml).")
    from ..solvers import noise_coefficients as NC

    out = [img(plots, "allan", "Allan deviation (deg/h, mg) against tau (s) with 68 % and 95 % "
                               "intervals, fitted total and each term")]
    src = d.results["allan"].get("source")
    if src:
        out.insert(0, f"<p>From the same unit's latest analysed capture: {esc(src)} (this recording has "
                      "no /results/allan).</p>")
    curves = allan_curves(d)
    rows = []
    for axis, cv in curves.items():
        fit = (cv.get("fit") or {}).get("terms") or {}
        if not (cv.get("fit") or {}).get("coefficients"):
            continue
        co = NC.as_coefficients(cv["fit"]["coefficients"])
        pw = ((cv.get("piecewise") or {}).get("terms")) or {}
        for t, e in fit.items():
            c, unit = NC.in_field_units(co, t)
            p = (pw.get(t) or {}).get(f"value_{unit}")
            rows.append([axis, e.get("name", t), unit, _term_cell(c), p, _need_cell(e, c.resolved)])
        # the fit's Gauss-Markov term: sigma_GM in B's unit, and Tc in s, each with its own
        # capture figure (the term's ``crb``, allan_fit._add_crb)
        crb = ((cv["fit"].get("gm_term") or {}).get("crb")) or {}
        for g in co.gm:
            unit, fac = NC.FIELD_UNITS[co.sensor]["B"]
            sig_e, tc_e = crb.get("sigma") or {}, crb.get("tc") or {}
            rows.append([axis, "Gauss-Markov sigma_GM", unit, _term_cell(g.sigma.scaled(fac)),
                         None, _need_cell(sig_e, not sig_e.get("bounded"))])
            tc = f"{g.tau_c_s:.4g} {g.tc_interval_text(4)}".rstrip()
            rows.append([axis, "Gauss-Markov correlation time Tc", "s", tc, None,
                         _need_cell(tc_e, not tc_e.get("bounded"))])
    if rows:
        out += ["<h3>Fitted noise terms (joint IEEE 952 fit; value [95 % interval] or bound)</h3>",
                table(["axis", "term", "unit", "joint fit", "piecewise read-off",
                       "capture for +-25 %"], rows, num_from=4),
                "<p class=\"muted\">Capture for +-25 %: where this capture cannot determine a term "
                "to +-25 % (95 %), the capture length that could (Cramer-Rao bound; for an upper "
                "bound, computed at the bound: at least that long).</p>"]
    out += _chi2_findings_html(curves)
    out += _bounds_html(curves)
    out += _excluded_html(curves)
    out += _excursions_html(curves)
    out += _quiet_stretch_html(curves)
    gm_rows = []
    for axis, cv in curves.items():
        gm = (cv.get("fit") or {}).get("gauss_markov") or {}
        if not gm.get("detected"):
            continue
        unit = gm.get("sigma_gm_unit", "")
        slug = unit.replace("/", "_per_").replace("(", "_").replace(")", "").replace("^", "")
        s_ci = gm.get(f"sigma_gm_ci95_{slug}") or [None, None]
        gm_rows.append([axis, f"{gm['tc_s']:.3g} {tc_interval(gm)}",
                        f"{gm[f'sigma_gm_{slug}']:.3g} [{_g3(s_ci[0])}, {_g3(s_ci[1])}] {unit}",
                        f"{gm['chi2_before']:.1f}/{gm['dof_before']} -> "
                        f"{gm['chi2_after']:.1f}/{gm['dof_after']}",
                        f"{gm['p_value']:.2g}"])
    if gm_rows:
        in_fit = all(((cv.get("fit") or {}).get("gauss_markov") or {}).get("in_fit")
                     for cv in curves.values()
                     if ((cv.get("fit") or {}).get("gauss_markov") or {}).get("detected"))
        what = ("fitted: in the terms above and the fitted total" if in_fit else
                "where fitted, in the terms above and the fitted total")
        out += [f"<h3>Gauss-Markov processes found at stationary bumps ({what})</h3>",
                table(["axis", "Tc [s] (95 %)", "sigma_GM (95 %)", "chi2/dof without -> with",
                       "likelihood-ratio p"], gm_rows),
                "<p class=\"muted\">A first-order Gauss-Markov process fits a bump of the curve "
                "that the IEEE 952 terms cannot follow and that is the same throughout the record "
                "(docs/allan.md, 'A stationary bump: a Gauss-Markov candidate').</p>"]
    if any(cv.get("quick") for cv in curves.values()):
        out.append("<p class=\"muted\">Curves marked 'quick' were computed for this report "
                   "(30 taus, fast mode): the results group lacked the curve arrays.</p>")
    return "\n".join(out)


def _chi2_findings_html(curves: dict[str, dict]) -> list[str]:
    """The axes whose fit has a chi-square beyond its 99 % point: a finding, never a pass,
    with the run of taus that carries it (rigctl.analysis.allan.chi2_finding)."""
    from ..analysis.allan import chi2_finding

    out = []
    for axis, cv in curves.items():
        for sentence in chi2_finding(((cv.get("fit") or {}).get("check")) or {}):
            out.append(f"<p class=\"warn\">{esc(axis)}: {esc(sentence)}</p>")
    return out


def _bounds_html(curves: dict[str, dict]) -> list[str]:
    """The axes whose self-check took terms known only as bounds into the total, within their
    bounds (rigctl.analysis.allan.bounds_sentence: the CLI's and the results' spelling)."""
    from ..analysis.allan import bounds_sentence

    out = []
    for axis, cv in curves.items():
        fit = cv.get("fit") or {}
        for sentence in bounds_sentence(fit.get("check") or {}, fit.get("sensor", "gyro")):
            out.append(f"<p>{esc(axis)}: {esc(sentence)}</p>")
    return out


def _excluded_html(curves: dict[str, dict]) -> list[str]:
    """The taus each axis' fit left out (a rising front, a low-pass filter's region) and why
    (rigctl.analysis.allan.excluded_sentences: the CLI's and the results' spelling)."""
    from ..analysis.allan import excluded_sentences

    out = []
    for axis, cv in curves.items():
        for sentence in excluded_sentences(((cv.get("fit") or {}).get("check")) or {}):
            out.append(f"<p>{esc(axis)}: {esc(sentence)}</p>")
    return out


def _chi2_cell(check: dict) -> str:
    """A chi-square beyond its 99 % point in a table cell: a finding, with what carries it."""
    from ..analysis.allan import chi2_carrier_text

    carrier = chi2_carrier_text(check)
    return ("self-check failed: chi-square beyond its 99 % point, a finding, not a pass"
            + (f"; carried by {carrier}" if carrier else ""))


def _excursions_html(curves: dict[str, dict]) -> list[str]:
    """The short excursions found before the fit (rigctl.analysis.allan_excursions), one row
    each, in the field's units; [] when none."""
    rows = []
    for axis, cv in curves.items():
        x = cv.get("excursions") or {}
        unit = x.get("unit", "")
        for e in x.get("excursions") or []:
            rows.append([axis, e["kind"], f"{e['start_s']:.0f}", f"{e['end_s']:.0f}",
                         f"{e[f'size_{unit}']:+.3g} {unit}", ", ".join(e.get("moving_with") or [])])
    if not rows:
        return []
    return ["<h3>Short excursions of the level, found before the fit</h3>",
            table(["axis", "kind", "start (s)", "end (s)", "size", "moving with"], rows),
            "<p class=\"muted\">Adjacent window means (30 s to 1/32 of the record) that differ "
            "beyond the record's own robust Allan deviation at that window (family-wise "
            "false-alarm probability 0.01 per axis); on a record shorter than 960 s, a step "
            "looked for against the fit's noise levels instead (false-alarm probability 0.01 "
            "per axis; docs/allan.md, 'Detection limits'); times from the start of the range "
            "analysed. "
            "They are in the samples the fit sees (the whole record's and the quiet stretch's): "
            "not the sensor's stationary noise (docs/allan.md, 'Short excursions before the "
            "fit').</p>"]


def _quiet_stretch_html(curves: dict[str, dict]) -> list[str]:
    """Non-stationary records: the terms fitted on the quiet stretch beside the whole
    record's (rigctl.analysis.allan_quiet), and the axes where no stretch qualified."""
    from ..solvers import noise_coefficients as NC

    rows, notes = [], []
    for axis, cv in curves.items():
        q = cv.get("quiet_stretch") or {}
        if not q:
            continue
        run = q["run"]
        why = (f"not stationary at {run['tau_tested_s']:.3g} s (Bartlett p = {run['p_value']:.2g}, "
               f"{run['windows']} windows of {run['window_s']:.0f} s)")
        if not q.get("fitted") or not (q.get("fit") or {}).get("coefficients"):
            notes.append(f"{axis}: {why}; {q.get('reason', 'no quiet stretch qualifies')}")
            continue
        whole = NC.as_coefficients(cv["fit"]["coefficients"])
        quiet = NC.as_coefficients(q["fit"]["coefficients"])
        stretch = (f"t = {q['t_s'][0]:.0f}-{q['t_s'][1]:.0f} s ({100 * q['fraction']:.0f} %; "
                   + (_chi2_cell(q["fit"]["check"]) if q["fit"]["check"].get("chi2_beyond_99")
                      else "self-check failed" if not q["fit"]["check"].get("ok")
                      else "self-check passed") + ")")
        ex = q.get("excursions_excluded")
        if ex:  # the excursions inside it, left out of its fit (--excursions exclude)
            stretch += (f"; without {len(ex['samples'])} excursion window(s) (t = "
                        + ", ".join(f"{a:.0f}-{b:.0f}" for a, b in ex["windows_s"])
                        + f" s, {ex['n_samples']} samples), {ex['handled']}")
        # the stretch's own self-check runs that no term follows, named under the table
        notes += [f"{axis}, quiet stretch: tau {o['tau_from_s']:.3g}-{o['tau_to_s']:.3g} s: "
                  f"{o['side']} ({over_fit_text(o['data_over_fit'], o['worst_tau_s'])}); "
                  f"likely {o['likely']}"
                  for o in q["fit"]["check"].get("outside") or [] if o.get("unexplained")]
        for i, t in enumerate(q["fit"]["terms"]):  # the stretch named on the axis' first row
            cw, unit = NC.in_field_units(whole, t)
            cq, _ = NC.in_field_units(quiet, t)
            rows.append([axis if not i else "", why if not i else "", stretch if not i else "",
                         t, unit, _term_cell(cw), _term_cell(cq)])
    if not rows and not notes:
        return []
    out = ["<h3>Non-stationary records: the quiet stretch's terms beside the whole record's</h3>"]
    if rows:
        out.append(table(["axis", "stationarity test", "quiet stretch", "term", "unit",
                          "whole record", "quiet stretch"], rows))
    out += [f"<p>{esc(n)}</p>" for n in notes]
    out.append("<p class=\"muted\">Where the self-check's stationarity test finds the record's "
               "Allan variance different across its windows, the terms are also fitted on the "
               "longest stretch whose windows agree (at least 2 windows and a quarter of the "
               "range); the whole record's terms and verdict stay as they are "
               "(docs/allan.md, 'Non-stationary records: the quiet stretch').</p>")
    return out


def _g3(v: float | None) -> str:
    return "inf" if v is None else f"{v:.3g}"


def s_sync(d: RunData, plots: dict[str, Path]) -> str:
    r = d.results.get("sync")
    if not r:
        return not_run("no /results/sync in the recording",
                       "Record a tap session with a pulse input, then run `rigctl sync RECORDING`.")
    s = r.get("json") or {}
    off = s.get("offset_s")
    rows = [["timing", s.get("timing")], ["clock offset [s]", off],
            ["offset 95 % half-width [ms]", None if s.get("offset_ci95_s") is None else s["offset_ci95_s"] * 1e3],
            ["drift [ppm]", s.get("drift_ppm")], ["drift 95 % half-width [ppm]", s.get("drift_ci95_ppm")],
            ["residual std [ms]", s.get("residual_std_ms")],
            ["taps detected / pulses / matched / inliers",
             f"{s.get('n_taps_detected')} / {s.get('n_pulses')} / {s.get('n_matched')} / {s.get('n_inliers')}"],
            ["taps without pulse / pulses without tap",
             f"{s.get('n_taps_without_pulse')} / {s.get('n_pulses_without_tap')}"],
            ["counter gaps (samples lost)",
             ", ".join(str(g.get("n_samples")) for g in s.get("counter_gaps") or []) or "none"]]
    return "\n".join([table(["quantity", "value"], rows),
                      img(plots, "sync_hist", "Tap matching error histogram (ms)"),
                      img(plots, "sync_residual", "Clock residual (ms) against reference time (s)")])


def s_thermal(d: RunData, plots: dict[str, Path]) -> str:
    """The thermal calibration (/results/thermal, docs/thermal.md): per sensor the fit's status,
    the loop's findings, the coefficients, before/after per temperature band, and the plots."""
    from ..display_units import display, format_value

    p = (d.results.get("thermal") or {}).get("json") or {}
    if p.get("mode") != "thermal":
        return not_run("thermal calibration", "a chamber run (procedures/thermal-ramp.yaml or thermal-soak.yaml), "
                       "then rigctl calibrate")
    out = [f"<p>Reference temperature {fmt(p.get('reference_c'))} degC. "
           + (f"Against the emulator's truth: {p['truth_coverage']['inside']} of {p['truth_coverage']['total']} "
              "95 % intervals cover it." if p.get("truth_coverage") else "") + "</p>",
           *[f"<p class=\"warn\">NOT TRUSTWORTHY: {esc(r)}</p>" for r in (p.get("reasons") or [])],
           img(plots, "thermal_parameters", "thermal parameters against temperature"),
           img(plots, "thermal_residuals", "residuals before and after against temperature")]
    for sensor, s in (p.get("sensors") or {}).items():
        w = s.get("windows") or {}
        found = ", ".join(s.get("effects_found") or []) or "none"
        lo, hi = s.get("chi2_band_99") or [None, None]
        out.append(f"<h3>{esc(sensor)}</h3><p>{w.get('total')} windows ({w.get('heating')} heating, "
                   f"{w.get('cooling')} cooling); chi2/dof {fmt(s.get('chi2_per_dof'), 3)} (99 % band "
                   f"{fmt(lo, 3)} .. {fmt(hi, 3)}): <b>{esc(s.get('status'))}</b>; thermal effects found: "
                   f"{esc(found)}</p>")
        rows = []
        for q in s.get("parameters") or []:
            dd = display(q["name"])
            v, u = format_value(dd.value(q["value"]), dd.sigma(q["sigma"]))
            ci = [format_value(dd.value(x), dd.sigma(q["sigma"]))[0] for x in q["ci95"]]
            rows.append([dd.base, v, u, f"[{ci[0]}, {ci[1]}]", dd.unit])
        out.append(table(["parameter", "value", "u", "95 % interval", "unit"], rows))
        ba = s.get("before_after") or {}
        dd = display(f"{sensor}_bias_x_{ba.get('unit', 'm_s2')}")
        brow = [[f"{b['from_c']:g} .. {b['to_c']:g} degC", b["windows"],
                 *[f"{dd.sigma(x):.4g} -> {dd.sigma(y):.4g}" for x, y in zip(b["rms_before"], b["rms_after"])]]
                for b in ba.get("by_temperature") or []]
        out.append(table(["temperature", "windows", *[f"{axis_name(sensor, i)}: RMS before -> after [{dd.unit}]" for i in range(3)]],
                         brow))
    return "\n".join(out)


def render(d: RunData, plots: dict[str, Path]) -> str:
    """The whole page as one string."""
    name = d.meta.get("procedure_name", d.recording.stem)
    nav = "".join(f"<a href=\"#{sid}\">{esc(t)}</a>" for sid, t in SECTIONS)
    body = [section("verdicts", s_verdicts(d)), section("summary", s_summary(d)), section("table", s_table(d, plots)),
            section("calibration", s_calibration(d, plots)),
            section("closed-loop", s_closed_loop(d, plots)),
            section("thermal", s_thermal(d, plots)),
            section("allan", s_allan(d, plots)), section("sync", s_sync(d, plots)),
            section("events", s_events(d)), section("provenance", s_provenance(d))]
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>rigctl report: {esc(name)}</title><style>{CSS}</style></head><body>"
            f"<header><h1>rigctl report: {esc(name)}</h1><p>{esc(d.recording)} - status "
            f"{esc(d.status)}</p></header><nav>{nav}</nav><main>\n" + "\n".join(body)
            + "\n</main></body></html>\n")
