"""The calibration certificate of one run: an HTML page printed to PDF by headless Chromium.

Why Chromium: the project already renders and tests its HTML report with Debian's headless
Chromium, whose ``--print-to-pdf`` gives a tagged, searchable PDF with real fonts and CSS paged
media (@page size, margins, page breaks) -- no second layout engine and no new dependency.

Content (docs/production.md): the unit (ID, serial, device ID), the procedure, the rig and its
traceability fields (rig config ``traceability:``), the environment (IMU temperature range),
each published result (:mod:`rigctl.analysis.results`: the calibration of the run and the Allan
results of the same unit's latest analysed capture) with its expanded uncertainty U = k u,
coverage factor k and effective degrees of freedom, the tolerance and verdict of each specified
parameter with the decision rule, the overall verdict, and a signatures block.
"""
from __future__ import annotations

import datetime as _dt
import html
import json
import math
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..recording.recording_reader import open_recording
from ..analysis import production
from ..analysis import results as R
from ..analysis.verdicts import evaluate
from ..config.config import traceability
from ..display_units import format_value
from ..config.spec import Spec
from ..errors import InputError
from ..yamlio import load_text

CSS = """
@page{size:A4;margin:16mm 14mm}
body{font-family:DejaVu Sans,Helvetica,Arial,sans-serif;font-size:9.5pt;color:#111}
h1{font-size:17pt;margin:0 0 2mm}h2{font-size:11.5pt;margin:5mm 0 1.5mm;border-bottom:1px solid #999}
table{border-collapse:collapse;width:100%;margin:1mm 0}th,td{border:1px solid #bbb;padding:1mm 1.5mm;
text-align:left;vertical-align:top}th{background:#eee}td.n{text-align:right;font-family:DejaVu Sans Mono,monospace}
.PASS{color:#0a6b22;font-weight:bold}.FAIL{color:#b3261e;font-weight:bold}.INDETERMINATE{color:#8a5a00;font-weight:bold}
.overall{font-size:13pt;margin:2mm 0;padding:2mm;border:2px solid #333}
.small{font-size:8pt;color:#333}.sig td{height:14mm;width:33%}tr{page-break-inside:avoid}
"""


def esc(x: Any) -> str:
    return html.escape("" if x is None else str(x), quote=True)


def _kv(rows: list[tuple[str, Any]]) -> str:
    return "<table>" + "".join(f"<tr><th style='width:32%'>{esc(k)}</th><td>{esc(v)}</td></tr>"
                               for k, v in rows) + "</table>"


def environment(recording: Path) -> dict[str, Any]:
    """IMU temperature range (degC) and recorded span (s) of a recording."""
    out: dict[str, Any] = {}
    with open_recording(recording, need=()) as f:
        if "imu/temperature" in f and f["imu/temperature"].shape[0]:
            t = f["imu/temperature"]
            lo, hi, n = math.inf, -math.inf, t.shape[0]
            for a in range(0, n, 1 << 20):
                x = np.asarray(t[a: a + (1 << 20)], dtype=float)
                x = x[np.isfinite(x)]
                if x.size:
                    lo, hi = min(lo, float(x.min())), max(hi, float(x.max()))
            if math.isfinite(lo):
                out["temperature_degC"] = (lo, hi)
        if "imu/time" in f and f["imu/time"].shape[0] > 1:
            out["span_s"] = float(f["imu/time"][-1] - f["imu/time"][0])
    return out


def certificate_data(recording: Path, spec: Spec | None) -> dict[str, Any]:
    """Everything the certificate shows, read from the recording (and the unit's Allan capture)."""
    with open_recording(recording, need=()) as f:
        g = f.get("results/calibration")
        cal = json.loads(g.attrs["json"]) if g is not None and "json" in g.attrs else None
    if cal is None:
        raise InputError("no /results/calibration in the recording", recording,
                         hint=f"run `rigctl calibrate {recording}` first")
    meta = production.read_meta(recording)
    measured = R.from_calibration(cal)
    allan = production.latest_allan(recording)
    if allan is not None:
        measured += R.from_allan(allan[1])
    cfg = load_text(meta.get("config_yaml", "") or "{}", "the recorded rig config") or {}
    trace = traceability(cfg) if isinstance(cfg, dict) else {}
    verdicts = evaluate(spec, measured, None) if spec is not None else None
    return {"meta": meta, "calibration": cal, "measured": measured, "allan": allan, "traceability": trace,
            "verdicts": verdicts, "environment": environment(recording),
            "unit_id": production.unit_id_of(meta, production.run_name(recording)),
            "run": production.run_name(recording), "recording": recording}


