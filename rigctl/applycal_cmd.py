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

A thermal calibration (``rigctl calibrate`` on a chamber run: /results/thermal, or its JSON with
``"mode": "thermal"``) is applied sample by sample at the recording's own temperature column
(/imu/temperature): bias and matrix are evaluated at each sample's temperature, plus the thermal
effects the loop accepted (hysteresis state and temperature rate along the record, the gradient
from /chamber), then inverted the same way (:func:`rigctl.solvers.thermal.correct`). Used when
the recording has /results/thermal and no /results/calibration, or with ``--calibration``
naming a thermal JSON.

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

from .recorder import utc_now
from .recording_reader import check_finite
from .segment_builder import open_recording
from .errors import InputError, RunFailure

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
                return _thermal_info(data, path), f"{path.resolve()}:/results/thermal"
            if g is None or "json" not in g.attrs:
                raise InputError("no /results/calibration in the recording", path,
                                 hint="run `rigctl calibrate` first, or give --calibration JSON")
            data = json.loads(g.attrs["json"])
        src = f"{path.resolve()}:/results/calibration"
    if isinstance(data, dict) and data.get("mode") == "thermal":
        return _thermal_info(data, calibration or path), src
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


def _thermal_info(data: dict[str, Any], where: Any) -> dict[str, Any]:
    """A thermal calibration payload, checked: {sensor: {name: value}}, accepted effects."""
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
            "trustworthy": all(d.get("status") == "ok" for d in data["sensors"].values()),
            "model": {"thermal": True, "reference_c": ref, "accepted": accepted}}


def _apply_thermal(fin: h5py.File, fo: h5py.File, src: Path, info: dict[str, Any]) -> int:
    from .solvers import thermal as th

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
    fa, fw = fo["imu/specific_force"], fo["imu/angular_rate"]
    n = fa.shape[0]
    for a0 in range(0, n, CHUNK):
        a1 = min(n, a0 + CHUNK)
        f_in, w_in = fin["imu/specific_force"][a0:a1], fin["imu/angular_rate"][a0:a1]
        check_finite(src, "imu/specific_force", f_in, a0)
        check_finite(src, "imu/angular_rate", w_in, a0)
        for ds, sensor, y in ((fa, "accel", f_in), (fw, "gyro", w_in)):
            ds[a0:a1] = th.correct(sensor, y, T[a0:a1], info["thermal"][sensor], info["reference_c"],
                                   {c: x[a0:a1] for c, x in regs[sensor].items()})
    return n


def apply_calibration(src: Path, out: Path, info: dict[str, Any], origin: str) -> int:
    """Write the corrected copy; returns the number of samples."""
    m = info["model"]
    if "thermal" in info:
        return _apply_copy(src, out, info, origin, lambda fin, fo: _apply_thermal(fin, fo, src, info))
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
            acc = invert_accel(f_in, ba, Ma, k2)
            fw[a0:a1] = invert_gyro(w_in, acc, bg, Mg, G)
            fa[a0:a1] = acc
        return n
    return _apply_copy(src, out, info, origin, fixed)


def _apply_copy(src: Path, out: Path, info: dict[str, Any], origin: str, correct: Any) -> int:
    """Copy the recording to OUT.h5.part, correct its IMU data with ``correct(fin, fo)``, record
    the provenance, rename into place; returns the number of samples."""
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
