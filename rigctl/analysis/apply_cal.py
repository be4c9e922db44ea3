"""``rigctl apply-cal``'s pipeline: a recording's IMU data corrected by a calibration, written
as a new recording (docs/calibration.md; the command: :mod:`rigctl.commands.applycal_cmd`).

The sensor model (``rigctl calibrate``: /results/calibration of the recording, or a JSON file),
SI, is inverted per sample by :mod:`rigctl.solvers.sensor_model`; a thermal calibration
(/results/thermal when there is no /results/calibration, or a JSON with ``"mode": "thermal"``) is
applied at each sample's temperature (/imu/temperature): :func:`rigctl.analysis.thermal.thermal_corrector`.

The output is a complete copy of the recording (docs/data-format.md) with /imu/specific_force and
/imu/angular_rate replaced, /results emptied (results of the raw data do not describe the
corrected data) and the provenance in /meta attrs ``calibration_applied_json`` (the model, its
source and the input file). It is built as OUT.h5.part and renamed when complete; nothing else
is written.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from collections.abc import Callable
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..recording.recorder import utc_now
from ..recording.recording_reader import check_finite
from ..recording.segment_builder import open_recording
from ..solvers.sensor_model import invert_gyro, invert_quadratic
from .thermal import thermal_corrector, thermal_info

CHUNK = 1 << 18


def load_model(path: Path, calibration: str | None) -> tuple[dict[str, Any], str]:
    """The sensor model and a description of where it came from."""
    if calibration:
        cp = Path(calibration)
        if not cp.is_file():
            raise InputError("calibration file not found", cp, hint="give the JSON written by rigctl calibrate")
        try:
            data = json.loads(cp.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise InputError(f"not valid JSON ({exc.msg})", cp, exc.lineno) from None
        except UnicodeDecodeError:
            raise InputError("not a UTF-8 text file", cp, hint="give the JSON written by rigctl calibrate") from None
        src = f"{cp.resolve()}"
    else:
        with open_recording(path) as f:
            g = f.get("results/calibration")
            if g is None and f.get("results/thermal") is not None and "json" in f["results/thermal"].attrs:
                data = json.loads(f["results/thermal"].attrs["json"])
                return thermal_info(data, path), f"{path.resolve()}:/results/thermal"
            if g is None or "json" not in g.attrs:
                raise InputError("no /results/calibration in the recording", path,
                                 hint="run `rigctl calibrate` first, or give --calibration JSON")
            data = json.loads(g.attrs["json"])
        src = f"{path.resolve()}:/results/calibration"
    if isinstance(data, dict) and data.get("mode") == "thermal":
        return thermal_info(data, calibration or path), src
    model = data.get("model") if isinstance(data, dict) else None
    try:
        for sensor, keys in (("accel", ("bias_m_s2", "M", "k2_s2_per_m")), ("gyro", ("bias_rad_s", "M"))):
            for k in keys:
                v = np.asarray(model[sensor][k], dtype=np.float64)
                if v.shape != ((3, 3) if k == "M" else (3,)) or not np.all(np.isfinite(v)):
                    raise ValueError(f"{sensor} {k}")
                if k == "M" and abs(np.linalg.det(v)) < 1e-6:
                    raise ValueError(f"{sensor} {k} is singular")
    except (TypeError, KeyError, ValueError):
        raise InputError("the calibration has no complete 'model' (accel bias_m_s2, M, k2_s2_per_m; "
                         "gyro bias_rad_s, M)", calibration or path,
                         hint="use a JSON written by rigctl calibrate (schema_version 1)") from None
    return {"model": model, "schema_version": data.get("schema_version"), "status": data.get("status"),
            "trustworthy": data.get("trustworthy")}, src


def apply_calibration(src: Path, out: Path, info: dict[str, Any], origin: str) -> int:
    """Write the corrected copy; returns the number of samples."""
    if "thermal" in info:  # rigctl/analysis/thermal.py
        return _apply_copy(src, out, info, origin, lambda fin: thermal_corrector(fin, src, info))
    m = info["model"]
    ba, Ma, k2 = (np.asarray(m["accel"][k], dtype=np.float64) for k in ("bias_m_s2", "M", "k2_s2_per_m"))
    bg, Mg = (np.asarray(m["gyro"][k], dtype=np.float64) for k in ("bias_rad_s", "M"))
    G = np.asarray(m["gyro"].get("G_rad_s_per_m_s2", np.zeros((3, 3))), dtype=np.float64)

    def fixed(a0: int, a1: int, f_in: NDArray[np.float64], w_in: NDArray[np.float64]) -> tuple[Any, Any]:
        acc = invert_quadratic(f_in, ba, Ma, k2)
        return acc, invert_gyro(w_in, acc, bg, Mg, G)
    return _apply_copy(src, out, info, origin, lambda fin: fixed)


def _correct_imu(fin: h5py.File, fo: h5py.File, src: Path, fix: Callable[..., tuple[Any, Any]]) -> int:
    """/imu of the copy ``fo`` corrected chunk by chunk: ``fix(a0, a1, f, w)`` -> (f, w) of
    samples a0:a1 (each chunk checked finite first); returns the number of samples."""
    fa, fw = fo["imu/specific_force"], fo["imu/angular_rate"]
    n = fa.shape[0]
    for a0 in range(0, n, CHUNK):
        a1 = min(n, a0 + CHUNK)
        f_in, w_in = fin["imu/specific_force"][a0:a1], fin["imu/angular_rate"][a0:a1]
        check_finite(src, "imu/specific_force", f_in, a0)
        check_finite(src, "imu/angular_rate", w_in, a0)
        fa[a0:a1], fw[a0:a1] = fix(a0, a1, f_in, w_in)
    return n


def _apply_copy(src: Path, out: Path, info: dict[str, Any], origin: str,
                corrector: Callable[[h5py.File], Callable[..., tuple[Any, Any]]]) -> int:
    """Copy to OUT.h5.part, correct its /imu with ``corrector(fin)`` (:func:`_correct_imu`),
    record the provenance, rename."""
    m = info["model"]
    part = out.with_name(out.name + ".part")
    n = 0
    try:
        with open_recording(src) as fin, h5py.File(part, "w", libver="latest") as fo:
            for k, v in fin.attrs.items():
                fo.attrs[k] = v
            for name in fin:
                if name == "results":
                    fo.create_group("results")
                    continue
                fin.copy(fin[name], fo, name=name)
            n = _correct_imu(fin, fo, src, corrector(fin))
            fo.require_group("meta").attrs["calibration_applied_json"] = json.dumps({
                "source": origin, "input": str(src.resolve()), "applied_utc": utc_now(),
                "schema_version": info["schema_version"], "status": info["status"],
                "trustworthy": info["trustworthy"], "model": m})
        os.replace(part, out)
    except BaseException:
        if part.exists():
            part.unlink()
        raise
    return n
