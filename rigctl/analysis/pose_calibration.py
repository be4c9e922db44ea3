"""Calibration of an orientation-free recording (``rigctl import``: hand-held / table-less poses),
with the closed loop of :mod:`rigctl.solvers.pose_loop` on every sub-model.

Steps: pose statistics (means, white and slow noise); the accelerometer (magnitude model, or the
six-face linear fit when every pose is a labelled face); the gyro's static means against the
calibrated specific force (bias, Earth rate, g-sensitivity ...); the gyro's scale and
misalignment from the motions between poses. Each step runs the loop and is judged against its
chi2 band; the session's STATUS is OK only when every step ends inside its band.

Before/after (per channel and axis, RMS over the poses, field units): *raw* (nominal scale, no
calibration), *declared* (the base model: Tedaldi's 9 parameters, gyro bias + Earth rate, gyro
scale/misalignment) and *final* (with the effects the loop claimed), beside the noise floor.
References: accelerometer, gravity (length g) along the final model's direction of each pose;
gyro at rest, the Earth rate's known part (vertical part when the latitude is given, else 0);
motions, the measured gravity direction of the next pose.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from .calibration_text import param_table
from ..errors import InputError
from ..recording.segment_builder import open_recording
from ..sensor_axes import axis_name
from ..solvers import pose_loop as pl
from ..solvers.calibration_result import STATUS_INSUFFICIENT, CalibrationResult

G0 = 9.80665
MG = 1.0 / (G0 * 1e-3)
DEG_H = 180.0 / np.pi * 3600.0
_FACE = re.compile(r"^(?:([xyz])_([pa])|([+-])([xyz]))$")
ALPHA = 0.01 / 3  # family-wise 1 % over the three sub-models


def faces(labels: list[str]) -> np.ndarray | None:
    """(P, 3) unit 'up' directions when every pose is a labelled face (x_p / x_a as imucal, or
    +x / -x: that axis up / down), else None."""
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


def _result(method: str, fit: pl.Fit, loop: pl.SubLoop, n_poses: int, n_base: int) -> CalibrationResult:
    """The loop's final fit as a CalibrationResult (status, warnings, t intervals when above band)."""
    res = CalibrationResult(method=method, names=fit.names, values=fit.values, covariance=fit.cov, dof=fit.dof,
                            chi2=fit.chi2, normalized_residuals=fit.r, residuals=fit.extra.get("resid", fit.r))
    res.extra = {"loop_status": loop.status, "band_chi2_per_dof": list(loop.band)}
    if loop.status == pl.STATUS_UNEXPLAINED and fit.dof > 0:
        res.covariance = res.covariance * fit.chi2_per_dof
        res.interval, res.status = "t", "poor_fit"
        res.warnings.append(f"chi2/dof {fit.chi2_per_dof:.3g} above its band: covariance inflated by chi2/dof")
    if n_poses < 2 * n_base:
        res.status = STATUS_INSUFFICIENT
        res.warnings.append(f"too few poses for a trustworthy {method} fit: {n_poses} poses for {n_base} "
                            f"parameters (need >= {2 * n_base}; Tedaldi et al. recommend 36-50)")
    return res


def _rms(x: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(np.asarray(x) ** 2, axis=0))


def _row(channel: str, unit: str, raw: np.ndarray, decl: np.ndarray, fin: np.ndarray, floor: np.ndarray,
         f: float) -> list[dict[str, Any]]:
    """Before/after rows of x, y, z. ``channel``: a sensor ('accel', 'gyro'), named by its axes'
    one spelling (rigctl.sensor_axes: 'ax', 'gx'), followed by what it is compared with (e.g.
    'gyro at rest' -> 'gx at rest'); anything else keeps its name with the axis letter after it."""
    sensor, _, what = channel.partition(" ")
    names = ([f"{axis_name(sensor, i)} {what}".rstrip() for i in range(3)] if sensor in ("accel", "gyro")
             else [f"{channel} {a}" for a in "xyz"])
    return [{"channel": name, "unit": unit, "raw": float(r * f), "declared": float(d * f),
             "final": float(q * f), "noise_floor": float(n * f)}
            for name, r, d, q, n in zip(names, raw, decl, fin, floor)]


