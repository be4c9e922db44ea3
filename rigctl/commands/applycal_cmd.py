"""``rigctl apply-cal RECORDING.h5 -o OUT.h5``: write calibrated IMU data.

The calibration's sensor model (``rigctl calibrate``: /results/calibration of the recording, or a
JSON file with ``--calibration``), SI units:

    accelerometer  A = b_a + M_a a + k2 o (a o a)        (o: element-wise)
    gyro           W = b_g + M_g w + G a

is inverted per sample. The accelerometer by Newton's method, vectorised over samples:

    a_0 = M_a^-1 (A - b_a),   a_{k+1} = a_k - J_k^-1 r_k,
    r_k = b_a + M_a a_k + k2 o a_k^2 - A,   J_k = M_a + diag(2 k2 o a_k)

(k2 |a| ~ 1e-4 at most, so a few iterations reach float64 precision; the iteration stops when
the largest step is below 1e-12 m/s^2). Then w = M_g^-1 (W - b_g - G a).

The output is a complete copy of the recording (docs/data-format.md) with /imu/specific_force and
/imu/angular_rate replaced, /results emptied (results of the raw data do not describe the
corrected data) and the provenance in /meta attrs ``calibration_applied_json`` (the model, its
source and the input file). It is built as OUT.h5.part and renamed when complete; nothing else
is written. The input is never modified and OUT may not be the input.

A thermal calibration (/results/thermal when there is no /results/calibration, or a JSON with
``"mode": "thermal"``) is applied at each sample's temperature (/imu/temperature):
:func:`rigctl.analysis.thermal.apply_thermal`, docs/thermal.md.

Exit codes: 0 written, 2 invalid input, 1 failure.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from ..analysis.thermal import apply_thermal, thermal_info
from ..recording.recorder import utc_now
from ..recording.recording_reader import check_finite
from ..recording.segment_builder import open_recording
from ..errors import InputError, RunFailure

CHUNK = 1 << 18


def invert_accel(A: NDArray[np.float64], b: NDArray[np.float64], M: NDArray[np.float64],
                 k2: NDArray[np.float64], max_iter: int = 20) -> NDArray[np.float64]:
    """True specific force a (n, 3) from measured A (n, 3) (module docstring)."""
    Minv = np.linalg.inv(M)
    a = (A - b) @ Minv.T
    if not np.any(k2):
        return a
    for _ in range(max_iter):
        r = b + a @ M.T + k2 * a * a - A
        J = np.broadcast_to(M, (len(a), 3, 3)).copy()
        J[:, [0, 1, 2], [0, 1, 2]] += 2.0 * k2 * a
        step = np.linalg.solve(J, r[..., None])[..., 0]
        a = a - step
        if np.max(np.abs(step), initial=0.0) < 1e-12:
            break
    return a


def invert_gyro(W: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64],
                M: NDArray[np.float64], G: NDArray[np.float64]) -> NDArray[np.float64]:
    """True rate w = M^-1 (W - b - G a), (n, 3)."""
    return (W - b - a @ G.T) @ np.linalg.inv(M).T


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
    m = info["model"]
    if "thermal" in info:  # rigctl/analysis/thermal.py
        return _apply_copy(src, out, info, origin, lambda fin, fo: apply_thermal(fin, fo, src, info, CHUNK))
    ba, Ma, k2 = (np.asarray(m["accel"][k], dtype=np.float64) for k in ("bias_m_s2", "M", "k2_s2_per_m"))
    bg, Mg = (np.asarray(m["gyro"][k], dtype=np.float64) for k in ("bias_rad_s", "M"))
    G = np.asarray(m["gyro"].get("G_rad_s_per_m_s2", np.zeros((3, 3))), dtype=np.float64)

    def fixed(fin: h5py.File, fo: h5py.File) -> int:
        fa, fw = fo["imu/specific_force"], fo["imu/angular_rate"]
        n = fa.shape[0]
        for a0 in range(0, n, CHUNK):
            a1 = min(n, a0 + CHUNK)
            f_in, w_in = fin["imu/specific_force"][a0:a1], fin["imu/angular_rate"][a0:a1]
            check_finite(src, "imu/specific_force", f_in, a0)
            check_finite(src, "imu/angular_rate", w_in, a0)
            fa[a0:a1] = acc = invert_accel(f_in, ba, Ma, k2)
            fw[a0:a1] = invert_gyro(w_in, acc, bg, Mg, G)
        return n
    return _apply_copy(src, out, info, origin, fixed)


def _apply_copy(src: Path, out: Path, info: dict[str, Any], origin: str, correct: Any) -> int:
    """Copy to OUT.h5.part, ``correct(fin, fo)`` its /imu, record the provenance, rename."""
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
            n = correct(fin, fo)
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


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl apply-cal``: 0 ok, 2 invalid input, 1 failure."""
    src, out = Path(args.recording), Path(args.output)
    if out.exists() and out.resolve() == src.resolve():
        raise InputError("-o names the input recording; apply-cal never modifies its input", out,
                         hint="choose another output file")
    if out.exists() and not args.force:
        raise InputError("output exists", out, hint="choose another -o or pass --force to replace it")
    if not out.parent.is_dir():
        raise InputError("output directory does not exist", out.parent)
    if args.calibration and args.from_results:
        raise InputError("give either --calibration JSON or --from-results, not both")
    info, origin = load_model(src, args.calibration)
    try:
        n = apply_calibration(src, out, info, origin)
    except (OSError, ValueError, np.linalg.LinAlgError) as exc:
        raise RunFailure(f"{src}: {exc}") from exc
    note = "" if info.get("trustworthy", True) is not False else " (WARNING: that calibration is NOT TRUSTWORTHY)"
    print(f"applied calibration from {origin} to {n} samples{note}")
    print(f"recording: {out}")
    return 0


def register(subparsers: Any) -> None:
    """Add the ``apply-cal`` sub-command."""
    p = subparsers.add_parser("apply-cal", help="write a recording with calibrated IMU data",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("recording", help="rigctl HDF5 recording (read only)")
    p.add_argument("-o", "--output", required=True, help="corrected recording to write (.h5)")
    p.add_argument("--calibration", help="calibration JSON written by rigctl calibrate")
    p.add_argument("--from-results", action="store_true",
                   help="use the recording's /results/calibration (the default)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)
