"""``rigctl calibrate RECORDING.h5``: calibration with uncertainty and the closed loop.

Turntable recordings (orientation and rate segments with table angles): the segment table
(:func:`rigctl.segment_builder.build_segment_table`), the published solvers and the joint
closed loop (:func:`rigctl.solvers.closed_loop.calibrate_session`); with /truth (emulator) the
parameter errors against truth before and after the loop.

Orientation-free recordings (``rigctl import``: no table, segment attitudes unknown): the
multi-position solver (:mod:`rigctl.solvers.multipos`, Tedaldi et al. 2014), and when the
static poses are labelled as faces (``x_p``/``x_a`` as imucal, or ``+x``/``-x``: that axis up /
down) the six-face linear fit f = b + M a with nominal references +-g (Ferraris' method).
A fit with too few poses is computed but printed as NOT TRUSTWORTHY (exit code 0; the JSON
has ``"trustworthy": false`` and the reasons).

Noise model for the segment means, including the covariance between segments that bias
instability and rate random walk create (the bias wanders during the 30-60 minute procedure;
:mod:`rigctl.solvers.segment_cov`): the IEEE 952 coefficients of /results/allan (``rigctl
allan``) when present, or of another recording of the same IMU (``--noise FILE.h5``: an
overnight capture that ``rigctl allan`` analysed; its /meta unit identity must match), else
estimated from the session itself (``--noise self``: white level from each window's batch means,
bias instability and random walk by REML of the segment means,
:mod:`rigctl.solvers.segment_noise`). The output says which, with the coefficients per channel.

Results: /results/calibration (attrs schema_version, created_utc, json) and a JSON file beside
the recording (RECORDING.calibration.json, or ``--json``). ``payload["model"]`` holds the sensor
model apply-cal inverts: A = b_a + M_a a + k2 o a^2, W = b_g + M_g w + G f (SI).
Exit codes: 0 done, 2 invalid input, 1 failure.
"""
from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np

from .analysis import production
from .analysis.verdicts import format_verdicts
from .cli_options import add_production_options
from .recorder import utc_now, write_results
from .segment_builder import build_segment_table, open_recording
from .solvers.calibration_result import CalibrationResult, _jsonable
from .solvers.segment_stats import NoiseModel
from .errors import InputError, RunFailure
from .spec import Spec, load_spec

SCHEMA_VERSION = 1
G0 = 9.80665
DEG_H = 180.0 / math.pi * 3600.0
DEG = math.pi / 180.0
_FACE = re.compile(r"^(?:([xyz])_([pa])|([+-])([xyz]))$")
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


# ------------------------------------------------------------------------------ noise model
def _allan_term_si(fit: dict[str, Any], term: str) -> float:
    """A term of one axis' Allan fit for the segment covariance (SI): the fitted value, or for a
    term the fit reports only as an upper bound its unconstrained estimate -- not zero: a
    12-hour capture rarely makes the rate random walk significant, and K = 0 would make the
    biases' intervals too narrow (docs/calibration.md, section 10)."""
    e = fit.get("terms", {}).get(term)
    if e is not None and not e.get("supported", True):
        est = [v for k, v in e.items() if k.startswith("estimate_")]
        return float(est[0]) if est else 0.0
    return math.sqrt(max(float(fit["coeff_sq_si"].get(term, 0.0)), 0.0))


def noise_from_allan(f: h5py.File) -> tuple[NoiseModel, NoiseModel] | None:
    """IEEE 952 NoiseModels (accel, gyro) from /results/allan's joint fits, if complete."""
    g = f.get("results/allan")
    if g is None or "json" not in g.attrs:
        return None
    axes = json.loads(g.attrs["json"]).get("axes", {})
    out = []
    for names in (("ax", "ay", "az"), ("gx", "gy", "gz")):
        if not all(a in axes for a in names):
            return None
        out.append(NoiseModel(**{t: np.array([_allan_term_si(axes[a]["fit"], t) for a in names])
                                 for t in "QNBKR"}))
    return out[0], out[1]


NOISE_CHOICES = ("auto", "allan", "self")


def _unit_ids(f: h5py.File) -> dict[str, str]:
    """The unit under test's identity recorded in /meta (non-empty entries only)."""
    m = f["meta"].attrs if "meta" in f else {}
    out = {}
    for key in ("imu_device_id", "imu_serial"):
        v = m.get(key, "")
        v = v.decode() if isinstance(v, bytes) else str(v)
        if v.strip():
            out[key] = v.strip()
    return out