def read_session(path: Path) -> dict[str, Any]:
    """The arrays the orientation-free path needs from a recording."""
    with open_recording(path) as f:
        out = {"fs": float(f["imu"].attrs["sample_rate_hz"]),
               "g": float(f["meta"].attrs.get("gravity_m_s2", G0)) if "meta" in f else G0,
               "acc": f["imu/specific_force"][()], "gyr": f["imu/angular_rate"][()],
               "temp": f["imu/temperature"][()] if "imu/temperature" in f else None}
        lat = f["meta"].attrs.get("latitude_deg", np.nan) if "meta" in f else np.nan
        out["latitude_rad"] = None if not np.isfinite(float(lat)) else float(np.radians(float(lat)))
        s = {k: f["segments"][k][()] for k in ("kind", "status", "first_sample", "last_sample", "label")}
        rows = [i for i in range(s["kind"].shape[0]) if s["kind"][i] == b"orientation"
                and s["status"][i] == b"complete"]
        out["intervals"] = [(int(s["first_sample"][i]), int(s["last_sample"][i])) for i in rows]
        out["labels"] = [s["label"][i].decode() for i in rows]
    if out["temp"] is not None and (out["temp"].ndim != 1 or not np.any(np.isfinite(out["temp"]))):
        out["temp"] = None
    return out


