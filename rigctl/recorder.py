"""HDF5 recorder: IMU samples, table state, pulses, segments, events, truth and metadata.

The layout is documented in docs/data-format.md (schema version :data:`SCHEMA_VERSION`). Every
dataset is created up front, chunked and extendable, and the file is switched to SWMR mode so
another process can read a run in progress (``h5py.File(path, "r", libver="latest",
swmr=True)``). Data are buffered in memory and appended at most ``flush_interval_s`` of wall
time apart, then flushed, so a crash loses at most that much. ``/run/status`` says whether a run
completed; a file left at ``running`` was cut off.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from . import __version__
from .devices import ImuBlock, Pulses, TableState

SCHEMA_VERSION = 1
FORMAT_NAME = "rigctl-recording"
STATUSES = ("running", "complete", "interrupted", "failed")

_STR = {"kind": "S16", "label": "S48", "status": "S16", "source": "S16", "message": "S200"}

#: group -> dataset -> (per-row shape, dtype, units)
LAYOUT: dict[str, dict[str, tuple[tuple[int, ...], Any, str]]] = {
    "imu": {
        "time": ((), np.float64, "s"),
        "counter": ((), np.uint64, "1"),
        "specific_force": ((3,), np.float64, "m/s^2"),
        "angular_rate": ((3,), np.float64, "rad/s"),
        "temperature": ((), np.float64, "degC"),
    },
    "table": {
        "time": ((), np.float64, "s"),
        "angle": ((3,), np.float64, "rad"),
        "rate": ((3,), np.float64, "rad/s"),
        "status": ((), np.uint64, "1"),
    },
    "pulses": {
        "time": ((), np.float64, "s"),
        "gps_week": ((), np.int32, "week"),
        "gps_seconds": ((), np.float64, "s"),
        "source": ((), _STR["source"], ""),
    },
    "segments": {
        "kind": ((), _STR["kind"], ""),
        "label": ((), _STR["label"], ""),
        "step": ((), np.int32, "1"),
        "first_sample": ((), np.int64, "sample"),
        "last_sample": ((), np.int64, "sample"),
        "t_start": ((), np.float64, "s"),
        "t_end": ((), np.float64, "s"),
        "settle_time": ((), np.float64, "s"),
        "commanded_angle": ((3,), np.float64, "rad"),
        "commanded_rate": ((3,), np.float64, "rad/s"),
        "measured_angle": ((3,), np.float64, "rad"),
        "measured_rate": ((3,), np.float64, "rad/s"),
        "status": ((), _STR["status"], ""),
    },
    "events": {
        "time": ((), np.float64, "s"),
        "kind": ((), _STR["kind"], ""),
        "message": ((), _STR["message"], ""),
    },
}
_CHUNK_ROWS = {"imu": 8192, "table": 1024, "pulses": 256, "segments": 64, "events": 64}


@dataclass
class Segment:
    """One row of /segments (see docs/data-format.md)."""

    kind: str
    label: str
    step: int
    first_sample: int
    last_sample: int
    t_start: float
    t_end: float
    settle_time: float
    commanded_angle: np.ndarray
    commanded_rate: np.ndarray
    measured_angle: np.ndarray
    measured_rate: np.ndarray
    status: str = "complete"


def utc_now() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def library_versions() -> dict[str, str]:
    import platform

    import scipy
    import serial
    import yaml

    try:
        import pymodbus
        pm = pymodbus.__version__
    except Exception as exc:  # noqa: BLE001 - report, don't fail a run on a version probe
        pm = f"unavailable ({type(exc).__name__})"
    return {"rigctl": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "h5py": h5py.__version__, "hdf5": h5py.version.hdf5_version,
            "pyserial": serial.__version__, "pymodbus": pm, "pyyaml": yaml.__version__}


class Recorder:
    """Append-only, crash-safe writer of one run's recording."""

    def __init__(self, path: str | Path, meta: dict[str, Any], truth: dict[str, Any] | None = None,
                 imu_rate_hz: float = 0.0, flush_interval_s: float = 0.5,
                 max_buffer_rows: int = 1 << 20) -> None:
        self.path = Path(path)
        self.flush_interval_s = flush_interval_s
        self.max_buffer_rows = max_buffer_rows
        self._buf: dict[str, dict[str, list[np.ndarray]]] = {g: {d: [] for d in ds} for g, ds in LAYOUT.items()}
        self._buffered_rows = 0
        self._last_flush = time.monotonic()
        self.n_imu = 0  # samples appended (buffered or written)
        self.n_segments = 0
        self.closed = False
        f = h5py.File(self.path, "w", libver="latest")
        f.attrs["format"] = FORMAT_NAME
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["rigctl_version"] = __version__
        run = f.create_group("run")
        run.create_dataset("status", data=np.array([b"running"], dtype="S16"))
        m = f.create_group("meta")
        for key, value in meta.items():
            m.attrs[key] = value if not isinstance(value, (dict, list)) else json.dumps(value)
        m.attrs.setdefault("started_utc", utc_now())
        m.attrs["ended_utc"] = ""
        for gname, datasets in LAYOUT.items():
            g = f.create_group(gname)
            for dname, (shape, dtype, units) in datasets.items():
                d = g.create_dataset(dname, shape=(0, *shape), maxshape=(None, *shape), dtype=dtype,
                                     chunks=(_CHUNK_ROWS[gname], *shape))
                d.attrs["units"] = units
        f["imu"].attrs["sample_rate_hz"] = float(imu_rate_hz)
        tg = f.create_group("truth")
        if truth is not None:
            tg.attrs["params_json"] = json.dumps(truth)
        f.create_group("results")
        f.swmr_mode = True
        self._f = f

    # -- appending ---------------------------------------------------------------------------
    def _put(self, group: str, columns: dict[str, Any], rows: int) -> None:
        for name, value in columns.items():
            self._buf[group][name].append(np.asarray(value))
        self._buffered_rows += rows

    def append_imu(self, block: ImuBlock) -> None:
        n = len(block)
        if n == 0:
            return
        self._put("imu", {"time": block.time, "counter": block.counter,
                          "specific_force": block.specific_force, "angular_rate": block.angular_rate,
                          "temperature": block.temperature}, n)
        self.n_imu += n
        self.maybe_flush()

    def append_table(self, s: TableState) -> None:
        self._put("table", {"time": [s.time], "angle": [s.angle], "rate": [s.rate],
                            "status": [s.status_word]}, 1)

    def append_pulses(self, p: Pulses) -> None:
        n = len(p)
        if n == 0:
            return
        week = p.gps_week if len(p.gps_week) == n else np.full(n, -1, np.int32)
        sec = p.gps_seconds if len(p.gps_seconds) == n else np.full(n, np.nan)
        self._put("pulses", {"time": p.time, "gps_week": week, "gps_seconds": sec,
                             "source": np.full(n, p.source.encode(), dtype="S16")}, n)

    def add_segment(self, seg: Segment) -> None:
        cols = {k: [getattr(seg, k)] for k in LAYOUT["segments"]}
        for k in ("kind", "label", "status"):
            cols[k] = [str(getattr(seg, k)).encode()[:48]]
        self._put("segments", cols, 1)
        self.n_segments += 1
        self.flush()

    def add_event(self, t: float, kind: str, message: str) -> None:
        self._put("events", {"time": [t], "kind": [kind.encode()[:16]],
                             "message": [message.encode("utf-8", "replace")[:200]]}, 1)
        self.flush()

    # -- writing -----------------------------------------------------------------------------
    def maybe_flush(self) -> None:
        if (self._buffered_rows >= self.max_buffer_rows
                or time.monotonic() - self._last_flush >= self.flush_interval_s):
            self.flush()

    def flush(self) -> None:
        """Append every buffered row to the file and flush it to disk."""
        if self.closed:
            return
        f = self._f
        for gname, cols in self._buf.items():
            if not any(cols.values()):
                continue
            for dname, parts in cols.items():
                data = np.concatenate(parts) if len(parts) > 1 else parts[0]  # rows first
                ds = f[gname][dname]
                n0 = ds.shape[0]
                ds.resize(n0 + data.shape[0], axis=0)
                ds[n0:] = data
                parts.clear()
        self._buffered_rows = 0
        f.flush()
        self._last_flush = time.monotonic()

    def close(self, status: str = "complete") -> None:
        """Write what is buffered, set /run/status and the end time, close the file."""
        if self.closed:
            return
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}")
        self.flush()
        self._f["run/status"][0] = status.encode()
        self._f.flush()
        self._f.close()
        self.closed = True
        with h5py.File(self.path, "r+", libver="latest") as f:
            f["meta"].attrs["ended_utc"] = utc_now()


def write_results(path: str | Path, name: str, payload: dict[str, Any],
                  arrays: dict[str, np.ndarray] | None = None, schema_version: int = 1) -> None:
    """Store a solver's results in /results/<name> of a closed recording (replacing old ones)."""
    with h5py.File(path, "r+", libver="latest") as f:
        res = f.require_group("results")
        if name in res:
            del res[name]
        g = res.create_group(name)
        g.attrs["schema_version"] = schema_version
        g.attrs["created_utc"] = utc_now()
        g.attrs["json"] = json.dumps(payload)
        for key, arr in (arrays or {}).items():
            g.create_dataset(key, data=np.asarray(arr))
