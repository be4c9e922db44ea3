"""The static thermal fit of ``rigctl thermal`` (application layer): a record held still in two or
more poses while its temperature moves (a unit in a fridge or a climatic chamber without a table,
a board turned by hand between soaks), read into windows by
:func:`rigctl.analysis.thermal.static_windows`, checked, fitted by
:func:`rigctl.analysis.thermal.fit_static_windows`, and turned into a result (SI and field
units, JSON-ready), its text and its CSV.

An IMU restart in the record (a ``device-restart`` event, or a time base begun again behind its
last stamp: the unit lost power) gives it a new turn-on bias that one pose offset cannot hold: no
window spans it, and the result is NOT TRUSTWORTHY naming the poses and windows on each side
(:func:`rigctl.analysis.thermal.restart_report`, the same lines as ``rigctl calibrate``'s).

The checks, each one line (:class:`rigctl.errors.InputError`, exit code 2): a recording without
a temperature column; one pose only (scale per K cannot then be told from bias per K, unless
``one_pose`` asks for the apparent bias only); an IMU temperature span over the windows below
:data:`rigctl.analysis.thermal.MIN_SPAN_K`; a chamber run (the chamber's own thermal calibration
is ``rigctl calibrate``) unless ``force_static``. The pose file (``--poses``) names the poses'
time ranges when the recording does not mark them (:func:`read_pose_file`).

Every chi-square is reported with its two-sided 99 % band; outside it the status says which
side and the text says it is a finding (never "ok").
"""
from __future__ import annotations

import csv
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..clock import utc_now
from ..display_units import display, format_value
from ..errors import InputError
from ..jsonable import jsonable
from ..sensor_axes import axis_name
from ..solvers import distributions as stats
from ..solvers import thermal as th
from ..solvers.allan_stream import blas_single_thread
from ..yamlio import load_file
from . import thermal as AT
from .calibration_text import noise_summary
from .restarts import untrusted_lines

SCHEMA_VERSION = 1
BAND_LEVEL = 0.99
_COEF = re.compile(r"^(accel|gyro)_(bias|scale)_([xyz])(?:_m_s2|_rad_s)?_per_K(\d?)$")
POSE_KEYS = ("label", "from_s", "to_s")


def read_pose_file(path: str | Path) -> list[tuple[str, float, float]]:
    """The poses of a YAML (or JSON) file: a list of ``{label, from_s, to_s}``, seconds on the
    recording's time axis (/imu/time: an imported log's own time column), in any order, not
    overlapping. InputError with the file and line for anything else."""
    data = load_file(path)
    if not isinstance(data, list) or not data:
        raise InputError("a pose file is a list of {label, from_s, to_s} (seconds on the recording's time axis)",
                         path, getattr(data, "line", None) or None)
    out: list[tuple[str, float, float, int]] = []
    for k, item in enumerate(data):
        line = data.line_of(k) if hasattr(data, "line_of") else None
        if not isinstance(item, dict) or set(item) != set(POSE_KEYS):
            got = ", ".join(map(str, item)) if isinstance(item, dict) else type(item).__name__
            raise InputError(f"pose {k + 1}: give exactly label, from_s and to_s (got {got})", path, line)
        try:
            a, z = float(item["from_s"]), float(item["to_s"])
        except (TypeError, ValueError):
            raise InputError(f"pose {k + 1}: from_s and to_s are numbers of seconds", path, line) from None
        if not (math.isfinite(a) and math.isfinite(z) and z > a):
            raise InputError(f"pose {k + 1}: from_s {item['from_s']} .. to_s {item['to_s']} is not a time range",
                             path, line)
        out.append((str(item["label"]), a, z, line or 0))
    out.sort(key=lambda p: p[1])
    for p, q in zip(out, out[1:]):
        if q[1] < p[2]:
            raise InputError(f"poses {p[0]!r} and {q[0]!r} overlap ({q[1]:g} s < {p[2]:g} s)", path, q[3] or None)
    return [(lab, a, z) for lab, a, z, _ in out]


def _band(chi2: float, dof: int) -> tuple[float, float, float, str]:
    """(chi2/dof, band low, band high, status) at BAND_LEVEL."""
    lo, hi = stats.chi2.ppf([(1 - BAND_LEVEL) / 2, (1 + BAND_LEVEL) / 2], dof) / dof
    c = chi2 / dof
    return c, float(lo), float(hi), "ok" if lo <= c <= hi else ("chi2_below_band" if c < lo else "chi2_above_band")