def render(d: dict[str, Any]) -> str:
    """The certificate page (HTML with print CSS)."""
    m, v = d["meta"], d["verdicts"]
    issued = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d")
    number = f"{d['unit_id']}/{d['run']}"
    env = d["environment"]
    temp = env.get("temperature_degC")
    out = [f"<h1>Calibration certificate</h1><p>Certificate {esc(number)} &middot; issued {issued} "
           f"&middot; rigctl {esc(__version__)}</p>"]
    if v is not None:
        out.append(f"<div class='overall'>Overall verdict against {esc(v['spec'])}: "
                   f"<span class='{v['overall']}'>{v['overall']}</span></div>")
    out += ["<h2>Unit under test</h2>", _kv([("unit ID", d["unit_id"]), ("serial (label)", m.get("imu_serial") or "not declared"),
                                             ("device ID (reported)", m.get("imu_device_id") or "not reported")])]
    out += ["<h2>Procedure</h2>", _kv([("procedure", m.get("procedure_name")), ("procedure file", m.get("procedure_path")),
                                      ("parameters", m.get("parameters_json")), ("run", d["run"]),
                                      ("recorded (UTC)", f"{m.get('started_utc', '?')} to {m.get('ended_utc', '?')}"
                                       if not str(m.get("capture_time", "")).startswith("unknown") else
                                       f"unknown (imported {m.get('import_utc', '?')}: no wall-clock time stamps in the file)"),
                                      ("procedure document", d["traceability"].get("procedure_document", "not stated"))])]
    tr = d["traceability"]
    out += ["<h2>Laboratory, rig and traceability</h2>",
            _kv([("laboratory", tr.get("laboratory", "not stated (rig config 'traceability:')")),
                 ("address", tr.get("address", "")), ("accreditation", tr.get("accreditation", "not stated")),
                 ("rig", m.get("rig")), ("turntable", tr.get("table_id", "not stated")),
                 ("turntable calibration", tr.get("table_calibration", "not stated")),
                 ("turntable calibration due", tr.get("table_calibration_due", "not stated")),
                 ("reference standards", tr.get("reference_standards", "not stated")),
                 ("site", f"latitude {m.get('latitude_deg', '?')} deg, height {m.get('height_m', '?')} m, "
                          f"g = {m.get('gravity_m_s2', '?')} m/s^2")])]
    out += ["<h2>Environment</h2>", _kv([
        ("IMU temperature", "not recorded" if temp is None else f"{temp[0]:.1f} degC to {temp[1]:.1f} degC"),
        ("recorded span", f"{env.get('span_s', float('nan')) / 60:.1f} min")])]
    rows = {r["parameter"]: r for r in (v or {}).get("parameters", [])}
    out.append("<h2>Results</h2><table><tr><th>parameter</th><th>unit</th><th>value</th><th>U (95 %)</th>"
               "<th>k</th><th>&nu;<sub>eff</sub></th><th>tolerance</th><th>verdict</th></tr>")
    for meas in d["measured"]:
        disp = meas.display
        lo, hi = meas.interval
        val, u = format_value(disp.value(meas.value), disp.sigma(meas.u))
        if meas.estimate.kind == "t":
            U = format_value(disp.value(meas.value), disp.sigma(meas.u) * meas.coverage_factor)[1]
            k = f"{meas.coverage_factor:.2f}"
        else:  # asymmetric: give the interval
            U = f"[{format_value(disp.value(lo), disp.sigma(meas.u))[0]}, {format_value(disp.value(hi), disp.sigma(meas.u))[0]}]"
            k = "-"
        dof = "inf" if math.isinf(meas.dof) else f"{meas.dof:.1f}"
        r = rows.get(disp.base)
        verdict = f"<span class='{r['verdict']}'>{r['verdict']}</span>" if r else ""
        out.append(f"<tr><td>{esc(disp.base)}</td><td>{esc(disp.unit)}</td><td class='n'>{esc(val)}</td>"
                   f"<td class='n'>{esc(U)}</td><td class='n'>{k}</td><td class='n'>{dof}</td>"
                   f"<td>{esc(r['tolerance'] if r else '')}</td><td>{verdict}</td></tr>")
    out.append("</table>")
    notes = ["U is the expanded uncertainty U = k u for a coverage probability of about 95 %; k is the "
             "Student-t factor for the effective degrees of freedom nu_eff (inf: normal, k = 1.96). A small "
             "nu_eff (large k) means the noise model behind u was estimated from this session's own "
             "segments and is itself uncertain; a calibration with the noise model of the unit's overnight "
             "capture (rigctl calibrate --noise OVERNIGHT.h5) has normal intervals.",
             "Noise terms (random walks, bias instability) are given with their 95 % interval, asymmetric "
             "(chi-square); a term the capture does not resolve as [0, its 95 % upper bound]."]
    if d["allan"] is not None:
        notes.append(f"Noise terms from the Allan analysis of {d['allan'][0]}.")
    else:
        notes.append("No Allan analysis of this unit was found: noise terms are not certified.")
    if v is not None:
        notes.append(f"Decision rule: {v['rule_text']}.")
        if v["not_measured"]:
            notes.append("Specified but not measured (overall verdict at best INDETERMINATE): "
                         + ", ".join(v["not_measured"]) + ".")
    out.append("<p class='small'>" + "</p><p class='small'>".join(esc(n) for n in notes) + "</p>")
    out.append("<h2>Signatures</h2><table class='sig'><tr><th>performed by (name, date, signature)</th>"
               "<th>checked by (name, date, signature)</th><th>approved by (name, date, signature)</th></tr>"
               "<tr><td></td><td></td><td></td></tr></table>"
               "<p class='small'>This certificate may only be reproduced in full. The results relate only to "
               "the unit and the run identified above.</p>")
    return ("<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>Calibration certificate "
            f"{esc(number)}</title><style>{CSS}</style></head><body>" + "\n".join(out) + "</body></html>\n")