def _noise_from_file(f: h5py.File, path: Path, src: Path) -> tuple[Any, Any, str]:
    """The noise model of another recording of the same unit (an overnight static capture that
    ``rigctl allan`` analysed): its /results/allan, after checking the unit's identity."""
    if not src.is_file():
        raise InputError(f"--noise {src}: no such file", hint="give a recording that `rigctl allan` "
                         "analysed (e.g. an overnight capture of procedures/allan-overnight.yaml), or auto/self")
    with open_recording(src) as g:
        nm = noise_from_allan(g)
        ids_src, fs_src = _unit_ids(g), float(g["imu"].attrs.get("sample_rate_hz", 0.0))
    if nm is None:
        raise InputError("no complete /results/allan (all six axes) in the noise recording", src,
                         hint=f"run `rigctl allan {src}` first")
    ids = _unit_ids(f)
    for key in sorted(set(ids) & set(ids_src)):
        if ids[key] != ids_src[key]:
            raise InputError(f"--noise {src}: that recording is of another unit ({key} "
                             f"{ids_src[key]!r}, this one {ids[key]!r})", path,
                             hint="use the Allan capture of the same IMU, or --noise self")
    fs = float(f["imu"].attrs.get("sample_rate_hz", 0.0))
    common = sorted(set(ids) & set(ids_src))
    note = (" (same unit: " + ", ".join(f"{k} {ids[k]}" for k in common) + ")" if common else
            " (the unit's identity is not recorded in both files: not checked)")
    rate = "" if fs_src == fs else f"; captured at {fs_src:g} Hz, this recording {fs:g} Hz"
    return nm[0], nm[1], (f"from {src}:/results/allan (IEEE 952 terms fitted by rigctl allan on another "
                          f"recording{note}{rate}; segment covariance from N, Q, B (flicker band 1 s - 1e4 s) "
                          "and K)")


def _noise(f: h5py.File, choice: str, path: Path) -> tuple[Any, Any, str]:
    if choice not in NOISE_CHOICES:
        return _noise_from_file(f, path, Path(choice))
    nm = noise_from_allan(f) if choice in ("auto", "allan") else None
    if choice == "allan" and nm is None:
        raise InputError("--noise allan: the recording has no complete /results/allan (all six axes)", path,
                         hint="run `rigctl allan` on it (if it holds a long static capture), give the "
                              "analysed overnight capture of the same IMU (--noise FILE.h5), or use --noise self")
    if nm is not None:
        return nm[0], nm[1], ("from /results/allan (IEEE 952 terms fitted by rigctl allan; segment "
                              "covariance from N, Q, B (flicker band 1 s - 1e4 s) and K)")
    return None, None, ("from the data (no /results/allan in the recording): white level per channel "
                        "and segment kind from each window's batch means (about what the reference "
                        "explains), bias instability B and rate random walk K by REML of the segment "
                        "means (declared model + time, temperature and per-kind offsets protected)")


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


# ------------------------------------------------------------------------------ turntable data
def _truth(f: h5py.File) -> dict[str, float] | None:
    from .solvers.segments import truth_from_emulator

    t = f.get("truth")
    if t is None or "params_json" not in t.attrs:
        return None
    p = json.loads(t.attrs["params_json"])
    imu = p.get("imu", p)
    if imu.get("model") == "declared":  # configs/sim.yaml without a profile (sim/imu.py)
        imu = {"accel_bias_m_per_s2": imu.get("accel_bias_m_s2"), "gyro_bias_rad_per_s": imu.get("gyro_bias_rad_s"),
               "accel_scale_misalignment_matrix": imu.get("accel_matrix"),
               "gyro_scale_misalignment_matrix": imu.get("gyro_matrix"),
               "accel_quadratic_per_m_per_s2": imu.get("accel_quadratic_per_m_s2")}
    return truth_from_emulator(imu) or None


def _model_from_final(final: CalibrationResult) -> dict[str, Any]:
    """The fitted sensor model (SI) for apply-cal from the closed loop's final fit."""
    v = dict(zip(final.names, np.nan_to_num(final.values)))
    ax = "xyz"
    G = [[v.get(f"gyro_g_sens_{a}{b}_rad_s_per_m_s2", 0.0) for b in ax] for a in ax]
    return {"accel": {"bias_m_s2": [v.get(f"accel_bias_{a}_m_s2", 0.0) for a in ax],
                      "M": [[v.get(f"accel_M_{a}{b}_ratio", float(a == b)) for b in ax] for a in ax],
                      "k2_s2_per_m": [v.get(f"accel_quad_{a}_s2_per_m", 0.0) for a in ax]},
            "gyro": {"bias_rad_s": [v.get(f"gyro_bias_{a}_rad_s", 0.0) for a in ax],
                     "M": [[v.get(f"gyro_M_{a}{b}_ratio", float(a == b)) for b in ax] for a in ax],
                     "G_rad_s_per_m_s2": G},
            "equations": "A = b_a + M_a a + k2 o a^2 (m/s^2); W = b_g + M_g w + G f (rad/s)"}