def calibrate_poses(path: Path, noise_note: str = "") -> tuple[dict[str, Any], str, str]:
    """(payload, text, explain) for an orientation-free recording (module doc)."""
    s = read_session(path)
    iv, fs, g = s["intervals"], s["fs"], s["g"]
    if len(iv) < 2:
        raise InputError(f"{len(iv)} static poses: a calibration needs several", path,
                         hint="import with --segments or a longer --t-init")
    d = pl.pose_statistics(s["acc"], s["gyr"], iv, fs, s["temp"])
    P = len(iv)
    ups = faces(s["labels"])
    lines = [f"rigctl calibrate: {path} ({P} static poses, {fs:g} Hz, no table)",
             "noise of the pose means: " + "; ".join(d.notes) + (f" ({noise_note})" if noise_note else "")]
    loops: dict[str, pl.SubLoop] = {}
    results: dict[str, CalibrationResult] = {}
    # ---- accelerometer
    if ups is not None:
        ref = g * ups
        loop = pl.judge("faces_accel", lambda e: pl.fit_faces(d, ref, e), pl.face_candidates(d), d.noise_dof,
                        _tile(pl.pose_variables(d, ups), 3), ALPHA)
        lines.append("poses labelled as faces (axis up/down): six-face linear fit f = b + M a with nominal "
                     "references +-g (Ferraris' method)")
        fin = loop.final
        v = dict(zip(fin.names, fin.values))
        M = np.array([[v[f"accel_M_{a}{b}_ratio"] for b in "xyz"] for a in "xyz"])
        b = np.array([v[f"accel_bias_{a}_m_s2"] for a in "xyz"])
        k2 = np.array([v.get(f"accel_quadratic_{a}_s2_per_m", 0.0) for a in "xyz"])
        f_cal = np.linalg.solve(M, (d.acc - b - k2 * ref ** 2).T).T
        results["faces_accel"] = _result("faces_accel", fin, loop, P, 2)
        accel_model = {"bias_m_s2": b.tolist(), "M": M.tolist(), "k2_s2_per_m": k2.tolist()}
        decl = np.linalg.solve(_m_of(loop.declared), (d.acc - _b_of(loop.declared)).T).T
        acc_rows = _row("accel", "mg", _rms(d.acc - ref), _rms(decl - ref), _rms(f_cal - ref),
                        np.sqrt(d.var_acc.mean(axis=0)), MG)
        if loop.status == pl.STATUS_UNEXPLAINED:
            tilt = float(np.sqrt(np.mean((f_cal - ref) ** 2)) / g)
            loop.findings.append(f"the faces' residuals amount to {tilt * 1e3:.3g} mrad RMS of tilt: the six-face "
                                 "method takes each face as exactly +-g along one axis, and faces held or placed "
                                 "by hand are not (use a levelled fixture or the multi-position method)")
    else:
        up0 = d.acc / np.linalg.norm(d.acc, axis=1)[:, None]
        loop = pl.judge("accel", lambda e: pl.fit_accel(d, g, e), pl.accel_candidates(d), d.noise_dof,
                        pl.pose_variables(d, up0), ALPHA)
        lines.append("accelerometer: magnitude model |T K (u - b)| = g at rest (Tedaldi et al. 2014)")
        f_cal = pl.accel_apply(loop.final, loop.claimed, d.acc, d)
        f_decl = pl.accel_apply(loop.declared, [], d.acc, d)
        ref = g * f_cal / np.linalg.norm(f_cal, axis=1)[:, None]
        results["multipos_accel"] = _result("multipos_accel", loop.final, loop, P, 9)
        p = loop.final.values
        TK = pl._tk(p[0:3], p[3:6])
        eff = pl._accel_split(p, loop.claimed)
        accel_model = {"bias_m_s2": p[6:9].tolist(), "M": np.linalg.inv(TK).tolist(),
                       "k2_s2_per_m": eff.get("accel_quadratic", np.zeros(3)).tolist()}
        acc_rows = _row("accel", "mg", _rms(d.acc - ref), _rms(f_decl - ref), _rms(f_cal - ref),
                        np.sqrt(d.var_acc.mean(axis=0)), MG)
    loops[loop.name] = loop
    up = f_cal / np.linalg.norm(f_cal, axis=1)[:, None]
    # ---- gyro, static poses
    lat = s["latitude_rad"]
    gv = pl.pose_variables(d, up)
    gloop = pl.judge("gyro_static", lambda e: pl.fit_gyro_static(d, f_cal, e, lat), pl.gyro_static_candidates(d),
                     d.noise_dof, {k: np.append(np.tile(x, 3), 0.0) if lat is None else np.tile(x, 3)
                                   for k, x in gv.items()}, ALPHA)
    loops["gyro_static"] = gloop
    results["gyro_static"] = _result("gyro_static", gloop.final, gloop, P, 4)
    gfin = dict(zip(gloop.final.names, gloop.final.values))
    bg = np.array([gfin[f"gyro_bias_{a}_rad_s"] for a in "xyz"])
    G = np.array([[gfin.get(f"gyro_g_sens_{a}{b}_rad_s_per_m_s2", 0.0) for b in "xyz"] for a in "xyz"])
    earth = np.zeros_like(d.gyr) if lat is None else pl.OMEGA_EARTH * np.sin(lat) * up
    gres = lambda f: f.extra["resid"][:3 * P].reshape(3, P).T  # noqa: E731
    gyro_rows = _row("gyro at rest", "deg/h", _rms(d.gyr - earth), _rms(gres(gloop.declared)),
                     _rms(gres(gloop.final)), np.sqrt(d.var_gyr.mean(axis=0)), DEG_H)
    # ---- gyro, motions between poses
    gyro_M = np.eye(3)
    rot_rows: list[dict[str, Any]] = []
    n_mot = P - 1
    if 2 * n_mot - 9 >= 3:
        peak = float(np.max(np.abs(s["gyr"])))
        if ups is not None:
            f_all = np.linalg.solve(np.array(accel_model["M"]), (s["acc"] - np.array(accel_model["bias_m_s2"])).T).T
        else:
            f_all = pl.accel_apply(loop.final, loop.claimed, s["acc"], _SampleTimes(d, len(s["acc"]), s["temp"]))
        bias_t = pl.gyro_static_model(gloop.final, f_all, np.arange(len(f_all)) / fs, s["temp"], d)
        clipped, n_clip = pl.clipped_motions(s["gyr"], iv)
        keep = ~clipped
        dvar = pl.direction_variance(loop.final, loop.claimed, d.acc, d) if ups is None else None
        rcands = pl.rotation_candidates(int(keep.sum()), peak)
        up_fn = None
        if ups is None:  # the accelerometer's cross-coupling, as the directions show it
            up_fn = pl.cross_split_up(loop.final, loop.claimed, d.acc, d)
            rcands.append(pl.Candidate(pl.SPLIT, 2) if "accel_cross_quadratic" in loop.claimed
                          else pl.Candidate("accel_cross_quadratic", 3))
        rloop = pl.judge("gyro_rotation", lambda e: pl.fit_rotations(s["gyr"], d, up, bias_t, e, keep, dvar, up_fn),
                         rcands, np.inf, {}, ALPHA)
        if clipped.any():
            rloop.claimed.insert(0, "gyro_range_exceeded")
            rloop.findings.insert(0, f"gyro_range_exceeded: {n_clip} samples at the gyro's range limit "
                                     f"({np.degrees(np.max(np.abs(s['gyr']))):.4g} deg/s) in {int(clipped.sum())} "
                                     f"of {n_mot} motions; those motions are left out of the rotation fit")
        loops["gyro_rotation"] = rloop
        results["multipos_gyro"] = _result("multipos_gyro", rloop.final, rloop, P, 9)
        gyro_M = np.linalg.inv(pl._tg(rloop.final.values))
        sig = rloop.final.extra["sigma_rad"]
        raw = pl.rotation_residuals_at(s["gyr"], d, up, np.zeros(3), np.concatenate([np.zeros(6), np.ones(3)]), keep, dvar)
        rot_rows = _row("motion (gravity direction)", "urad", _rms(raw), _rms(rloop.declared.extra["resid"]),
                        _rms(rloop.final.extra["resid"]), np.full(3, _rms(sig) / np.sqrt(2)), 1e6)
    else:
        lines.append(f"gyro scale/misalignment NOT FITTED: {P} poses give {2 * n_mot} rotation residuals for 9 "
                     "parameters (>= 7 poses needed; >= 18 for a trustworthy fit); gyro model: bias only")
    for lp, sl, what in ((loop, slice(0, 3), "accelerometer"), (gloop, slice(3, 6), "gyro")):
        x = s["acc"] if what == "accelerometer" else s["gyr"]
        c, pv = pl.stationarity(x, iv, d.white[sl])
        moving = [f"{a} chi2/P {ci:.3g} (p {pi:.2g})" for a, ci, pi in zip("xyz", c, pv) if pi < ALPHA]
        if moving and lp.status != pl.STATUS_OK:
            lp.findings.append(f"the {what} pose means drift within the poses (half-split test: " + ", ".join(moving)
                               + "): the poses are not static at the noise level (settling, hand or table motion) "
                               "-- scatter no sensor model describes")
    model = {"accel": accel_model,
             "gyro": {"bias_rad_s": bg.tolist(), "M": gyro_M.tolist(), "G_rad_s_per_m_s2": G.tolist()},
             "effects": {n: lp.claimed for n, lp in loops.items()},
             "source": "faces" if ups is not None else "multipos",
             "equations": "A = b_a + M_a a + k2 o a^2 (m/s^2); W = b_g + M_g w + G f (rad/s)"}
    before_after = acc_rows + gyro_rows + rot_rows
    # ---- status
    insufficient = [r for r in results.values() if r.status == STATUS_INSUFFICIENT]
    bad = [lp for lp in loops.values() if lp.status != pl.STATUS_OK]
    reasons = [w for r in insufficient for w in r.warnings if "too few poses" in w]
    if ups is not None:
        reasons = [w for w in reasons if "faces_accel" not in w]
    accel_trusted = not any(r.method in ("multipos_accel",) for r in insufficient)
    if not accel_trusted:
        status = "NOT TRUSTWORTHY"
    elif bad:
        status = pl.STATUS_UNEXPLAINED if any(lp.status == pl.STATUS_UNEXPLAINED for lp in bad) else bad[0].status
        first = sorted(bad, key=lambda lp: lp.status != status)  # the reason of the status comes first
        reasons = [f"{lp.name}: {x}" for lp in first for x in lp.findings] + reasons
    elif reasons:
        status = "OK (accelerometer); gyro scale NOT TRUSTWORTHY"
    else:
        status = "OK"
    for key, r in results.items():
        lines.append(param_table(r, key))
    lines.append(format_loops(loops))
    lines.append(format_before_after(before_after))
    lines.append(f"STATUS: {status}" + (f": {reasons[0]}" if reasons and status != "OK" else ""))
    payload = {"mode": "orientation_free", "n_poses": P, "pose_labels": s["labels"],
               "results": {k: r.to_dict() for k, r in results.items()}, "model": model,
               "closed_loop": {k: lp.to_dict() for k, lp in loops.items()}, "before_after": before_after,
               "noise": {"notes": d.notes, "noise_dof": d.noise_dof},
               "trustworthy": bool(accel_trusted), "status": status, "reasons": reasons}
    explain = format_explain(loops)
    return payload, "\n".join(lines), explain