def chromium() -> str:
    """The headless Chromium executable (Debian's chromium)."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise RuntimeError("the certificate needs Chromium to print its PDF: apt-get install chromium")
    return exe


def print_pdf(html_path: Path, pdf_path: Path, timeout_s: float = 120.0) -> None:
    """Print an HTML file to PDF with headless Chromium (no network, a throw-away profile)."""
    with tempfile.TemporaryDirectory(prefix="rigctl-chromium-") as prof:
        cmd = [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
               "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
               f"--user-data-dir={prof}", "--no-pdf-header-footer", f"--print-to-pdf={pdf_path}",
               html_path.resolve().as_uri()]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if r.returncode != 0 or not pdf_path.is_file() or pdf_path.stat().st_size == 0:
        raise RuntimeError(f"Chromium did not print the PDF (exit {r.returncode}): {r.stderr.strip()[-300:]}")


def write_certificate(recording: Path, out_dir: Path, spec: Spec | None) -> tuple[Path, dict[str, Any]]:
    """certificate.html and certificate.pdf in ``out_dir``; returns (PDF path, the data)."""
    d = certificate_data(recording, spec)
    out_dir.mkdir(parents=True, exist_ok=True)
    page = out_dir / "certificate.html"
    page.write_text(render(d), encoding="utf-8")
    pdf = out_dir / "certificate.pdf"
    tmp = out_dir / "certificate.pdf.tmp"
    print_pdf(page, tmp)
    tmp.replace(pdf)
    return pdf, d