def calibrate_table(path: Path, noise: str) -> tuple[dict[str, Any], str, str]:
    """Returns (payload, report text, explain text) for a turntable recording."""
    from .solvers.closed_loop import calibrate_session, format_report, session_to_dict

    from .solvers.segment_noise import apply_session_noise

    with open_recording(path) as f:
        nf, nw, noise_txt = _noise(f, noise, path)
        truth = _truth(f)
    seg = build_segment_table(path, noise_f=nf, noise_w=nw)
    models = apply_session_noise(seg, nf, nw)
    noise_lines, noise_rows = noise_summary(models) if models else ([], [])
    if not models:
        noise_txt += " (segment windows unknown: means treated as independent)"
    out = calibrate_session(seg, truth=truth)
    cl = out["closed_loop"]
    kinds = {k: int(np.sum(seg.kind == k)) for k in np.unique(seg.kind)}
    head = [f"rigctl calibrate: {path} ({', '.join(f'{v} {k}' for k, v in kinds.items())} segments)",
            f"noise model: {noise_txt}", *noise_lines]
    for key, title in (("accel24", "accel24 (A3, static positions)"), ("gyro_rate", "gyro rate test (A4)")):
        r = out.get(key)
        if r is not None:
            head.append(f"{title}: status {r.status}, dof {r.dof}, chi2/dof {r.chi2_per_dof:.3g}")
    text = "\n".join(head + [param_table(cl.final, "Calibration (closed-loop model, all segments)"),
                             format_report(cl, explain=False)])
    explain = "\n".join(["explain (step | residual pattern | candidate | statistic | decision):"]
                        + [f"  [{x['step']}] {x['residual_pattern']} | {x['candidate']} | {x['statistic']} | "
                           f"{x['decision']}" for x in cl.explain])
    trust = cl.final.status in ("ok", "poor_fit")
    payload = {"mode": "turntable", "noise_model": noise_txt, "noise_model_channels": noise_rows,
               "results": session_to_dict(out),
               "model": _model_from_final(cl.final), "truth_available": truth is not None,
               "trustworthy": trust, "status": cl.final.status,
               "reasons": list(cl.final.warnings)}
    return payload, text, explain


# ------------------------------------------------------------------------------ orientation-free
def _faces(labels: list[str]) -> np.ndarray | None:
    """(P, 3) unit 'up' directions when every pose is a labelled face, else None."""
    ups = []
    for lab in labels:
        m = _FACE.match(lab.strip().lower())
        if not m:
            return None
        axis, sign = (m.group(1), 1.0 if m.group(2) == "p" else -1.0) if m.group(1) else \
            (m.group(4), 1.0 if m.group(3) == "+" else -1.0)
        e = np.zeros(3)
        e["xyz".index(axis)] = sign
        ups.append(e)
    u = np.array(ups)
    return u if len(u) >= 6 and np.linalg.matrix_rank(u) == 3 else None


