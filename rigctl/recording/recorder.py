"""HDF5 recorder: IMU samples, table state, pulses, segments, events, truth and metadata.

The layout is documented in docs/data-format.md (schema version :data:`SCHEMA_VERSION`). Every
dataset is created up front, chunked and extendable, and the file is switched to SWMR mode so
another process can read a run in progress (``h5py.File(path, "r", libver="latest",
swmr=True)``). The file is built under a temporary name and renamed into place once it is in
SWMR mode, so a ``recording.h5`` that exists is always openable. Data are buffered in memory
(at most ``flush_interval_s`` of wall time, or ``max_buffer_rows``) and appended, then flushed,
so a crash loses at most that much. ``/run/status`` says whether a run completed; a file left at
``running`` was cut off.

Crash safety: after ``kill -9`` a reader opens the file with ``swmr=True``; :meth:`Recorder.reopen`
clears HDF5's status flags (:func:`rigctl.recording.checkpoint.clear_status_flags`) and appends to the same
file, shifting the new session's times and IMU counters past what is already recorded.

Truth drawn during a run: an emulator's truth object (a dict) may also carry ``truth_tables``
({table: {column: (per-row shape, dtype, units)}}, created as /truth/<table>/<column> at open)
and ``drain_truth_rows()`` (new rows, {table: {column: array}}), appended at every flush.

Disk space: before every write the recorder checks the free space of its filesystem; below
``min_free_bytes`` it holds: it keeps what is buffered, drops (and counts) newly arriving IMU,
table and pulse rows rather than risk a partial write, and reports it as an event once it can
write again.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .. import __version__
from .checkpoint import clear_status_flags
from .shield import shielded
from ..clock import utc_now  # noqa: F401  (re-exported: the recorder's time stamps)
from ..devices import ImuBlock, Pulses, TableState

SCHEMA_VERSION = 1
FORMAT_NAME = "rigctl-recording"
STATUSES = ("running", "complete", "interrupted", "failed")

_STR = {"kind": "S16", "label": "S48", "status": "S16", "source": "S16", "message": "S200"}
#: dtype of /run/status (one of STATUSES)
STATUS_DTYPE = _STR["status"]

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
    "chamber": {  # the climatic chamber, one row per engine poll (empty without a chamber)
        "time": ((), np.float64, "s"),
        "air_c": ((), np.float64, "degC"),
        "product_c": ((), np.float64, "degC"),
        "setpoint_c": ((), np.float64, "degC"),
        "status": ((), _STR["status"], ""),
    },
}
_CHUNK_ROWS = {"imu": 8192, "table": 1024, "pulses": 256, "segments": 64, "events": 64, "chamber": 1024}


#: the longest /events message, bytes of UTF-8 (the dataset's dtype, S200)
EVENT_MESSAGE_BYTES = int(np.dtype(_STR["message"]).itemsize)
#: what ends a shortened part of an event message
ELLIPSIS = "\u2026"


class Elide(str):
    """A part of an event message that :func:`event_text` may shorten (its beginning kept, an
    ellipsis after it) to keep the message within :data:`EVENT_MESSAGE_BYTES`: a step label, a
    reason quoted from another message -- never what happened or what to do."""


def _utf8(text: str) -> bytes:
    return text.encode("utf-8", "replace")


def shorten(text: str, limit: int) -> str:
    """``text`` within ``limit`` bytes of UTF-8: whole when it fits, else its beginning and
    :data:`ELLIPSIS` (no character cut in two; "" when not even the ellipsis fits)."""
    b = _utf8(text)
    if len(b) <= limit:
        return text
    keep = limit - len(_utf8(ELLIPSIS))
    return b[:keep].decode("utf-8", "ignore") + ELLIPSIS if keep >= 0 else ""


def event_text(*parts: str, limit: int = EVENT_MESSAGE_BYTES) -> str:
    """The event message of ``parts`` joined, within ``limit`` bytes of UTF-8: when it is longer,
    the :class:`Elide` parts are shortened (:func:`shorten`), the longest first, to one common
    length c -- the largest with sum_i min(n_i, c) <= the bytes the other parts leave -- so the
    other parts (what happened, what to do) stay whole. Only when those alone exceed ``limit`` is
    the end cut (with an ellipsis, as :meth:`Recorder.add_event` cuts any message)."""
    sizes = [len(_utf8(p)) for p in parts]
    if sum(sizes) <= limit:
        return "".join(parts)
    cut = [i for i, p in enumerate(parts) if isinstance(p, Elide)]
    left = limit - sum(n for i, n in enumerate(sizes) if i not in cut)
    cap, ns = max(0, left), sorted(sizes[i] for i in cut)
    for k, n in enumerate(ns):   # water-filling: the parts shorter than the cap keep their length
        if n * (len(ns) - k) > left:
            cap = max(0, left) // (len(ns) - k)
            break
        left -= n
    return shorten("".join(shorten(p, cap) if i in cut else p for i, p in enumerate(parts)), limit)


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


def library_versions() -> dict[str, str]:
    import importlib.metadata
    import platform

    import scipy
    import serial
    import yaml

    try:  # the installed distribution's version: importing pymodbus to read it cost ~0.1 s of CPU
        # in every run (an emulated rig does not use it); the same string as pymodbus.__version__
        pm = (sys.modules["pymodbus"].__version__ if "pymodbus" in sys.modules
              else importlib.metadata.version("pymodbus"))
    except Exception as exc:  # noqa: BLE001 - report, don't fail a run on a version probe
        pm = f"unavailable ({type(exc).__name__})"
    return {"rigctl": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "h5py": h5py.__version__, "hdf5": h5py.version.hdf5_version,
            "pyserial": serial.__version__, "pymodbus": pm, "pyyaml": yaml.__version__}


class Recorder:
    """Append-only, crash-safe writer of one run's recording."""

    def __init__(self, path: str | Path, meta: dict[str, Any], truth: dict[str, Any] | None = None,
                 imu_rate_hz: float = 0.0, flush_interval_s: float = 0.5,
                 max_buffer_rows: int = 1 << 18, min_free_bytes: int = 0) -> None:
        self._init_state(path, flush_interval_s, max_buffer_rows, min_free_bytes)
        part = self.path.with_name(self.path.name + ".part")
        f = h5py.File(part, "w", libver="latest")
        f.attrs["format"] = FORMAT_NAME
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["rigctl_version"] = __version__
        run = f.create_group("run")
        run.create_dataset("status", data=np.array([b"running"], dtype=STATUS_DTYPE))
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
        # truth drawn during the run (emulator): its tables must exist before SWMR mode
        self._truth_rows = getattr(truth, "drain_truth_rows", None)
        for tname, cols in (getattr(truth, "truth_tables", None) or {}).items():
            g = tg.create_group(tname)
            for dname, (shape, dtype, units) in cols.items():
                d = g.create_dataset(dname, shape=(0, *shape), maxshape=(None, *shape), dtype=dtype,
                                     chunks=(256, *shape))
                d.attrs["units"] = units
        f.create_group("results")
        f.swmr_mode = True
        f.flush()
        os.replace(part, self.path)  # appears only once complete and in SWMR mode
        self._f = f

    def _init_state(self, path: str | Path, flush_interval_s: float, max_buffer_rows: int,
                    min_free_bytes: int) -> None:
        self.path = Path(path)
        self.flush_interval_s = flush_interval_s
        self.max_buffer_rows = max_buffer_rows
        self.min_free_bytes = int(min_free_bytes)
        self._buf: dict[str, dict[str, list[np.ndarray]]] = {g: {d: [] for d in ds} for g, ds in LAYOUT.items()}
        self._buffered_rows = 0
        self._last_flush = time.monotonic()
        self.n_imu = 0  # samples appended (buffered or written)
        self.n_segments = 0
        self.closed = False
        #: added to every time written (s) and to every IMU counter, for a resumed session
        self.time_offset = 0.0
        self.counter_offset = 0
        self.holding: str | None = None  # why writes are held (disk space low), else None
        self._truth_rows: Any = None  # callable giving new /truth/<table> rows (emulator), or None
        self.dropped: dict[str, int] = {}
        self._dropped_t: list[float] = []

    @classmethod
    def reopen(cls, path: str | Path, *, imu_rate_hz: float, flush_interval_s: float = 0.5,
               max_buffer_rows: int = 1 << 18, min_free_bytes: int = 0,
               resume_gap_s: float = 1.0) -> "Recorder":
        """Reopen a cut-off (or interrupted) recording to append a new session to it.

        Clears HDF5's status flags left by a crash, trims every group to the rows all its
        datasets have (a crash mid-flush can leave them uneven), sets ``/run/status`` back to
        ``running`` and sets the offsets so the new session's time t (from 0) is written as
        ``time_offset + t`` and IMU counter c as ``counter_offset + c``, where
        ``counter_offset = max(last counter + 1, ceil(last time * rate) + 1) + round(gap * rate)``
        and ``time_offset = counter_offset / rate``: the gap shows as missing samples.
        """
        self = cls.__new__(cls)
        self._init_state(path, flush_interval_s, max_buffer_rows, min_free_bytes)
        clear_status_flags(self.path)
        # straight into SWMR-write mode (status flags 0 -> 5 in one step): a kill during the
        # reopen leaves flags that readers and the next resume accept
        fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
        fapl.set_libver_bounds(h5py.h5f.LIBVER_LATEST, h5py.h5f.LIBVER_LATEST)
        f = h5py.File(h5py.h5f.open(os.fsencode(str(self.path)),
                                    h5py.h5f.ACC_RDWR | h5py.h5f.ACC_SWMR_WRITE, fapl=fapl))
        try:
            if f.attrs.get("format") != FORMAT_NAME:
                raise ValueError(f"{self.path} is not a rigctl recording")
            last_t = 0.0
            for gname in LAYOUT:
                if gname not in f:  # a recording from before the group existed (chamber)
                    continue
                g = f[gname]
                n = min(g[d].shape[0] for d in LAYOUT[gname])
                for d in LAYOUT[gname]:
                    if g[d].shape[0] != n:
                        g[d].resize(n, axis=0)
                tcol = {"segments": "t_end"}.get(gname, "time")
                if n:
                    last_t = max(last_t, float(np.nanmax(g[tcol][max(0, n - 64):n])))
            self.n_imu = int(f["imu/time"].shape[0])
            self.n_segments = int(f["segments/kind"].shape[0])
            last_c = int(f["imu/counter"][-1]) if self.n_imu else -1
            rate = float(imu_rate_hz) or float(f["imu"].attrs.get("sample_rate_hz", 0.0)) or 1.0
            c0 = max(last_c + 1, math.ceil(last_t * rate) + 1) + round(resume_gap_s * rate)
            self.counter_offset, self.time_offset = int(c0), c0 / rate
            f["run/status"][0] = b"running"
            f["meta"].attrs["ended_utc"] = ""
            f.flush()
        except Exception:
            f.close()
            raise
        self._f = f
        return self

    def last_times(self) -> dict[str, float]:
        """Last written time of each group on the file's time base, s (NaN when empty)."""
        out = {}
        for g, col in (("imu", "time"), ("table", "time"), ("events", "time")):
            ds = self._f[g][col]
            out[g] = float(ds[-1]) if ds.shape[0] else math.nan
        return out

    # -- appending ---------------------------------------------------------------------------
    def _put(self, group: str, columns: dict[str, Any], rows: int) -> None:
        for name, value in columns.items():
            self._buf[group][name].append(np.asarray(value))
        self._buffered_rows += rows

    def _drop(self, group: str, n: int, t: Any) -> bool:
        """While writes are held, count and drop incoming rows; True if dropped."""
        if self.holding is None:
            return False
        self.dropped[group] = self.dropped.get(group, 0) + n
        t = np.atleast_1d(np.asarray(t, float))
        if t.size:
            lo, hi = float(t.min()), float(t.max())
            if self._dropped_t:
                lo, hi = min(lo, self._dropped_t[0]), max(hi, self._dropped_t[1])
            self._dropped_t = [lo, hi]
        self.maybe_flush()
        return True

    def append_imu(self, block: ImuBlock) -> None:
        n = len(block)
        if n == 0:
            return
        if self._drop("imu", n, block.time + self.time_offset):
            return
        counter = block.counter + np.uint64(self.counter_offset) if self.counter_offset else block.counter
        self._put("imu", {"time": block.time + self.time_offset, "counter": counter,
                          "specific_force": block.specific_force, "angular_rate": block.angular_rate,
                          "temperature": block.temperature}, n)
        self.n_imu += n
        self.maybe_flush()

    def append_table(self, s: TableState) -> None:
        if self._drop("table", 1, s.time + self.time_offset):
            return
        self._put("table", {"time": [s.time + self.time_offset], "angle": [s.angle], "rate": [s.rate],
                            "status": [s.status_word]}, 1)

    def append_chamber(self, s: Any) -> None:
        """One chamber reading (rigctl.config.chamber.ChamberState)."""
        if self._drop("chamber", 1, s.time + self.time_offset):
            return
        self._put("chamber", {"time": [s.time + self.time_offset], "air_c": [s.air_c],
                              "product_c": [s.product_c], "setpoint_c": [s.setpoint_c],
                              "status": [s.status.encode()[:16]]}, 1)

    def append_pulses(self, p: Pulses) -> None:
        n = len(p)
        if n == 0:
            return
        if self._drop("pulses", n, p.time + self.time_offset):
            return
        week = p.gps_week if len(p.gps_week) == n else np.full(n, -1, np.int32)
        sec = p.gps_seconds if len(p.gps_seconds) == n else np.full(n, np.nan)
        self._put("pulses", {"time": p.time + self.time_offset, "gps_week": week, "gps_seconds": sec,
                             "source": np.full(n, p.source.encode(), dtype="S16")}, n)

    def add_segment(self, seg: Segment, file_time: bool = False, flush: bool = True) -> None:
        """Append a segment row; its times are session times unless ``file_time``. The row is
        flushed to the file at once (a live run's segment boundary is on disk) unless ``flush``
        is false: a writer of a whole recording at once (an import) flushes on close."""
        cols = {k: [getattr(seg, k)] for k in LAYOUT["segments"]}
        for k in ("kind", "label", "status"):
            cols[k] = [str(getattr(seg, k)).encode()[:48]]
        if not file_time:
            cols["t_start"] = [seg.t_start + self.time_offset]
            cols["t_end"] = [seg.t_end + self.time_offset]
        self._put("segments", cols, 1)
        self.n_segments += 1
        if flush:
            self.flush()

    def add_event(self, t: float, kind: str, message: str, file_time: bool = False) -> None:
        """Append an event at session time ``t`` (file time if ``file_time``), s. A message longer
        than :data:`EVENT_MESSAGE_BYTES` is cut at its end with an ellipsis (:func:`shorten`);
        one built by :func:`event_text` fits already."""
        t = t if file_time else t + self.time_offset
        self._put("events", {"time": [t], "kind": [kind.encode()[:16]],
                             "message": [_utf8(shorten(message, EVENT_MESSAGE_BYTES))]}, 1)
        self.flush()

    # -- writing -----------------------------------------------------------------------------
    def maybe_flush(self) -> None:
        if (self._buffered_rows >= self.max_buffer_rows
                or time.monotonic() - self._last_flush >= self.flush_interval_s):
            self.flush()

    def _disk_ok(self) -> bool:
        """Free space check before a write; sets or clears :attr:`holding`."""
        if self.min_free_bytes <= 0:
            return True
        try:
            free = shutil.disk_usage(self.path.parent).free
        except OSError:
            free = 0
        if free < self.min_free_bytes:
            if self.holding is None:
                self.holding = (f"disk space low: {free / 2**20:.2f} MiB free on {self.path.parent}, "
                                f"below the recorder's reserve of {self.min_free_bytes / 2**20:.2f} "
                                "MiB; writes held until space is freed")
            self._last_flush = time.monotonic()
            return False
        if self.holding is not None:
            self.holding = None
            if self.dropped:
                t = self._dropped_t or [math.nan, math.nan]
                what = ", ".join(f"{n} {g} rows" for g, n in self.dropped.items())
                self._put("events", {"time": [t[0]], "kind": [b"data-lost"], "message": [
                    f"not recorded while the disk was full: {what}, t {t[0]:.3f}..{t[1]:.3f} s"
                    .encode()[:200]]}, 1)
            self.dropped, self._dropped_t = {}, []
        return True

    def flush(self) -> None:
        """Append every buffered row to the file and flush it to disk."""
        if self.closed or not self._disk_ok():
            return
        # Each dataset is opened for its write and closed after it, as before (datasets held open
        # between flushes change where HDF5 puts its metadata: the same contents in other bytes),
        # through h5py's low-level calls: its high-level path lookup, resize and write cost
        # ~7 ms of CPU per flush in Python, paid at every segment, event and buffer flush
        f = self._f
        if self._truth_rows is not None:  # truth the emulator drew since the last flush
            for tname, cols in self._truth_rows().items():
                gid = h5py.h5g.open(f.id, f"truth/{tname}".encode())
                try:
                    for dname, data in cols.items():
                        _append(gid, dname, data)
                finally:
                    gid.close()
        for gname, cols in self._buf.items():
            if not any(cols.values()):
                continue
            if gname not in f:
                for parts in cols.values():
                    parts.clear()
                continue
            gid = h5py.h5g.open(f.id, gname.encode())
            try:
                for dname, parts in cols.items():
                    data = np.concatenate(parts) if len(parts) > 1 else parts[0]  # rows first
                    _append(gid, dname, data)
                    parts.clear()
            finally:
                gid.close()
        self._buffered_rows = 0
        f.flush()
        self._last_flush = time.monotonic()

    def close(self, status: str = "complete") -> None:
        """Write what is buffered, set /run/status and the end time, close the file.

        The status is written even when the last flush fails (a disk error): then it is
        ``failed`` (a ``complete`` run whose last rows could not be written is not complete),
        the buffered rows are dropped, the file is closed, and the flush's error is raised."""
        if self.closed:
            return
        if status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}")
        error: OSError | None = None
        try:
            try:
                if self._disk_ok():
                    self.flush()
                    self._f["meta"].attrs["ended_utc"] = utc_now()
                else:  # disk still full: keep what is on disk consistent, drop the buffer
                    self._clear_buffer()
            except OSError as exc:
                error = exc
                self._clear_buffer()
                status = "failed" if status == "complete" else status
            self._f["run/status"][0] = status.encode()  # in place: needs no new space
            self._f.flush()
        finally:
            try:
                self._f.close()
            finally:
                self.closed = True
        if error is not None:
            raise error

    def _clear_buffer(self) -> None:
        for cols in self._buf.values():
            for parts in cols.values():
                parts.clear()
        self._buffered_rows = 0