FINDING = {
    "ok": "inside the band",
    "chi2_below_band": "BELOW the band -- a finding: the noise model over-predicts the scatter of the window "
                       "means (the uncertainties are too large); a fast temperature change at the start of "
                       "each pose counted as noise is one cause (--settle-s, docs/thermal.md)",
    "chi2_above_band": "ABOVE the band -- a finding: the model or the noise model misses something the data "
                       "hold (the uncertainties are too small)",
}


def _param(q: dict[str, Any]) -> dict[str, Any]:
    d = display(q["name"])
    # the per-K coefficients: their power in the name, not only in the unit
    return {"name": q["name"], "quantity": AT.quantity_name(q["name"]), "unit": d.unit, "value": d.value(q["value"]),
            "sigma": d.sigma(q["sigma"]), "ci95": [d.value(q["ci95"][0]), d.value(q["ci95"][1])],
            "si": {"value": q["value"], "sigma": q["sigma"], "ci95": list(q["ci95"]), "unit": d.si_unit}}


def _sensor(w: th.ThermalWindows, fit: th.ThermalFit) -> dict[str, Any]:
    c2, lo, hi, status = _band(fit.chi2, fit.dof)
    params = [_param(q) for q in fit.parameters()]
    per_axis: dict[str, dict[str, Any]] = {a: {} for a in th.AXES}
    for p in params:
        m = _COEF.match(p["name"])
        if m:
            per_axis[m.group(3)][f"{m.group(2)}_per_K{m.group(4)}"] = {
                k: p[k] for k in ("name", "unit", "value", "sigma", "ci95")}
    axes = []
    for i, (a, ax) in enumerate(zip(th.AXES, fit.axes)):
        ac2, alo, ahi, ast = _band(ax.chi2, ax.dof)
        axes.append({"axis": axis_name(w.sensor, i), "chi2": ax.chi2, "dof": ax.dof, "chi2_per_dof": ac2, "chi2_band_99": [alo, ahi],
                     "status": ast, "coefficients": per_axis[a]})
    return {"degrees": fit.degrees, "windows": len(w), "accepted": fit.accepted,
            "effects_found": [th.CANDIDATE_TEXT[c] for c in fit.accepted], "explain": fit.explain,
            "chi2": fit.chi2, "dof": fit.dof, "chi2_per_dof": c2, "chi2_band_99": [lo, hi], "status": status,
            "finding": FINDING[status], "axes": axes, "parameters": params}


