"""The run report: ``report.html`` (self-contained) plus PNGs, from one recording.

:func:`load_run` reads what a report needs from a recording (docs/data-format.md): /meta,
/run/status, /events, /table, /segments, the IMU counter gaps (dropped samples, read in
chunks) and the results groups /results/calibration, /results/allan, /results/sync -- each
may be absent (its section then says "not run"). :mod:`rigctl.report.report_build` draws the plots
(:mod:`rigctl.report.report_plots`, matplotlib Agg) and writes the page (:mod:`rigctl.report.report_html`).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis.production import latest_allan
from ..recording.recording_reader import open_recording
from ..errors import InputError

REPORT_HTML = "report.html"
RECORDING = "recording.h5"
RUN_LOG = "run.log.jsonl"
#: Segment kinds in the calibration's segment table (same rule as rigctl.recording.segment_builder).
CAL_KINDS = ("orientation", "rate")
#: Event kinds shown as faults / suspender events (the rest, e.g. state transitions and the
#: end-of-run safe-state, are listed under "All events").
FAULT_KINDS = ("suspend", "resume", "incomplete", "interrupted", "failed", "data-lost",
               "fault", "error", "device-restart")
COUNTER_CHUNK = 1 << 20
MAX_TABLE_POINTS = 20000


class ReportDependencyError(InputError):
    """matplotlib is missing: ``pip install 'rigctl[report]'`` (exit code 2)."""


@dataclass
class RunData:
    """Everything a report shows, read from one recording (SI units as stored)."""

    recording: Path
    root_attrs: dict[str, Any]
    meta: dict[str, Any]
    status: str
    events: list[tuple[float, str, str]]
    table: dict[str, np.ndarray] | None
    segments: dict[str, np.ndarray] | None
    imu: dict[str, Any]
    results: dict[str, dict[str, Any]] = field(default_factory=dict)
    run_log: list[dict[str, Any]] = field(default_factory=list)
    cache: dict[str, Any] = field(default_factory=dict)

    @property
    def cal_rows(self) -> list[int]:
        """Rows of /segments that form the calibration's segment table, in its order."""
        s = self.segments
        if s is None or "kind" not in s:
            return []
        status = s.get("status", np.array(["complete"] * len(s["kind"])))
        first, last = s.get("first_sample"), s.get("last_sample")
        return [i for i, k in enumerate(s["kind"]) if k in CAL_KINDS and status[i] == "complete"
                and (first is None or last[i] - first[i] >= 2)]


def resolve_run(run: str | Path) -> tuple[Path, Path]:
    """(recording path, run directory) from a run directory or a recording path."""
    p = Path(run)
    if p.is_dir():
        rec = p / RECORDING
        if not rec.is_file():
            cands = sorted(p.glob("*.h5"))
            if len(cands) != 1:
                raise InputError(f"no {RECORDING} in the run directory", p,
                                 hint="pass a run directory made by rigctl run, or a recording .h5")
            rec = cands[0]
        return rec, p
    if p.is_file():
        return p, p.parent
    raise InputError("no such run directory or recording", p,
                     hint="pass runs/<timestamp>-<procedure> or its recording.h5")


def _text(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.generic):
        return v.item()
    return v


def _strings(a: np.ndarray) -> np.ndarray:
    return np.array([x.decode("utf-8", "replace").rstrip("\x00") if isinstance(x, bytes) else str(x)
                     for x in a], dtype=object)


def _group_arrays(g: Any) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}

    def visit(name: str, obj: Any) -> None:
        if hasattr(obj, "shape"):
            d = obj[()]
            out[name] = _strings(d) if getattr(d, "dtype", None) is not None and d.dtype.kind == "S" else d

    g.visititems(visit)
    return out


def _counter_gaps(ds: Any) -> tuple[int, int]:
    """(samples dropped, number of gaps) from the IMU counter, in chunks (bounded memory)."""
    n = ds.shape[0]
    dropped = gaps = 0
    prev: int | None = None
    for a in range(0, n, COUNTER_CHUNK):
        c = ds[a: a + COUNTER_CHUNK].astype(np.int64)
        if prev is not None:
            c = np.concatenate(([prev], c))
        d = np.diff(c) - 1
        dropped += int(d[d > 0].sum())
        gaps += int((d > 0).sum())
        if c.size:
            prev = int(c[-1])
    return dropped, gaps


def _read_run_log(run_dir: Path) -> list[dict[str, Any]]:
    p = run_dir / RUN_LOG
    out: list[dict[str, Any]] = []
    if not p.is_file():
        return out
    for line in p.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and rec.get("kind") in ("warning", "error"):
            out.append(rec)
    return out