def _append(group: h5py.h5g.GroupID, name: str, data: Any) -> None:
    """Append ``data``'s rows to dataset ``name`` of ``group`` (extendable along its first axis),
    opened for the write and closed after it: the HDF5 calls of h5py's ``ds = group[name];
    ds.resize(n0 + n, axis=0); ds[n0:] = data`` (the same extent, the same hyperslab, the same
    memory type -- an array's own dtype, converted by HDF5; anything else first made an array of
    the dataset's dtype), without the high-level wrapper's per-call Python cost."""
    ds = h5py.h5d.open(group, name.encode())
    try:
        if not isinstance(data, np.ndarray):
            data = np.asarray(data, order="C", dtype=ds.dtype)
        data = np.ascontiguousarray(data)
        shape = ds.shape
        n0, n = shape[0], data.shape[0]
        ds.set_extent((n0 + n, *shape[1:]))
        if n == 0:
            return
        if data.shape[1:] != tuple(shape[1:]):
            raise ValueError(f"{name}: rows of shape {data.shape[1:]} for a dataset of rows {tuple(shape[1:])}")
        fspace = ds.get_space()
        fspace.select_hyperslab((n0, *(0 for _ in shape[1:])), data.shape)
        ds.write(h5py.h5s.create_simple(data.shape), fspace, data)
    finally:
        ds.close()


def write_results(path: str | Path, name: str, payload: dict[str, Any],
                  arrays: dict[str, tuple[Any, str]] | None = None, schema_version: int = 1) -> None:
    """Store a solver's results in /results/<name> of a closed recording (replacing old ones).

    Args:
        payload: JSON-serialisable summary (units in the key names), stored as attribute ``json``.
        arrays: datasets as ``{name: (data, units)}``; every dataset gets its ``units`` attribute.

    Written whole even when an interruption arrives meanwhile (:func:`rigctl.recording.shield.shielded`).
    """
    with shielded(), h5py.File(path, "r+", libver="latest") as f:
        res = f.require_group("results")
        if name in res:
            del res[name]
        g = res.create_group(name)
        g.attrs["schema_version"] = schema_version
        g.attrs["created_utc"] = utc_now()
        g.attrs["json"] = json.dumps(payload)
        for key, (arr, units) in (arrays or {}).items():
            g.create_dataset(key, data=np.asarray(arr)).attrs["units"] = units