def static_fit(path: str | Path, settle_s: float = 0.0, window_s: float = AT.STATIC_WINDOW_S,
               bias_degree: int = 2, loop: bool = True, poses_file: str | Path | None = None,
               one_pose: bool = False, force_static: bool = False, reference_c: float = 25.0,
               progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The result of ``rigctl thermal`` (module docstring): JSON-ready, values in field units with
    their SI originals. ``progress``: called with a line as each stage of the fit starts.
    The solvers run with one OpenBLAS thread, as ``rigctl calibrate``'s (docs/calibration.md
    section 7: small matrices, on which the helper threads only spin)."""
    with blas_single_thread():
        return _static_fit(Path(path), settle_s, window_s, bias_degree, loop, poses_file, one_pose,
                           force_static, reference_c, progress)


def _static_fit(p: Path, settle_s: float, window_s: float, bias_degree: int, loop: bool,
                poses_file: str | Path | None, one_pose: bool, force_static: bool, reference_c: float,
                progress: Callable[[str], None] | None) -> dict[str, Any]:
    """:func:`static_fit`'s work."""
    if not 1 <= bias_degree <= AT.MAX_FIT_DEGREE:
        raise InputError(f"--bias-degree {bias_degree}: give 1 .. {AT.MAX_FIT_DEGREE} (the temperature "
                         "coefficients per K, per K^2, ...)")
    if not (math.isfinite(settle_s) and settle_s >= 0):
        raise InputError(f"--settle-s {settle_s:g}: give the seconds to leave out at the start of each pose (>= 0)")
    if not (math.isfinite(window_s) and window_s > 0):
        raise InputError(f"--window-s {window_s:g}: give a window length in seconds (> 0)")
    if not force_static and AT.is_thermal(p):
        raise InputError("a chamber run (/chamber readings): rigctl calibrate RECORDING does its thermal "
                         "calibration", p, hint="--static fits it as a static record anyway")
    sections = read_pose_file(poses_file) if poses_file else None
    wins = AT.static_windows(p, window_s, reference_c, max(AT.MAX_FIT_DEGREE, bias_degree), settle_s=settle_s,
                             sections=sections)
    wa = wins["accel"]
    poses = wa.poses()
    if not poses and not one_pose:
        raise InputError("one pose: every static section's specific force points the same way (within "
                         f"{AT.SAME_POSE_DEG:g} deg), so scale per K cannot be told from bias per K", p,
                         hint="hold the unit with another axis along gravity as well and mark the poses "
                              "(rigctl import ... section=COLUMN, or --poses FILE); --one-pose fits the "
                              "apparent bias per K only")
    T = wa.temperature
    span = float(np.ptp(T))
    if span < AT.MIN_SPAN_K:
        raise InputError(f"the IMU temperature spans {span:.2f} K over the {len(wa)} windows "
                         f"({T.min():.2f} .. {T.max():.2f} degC): a thermal fit needs at least {AT.MIN_SPAN_K:g} K",
                         p, hint="a longer record, or one through a wider temperature range")
    labels = np.asarray(wa.pose).astype(str) if wa.pose is not None else np.array(["whole record"] * len(wa))
    pose_rows = []
    for lab in (poses or ["whole record"]):
        m = labels == lab
        ref = wa.ref[m][0]
        pose_rows.append({"label": lab, "windows": int(m.sum()),
                          "temperature_c": [float(T[m].min()), float(T[m].max())],
                          "gravity_reference_m_s2": ref.tolist(),
                          "direction": (ref / np.linalg.norm(ref)).tolist()})
    fits = AT.fit_static_windows(wins, bias_degree, loop, progress=progress)
    sensors = {s: _sensor(w, f) for s, (w, f) in fits.items()}
    notes, mixed = AT.restart_report(p, wa)     # IMU restarts: as rigctl calibrate's thermal path
    noise_lines, noise_rows = noise_summary(fits["accel"][0].noise + fits["gyro"][0].noise, wa.t0)
    return jsonable({
        "schema_version": SCHEMA_VERSION, "created_utc": utc_now(), "recording": str(p.resolve()),
        "mode": "thermal_static",
        "settings": {"settle_s": settle_s, "window_s": window_s, "bias_degree": bias_degree, "loop": loop,
                     "reference_c": reference_c, "one_pose": not poses,
                     "poses_from": str(poses_file) if poses_file else "the recording's segments"},
        "temperature_c": {"min": float(T.min()), "max": float(T.max()), "span_K": span, "of": "window means"},
        "poses": pose_rows, "sensors": sensors,
        "trustworthy": not mixed and all(d["status"] == "ok" for d in sensors.values()),
        "device_restarts": notes, "reasons": mixed,
        "noise_model": {"text": "estimated from the record (REML: white, bias instability, random walk)",
                        "channels": noise_rows, "lines": noise_lines},
        "findings": [f"{s} chi2/dof {d['chi2_per_dof']:.3g} {d['finding']}" for s, d in sensors.items()
                     if d["status"] != "ok"] + [
            f"{a['axis']} chi2/dof {a['chi2_per_dof']:.3g} outside its 99 % band "
            f"{a['chi2_band_99'][0]:.3g} .. {a['chi2_band_99'][1]:.3g}"
            for s, d in sensors.items() for a in d["axes"] if a["status"] != "ok"],
        "model": "y_i - u_i = sum_j <dT^j> b_ij + sum_j>=1 <dT^j> u_i s_ij + pose offsets [+ effects]; "
                 "dT = T - reference_c; u the pose's gravity reference (accelerometer), 0 (gyro)"})


def _pm(q: dict[str, Any] | None) -> str:
    if q is None:
        return "-"
    v, u = format_value(q["value"], q["sigma"])
    return f"{v} +- {u}"


