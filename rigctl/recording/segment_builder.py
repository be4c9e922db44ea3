"""Build the calibration solvers' per-segment table from a recording (the I/O edge).

For every complete static or constant-rate segment of /segments it takes the IMU samples of
the sampling window and the true references evaluated at every sample time from the table's
attitude (:func:`rigctl.frames.body_references`), and hands both to
:func:`rigctl.solvers.segments.segment_table_from_samples`, which forms the means, their
uncertainties (:mod:`rigctl.solvers.segment_stats`) and the moments of the references (mean of
f f^T, of w^3, ...; nonlinear terms act on them, not on the means).

On a rate segment the turning axis' angle is reconstructed at every IMU sample by a straight
line fitted to the table polls inside the window (angle unwrapped), so gravity and Earth rate
are integrated over exactly the revolutions the window holds.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from . import recording_reader
from .recorder import write_results
from ..frames import body_references, earth_rate_enu, gimbal_dcm, normal_gravity
from ..solvers.segment_stats import SensorNoise, self_noise_sigma
from ..solvers.segments import SegmentTable, about_reference, rest_batches, segment_table_from_samples
from ..errors import InputError

#: Segment kinds a calibration uses.
CAL_KINDS = (b"orientation", b"rate")
#: Static segment kinds whose samples inform the noise model only (SegmentTable.rest)
REST_KINDS = (b"warmup",)


#: what a calibration reads (rigctl.recording.recording_reader checks it)
CAL_NEED = ("imu/time", "imu/specific_force", "imu/angular_rate", "segments")


def open_recording(path: str | Path, also: tuple[str, ...] = ()) -> h5py.File:
    """Open a rigctl recording read-only for a calibration (SWMR-capable), checked by
    :func:`rigctl.recording.recording_reader.open_recording` for what a calibration reads and
    ``also`` (groups or "group/name" the caller reads too); InputError if it cannot be used."""
    return recording_reader.open_recording(path, CAL_NEED + also)


def store_calibration_results(path: Path, name: str, payload: dict[str, Any],
                              arrays: dict[str, tuple[Any, str]] | None = None,
                              schema_version: int = 1) -> str | None:
    """:func:`rigctl.recording.recorder.write_results` of a calibration (/results/``name``),
    unless a run is still writing the recording (/run/status "running"): then nothing is
    written and the line saying so is returned (None when stored)."""
    with open_recording(path) as f:
        status = bytes(f["run/status"][0]).rstrip(b"\0").decode() if "run/status" in f else "complete"
    if status == "running":
        return "not stored in the recording: it is still being written (status running)"
    write_results(path, name, payload, arrays, schema_version=schema_version)
    return None


def _site(f: h5py.File) -> tuple[float, float, float]:
    m = f["meta"].attrs if "meta" in f else {}
    lat = math.radians(float(m.get("latitude_deg", 45.0)))
    h = float(m.get("height_m", 0.0))
    g = m.get("gravity_m_s2", None)
    g = float(g) if g is not None and np.isfinite(g) else normal_gravity(lat, h)
    return lat, h, g


def _angles_at(t: np.ndarray, seg: dict, i: int, tab_t: np.ndarray, tab_ang: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angles (n, 3) and gimbal rates (n, 3) at IMU times ``t`` for segment ``i``."""
    n = t.shape[0]
    ang = np.broadcast_to(seg["measured_angle"][i], (n, 3)).copy()
    rates = np.zeros((n, 3))
    cmd_rate = seg["commanded_rate"][i]
    inside = (tab_t >= seg["t_start"][i]) & (tab_t <= seg["t_end"][i])
    for ax in np.flatnonzero(cmd_rate != 0.0):
        if inside.sum() >= 2:
            th = np.unwrap(tab_ang[inside, ax])
            slope, icpt = np.polyfit(tab_t[inside], th, 1)
        else:
            slope, icpt = cmd_rate[ax], seg["measured_angle"][i][ax] - cmd_rate[ax] * seg["t_start"][i]
        ang[:, ax] = icpt + slope * t
        rates[:, ax] = slope
    return ang, rates


def _residual_sigma(x: np.ndarray, ref: np.ndarray, fs: float) -> np.ndarray:
    """Noise of a segment mean estimated from the segment itself (rigctl.solvers.segment_stats.
    self_noise_sigma) after removing what the reference explains
    (:func:`rigctl.solvers.segments.about_reference`: on a rate segment gravity turns through the
    sensor axes and the samples swing by ~g, which is not noise).
    """
    return self_noise_sigma(about_reference(x, ref), fs)


