"""Calibration of a recording (application layer of ``rigctl calibrate``, the solve hook and batch).

Turntable recordings (orientation and rate segments with table angles): the segment table
(:func:`rigctl.recording.segment_builder.build_segment_table`), the published solvers and the joint
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

import json
import math
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np

from . import production
from .verdicts import format_verdicts
from .calibration_text import effect_parameter_line, noise_summary, param_table
from ..recording.checkpoint import write_atomic
from ..recording.recorder import utc_now
from ..recording.segment_builder import CAL_KINDS, build_segment_table, open_recording, store_calibration_results
from ..jsonable import jsonable
from ..sensor_axes import ACCEL_AXES, GYRO_AXES
from ..solvers.calibration_result import CalibrationResult
from ..solvers.allan_stream import blas_single_thread
from ..solvers.noise_coefficients import Triad
from .allan import load_noise
from .restarts import restart_lines, restart_notes, truth_across_power_cycles
from ..errors import InputError
from ..config.spec import Spec

SCHEMA_VERSION = 1
G0 = 9.80665
DEG_H = 180.0 / math.pi * 3600.0
DEG = math.pi / 180.0



# ------------------------------------------------------------------------------ noise model
def noise_from_allan(f: h5py.File, where: Path | None = None) -> tuple[Triad, Triad] | None:
    """IEEE 952 coefficients (accel, gyro: three axes each) from /results/allan's joint fits
    (:func:`rigctl.analysis.allan.load_noise`), if complete. A term the fit reports only as an
    upper bound enters at its unconstrained estimate (``Coefficient.value``), not zero: a 12-hour
    capture rarely makes the rate random walk significant, and K = 0 would make the biases'
    intervals too narrow (docs/calibration.md, section 10)."""
    axes = load_noise(f, where)
    out = []
    for names in (ACCEL_AXES, GYRO_AXES):
        if not all(a in axes for a in names):
            return None
        out.append(tuple(axes[a] for a in names))
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
    check_noise_choice(str(src))
    with open_recording(src) as g:
        nm = noise_from_allan(g, src)
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


def check_noise_choice(choice: str) -> None:
    """Refuse a ``--noise`` that is neither auto/allan/self nor a recording file: one line saying
    what was given (a directory, a missing file) and what to give. Cheap: the commands call it
    before the analysis, so the error comes before any progress line."""
    if choice in NOISE_CHOICES:
        return
    src = Path(choice)
    what = ("is a directory, not a recording" if src.is_dir() else
            "no such file" if not src.exists() else "" if src.is_file() else "is not a regular file")
    if what:
        raise InputError(f"--noise {src}: {what}",
                         hint="give the recording.h5 of a capture that `rigctl allan` analysed (e.g. "
                              f"{src / 'recording.h5' if src.is_dir() else 'runs/<run>/recording.h5'}"
                              " of procedures/allan-overnight.yaml), or auto, allan or self")


def _noise(f: h5py.File, choice: str, path: Path) -> tuple[Any, Any, str]:
    if choice not in NOISE_CHOICES:
        return _noise_from_file(f, path, Path(choice))
    nm = noise_from_allan(f, path) if choice in ("auto", "allan") else None
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


# ------------------------------------------------------------------------------ turntable data
def _truth(f: h5py.File) -> dict[str, float] | None:
    from ..solvers.segments import truth_from_emulator

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
    from ..solvers.closed_loop import calibrate_session, format_report, session_to_dict

    from ..solvers.segment_noise import apply_session_noise

    with open_recording(path) as f:
        nf, nw, noise_txt = _noise(f, noise, path)
        truth, truth_note = truth_across_power_cycles(f, _truth(f))
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
    notes = _observability_notes(kinds, cl.final)
    text = "\n".join(head + [param_table(cl.final, "Calibration (closed-loop model, all segments)"),
                             *notes, format_report(cl, explain=False, effect_line=effect_parameter_line)])
    explain = "\n".join(["explain (step | residual pattern | candidate | statistic | decision):"]
                        + [f"  [{x['step']}] {x['residual_pattern']} | {x['candidate']} | {x['statistic']} | "
                           f"{x['decision']}" for x in cl.explain])
    restarts = restart_notes(path)
    mixed = restart_lines(restarts)
    trust = cl.final.status in ("ok", "poor_fit") and not mixed
    loop_status, why = table_status(cl, trust)
    if mixed:
        text += "\n" + "\n".join(f"warning: {line}" for line in mixed)
        why = mixed[0]
    if truth_note:
        text += f"\nnote: {truth_note}"
    text += f"\nSTATUS: {loop_status}" + (f": {why}" if why else "")
    payload = {"mode": "turntable", "noise_model": noise_txt, "noise_model_channels": noise_rows,
               "results": session_to_dict(out),
               "model": _model_from_final(cl.final), "truth_available": truth is not None,
               "truth_note": truth_note,
               "trustworthy": trust, "status": cl.final.status, "loop_status": loop_status,
               "reasons": list(cl.final.warnings) + ([why] if why else []) + mixed[1:],
               "device_restarts": restarts,
               "notes": [n.strip().removeprefix("note: ") for n in notes]}
    return payload, text, explain


def _observability_notes(kinds: dict[str, int], final: CalibrationResult) -> list[str]:
    """What the recording cannot determine well, and which procedure would: without rate
    segments the gyro scale factors and misalignments rest on Earth rate alone
    (7.29e-5 rad/s, 15.04 deg/h), so their 1-sigma is of order (gyro noise on a pose mean) /
    Earth rate -- tens of percent for a MEMS gyro."""
    if kinds.get("rate", 0) or kinds.get("ramp", 0):
        return []
    idx = [i for i, n in enumerate(final.names) if n.startswith("gyro_M_")]
    if not idx:
        return []
    worst = float(np.max(np.abs(np.asarray(final.sigma)[idx])))
    return [f"note: no rate segments in this recording: the gyro scale factors and misalignments rest on "
            f"Earth rate alone (largest 1-sigma {worst * 1e6:.3g} ppm); run procedures/rates.yaml or "
            f"procedures/full-calibration.yaml to determine them"]


def table_status(cl: Any, trusted: bool) -> tuple[str, str]:
    """The session's STATUS after the closed loop: OK only when the final model's chi2/dof is
    inside its 99 % band (chi2 quantiles for its dof) and no residual structure is left."""
    from ..solvers.pose_loop import STATUS_OK, STATUS_PESSIMISTIC, STATUS_UNEXPLAINED, chi2_band

    f = cl.final
    if not trusted:
        return "NOT TRUSTWORTHY", "; ".join(f.warnings[:1])
    lo, hi = chi2_band(f.dof, float("inf"))
    band = f"chi2/dof {f.chi2_per_dof:.3g}, 99 % band [{lo:.3g}, {hi:.3g}]"
    if f.chi2_per_dof > hi or cl.unexplained:
        what = "; ".join(u["pattern"] for u in cl.unexplained[:3])
        return STATUS_UNEXPLAINED, band + (f"; {what}" if what else "")
    if f.chi2_per_dof < lo:
        return STATUS_PESSIMISTIC, band
    return STATUS_OK, ""



# ------------------------------------------------------------------------------ orientation-free
def calibrate_free(path: Path, noise: str) -> tuple[dict[str, Any], str, str]:
    """Orientation-free recording: the pose pipeline with its closed loop
    (:mod:`rigctl.analysis.pose_calibration`). The pose means' noise comes from the session
    itself (white and slow parts measured on it); ``--noise`` applies to turntable recordings."""
    from .pose_calibration import calibrate_poses

    note = "" if noise == "auto" else f"--noise {noise} is for turntable sessions: not used here"
    return calibrate_poses(path, note)


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
              spec: Spec | None = None, thermal_degree: str | None = None,
              progress: Callable[[str], None] | None = None) -> tuple[dict[str, Any], str, str]:
    """Calibrate a recording, store /results/calibration and the JSON; (payload, text, explain).
    With ``spec`` the verdicts are computed, printed and stored with the results. ``thermal_degree``:
    the polynomial degrees of a thermal calibration (None: default; N, 'B,S,M' or 'auto').
    ``progress``: called with a line as each long stage starts (a thermal calibration's).

    The solvers run with the bundled OpenBLAS at one thread in the calling thread
    (:func:`~rigctl.solvers.allan_stream.blas_single_thread`): their matrices are small (tens to
    a few hundred rows), OpenBLAS' helper threads only spin on them (a table session's
    calibration took twice the CPU with two threads), and the numbers are those of a one-core
    machine wherever it runs (OpenBLAS' threaded Cholesky, inverse and triangular solve round
    differently from its single-threaded ones from about 66 rows on)."""
    with blas_single_thread():
        return _calibrate(Path(path), noise, store, json_path, spec, thermal_degree, progress)


def _calibrate(p: Path, noise: str, store: bool, json_path: str | Path | None, spec: Spec | None,
               thermal_degree: str | None, progress: Callable[[str], None] | None
               ) -> tuple[dict[str, Any], str, str]:
    """:func:`calibrate`'s work."""
    # -- thermal hook (docs/thermal.md): a chamber run across temperature is calibrated by
    # rigctl/analysis/thermal.py into /results/thermal (and RECORDING.thermal.json)
    from . import thermal
    if thermal.is_thermal(p):
        with open_recording(p) as f:
            noise_models = _noise(f, noise, p)
        payload, text = thermal.calibrate_and_store(p, store, json_path, thermal_degree, noise_models,
                                                    progress=progress)
        return payload, text, ""
    # -- end of the thermal hook
    free = is_orientation_free(p)
    payload, text, explain = (calibrate_free if free else calibrate_table)(p, noise)
    payload = jsonable({"schema_version": SCHEMA_VERSION, "created_utc": utc_now(),
                         "recording": str(p.resolve()), **payload})
    if spec is not None:
        payload["verdicts"] = production.verdicts_for(spec, "calibration", payload)
        text += "\n" + format_verdicts(payload["verdicts"])
    if store:
        not_stored = store_calibration_results(p, "calibration", payload, schema_version=SCHEMA_VERSION)
        if not_stored:
            text += "\n" + not_stored
        jp = Path(json_path) if json_path else p.with_name(p.stem + ".calibration.json")
        write_atomic(jp, json.dumps(payload, indent=1).encode())  # whole or not at all
        text += f"\nresults: {p}:/results/calibration and {jp}"
    return payload, text, explain


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
        db_line = production.to_database(recording, "calibration", payload, None)
        text += "\n" + db_line if db_line else ""
    except InputError as exc:
        log("warning", f"calibration: {exc}")
        return
    except (OSError, ValueError, np.linalg.LinAlgError) as exc:
        log("error", f"calibration failed: {exc}")
        return
    log("info", text)