def format_text(r: dict[str, Any]) -> str:
    """The printed result of ``rigctl thermal``."""
    s = r["settings"]
    T = r["temperature_c"]
    n = max(d["windows"] for d in r["sensors"].values())
    lines = [f"rigctl thermal: {r['recording']} -- static thermal fit: {len(r['poses'])} pose(s), {n} windows "
             f"of {s['window_s']:g} s, reference {s['reference_c']:g} degC",
             f"settle: " + (f"the first {s['settle_s']:g} s of every pose left out" if s["settle_s"] > 0 else
                            "none (every window from the start of each pose; --settle-s leaves a fast start out)"),
             f"temperature covered (window means): {T['min']:.2f} .. {T['max']:.2f} degC, span {T['span_K']:.2f} K",
             f"noise of the window means: {r['noise_model']['text']}", *r["noise_model"]["lines"],
             f"poses ({s['poses_from']}; the offsets pose2, pose3 ... are against the first):"]
    for p in r["poses"]:
        d = p["direction"]
        lines.append(f"  {p['label']:<24} {p['windows']:4d} windows  {p['temperature_c'][0]:6.2f} .. "
                     f"{p['temperature_c'][1]:6.2f} degC  gravity reference along ({d[0]:+.3f}, {d[1]:+.3f}, "
                     f"{d[2]:+.3f})")
    for name, d in r["sensors"].items():
        lo, hi = d["chi2_band_99"]
        deg = d["degrees"]
        held = ", scale and misalignment held" if deg["scale"] < 0 else ", misalignment held"
        lines += ["", f"{name}: bias degree {deg['bias']}{held}; chi2/dof {d['chi2_per_dof']:.3f} "
                  f"(99 % band {lo:.3f} .. {hi:.3f}): {d['finding']}",
                  "  thermal effects found (closed loop): " + ("; ".join(d["effects_found"]) or "none")
                  if r["settings"]["loop"] else "  closed loop off (--no-loop)"]
        keys = sorted({k for a in d["axes"] for k in a["coefficients"]}, key=lambda k: (k[:4] != "bias", k))
        if keys:
            unit = {k: next(a["coefficients"][k]["unit"] for a in d["axes"] if k in a["coefficients"]) for k in keys}
            head = [f"{k.replace('_per_K', '/K^').rstrip('^')} [{unit[k]}]" for k in keys]
            lines.append("  axis  " + "".join(f"{h:>26}" for h in head) + f"  {'chi2/dof (99 % band)':>26}")
            for a in d["axes"]:
                band = f"{a['chi2_per_dof']:.3f} ({a['chi2_band_99'][0]:.2f} .. {a['chi2_band_99'][1]:.2f})"
                flag = "" if a["status"] == "ok" else "  <- outside its band: a finding"
                lines.append(f"  {a['axis']:<4}  " + "".join(f"{_pm(a['coefficients'].get(k)):>26}" for k in keys)
                             + f"  {band:>26}{flag}")
        lines.append(f"  every coefficient: {'parameter':<28} {'value':>12} {'+-':>10} {'95 % interval':>26}  unit")
        for q in d["parameters"]:
            v, u = format_value(q["value"], q["sigma"])
            ci = (f"[{format_value(q['ci95'][0], q['sigma'])[0]}, {format_value(q['ci95'][1], q['sigma'])[0]}]")
            lines.append(f"  {'':<19}{q['quantity']:<28} {v:>12} {u:>10} {ci:>26}  {q['unit']}")
    if r["settings"]["one_pose"]:
        lines += ["", "one pose (--one-pose): the bias per K is the apparent one -- the bias's plus, on the axis "
                  "along gravity, the scale factor's per K times g"]
    lines += ["", "findings: " + ("; ".join(r["findings"]) if r["findings"] else
                                   "none (every chi-square inside its 99 % band)")]
    lines += untrusted_lines(r.get("reasons") or [])
    return "\n".join(lines)


CSV_FIELDS = ("sensor", "parameter", "quantity", "unit", "value", "sigma", "ci95_low", "ci95_high",
              "si_unit", "si_value", "si_sigma")


def write_csv(r: dict[str, Any], path: str | Path) -> Path:
    """One row per coefficient: field unit and SI (the JSON's ``parameters``)."""
    p = Path(path)
    with p.open("w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(CSV_FIELDS)
        for s, d in r["sensors"].items():
            for q in d["parameters"]:
                wr.writerow([s, q["name"], q["quantity"], q["unit"], repr(q["value"]), repr(q["sigma"]),
                             repr(q["ci95"][0]), repr(q["ci95"][1]), q["si"]["unit"], repr(q["si"]["value"]),
                             repr(q["si"]["sigma"])])
    return p