def build_segment_table(path: str | Path, kinds: tuple[bytes, ...] = CAL_KINDS,
                        noise_f: SensorNoise | None = None,
                        noise_w: SensorNoise | None = None) -> SegmentTable:
    """Per-segment means, uncertainties and references of a recording's complete segments.

    Reads the windows and the references of each segment, then builds the table with
    :func:`rigctl.solvers.segments.segment_table_from_samples` (the one place where means,
    moments and the mean angular acceleration are formed).

    Args:
        path: a recording following docs/data-format.md.
        kinds: segment kinds to include.
        noise_f, noise_w: accelerometer / gyro noise models for the uncertainty of a mean; None
            estimates it from each segment itself (:func:`_residual_sigma`).

    The table carries each window's [t_start, t_end) (run time of its first sample, plus n/fs),
    its batch means, and the batch means of the warm-up (``rest``: static data before the
    calibration, the noise model's best view of slow noise), from which
    :func:`rigctl.solvers.segment_noise.apply_session_noise` builds the covariance of the means
    under time-correlated noise.
    """
    with open_recording(path) as f:
        lat, h, g = _site(f)
        fs = recording_reader.sample_rate(f)
        t_imu = f["imu/time"]
        seg = {k: f["segments"][k][()] for k in f["segments"]}
        tab_t = f["table/time"][()] if "table/time" in f else np.empty(0)
        tab_ang = f["table/angle"][()] if "table/angle" in f else np.empty((0, 3))
        temp_ds = f["imu/temperature"] if "imu/temperature" in f else None
        status = seg.get("status", np.full(len(seg["kind"]), b"complete"))
        rows = [i for i, k in enumerate(seg["kind"]) if k in kinds and status[i] == b"complete"
                and seg["last_sample"][i] - seg["first_sample"][i] >= 2]
        if not rows:
            raise InputError("the recording has no complete orientation or rate segments", path,
                             hint="run procedures/24pos.yaml or rates.yaml first")
        cols: dict[str, list] = {k: [] for k in ("kind", "label", "acc", "gyro", "f_ref", "w_ref", "time",
                                                 "temperature", "table_rate", "angles", "attitude",
                                                 "t_start", "t_end")}
        for i in rows:
            a, z = int(seg["first_sample"][i]), int(seg["last_sample"][i])
            t = t_imu[a:z]
            acc = np.asarray(f["imu/specific_force"][a:z], dtype=np.float64)
            gyro = np.asarray(f["imu/angular_rate"][a:z], dtype=np.float64)
            for name, block in (("imu/time", t), ("imu/specific_force", acc), ("imu/angular_rate", gyro)):
                recording_reader.check_finite(path, name, block, a)
            ang, rates = _angles_at(t, seg, i, tab_t, tab_ang)
            fr, wr = body_references(ang, rates, lat, h, g)
            cols["kind"].append(seg["kind"][i].decode())
            cols["label"].append(seg["label"][i].decode())
            cols["acc"].append(acc)
            cols["gyro"].append(gyro)
            cols["f_ref"].append(fr)
            cols["w_ref"].append(wr)
            cols["time"].append(float(t.mean()))
            cols["t_start"].append(float(t[0]))  # the window the n samples cover: n / fs
            cols["t_end"].append(float(t[0]) + (z - a) / fs)
            cols["temperature"].append(float(temp_ds[a:z].mean()) if temp_ds is not None else np.nan)
            cols["table_rate"].append(rates.mean(axis=0))
            cols["angles"].append(ang.mean(axis=0))
            cols["attitude"].append(gimbal_dcm(ang).mean(axis=0))
        rest = None
        warm = [i for i, k in enumerate(seg["kind"]) if k in REST_KINDS and status[i] == b"complete"]
        if warm:  # the longest complete warm-up, if it holds at least 8 batches of 10 s
            i = max(warm, key=lambda j: int(seg["last_sample"][j] - seg["first_sample"][j]))
            a, z = int(seg["first_sample"][i]), int(seg["last_sample"][i])
            if (z - a) / fs >= 80.0:
                rest = rest_batches(t_imu[a:z], f["imu/specific_force"][a:z], f["imu/angular_rate"][a:z], fs,
                                    temp_ds[a:z] if temp_ds is not None else None)
    temps = np.asarray(cols["temperature"])
    table = segment_table_from_samples(
        cols["kind"], cols["acc"], cols["gyro"], fs, cols["f_ref"], cols["w_ref"], noise_f, noise_w,
        label=np.asarray(cols["label"]), time=np.asarray(cols["time"]),
        temperature=temps if np.all(np.isfinite(temps)) else None,
        table_rate=np.asarray(cols["table_rate"]), angles=np.asarray(cols["angles"]),
        attitude=np.asarray(cols["attitude"]), earth_rate_n=earth_rate_enu(lat), gravity_m_s2=g,
        t_start=np.asarray(cols["t_start"]), t_end=np.asarray(cols["t_end"]), rest=rest)
    if noise_f is None:
        table.f_sigma = np.array([_residual_sigma(x, r, fs) for x, r in zip(cols["acc"], cols["f_ref"])])
    if noise_w is None:
        table.w_sigma = np.array([_residual_sigma(x, r, fs) for x, r in zip(cols["gyro"], cols["w_ref"])])
    table.extra["sample_rate_hz"] = fs
    table.extra["latitude_rad"] = lat
    table.extra["height_m"] = h
    return table