def calibrate_free(path: Path, noise: str) -> tuple[dict[str, Any], str, str]:
    """Multi-position (and six-face, when labelled) calibration of an orientation-free recording."""
    from .solvers import multipos as mp
    from .solvers.accel24 import calibrate_accel, calibrate_gyro_bias_static

    with open_recording(path) as f:
        nf, nw, noise_txt = _noise(f, noise, path)
        fs = float(f["imu"].attrs["sample_rate_hz"])
        g = float(f["meta"].attrs.get("gravity_m_s2", G0))
        acc = f["imu/specific_force"][()]
        gyr = f["imu/angular_rate"][()]
        s = f["segments"]
        rows = [i for i in range(s["kind"].shape[0]) if s["kind"][i] == b"orientation"
                and s["status"][i] == b"complete"]
        iv = [(int(s["first_sample"][i]), int(s["last_sample"][i])) for i in rows]
        labels = [s["label"][i].decode() for i in rows]
    if len(iv) < 2:
        raise InputError(f"{len(iv)} static poses: a calibration needs several", path,
                         hint="import with --segments or a longer --t-init")
    lines = [f"rigctl calibrate: {path} ({len(iv)} static poses, {fs:g} Hz, no table)",
             "orientation-free data: multi-position solver (Tedaldi et al. 2014: |a| = g at rest; "
             "rotations between poses for the gyro)",
             f"noise model: {noise_txt}"]
    fa, sa = mp.pose_means(acc, iv, fs, nf)
    # IEEE 952 coefficients (rigctl allan): pose means correlated by the slow terms. Without them
    # the poses are treated as independent (a few hand-held poses cannot estimate slow noise).
    pc_a = mp.pose_cov(iv, fs, nf) if isinstance(nf, NoiseModel) else None
    pc_g = mp.pose_cov(iv, fs, nw) if isinstance(nw, NoiseModel) else None
    if pc_a is not None:
        sa = np.sqrt(np.diagonal(pc_a, axis1=1, axis2=2)).T
    acc_res = mp.calibrate_accel_multipos(fa, sa, g, unit="m_s2", pose_cov=pc_a)
    acc_cal = mp.calibrate_accel_apply(acc_res.values, acc)
    results: dict[str, Any] = {"multipos_accel": acc_res}
    if 2 * (len(iv) - 1) - 9 >= 2:
        gyr_res = mp.calibrate_gyro_multipos(gyr, acc_cal, iv, fs, 1.0, unit="rad_s")
        results["multipos_gyro"] = gyr_res
        Mg, bg = np.linalg.inv(mp._tg(gyr_res.values)), gyr_res.extra["bias_rad_s"]
    else:  # 3 residuals (2 independent) per transition, 9 parameters
        gyr_res = None
        Mg, bg = np.eye(3), gyr[iv[0][0]:iv[0][1]].mean(axis=0)
        lines.append(f"gyro scale/misalignment NOT FITTED: {len(iv)} poses give {2 * (len(iv) - 1)} "
                     "rotation residuals for 9 parameters (>= 18 poses needed for a trustworthy fit); "
                     "gyro model: bias only")
    TK = acc_res.extra["T_times_K"]
    model = {"accel": {"bias_m_s2": acc_res.values[6:9].tolist(), "M": np.linalg.inv(TK).tolist(),
                       "k2_s2_per_m": [0.0, 0.0, 0.0]},
             "gyro": {"bias_rad_s": np.asarray(bg).tolist(), "M": Mg.tolist(),
                      "G_rad_s_per_m_s2": np.zeros((3, 3)).tolist()},
             "source": "multipos", "equations": "A = b_a + M_a a (m/s^2); W = b_g + M_g w (rad/s)"}
    reasons = [w for r in results.values() for w in r.warnings if r.status == "insufficient_poses"]
    if gyr_res is None:
        reasons.append(f"gyro scale/misalignment not fitted: {len(iv)} poses are too few")
    trust = acc_res.status in ("ok", "poor_fit")
    ups = _faces(labels)
    if ups is not None:
        lines.append("poses labelled as faces (axis up/down): six-face linear fit f = b + M a with nominal "
                     "references +-g (Ferraris' method); gyro bias from the same faces (Earth rate ignored: "
                     "heading unknown)")
        ws = [mp.pose_means(gyr, iv, fs, nw)[k] for k in (0, 1)]
        fr = g * ups
        face = calibrate_accel(fa, sa, fr, quadratic=False, f_cov=pc_a)
        gb = calibrate_gyro_bias_static(ws[0], ws[1] if pc_g is None else np.sqrt(
            np.diagonal(pc_g, axis1=1, axis2=2)).T, np.zeros_like(fr), None, pc_g)
        results.update({"faces_accel": face, "faces_gyro_bias": gb})
        model["accel"] = {"bias_m_s2": face.extra["bias_m_s2"].tolist(), "M": face.extra["M"].tolist(),
                          "k2_s2_per_m": [0.0, 0.0, 0.0]}
        model["gyro"]["bias_rad_s"] = gb.values.tolist()
        model["source"] = "faces (accelerometer, gyro bias) + multipos (gyro scale)"
        trust = face.status in ("ok", "poor_fit")
        reasons = [w for w in reasons if "accelerometer" not in w]
    shown = [(k, r) for k, r in results.items()]
    for key, r in shown:
        lines.append(param_table(r, key))
    status = "OK" if trust else "NOT TRUSTWORTHY"
    if reasons and trust:
        status = "OK (accelerometer); gyro scale NOT TRUSTWORTHY"
    lines.append(f"STATUS: {status}" + (f": {reasons[0]}" if reasons and not trust else ""))
    payload = {"mode": "orientation_free", "noise_model": noise_txt, "n_poses": len(iv), "pose_labels": labels,
               "results": {k: r.to_dict() for k, r in results.items()}, "model": model,
               "trustworthy": bool(trust), "status": status, "reasons": reasons}
    return payload, "\n".join(lines), ""