def load_run(recording: str | Path, run_dir: str | Path | None = None) -> RunData:
    """Read a recording for the report; raises InputError if it is not a rigctl recording."""
    path = Path(recording)
    with open_recording(path, need=("imu/time", "imu/specific_force", "imu/angular_rate")) as f:
        root = {k: _text(v) for k, v in f.attrs.items()}
        meta = {k: _text(v) for k, v in f["meta"].attrs.items()} if "meta" in f else {}
        status = _text(f["run/status"][0]).rstrip("\x00") if "run/status" in f else "unknown"
        events: list[tuple[float, str, str]] = []
        if "events/time" in f:
            t = f["events/time"][()]
            k = _strings(f["events/kind"][()])
            m = _strings(f["events/message"][()])
            events = [(float(a), str(b), str(c)) for a, b, c in zip(t, k, m)]
        table = None
        if "table/time" in f and f["table/time"].shape[0] > 0:
            n = f["table/time"].shape[0]
            step = max(1, math.ceil(n / MAX_TABLE_POINTS))
            table = {k: f[f"table/{k}"][::step] for k in ("time", "angle", "rate") if f"table/{k}" in f}
        segments = _group_arrays(f["segments"]) if "segments" in f and "kind" in f["segments"] else None
        imu: dict[str, Any] = {"n": 0, "rate_hz": None, "dropped": 0, "gaps": 0}
        if "imu/time" in f:
            imu["n"] = int(f["imu/time"].shape[0])
            r = f["imu"].attrs.get("sample_rate_hz")
            imu["rate_hz"] = float(r) if r is not None else None
            if imu["n"] > 0:
                imu["t_first"], imu["t_last"] = float(f["imu/time"][0]), float(f["imu/time"][-1])
        if "imu/counter" in f:
            imu["dropped"], imu["gaps"] = _counter_gaps(f["imu/counter"])
        results: dict[str, dict[str, Any]] = {}
        if "results" in f:
            for name, g in f["results"].items():
                attrs = {k: _text(v) for k, v in g.attrs.items()}
                try:
                    payload = json.loads(attrs.get("json", "{}"))
                except (TypeError, json.JSONDecodeError):
                    payload = {}
                results[name] = {"json": payload, "created_utc": attrs.get("created_utc", ""),
                                 "schema_version": attrs.get("schema_version"),
                                 "arrays": _group_arrays(g) if name != "sync" else _sync_arrays(f, g)}
    if "allan" not in results:  # the Allan results of the same unit's latest analysed capture
        found = latest_allan(path)
        if found is not None:
            try:
                with open_recording(found[0], need=()) as g:
                    grp = g["results/allan"]
                    results["allan"] = {"json": found[1], "created_utc": _text(grp.attrs.get("created_utc", "")),
                                        "schema_version": _text(grp.attrs.get("schema_version")),
                                        "arrays": _group_arrays(grp), "source": str(found[0])}
            except InputError:  # a damaged capture beside the run: the report goes on without it
                pass
    rd = Path(run_dir) if run_dir is not None else path.parent
    return RunData(path, root, meta, status, events, table, segments, imu, results,
                   _read_run_log(rd))


def _sync_arrays(f: Any, g: Any) -> dict[str, np.ndarray]:
    """/results/sync's per-tap datasets, and the clock's reference time at each tap.

    Recordings synchronised by this version store it (``tap_reference_time``). For older ones:
    the clock is affine between samples, so the reference time of a tap at fractional counter
    c = t_tap * rate is interpolated linearly between the reference times (per IMU row,
    /results/sync/reference_time) of the tap's detection row and the next row; only those
    rows are read.
    """
    out = {k: g[k][()] for k in ("tap_time_imu", "tap_row", "pulse_time", "local_residual",
                                 "inlier", "tap_reference_time") if k in g}
    if "tap_reference_time" in out:
        return out
    rate = f["imu"].attrs.get("sample_rate_hz") if "imu" in f else None
    if not ("reference_time" in g and "imu/counter" in f and "tap_row" in out
            and "tap_time_imu" in out and rate is not None and out["tap_row"].size):
        return out
    n = g["reference_time"].shape[0]
    lo = np.clip(out["tap_row"].astype(np.int64), 0, max(0, n - 2))
    rows = np.unique(np.concatenate((lo, np.minimum(lo + 1, n - 1))))
    ref = dict(zip(rows.tolist(), g["reference_time"][rows]))
    cnt = dict(zip(rows.tolist(), f["imu/counter"][rows].astype(np.float64)))
    hi = np.minimum(lo + 1, n - 1)
    r_lo = np.array([ref[i] for i in lo.tolist()])
    r_hi = np.array([ref[i] for i in hi.tolist()])
    c_lo = np.array([cnt[i] for i in lo.tolist()])
    c_hi = np.array([cnt[i] for i in hi.tolist()])
    c_tap = out["tap_time_imu"] * float(rate)
    span = np.where(c_hi > c_lo, c_hi - c_lo, 1.0)
    out["tap_reference_time"] = r_lo + (c_tap - c_lo) * (r_hi - r_lo) / span
    return out


def find_session(payload: Any) -> dict[str, Any] | None:
    """The calibration session dict (keys accel24, gyro_rate, closed_loop, ...) in a payload."""
    if isinstance(payload, dict):
        cl = payload.get("closed_loop")
        if isinstance(cl, dict) and ("declared" in cl or "final" in cl):
            return payload
        for v in payload.values():
            got = find_session(v)
            if got is not None:
                return got
    return None


def require_matplotlib() -> None:
    """Raise ReportDependencyError when matplotlib is not installed."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ReportDependencyError("the report needs matplotlib: pip install 'rigctl[report]'") from None
