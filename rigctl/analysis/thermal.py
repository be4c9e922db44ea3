"""Thermal calibration of a recording (application layer): the windows of a soak or ramp run
(procedures/thermal-soak.yaml, thermal-ramp.yaml) into :mod:`rigctl.solvers.thermal`, the
results into /results/thermal and a JSON file beside the recording.

A recording is *thermal* when it holds chamber readings (/chamber) and its static and rate
windows span at least :data:`MIN_SPAN_K` of IMU temperature (a chamber run; an imported log
whose temperature drifts is not). Per window: the mean outputs, its times and
batch means (for the covariance of the means under white noise, bias instability and rate
random walk, :func:`rigctl.solvers.thermal.estimate_noise`), the reference input from the table's angles
(:func:`rigctl.frames.body_references`), the means of powers of the temperature offset, and the
candidates' regressors (hysteresis state from a play operator on the IMU temperature, the
temperature rate, the chamber air minus the IMU temperature from /chamber). Accelerometer: the
static windows; gyro: static and rate windows.

With /truth (the emulator) every coefficient is compared with the truth: how many 95 %
intervals cover it.
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..recording import recording_reader
from ..display_units import display, format_value
from ..sensor_axes import axis_name
from ..errors import InputError
from ..frames import body_references
from ..recording.checkpoint import write_atomic
from ..recording.recorder import utc_now
from ..recording.recording_reader import check_finite
from ..recording.segment_builder import _angles_at, _site, open_recording, store_calibration_results
from ..solvers import thermal as th
from . import restarts
from ..solvers.segment_noise import window_revolutions
from ..solvers.segment_stats import N_BATCHES, batch_means, batch_var
from ..solvers.segments import about_reference

SCHEMA_VERSION = 1
#: IMU temperature span (max - min over the calibration windows) that makes a recording thermal, K
MIN_SPAN_K = 5.0
#: width of the play operator behind the hysteresis candidate, K
HYSTERESIS_WIDTH_K = 2.0
DEFAULT_DEGREES = {"bias": 2, "scale": 2, "misalignment": 1}
#: highest polynomial degree of --thermal-degree, and the degree of the noise estimate's protected design
MAX_DEGREE = 4
MAX_FIT_DEGREE = 3


def quantity_name(name: str) -> str:
    """The shown name of a thermal coefficient (SI ``name``): the display base name
    (rigctl.display_units) with the power of temperature kept, ``accel_bias_x_m_s2_per_K2`` ->
    ``accel_bias_x_per_K2`` (the display base alone, ``accel_bias_x``, is the same for the value
    at the reference temperature and each of its coefficients per K)."""
    m = re.search(r"_per_K(\d?)$", name)
    base = display(name).base
    return f"{base}_per_K{m.group(1)}" if m and not base.endswith("_per_K" + m.group(1)) else base

def _cal_rows(f: Any) -> list[int]:
    seg = f["segments"]
    kinds, status = seg["kind"][()], seg["status"][()]
    first, last = seg["first_sample"][()], seg["last_sample"][()]
    return [i for i, k in enumerate(kinds) if k in (b"orientation", b"rate") and status[i] == b"complete"
            and last[i] - first[i] >= 10]


def _detrend(x: np.ndarray) -> np.ndarray:
    """The samples less a straight line in time per axis: a temperature changing inside the
    window (a ramp) moves the output along it, which the model takes from the window's mean
    powers of dT; left in, the batch means would count that drift as noise."""
    n = x.shape[0]
    if n < 3:
        return x
    k = np.arange(n, dtype=float) - (n - 1) / 2.0
    slope = (k @ (x - x.mean(axis=0))) / (k @ k)
    return x - np.outer(k, slope)


def _noise_parts(x: np.ndarray) -> np.ndarray:
    """(2, c): the white-noise variance of the window mean s^2 / n and the batch-means variance
    (8 batches) of the same mean."""
    n = x.shape[0]
    white = x.var(axis=0, ddof=1) / n
    batch = batch_var(x, 8) if n >= 32 else 4.0 * white
    return np.vstack([white, batch])


def _pooled_sigma(parts: np.ndarray) -> np.ndarray:
    """Standard uncertainties (n, c) of the window means of one sensor when no covariance is
    set (the fallback of :class:`rigctl.solvers.thermal.ThermalWindows`): each window's white
    level s^2 / n (thousands of samples: precise) times one factor per axis, the ratio of the
    batch-means variance to the white variance averaged over all the sensor's windows (never
    below 1): correlated noise raises it, and pooling over the windows gives it hundreds of
    degrees of freedom instead of the 7 of one window (whose noisy maximum would bias every
    uncertainty up and the chi-square down)."""
    white, batch = parts[:, 0, :], parts[:, 1, :]
    factor = np.maximum(1.0, np.mean(batch / white, axis=0))
    return np.sqrt(white * factor)


def is_thermal(path: str | Path) -> bool:
    """True for a chamber run whose calibration windows span at least MIN_SPAN_K of IMU temperature."""
    with open_recording(path) as f:
        if "imu/temperature" not in f or "chamber/time" not in f or f["chamber/time"].shape[0] == 0:
            return False
        rows = _cal_rows(f)
        if len(rows) < 2:
            return False
        seg, T = f["segments"], f["imu/temperature"]
        means = [float(np.mean(T[int(seg["first_sample"][i]):int(seg["last_sample"][i])])) for i in rows]
    return bool(np.all(np.isfinite(means)) and max(means) - min(means) >= MIN_SPAN_K)


def read_windows(path: str | Path, reference_c: float = 25.0, max_degree: int = 3,
                 hysteresis_width_K: float = HYSTERESIS_WIDTH_K) -> dict[str, th.ThermalWindows]:
    """The accelerometer and gyro windows of a recording (module docstring)."""
    with open_recording(path) as f:
        lat, h, g = _site(f)
        fs = recording_reader.sample_rate(f)
        seg = {k: f["segments"][k][()] for k in f["segments"]}
        rows = _cal_rows(f)
        if len(rows) < 12:
            raise InputError(f"{len(rows)} complete static or rate windows: a thermal calibration needs "
                             "many more", path, hint="run procedures/thermal-ramp.yaml or thermal-soak.yaml")
        t_imu = f["imu/time"][()]
        T_all = f["imu/temperature"][()]
        acc_all, gyr_all = f["imu/specific_force"], f["imu/angular_rate"]
        tab_t = f["table/time"][()] if "table/time" in f else np.empty(0)
        tab_ang = f["table/angle"][()] if "table/angle" in f else np.empty((0, 3))
        ch_t = f["chamber/time"][()] if "chamber/time" in f else np.empty(0)
        ch_air = f["chamber/air_c"][()] if "chamber/air_c" in f else np.empty(0)
        recording_reader.check_finite(path, "imu/temperature", T_all, 0)
        # hysteresis state along the run: play operator on the temperature at ~1 Hz
        step = max(1, int(round(fs)))
        Hs = th.play_operator(T_all[::step], hysteresis_width_K)
        H_all = np.interp(np.arange(T_all.size), np.arange(0, T_all.size, step)[: Hs.size], Hs)
        cols: dict[str, list] = {k: [] for k in ("kind", "acc", "gyro", "sa", "sg", "fr", "wr", "fq", "T",
                                                 "bounds", "H", "R", "G", "ta", "tb", "revs",
                                                 "ba", "bg")}
        for i in rows:
            a, z = int(seg["first_sample"][i]), int(seg["last_sample"][i])
            t = t_imu[a:z]
            acc = np.asarray(acc_all[a:z], float)
            gyr = np.asarray(gyr_all[a:z], float)
            recording_reader.check_finite(path, "imu/specific_force", acc, a)
            recording_reader.check_finite(path, "imu/angular_rate", gyr, a)
            ang, rates = _angles_at(t, seg, i, tab_t, tab_ang)
            fr, wr = body_references(ang, rates, lat, h, g)
            T = T_all[a:z]
            cols["kind"].append(seg["kind"][i].decode())
            cols["acc"].append(acc.mean(axis=0))
            cols["gyro"].append(gyr.mean(axis=0))
            acc_r, gyr_r = about_reference(acc, fr), about_reference(gyr, wr)
            cols["sa"].append(_noise_parts(_detrend(acc_r)))
            cols["sg"].append(_noise_parts(_detrend(gyr_r)))
            cols["ba"].append(batch_means(acc_r, N_BATCHES))
            cols["bg"].append(batch_means(gyr_r, N_BATCHES))
            cols["ta"].append(float(t[0]))  # the window the n samples cover: n / fs
            cols["tb"].append(float(t[0]) + (z - a) / fs)
            cols["revs"].append(window_revolutions(seg["kind"][i].decode(), rates, (z - a) / fs))
            cols["fr"].append(fr.mean(axis=0))
            cols["wr"].append(wr.mean(axis=0))
            cols["fq"].append((fr * fr).mean(axis=0))
            cols["T"].append(float(T.mean()))
            cols["bounds"].append((a, z))
            cols["H"].append(float(H_all[a:z].mean()))
            cols["R"].append(float(np.polyfit(t - t[0], T, 1)[0]) if t.size > 2 and np.ptp(T) > 0 else 0.0)
            cols["G"].append(float(np.interp(t.mean(), ch_t, ch_air)) - float(T.mean())
                             if ch_t.size >= 2 else 0.0)
        powers = th.power_means(T_all, np.asarray(cols["bounds"]), reference_c, max_degree)
        t0 = float(t_imu[0])  # the emulator's random walk starts at the first sample (power-on)
    kind = np.asarray(cols["kind"])
    T = np.asarray(cols["T"])
    H = np.asarray(cols["H"])
    R = np.asarray(cols["R"])
    heating = np.where(np.abs(R) > 1e-4, R > 0, H > 0)
    regs = {"hysteresis": H, "temperature_rate": R}
    if np.ptp(np.asarray(cols["G"])) > 0:
        regs["thermal_gradient"] = np.asarray(cols["G"])
    static = kind == "orientation"
    ta, tb = np.asarray(cols["ta"]), np.asarray(cols["tb"])

    def sub(mask: np.ndarray, sensor: str) -> th.ThermalWindows:
        y, s, ref, bm = (("acc", "sa", "fr", "ba") if sensor == "accel" else ("gyro", "sg", "wr", "bg"))
        return th.ThermalWindows(
            sensor=sensor, y=np.asarray(cols[y])[mask], sigma=_pooled_sigma(np.asarray(cols[s])[mask]),
            ref=np.asarray(cols[ref])[mask], powers=powers[mask], temperature=T[mask], heating=heating[mask],
            reference_c=reference_c, quad=np.asarray(cols["fq"])[mask] if sensor == "accel" else None,
            regressors={k: v[mask] for k, v in regs.items()},
            t_start=ta[mask], t_end=tb[mask], kind=kind[mask],
            revolutions=[r for r, m in zip(cols["revs"], mask) if m], batch=np.asarray(cols[bm])[mask], t0=t0)

    return {"accel": sub(static, "accel"), "gyro": sub(np.ones(len(kind), bool), "gyro")}


#: window length of a static record's thermal fit (:func:`static_windows`), s
STATIC_WINDOW_S = 1800.0
#: static sections whose mean specific force directions are within this angle are one pose, deg
SAME_POSE_DEG = 10.0


def group_poses(downs: list[np.ndarray], labels: list[str], same_deg: float = SAME_POSE_DEG) -> list[str]:
    """A pose label per static section: sections whose mean specific force points within
    ``same_deg`` of an earlier section's share its pose (labelled by the first such section); a
    new pose whose label an earlier pose already has gets its section number appended (two
    directions under one name would otherwise be one pose)."""
    out: list[str] = []
    for k, d in enumerate(downs):
        u = d / np.linalg.norm(d)
        for j in range(k):
            v = downs[j] / np.linalg.norm(downs[j])
            if np.degrees(np.arccos(np.clip(u @ v, -1.0, 1.0))) <= same_deg:
                out.append(out[j])
                break
        else:
            out.append(labels[k] if labels[k] not in out else f"{labels[k]} (section {k + 1})")
    return out


def static_windows(path: str | Path, window_s: float = STATIC_WINDOW_S, reference_c: float = 25.0,
                   max_degree: int = 3, hysteresis_width_K: float = HYSTERESIS_WIDTH_K,
                   min_fill: float = 0.5, settle_s: float = 0.0,
                   sections: list[tuple[str, float, float]] | None = None) -> dict[str, th.ThermalWindows]:
    """The accelerometer and gyro windows of a *static* record with a temperature column: an
    imported bench log (a warm-up after power-on, days at room temperature), one orientation,
    no table and no chamber. Each static section (/segments, kind orientation; the whole record
    when there is none) is cut into windows of ``window_s`` seconds; a window with fewer than
    ``min_fill`` of its nominal samples (gaps) or fewer than 16 is left out; ``settle_s``
    leaves out the first seconds of every section (a unit put into a fridge or chamber: its
    temperature falls fast along a curve the windows' straight-line contrasts count as noise).
    ``sections``: (label, from_s, to_s) on the recording's time axis (/imu/time) instead of
    /segments (a record whose poses were not marked when it was made or imported).

    Reference inputs: gravity (the recording's g) along the mean specific force of each static
    section, and a zero rate (the earth's rate has no known direction here). Sections whose
    directions agree within :data:`SAME_POSE_DEG` are one pose (:func:`group_poses`). One pose:
    every window has the same reference, so only the bias terms are identifiable
    (:func:`rigctl.solvers.thermal.one_orientation`; fit with
    :data:`rigctl.solvers.thermal.BIAS_ONLY`) and their constant term holds what the reference
    misses. Several poses (a record held still in a few orientations): the windows carry their
    pose (``ThermalWindows.pose``) and the solver fits an offset per pose (the gyro's
    g-sensitivity and earth rate, what the measured direction misses) beside the temperature
    terms. The candidates' regressors: the hysteresis state (play operator on the temperature)
    and the temperature rate (slope in the window, K/s); no chamber, so no gradient."""
    given = sections
    with open_recording(path) as f:
        _, _, g = _site(f)
        fs = recording_reader.sample_rate(f)
        t_all = f["imu/time"][()]
        T_all = f["imu/temperature"][()] if "imu/temperature" in f else np.empty(0)
        if not np.isfinite(T_all).any():  # an import without temp= writes the column as NaN
            raise InputError("a thermal fit needs the recording's temperature column (/imu/temperature"
                             + ("): it has none" if T_all.size == 0 else " holds no reading)"), path,
                             hint="import the log with temp=COLUMN in --columns")
        acc_all = np.asarray(f["imu/specific_force"][()], float)
        gyr_all = np.asarray(f["imu/angular_rate"][()], float)
        check_finite(path, "imu/time", t_all, 0)
        check_finite(path, "imu/temperature", T_all, 0)
        check_finite(path, "imu/specific_force", acc_all, 0)
        check_finite(path, "imu/angular_rate", gyr_all, 0)
        seg = f["segments"] if "segments" in f else None
        rows = [i for i in range(seg["kind"].shape[0]) if seg["kind"][i] == b"orientation"
                and seg["status"][i] == b"complete"] if seg is not None else []
        sections = [(int(seg["first_sample"][i]), int(seg["last_sample"][i])) for i in rows]
        labels = [seg["label"][i].decode() if "label" in seg else f"section {k + 1}" for k, i in enumerate(rows)]
    if given is not None:
        bounds_of = [(int(np.searchsorted(t_all, a)), int(np.searchsorted(t_all, z))) for _, a, z in given]
        empty = [lab for (lab, _, _), (a, z) in zip(given, bounds_of) if z <= a]
        if empty:
            raise InputError(f"pose {empty[0]!r} holds no sample of the record (its time axis runs "
                             f"{t_all[0]:g} .. {t_all[-1]:g} s)", path)
        sections, labels = bounds_of, [lab for lab, _, _ in given]
    if not sections:
        sections, labels = [(0, t_all.size)], ["whole record"]
    # no window across an IMU restart (a new turn-on bias; a time base begun again does not run
    # forward): a section is cut there, its pieces keep its label (static_restart_report names them)
    cuts = sorted({n["row"] for n in restarts.restarts_by_row(path, t_all)})
    pieces = [(lab, [a, *(k for k in cuts if a < k < z), z]) for (a, z), lab in zip(sections, labels)]
    sections = [(e0, e1) for _, e in pieces for e0, e1 in zip(e[:-1], e[1:])]
    labels = [lab for lab, e in pieces for _ in e[1:]]
    downs = [acc_all[a:z].mean(axis=0) for a, z in sections]
    poses = group_poses(downs, labels)
    # the reference of a pose: gravity along the mean specific force of all its sections
    down_of = {p: np.mean(np.concatenate([acc_all[a:z] for (a, z), q in zip(sections, poses) if q == p]), axis=0)
               for p in set(poses)}
    step = max(1, int(round(fs)))
    Hs = th.play_operator(T_all[::step], hysteresis_width_K)
    H_all = np.interp(np.arange(T_all.size), np.arange(0, T_all.size, step)[: Hs.size], Hs)
    nominal = window_s * fs
    bounds: list[tuple[int, int]] = []
    fr_w: list[np.ndarray] = []
    pose_w: list[str] = []
    for (a, z), pose in zip(sections, poses):
        down = down_of[pose]
        a = int(np.searchsorted(t_all[a:z], t_all[a] + settle_s)) + a if settle_s > 0 else a
        if z - a < 1:
            continue
        edges = np.arange(t_all[a], t_all[z - 1] + window_s, window_s)
        idx = np.searchsorted(t_all[a:z], edges) + a
        keep = [(int(i0), int(i1)) for i0, i1 in zip(idx[:-1], idx[1:]) if i1 - i0 >= max(16, min_fill * nominal)]
        bounds += keep
        fr_w += [g * down / np.linalg.norm(down)] * len(keep)
        pose_w += [pose] * len(keep)
    if len(bounds) < 4:
        raise InputError(f"{len(bounds)} windows of {window_s:g} s in the static record: a thermal fit needs "
                         "more (a longer record or shorter windows)", path)
    several = len(set(poses)) > 1
    cols: dict[str, list] = {k: [] for k in ("acc", "gyro", "sa", "sg", "ba", "bg", "T", "R", "H", "ta", "tb")}
    for (a, z), fr in zip(bounds, fr_w):
        t, T = t_all[a:z], T_all[a:z]
        acc, gyr = acc_all[a:z], gyr_all[a:z]
        cols["acc"].append(acc.mean(axis=0))
        cols["gyro"].append(gyr.mean(axis=0))
        cols["sa"].append(_noise_parts(_detrend(acc - fr)))
        cols["sg"].append(_noise_parts(_detrend(gyr)))
        cols["ba"].append(batch_means(acc - fr, N_BATCHES))
        cols["bg"].append(batch_means(gyr, N_BATCHES))
        cols["T"].append(float(T.mean()))
        cols["R"].append(float(np.polyfit(t - t[0], T, 1)[0]) if np.ptp(T) > 0 else 0.0)
        cols["H"].append(float(H_all[a:z].mean()))
        cols["ta"].append(float(t[0]))
        cols["tb"].append(float(t[0]) + (z - a) / fs)
    n = len(bounds)
    powers = th.power_means(T_all, np.asarray(bounds), reference_c, max_degree)
    R, H = np.asarray(cols["R"]), np.asarray(cols["H"])
    out = {}
    for sensor, y, s, bm, ref in (("accel", "acc", "sa", "ba", np.asarray(fr_w)),
                                  ("gyro", "gyro", "sg", "bg", np.zeros((n, 3)))):
        out[sensor] = th.ThermalWindows(
            sensor=sensor, y=np.asarray(cols[y]), sigma=_pooled_sigma(np.asarray(cols[s])),
            ref=ref, pose=np.asarray(pose_w) if several else None, powers=powers, temperature=np.asarray(cols["T"]),
            heating=np.where(R != 0, R > 0, H > 0), reference_c=reference_c,
            regressors={"hysteresis": H, "temperature_rate": R},
            t_start=np.asarray(cols["ta"]), t_end=np.asarray(cols["tb"]), kind=np.array(["orientation"] * n),
            revolutions=[0.0] * n, batch=np.asarray(cols[bm]), t0=float(t_all[0]), rows=np.asarray(bounds))
    return out


def fit_static(path: str | Path, bias_degree: int = 2, window_s: float = STATIC_WINDOW_S,
               reference_c: float = 25.0, loop: bool = True,
               noise: tuple[Any, Any] | None = None, settle_s: float = 0.0,
               sections: list[tuple[str, float, float]] | None = None
               ) -> dict[str, tuple[th.ThermalWindows, th.ThermalFit]]:
    """Bias against temperature of a static record (:func:`static_windows`): per sensor the windows
    and the fit, the covariance of the window means from ``noise`` (accel, gyro: three axes'
    NoiseCoefficients; None: estimated from the record) and, with ``loop``, the thermal
    candidates tested. One pose: scale and misalignment held (only the bias terms are
    identifiable). Several poses: an offset per pose and axis; the accelerometer's scale per K
    is fitted too (degree ``bias_degree``, from K^1: its constant is in the pose offsets), its
    misalignment held (a few poses with one axis each along gravity cannot separate
    misalignment per K from bias per K); the gyro has no rate input: bias only. ``sections``:
    the poses' time ranges instead of /segments (:func:`static_windows`)."""
    wins = static_windows(path, window_s, reference_c, max(MAX_FIT_DEGREE, bias_degree), settle_s=settle_s,
                          sections=sections)
    return fit_static_windows(wins, bias_degree, loop, noise)


def fit_static_windows(wins: dict[str, th.ThermalWindows], bias_degree: int = 2, loop: bool = True,
                       noise: tuple[Any, Any] | None = None,
                       progress: Callable[[str], None] | None = None
                       ) -> dict[str, tuple[th.ThermalWindows, th.ThermalFit]]:
    """:func:`fit_static` of windows :func:`static_windows` made. ``progress``: called with a
    line as each stage starts (the noise estimate and the fit take minutes on a long record)."""
    out = {}
    say = progress or (lambda _line: None)
    for sensor, model in zip(("accel", "gyro"), noise or (None, None)):
        w = wins[sensor]
        if model is None:
            say(f"{sensor}: noise of the {len(w)} window means by REML (white, bias instability, random walk) ...")
        th.estimate_noise(w, model)
        deg = ({"bias": bias_degree, **th.BIAS_ONLY} if th.one_orientation(w.ref)
               else {"bias": bias_degree, "scale": bias_degree, "misalignment": th.HELD})
        say(f"{sensor}: generalised least-squares fit" + (" and its closed loop" if loop else "") + " ...")
        out[sensor] = (w, th.fit_thermal(w, deg, loop=loop))
    return out


def truth_coefficients(f: Any) -> dict[str, float] | None:
    """The emulator's true coefficients under the solver's names (declared IMU + thermal)."""
    t = f.get("truth")
    if t is None or "params_json" not in t.attrs:
        return None
    imu = json.loads(t.attrs["params_json"]).get("imu", {})
    therm = imu.get("thermal")
    if imu.get("model") != "declared" or therm is None:
        return None
    out: dict[str, float] = {}
    for s, u in th.UNIT.items():
        bias = imu[f"{s}_bias_{u}"]
        M = imu[f"{s}_matrix"]
        for i, a in enumerate(th.AXES):
            out[f"{s}_bias_{a}_{u}"] = bias[i]
            out[f"{s}_bias_{a}_{u}_per_K"] = therm[f"{s}_bias_{u}_per_K"][i]
            out[f"{s}_bias_{a}_{u}_per_K2"] = therm[f"{s}_bias_{u}_per_K2"][i]
            out[f"{s}_hysteresis_{a}_{u}"] = therm[f"{s}_hysteresis_{u}"][i]
            out[f"{s}_temp_rate_{a}_{u}_per_K_per_s"] = therm[f"{s}_rate_{u}_per_K_per_s"][i]
            for k, b in enumerate(th.AXES):
                out[f"{s}_M_{a}{b}_ratio"] = M[i][k]
                if i == k:
                    out[f"{s}_scale_{a}_per_K"] = therm[f"{s}_M_per_K"][i][k]
                    out[f"{s}_scale_{a}_per_K2"] = therm[f"{s}_M_per_K2"][i][k]
                    out[f"{s}_scale_{a}_per_K3"] = 0.0
                else:
                    out[f"{s}_misalignment_{a}{b}_rad_per_K"] = therm[f"{s}_M_per_K"][i][k]
                    out[f"{s}_misalignment_{a}{b}_rad_per_K2"] = therm[f"{s}_M_per_K2"][i][k]
            out[f"{s}_bias_{a}_{u}_per_K3"] = 0.0
        if s == "accel":
            for i, a in enumerate(th.AXES):
                out[f"accel_quad_{a}_s2_per_m"] = imu["accel_quadratic_per_m_s2"][i]
    out["reference_c"] = therm["reference_c"]
    return out


def _before_after(w: th.ThermalWindows, fit: th.ThermalFit) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """RMS of the window residuals with the reference-temperature model only (before: one
    calibration at T_ref) and with the thermal model (after), per axis and per 10-K bin."""
    after = np.column_stack([a.residuals for a in fit.axes])
    before = np.empty_like(after)
    for i, a in enumerate(fit.axes):
        p = dict(zip(a.names, a.values))
        A = th.design(w, i, fit.degrees, fit.accepted)
        keep = np.array([("_per_K" not in n) and n not in (
            f"{w.sensor}_hysteresis_{th.AXES[i]}_{th.UNIT[w.sensor]}",) and "gradient" not in n and
            "temp_rate" not in n for n in a.names])
        before[:, i] = w.y[:, i] - A[:, keep] @ np.array([p[n] for n, k in zip(a.names, keep) if k])
    edges = np.arange(math.floor(w.temperature.min() / 10) * 10, w.temperature.max() + 10, 10.0)
    bins = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (w.temperature >= lo) & (w.temperature < hi)
        if m.any():
            bins.append({"from_c": float(lo), "to_c": float(hi), "windows": int(m.sum()),
                         "rms_before": np.sqrt(np.mean(before[m] ** 2, axis=0)).tolist(),
                         "rms_after": np.sqrt(np.mean(after[m] ** 2, axis=0)).tolist()})
    return ({"rms_before": np.sqrt(np.mean(before**2, axis=0)).tolist(),
             "rms_after": np.sqrt(np.mean(after**2, axis=0)).tolist(), "by_temperature": bins,
             "unit": th.UNIT[w.sensor]}, before, after)


#: what a bias step across a restart does to a thermal fit, and what to do
THERMAL_RESTART = ("the model has one bias polynomial in temperature per axis, so the bias step between them is "
                   "fitted as a temperature dependence (bias, scale and misalignment coefficients) -- run the "
                   "soaks / ramps of one side again after a warm-up, or calibrate one side only")


def restart_report(path: Path, w: th.ThermalWindows) -> tuple[list[dict[str, Any]], list[str]]:
    """The IMU restarts with thermal windows on both sides and one line per restart for the text
    and the reasons (no restart: ([], [])). A chamber run (``w.rows`` None):
    :func:`rigctl.analysis.restarts.restart_notes`, naming the windows and the chamber steps --
    soaks and ramps -- in effect on each side. A static record (``w.rows``: its windows' sample
    rows): :func:`rigctl.analysis.restarts.restarts_by_row` -- its ``device-restart`` events and
    a time base begun again behind its last stamp -- naming the poses and their windows on each
    side (:func:`rigctl.analysis.restarts.window_sides`). Either way with the IMU temperature span
    of the windows ``w`` on each side, degC."""
    from ..engine.procedure import CHAMBER_KINDS

    if w.rows is None:
        notes = restarts.restart_notes(path, within=tuple(k.encode() for k in CHAMBER_KINDS))
        sides = [(w.t_end <= n["time_s"], w.t_start >= n["time_s"]) for n in notes]
    else:
        with open_recording(path) as f:
            t = f["imu/time"][()]
        group = w.pose if w.pose is not None else np.array(["whole record"] * len(w))
        notes = restarts.window_sides(restarts.restarts_by_row(path, t), w.rows, group)
        idx = np.arange(len(w))
        sides = [(np.isin(idx, n.pop("windows_before")), np.isin(idx, n.pop("windows_after"))) for n in notes]
    for n, (before, after) in zip(notes, sides):
        for key, sel in (("before", before), ("after", after)):
            T = w.temperature[sel]
            n[f"temperature_{key}_c"] = [float(T.min()), float(T.max())] if T.size else None

    def context(n: dict[str, Any], key: str) -> str:
        steps, T = n.get(f"within_{key}"), n[f"temperature_{key}_c"]
        return (f"; in {', '.join(steps)}" if steps else "") + (f"; IMU {T[0]:.1f} .. {T[1]:.1f} degC" if T else "")
    return notes, restarts.restart_lines(notes, "windows", THERMAL_RESTART, context)


def parse_degrees(spec: str | int | dict[str, int] | None) -> dict[str, int] | str:
    """Polynomial degrees from ``--thermal-degree``: None (the default 2, 2, 1), 'auto', N (every
    group), or 'B,S,M' (bias, scale, misalignment); each 0..MAX_DEGREE."""
    if spec is None:
        return dict(DEFAULT_DEGREES)
    if isinstance(spec, dict):
        return dict(spec)
    text = str(spec).strip().lower()
    if text == "auto":
        return "auto"
    parts = text.split(",")
    try:
        vals = [int(x) for x in parts]
    except ValueError:
        vals = []
    if len(vals) not in (1, 3) or not all(0 <= v <= MAX_DEGREE for v in vals):
        raise InputError(f"--thermal-degree {spec}: give auto, N (every group) or B,S,M (bias, scale, "
                         f"misalignment), each 0..{MAX_DEGREE}")
    return dict(zip(("bias", "scale", "misalignment"), vals * 3 if len(vals) == 1 else vals))


def calibrate_thermal(path: str | Path, degrees: dict[str, int] | str | None = None,
                      reference_c: float = 25.0, noise: tuple[Any, Any, str] | None = None,
                      progress: Callable[[str], None] | None = None
                      ) -> tuple[dict[str, Any], str, dict[str, tuple[Any, str]]]:
    """(payload, text, arrays) of the thermal calibration of a recording; ``arrays`` are the
    datasets of /results/thermal (per sensor: the windows' temperatures, heating flags, residuals
    before and after, and each axis' coefficient covariance). ``degrees``: per group
    ({'bias': 2, 'scale': 2, 'misalignment': 1}, the default), N / 'B,S,M' (:func:`parse_degrees`)
    or 'auto' (chosen per sensor by :func:`rigctl.solvers.thermal.select_degrees`). ``noise``:
    (accel, gyro: three axes' NoiseCoefficients each, description) as ``rigctl calibrate --noise`` resolved it
    (IEEE 952 coefficients of /results/allan or of another recording of the unit); a None model,
    or no ``noise``, estimates that sensor's noise from the session
    (:func:`rigctl.solvers.thermal.estimate_noise`). The covariance of the window means follows.
    ``progress``: called with a line as each stage starts (minutes on a long chamber run)."""
    from .calibration_text import noise_summary

    say = progress or (lambda _line: None)

    p = Path(path)
    degrees = parse_degrees(degrees)
    wins = read_windows(p, reference_c, max(MAX_FIT_DEGREE, *(degrees.values() if isinstance(degrees, dict)
                                                              else [0])))
    with open_recording(p) as f:
        truth, truth_note = restarts.truth_across_power_cycles(f, truth_coefficients(f))
    nf, nw, noise_txt = noise or (None, None, "")
    if nf is None and nw is None:
        noise_txt = ("estimated from the session (no /results/allan): white level per window kind from the "
                     "batch means within each window (contrasts free of a linear drift), bias instability B "
                     "and rate random walk K by REML of the window means about the protected design "
                     "(cubic in temperature, every thermal candidate, an offset per window kind)")
    models = []
    for sensor, model in (("accel", nf), ("gyro", nw)):
        if model is None:
            say(f"{sensor}: noise of the {len(wins[sensor])} window means by REML (white, bias instability, "
                "random walk) ...")
        models += th.estimate_noise(wins[sensor], model)
    noise_lines, noise_rows = noise_summary(models, wins["accel"].t0) if len(models) == 6 else ([], [])
    if len(models) != 6:
        noise_txt += " (window times unknown: means treated as independent)"
    sensors: dict[str, Any] = {}
    lines = [f"rigctl calibrate: {p} -- thermal calibration ({len(wins['gyro'])} windows, IMU temperature "
             f"{wins['gyro'].temperature.min():.1f} .. {wins['gyro'].temperature.max():.1f} degC, "
             f"reference {reference_c:g} degC)", f"noise model: {noise_txt}", *noise_lines]
    n_in = n_all = 0
    misses: list[str] = []
    arrays: dict[str, tuple[Any, str]] = {}
    for sensor, w in wins.items():
        say(f"{sensor}: " + ("degrees, then " if degrees == "auto" else "")
            + "generalised least-squares fit and its closed loop ...")
        deg = th.select_degrees(w) if degrees == "auto" else dict(degrees)
        try:
            fit = th.fit_thermal(w, deg)
        except ValueError as e:  # one orientation: only the bias terms are identifiable
            raise InputError(str(e), p, hint="a static record: docs/thermal.md, 'One orientation'") from None
        params = fit.parameters()
        lo, hi = fit.band()
        c2 = fit.chi2 / fit.dof
        status = "ok" if lo <= c2 <= hi else "chi2_outside_band"
        heat = w.heating
        ba, before, after = _before_after(w, fit)
        unit = "m/s^2" if sensor == "accel" else "rad/s"
        arrays.update({f"{sensor}_window_temperature": (w.temperature, "degC"),
                       f"{sensor}_window_heating": (w.heating.astype(np.int8), "1"),
                       f"{sensor}_residual_before": (before, unit), f"{sensor}_residual_after": (after, unit)})
        for i, a in enumerate(fit.axes):
            arrays[f"{sensor}_cov_{th.AXES[i]}"] = (a.cov, "SI (see names)")
            arrays[f"{sensor}_names_{th.AXES[i]}"] = (np.array([n.encode() for n in a.names]), "")
        sensors[sensor] = {
            "degrees": deg, "accepted": fit.accepted,
            "effects_found": [th.CANDIDATE_TEXT[c] for c in fit.accepted],
            "confounded_with": fit.confounded,
            "chi2": fit.chi2, "dof": fit.dof, "chi2_per_dof": c2, "chi2_band_99": [lo, hi], "status": status,
            "windows": {"total": len(w), "heating": int(heat.sum()), "cooling": int((~heat).sum()),
                        "heating_span_c": [float(w.temperature[heat].min()), float(w.temperature[heat].max())]
                        if heat.any() else None,
                        "cooling_span_c": [float(w.temperature[~heat].min()), float(w.temperature[~heat].max())]
                        if (~heat).any() else None},
            "parameters": params, "explain": fit.explain, "before_after": ba}
        lines.append(f"\n{sensor}: degrees bias {deg['bias']}, scale {deg['scale']}, misalignment "
                     f"{deg['misalignment']}; {len(w)} windows ({int(heat.sum())} heating, "
                     f"{int((~heat).sum())} cooling); chi2/dof {c2:.3g} (99 % band {lo:.3g} .. {hi:.3g})"
                     + ("" if status == "ok" else "  <- OUTSIDE THE BAND: the model or the noise is wrong"))
        conf = fit.confounded
        found = "; ".join(th.CANDIDATE_TEXT[c] + (
            f" -- this run cannot tell it from: {', '.join(th.CANDIDATE_TEXT[o] for o in conf[c])} (all "
            "explain the data nearly as well; a longer hold at each end separates them)" if conf[c] else "")
            for c in fit.accepted) or "none"
        lines.append(f"  closed loop: thermal effects found: {found}")
        for e in fit.explain:
            lines.append(f"    [{e['step']}] {e['candidate']}: {e['statistic']}, p_adj {e['p_adj']:.2g} -> "
                         f"{e['decision']}")
        dsp = display(f"{sensor}_bias_x_{th.UNIT[sensor]}")
        lines.append("  residual RMS per axis, before (one calibration at the reference temperature) -> after: "
                     + ", ".join(f"{axis_name(sensor, i)} {dsp.sigma(b):.4g} -> {dsp.sigma(x):.4g} {dsp.unit}"
                                 for i, (b, x) in enumerate(zip(ba["rms_before"], ba["rms_after"]))))
        lines.append(f"  {'parameter':<34} {'value':>14} {'+-':>10} {'95 % interval':>26}  unit"
                     + ("   truth" if truth else ""))
        for q in params:
            d = display(q["name"])
            v, u = format_value(d.value(q["value"]), d.sigma(q["sigma"]))
            ci = f"[{format_value(d.value(q['ci95'][0]), d.sigma(q['sigma']))[0]}, " \
                 f"{format_value(d.value(q['ci95'][1]), d.sigma(q['sigma']))[0]}]"
            tv = ""
            if truth is not None and q["name"] in truth:
                n_all += 1
                inside = q["ci95"][0] <= truth[q["name"]] <= q["ci95"][1]
                n_in += inside
                q["truth"], q["truth_inside_ci95"] = truth[q["name"]], bool(inside)
                if not inside:
                    misses.append(q["name"])
                tv = f"   {d.value(truth[q['name']]):.5g}" + ("" if inside else " (outside)")
            lines.append(f"  {quantity_name(q['name']):<34} {v:>14} {u:>10} {ci:>26}  {d.unit}{tv}")
    notes, mixed = restart_report(p, wins["gyro"])
    payload: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION, "created_utc": utc_now(), "recording": str(p.resolve()),
        "mode": "thermal", "reference_c": reference_c, "hysteresis_width_K": HYSTERESIS_WIDTH_K,
        "model": "y_i = sum_j dT^j b_ij + sum_k sum_j dT^j u_k M_ikj [+ k2_i u_i^2] + effects; dT = T - reference_c",
        "sensors": sensors, "truth_available": truth is not None, "truth_note": truth_note,
        "noise_model": {"text": noise_txt, "channels": noise_rows},
        "trustworthy": not mixed and all(d["status"] == "ok" for d in sensors.values()),
        "device_restarts": notes, "reasons": mixed}
    if truth is not None:
        payload["truth_coverage"] = {"inside": n_in, "total": n_all, "fraction": n_in / n_all if n_all else None,
                                     "outside": misses}
        lines.append(f"\nagainst the emulator's truth: {n_in} of {n_all} 95 % intervals cover it"
                     + (f" (outside: {', '.join(misses)})" if misses else ""))
        if truth_note:
            lines.append(f"note: {truth_note}")
    lines += restarts.untrusted_lines(mixed)
    return payload, "\n".join(lines), arrays


def calibrate_and_store(path: str | Path, store: bool = True, json_path: str | Path | None = None,
                        degrees: dict[str, int] | str | None = None, noise: tuple[Any, Any, str] | None = None,
                        progress: Callable[[str], None] | None = None) -> tuple[dict[str, Any], str]:
    """Thermal calibration stored in /results/thermal and RECORDING.thermal.json (or ``json_path``);
    ``progress`` as :func:`calibrate_thermal`'s."""
    p = Path(path)
    payload, text, arrays = calibrate_thermal(p, degrees, noise=noise, progress=progress)
    if store:
        for s, d in payload["sensors"].items():
            arrays[f"{s}_names"] = (np.array([q["name"].encode() for q in d["parameters"]]), "")
            arrays[f"{s}_values"] = (np.array([q["value"] for q in d["parameters"]]), "SI (see names)")
            arrays[f"{s}_sigma"] = (np.array([q["sigma"] for q in d["parameters"]]), "SI (see names)")
        not_stored = store_calibration_results(p, "thermal", payload, arrays, schema_version=SCHEMA_VERSION)
        if not_stored:
            text += "\n" + not_stored
        jp = Path(json_path) if json_path else p.with_name(p.stem + ".thermal.json")
        write_atomic(jp, json.dumps(payload, indent=1, default=float).encode())  # whole or not at all
        text += f"\nresults: {p}:/results/thermal and {jp}"
    return payload, text


# ------------------------------------------------------------------------------ apply-cal
def thermal_info(data: dict[str, Any], where: Any) -> dict[str, Any]:
    """A thermal calibration payload (for rigctl apply-cal), checked: {sensor: {name: value}}, accepted effects."""
    try:
        sensors = {s: {q["name"]: float(q["value"]) for q in data["sensors"][s]["parameters"]}
                   for s in ("accel", "gyro")}
        accepted = {s: list(data["sensors"][s].get("accepted", [])) for s in ("accel", "gyro")}
        ref = float(data["reference_c"])
        width = float(data.get("hysteresis_width_K", 2.0))
    except (TypeError, KeyError, ValueError):
        raise InputError("the thermal calibration is incomplete (sensors accel / gyro with parameters, "
                         "reference_c)", where, hint="use the JSON written by rigctl calibrate") from None
    if not all(np.isfinite(v) for p in sensors.values() for v in p.values()):
        raise InputError("the thermal calibration holds non-finite values", where)
    return {"thermal": sensors, "accepted": accepted, "reference_c": ref, "hysteresis_width_K": width,
            "schema_version": data.get("schema_version"), "status": "thermal",
            "trustworthy": data.get("trustworthy", True) is not False
            and all(d.get("status") == "ok" for d in data["sensors"].values()),
            "model": {"thermal": True, "reference_c": ref, "accepted": accepted}}


def thermal_corrector(fin: Any, src: Path, info: dict[str, Any]) -> Callable[..., tuple[np.ndarray, np.ndarray]]:
    """A thermal calibration's per-chunk correction for ``rigctl apply-cal``
    (:mod:`rigctl.analysis.apply_cal`): reads the recording's IMU temperature (and the chamber's
    air temperature) once; returns ``fix(a0, a1, f, w)`` -> the corrected (specific force, rate)
    of samples a0:a1."""
    if "imu/temperature" not in fin:
        raise InputError("a thermal calibration needs the recording's temperature column (/imu/temperature)", src)
    T = fin["imu/temperature"][()]
    t = fin["imu/time"][()]
    check_finite(src, "imu/temperature", T, 0)
    air = None
    if "chamber/time" in fin and fin["chamber/time"].shape[0] >= 2:
        air = np.interp(t, fin["chamber/time"][()], fin["chamber/air_c"][()])
    regs = {s: th.regressors_along(T, t, info["accepted"][s], info["hysteresis_width_K"], air)
            for s in ("accel", "gyro")}

    def fix(a0: int, a1: int, f_in: np.ndarray, w_in: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        f, w = (th.correct(sensor, y, T[a0:a1], info["thermal"][sensor], info["reference_c"],
                           {c: x[a0:a1] for c, x in regs[sensor].items()})
                for sensor, y in (("accel", f_in), ("gyro", w_in)))
        return f, w
    return fix
