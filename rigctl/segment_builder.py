"""Build the calibration solvers' per-segment table from a recording (the I/O edge).

For every complete static or constant-rate segment of /segments it takes the IMU samples of
the sampling window, their means and uncertainties (:func:`rigctl.solvers.segment_stats.
segment_mean`), and the true references evaluated at every sample time from the table's
attitude (:func:`rigctl.frames.body_references`) and averaged over the window -- the moments
(mean of f f^T, of w^3, ...) as well, because nonlinear terms act on them, not on the means.

On a rate segment the turning axis' angle is reconstructed at every IMU sample by a straight
line fitted to the table polls inside the window (angle unwrapped), so gravity and Earth rate
are integrated over exactly the revolutions the window holds.
"""
from __future__ import annotations

import math
from pathlib import Path

import h5py
import numpy as np

from .frames import body_references, earth_rate_enu, gimbal_dcm, normal_gravity
from .solvers.segment_stats import AllanCurve, NoiseModel, segment_mean
from .solvers.segments import SegmentTable
from .yamlio import InputError

#: Segment kinds a calibration uses.
CAL_KINDS = (b"orientation", b"rate")


def open_recording(path: str | Path) -> h5py.File:
    """Open a rigctl recording read-only (SWMR-capable); InputError if it is not one."""
    p = Path(path)
    if not p.is_file():
        raise InputError("recording not found", p, hint="give the path of a recording.h5")
    try:
        f = h5py.File(p, "r", libver="latest", swmr=True)
    except OSError:
        try:
            f = h5py.File(p, "r")
        except OSError as exc:
            raise InputError(f"not an HDF5 file ({exc})", p) from None
    if f.attrs.get("format") != "rigctl-recording":
        f.close()
        raise InputError("not a rigctl recording (root attribute format != 'rigctl-recording')", p,
                         hint="see docs/data-format.md, or convert it with rigctl import")
    for name in ("imu/specific_force", "imu/angular_rate", "imu/time", "segments/kind"):
        if name not in f:
            f.close()
            raise InputError(f"the recording has no /{name}", p, hint="see docs/data-format.md")
    return f


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


def build_segment_table(path: str | Path, kinds: tuple[bytes, ...] = CAL_KINDS,
                        noise_f: NoiseModel | AllanCurve | None = None,
                        noise_w: NoiseModel | AllanCurve | None = None) -> SegmentTable:
    """Per-segment means, uncertainties and references of a recording's complete segments.

    Args:
        path: a recording following docs/data-format.md.
        kinds: segment kinds to include.
        noise_f, noise_w: accelerometer / gyro noise models for the uncertainty of a mean; None
            estimates it from each segment itself.
    """
    with open_recording(path) as f:
        lat, h, g = _site(f)
        fs = float(f["imu"].attrs.get("sample_rate_hz", 0.0))
        t_imu = f["imu/time"]
        if fs <= 0:
            tt = t_imu[: min(1000, t_imu.shape[0])]
            fs = 1.0 / float(np.median(np.diff(tt)))
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
        out: dict[str, list] = {k: [] for k in ("kind", "label", "f", "w", "f_sigma", "w_sigma",
                                                "f_ref", "w_ref", "time", "temperature", "table_rate",
                                                "attitude", "f_ref_outer", "w_ref_outer",
                                                "w_ref_cube", "w_ref_abs", "f_ref_abs")}
        for i in rows:
            a, z = int(seg["first_sample"][i]), int(seg["last_sample"][i])
            fm = segment_mean(f["imu/specific_force"][a:z], fs, noise_f)
            wm = segment_mean(f["imu/angular_rate"][a:z], fs, noise_w)
            t = t_imu[a:z]
            ang, rates = _angles_at(t, seg, i, tab_t, tab_ang)
            fr, wr = body_references(ang, rates, lat, h, g)
            out["kind"].append(seg["kind"][i].decode())
            out["label"].append(seg["label"][i].decode())
            out["f"].append(fm.mean)
            out["w"].append(wm.mean)
            out["f_sigma"].append(fm.sigma)
            out["w_sigma"].append(wm.sigma)
            out["f_ref"].append(fr.mean(axis=0))
            out["w_ref"].append(wr.mean(axis=0))
            out["time"].append(float(t.mean()))
            out["temperature"].append(float(temp_ds[a:z].mean()) if temp_ds is not None else np.nan)
            out["table_rate"].append(rates.mean(axis=0))
            out["attitude"].append(gimbal_dcm(ang).mean(axis=0))
            out["f_ref_outer"].append(np.einsum("ni,nj->ij", fr, fr) / len(fr))
            out["w_ref_outer"].append(np.einsum("ni,nj->ij", wr, wr) / len(wr))
            out["w_ref_cube"].append((wr**3).mean(axis=0))
            out["w_ref_abs"].append(np.abs(wr).mean(axis=0))
            out["f_ref_abs"].append(np.abs(fr).mean(axis=0))
    temps = np.asarray(out.pop("temperature"))
    return SegmentTable(**{k: np.asarray(v) for k, v in out.items()},
                        temperature=temps if np.all(np.isfinite(temps)) else None,
                        ang_accel=np.zeros((len(rows), 3)), earth_rate_n=earth_rate_enu(lat),
                        gravity_m_s2=g)