# ------------------------------------------------------------------------------ entry points
def is_orientation_free(path: Path) -> bool:
    """True for recordings without a table: the import's flag, or NaN/absent table angles."""
    with open_recording(path) as f:
        if int(f["meta"].attrs.get("orientation_free", 0)) == 1 if "meta" in f else False:
            return True
        if "table/time" not in f or f["table/time"].shape[0] == 0:
            return True
        ang = f["segments/commanded_angle"][()]
        kinds = f["segments/kind"][()]
        sel = np.isin(kinds, (b"orientation", b"rate"))
        return bool(sel.any() and np.all(np.isnan(ang[sel])))


def calibrate(path: str | Path, noise: str = "auto", store: bool = True, json_path: str | Path | None = None,
              spec: Spec | None = None) -> tuple[dict[str, Any], str, str]:
    """Calibrate a recording, store /results/calibration and the JSON; (payload, text, explain).
    With ``spec`` the verdicts are computed, printed and stored with the results."""
    p = Path(path)
    free = is_orientation_free(p)
    payload, text, explain = (calibrate_free if free else calibrate_table)(p, noise)
    payload = _jsonable({"schema_version": SCHEMA_VERSION, "created_utc": utc_now(),
                         "recording": str(p.resolve()), **payload})
    if spec is not None:
        payload["verdicts"] = production.verdicts_for(spec, "calibration", payload)
        text += "\n" + format_verdicts(payload["verdicts"])
    if store:
        with open_recording(p) as f:
            status = bytes(f["run/status"][0]).rstrip(b"\0").decode() if "run/status" in f else "complete"
        if status == "running":
            text += "\nnot stored in the recording: it is still being written (status running)"
        else:
            write_results(p, "calibration", payload, schema_version=SCHEMA_VERSION)
        jp = Path(json_path) if json_path else p.with_name(p.stem + ".calibration.json")
        jp.write_text(json.dumps(payload, indent=1))
        text += f"\nresults: {p}:/results/calibration and {jp}"
    return payload, text, explain


def run(args: argparse.Namespace) -> int:
    """``rigctl calibrate``: 0 done, 2 invalid input, 1 failure."""
    spec = load_spec(args.spec, args.decision_rule) if args.spec else None
    try:
        payload, text, explain = calibrate(args.recording, args.noise, True, args.json, spec)
        text += "\n" + production.to_database(args.recording, "calibration", payload, args.db)
    except InputError:
        raise
    except (OSError, ValueError, np.linalg.LinAlgError) as exc:
        raise RunFailure(f"{args.recording}: {exc}") from exc
    print(text.rstrip())
    if args.explain and explain:
        print(explain)
    return 0


_DONE: set[str] = set()


def solve_hook(recording: str | Path, log: Callable[..., None]) -> None:
    """Solver hook of ``solve: [accel24, gyro-rate, closed-loop]``: one calibration per recording.

    The first of these solvers on a recording computes everything (the joint closed loop holds
    the published fits) and prints it; the others are no-ops that point to it.
    """
    key = str(Path(recording).resolve())
    if key in _DONE:
        return
    _DONE.add(key)
    try:
        payload, text, _ = calibrate(recording)
        text += "\n" + production.to_database(recording, "calibration", payload, None)
    except InputError as exc:
        log("warning", f"calibration: {exc}")
        return
    except (OSError, ValueError, np.linalg.LinAlgError) as exc:
        log("error", f"calibration failed: {exc}")
        return
    log("info", text)


def register(subparsers: Any) -> None:
    """Add the ``calibrate`` sub-command."""
    p = subparsers.add_parser("calibrate", help="calibrate a recording (uncertainty, closed loop)",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("recording", help="rigctl HDF5 recording (results are stored in it)")
    p.add_argument("--explain", action="store_true", help="print the closed loop's chain of decisions")
    p.add_argument("--json", help="JSON output path (default: RECORDING.calibration.json beside it)")
    p.add_argument("--noise", default="auto", metavar="{auto,allan,self,FILE.h5}",
                   help="segment noise model: this recording's /results/allan (allan), the data (self), "
                        "allan if present else self (auto, default), or FILE.h5: the /results/allan of an "
                        "overnight capture of the same IMU (best: a 40-minute session cannot pin down the "
                        "slow terms)")
    add_production_options(p)
    p.set_defaults(func=run)

