"""A few minutes of decimated IMU and table data for live views (the daemon's web page).

The engine hands every IMU block and table reading it records to :meth:`LiveFeed.add_imu` and
:meth:`LiveFeed.add_table` (engine thread); readers (the HTTP server's threads) take the points
newer than a sequence number with :meth:`LiveFeed.since`. IMU samples are averaged over bins of
``bin_s`` seconds of IMU time (a boxcar: the plot shows the mean of each bin, not a picked
sample); the table is kept at one reading per bin. Memory is bounded by ``history_s / bin_s``
points per stream. SI units inside (m/s^2, rad/s, rad); the web page converts for display.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Any

import numpy as np


class LiveFeed:
    def __init__(self, bin_s: float = 0.1, history_s: float = 300.0) -> None:
        self.bin_s, self.history_s = float(bin_s), float(history_s)
        n = max(1, int(round(history_s / bin_s)))
        self._lock = threading.Lock()
        self.imu: deque[tuple[int, float, list[float], list[float], float]] = deque(maxlen=n)
        self.table: deque[tuple[int, float, list[float], list[float]]] = deque(maxlen=n)
        self.seq = 0
        self.samples = 0            # IMU samples seen (all, before decimation)
        self._bin_k: float | None = None  # index of the open bin (IMU time / bin_s, floored)
        self._sum = np.zeros(7)     # accel 3, gyro 3, temperature
        self._n = 0
        self._table_t: float | None = None

    def reset(self) -> None:
        """A new run: drop the partial bin (history stays; times restart with the run)."""
        with self._lock:
            self._bin_k, self._n, self._table_t = None, 0, None
            self._sum[:] = 0.0

    def add_imu(self, block: Any) -> None:
        n = len(block)
        if n == 0:
            return
        t = np.asarray(block.time, float)
        vals = np.column_stack([np.asarray(block.specific_force, float), np.asarray(block.angular_rate, float),
                                np.asarray(block.temperature, float)])
        keys = np.floor(t / self.bin_s)  # a sample's bin is its key: no float comparison of edges
        finite = np.isfinite(keys)
        with self._lock:
            self.samples += n
            if not finite.all():
                keys, vals = keys[finite], vals[finite]
            # runs of equal keys: each run adds to the open bin, a new key emits it first
            starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]]) if len(keys) else []
            bounds = list(starts) + [len(keys)]
            for a, b in zip(bounds[:-1], bounds[1:]):
                k = float(keys[a])
                if self._bin_k is not None and k != self._bin_k:
                    self._emit()
                self._bin_k = k
                self._sum += vals[a:b].sum(axis=0)
                self._n += b - a

    def _emit(self) -> None:
        if self._n:
            m = self._sum / self._n
            self.seq += 1
            self.imu.append((self.seq, (self._bin_k + 0.5) * self.bin_s, _finite(m[0:3]), _finite(m[3:6]),
                             _finite(m[6:7])[0]))
        self._sum[:] = 0.0
        self._n = 0

    def add_table(self, state: Any) -> None:
        t = float(state.time)
        with self._lock:
            if self._table_t is not None and 0 <= t - self._table_t < self.bin_s:
                return
            self._table_t = t
            self.seq += 1
            self.table.append((self.seq, t, _finite(state.angle), _finite(state.rate)))

    def since(self, seq: int, limit: int = 3000) -> dict[str, Any]:
        """Points with a sequence number above ``seq`` (at most ``limit`` per stream, newest)."""
        with self._lock:
            imu = [p for p in self.imu if p[0] > seq][-limit:]
            table = [p for p in self.table if p[0] > seq][-limit:]
            last = self.seq
        return {"seq": last, "samples": self.samples, "bin_s": self.bin_s,
                "imu": [{"t": t, "f": f, "w": w, "temp": c} for _s, t, f, w, c in imu],
                "table": [{"t": t, "angle": a, "rate": r} for _s, t, a, r in table]}


def _finite(values: Any) -> list[float | None]:
    """Plain floats, None for NaN/inf (JSON has no NaN)."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, float).ravel()]