class _SampleTimes:
    """Per-sample stand-in for PoseData in the accelerometer candidates (time, temperature)."""

    def __init__(self, d: pl.PoseData, n: int, temp: np.ndarray | None) -> None:
        self.t_s = np.arange(n) / d.fs_hz
        self.t_ref, self.temp_ref = d.t_ref, d.temp_ref
        self.temp_c = None if temp is None else np.nan_to_num(temp, nan=d.temp_ref)


def _tile(v: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    return {k: np.tile(x, n) for k, x in v.items()}


def _m_of(fit: pl.Fit) -> np.ndarray:
    v = dict(zip(fit.names, fit.values))
    return np.array([[v[f"accel_M_{a}{b}_ratio"] for b in "xyz"] for a in "xyz"])


def _b_of(fit: pl.Fit) -> np.ndarray:
    v = dict(zip(fit.names, fit.values))
    return np.array([v[f"accel_bias_{a}_m_s2"] for a in "xyz"])


def format_loops(loops: dict[str, pl.SubLoop]) -> str:
    """One block per sub-model: chi2/dof declared -> final against its band, effects, findings."""
    out = ["closed loop (each sub-model: declared -> final chi2/dof, 99 % band):"]
    for lp in loops.values():
        out.append(f"  {lp.name}: {lp.declared.chi2_per_dof:.3g} -> {lp.final.chi2_per_dof:.3g} "
                   f"(dof {lp.final.dof}, band [{lp.band[0]:.3g}, {lp.band[1]:.3g}]) {lp.status}; "
                   f"effects found: {', '.join(lp.claimed) or 'none'}")
        out += [f"    {x}" for x in lp.findings]
    return "\n".join(out)


def format_before_after(rows: list[dict[str, Any]]) -> str:
    """The before/after table: raw, declared, final and noise floor (RMS over the poses)."""
    out = ["before/after (RMS over the poses; raw: nominal scale, no calibration):",
           f"  {'channel':<34} {'unit':<6} {'raw':>11} {'declared':>11} {'final':>11} {'noise floor':>11}"]
    out += [f"  {r['channel']:<34} {r['unit']:<6} {r['raw']:>11.4g} {r['declared']:>11.4g} {r['final']:>11.4g} "
            f"{r['noise_floor']:>11.4g}" for r in rows]
    return "\n".join(out)


def format_explain(loops: dict[str, pl.SubLoop]) -> str:
    """--explain: per sub-model, every candidate with its statistic and decision."""
    out = ["explain (sub-model | step | candidate | statistic | decision):"]
    for lp in loops.values():
        for x in lp.explain:
            out.append(f"  {lp.name} | {x['step']} | {x['candidate']} | {x['statistic']} | {x['decision']}")
        for c in lp.correlations[:6]:
            out.append(f"  {lp.name} | residual | {c['variable']} | r = {c['r']:.3f}, p = {c['p']:.2g} | "
                       "partial correlation of the final residual")
    return "\n".join(out)
