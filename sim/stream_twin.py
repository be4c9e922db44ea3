"""Base of the emulated streaming IMUs other than Xsens (VectorNav, declarative frame): a pty, a
measurement state, frames on the world's sample grid stepped by the IMU stream thread, and byte
errors injected as a renewal process over the byte stream (as :class:`HwXsensServer`), with
``frames_hit`` counting the frames that received at least one error.

A subclass provides ``_frames(k, t, src) -> (n, L) uint8`` (one row per sample: the frames all
have one length; frames of different lengths come as one row, with ``_line_ends`` the end
offset of each) and, for a commanded device, ``_on_data``.
"""
from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import numpy as np

from .links import PtyEndpoint

MAX_BATCH = 20000


class StreamTwin:
    grid_rate_hz = 100.0

    def __init__(self, source: Callable[[np.ndarray], dict], clock: Callable[[], float], rate_hz: float,
                 seed: int = 0, streaming: bool = False, name: str = "imu-pty") -> None:
        self.source, self.clock, self.rate_hz = source, clock, float(rate_hz)
        self.t_origin = self.clock()
        self.true_clock: Callable[[], float] | None = None
        self.byte_error_rate, self._rng = 0.0, np.random.default_rng(seed)
        self.frames_sent = self.frames_hit = self.errors_injected = 0
        self.measurement_starts: list[float] = []
        self.state = "config"
        self._t0, self._k = 0.0, 0
        self._lock = threading.RLock()
        self._err_pending: np.ndarray | None = None
        self._err_values = np.empty(0, np.uint8)
        self._err_next = 0
        self._stream_bytes = 0
        self.port = PtyEndpoint(self._on_data, name=name)
        self.path = self.port.path
        if streaming:
            self._enter_measurement()

    # ----------------------------------------------------------------------- subclass
    def _on_data(self, data: bytes, write: Callable[[bytes], None]) -> None:
        """Bytes from the client (ignored by a device that takes no commands)."""

    def _frames(self, k: np.ndarray, t: np.ndarray, src: dict) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    # ---------------------------------------------------------------------- streaming
    def _enter_measurement(self) -> None:
        g = self.grid_rate_hz
        now = self.true_clock() if self.true_clock is not None else self.clock()
        self._t0, self._k = math.ceil(now * g - 1e-9) / g, 0
        self.state = "measurement"
        self.measurement_starts.append(time.monotonic())

    def next_time(self) -> float | None:
        """Time of the next frame not yet encoded, s (None when not measuring)."""
        return self._t0 + self._k / self.rate_hz if self.state == "measurement" else None

    def encode(self, k: np.ndarray) -> bytes:
        """Frames of samples ``k`` of the current measurement period, with byte errors."""
        t = self._t0 + k / self.rate_hz
        rows = self._frames(k, t, self.source(t))
        self.frames_sent += len(k)
        rate = self.byte_error_rate
        if rate <= 0:
            self._err_pending = None
            return rows.tobytes()
        out = rows.reshape(-1).copy()
        start = self._stream_bytes
        self._stream_bytes += out.size
        pos, vals = self._error_positions(start, start + out.size, rate)
        if pos.size:
            out[pos - start] ^= vals
            ends = getattr(self, "_line_ends", None)          # variable-length frames (CSV lines)
            idx = (pos - start) // rows.shape[1] if ends is None else np.searchsorted(ends, pos - start, "right")
            self.frames_hit += int(np.unique(idx).size)
            self.errors_injected += int(pos.size)
        return out.tobytes()

    def _error_positions(self, start: int, end: int, rate: float) -> tuple[np.ndarray, np.ndarray]:
        if self._err_pending is None:
            self._err_pending, self._err_values = np.empty(0, np.int64), np.empty(0, np.uint8)
            self._err_next = start
        while not self._err_pending.size or self._err_pending[-1] < end:
            gaps = self._rng.geometric(rate, 4096)
            pos = self._err_next - 1 + np.cumsum(gaps)
            self._err_next = int(pos[-1]) + 1
            self._err_pending = np.concatenate((self._err_pending, pos))
            self._err_values = np.concatenate((self._err_values, self._rng.integers(1, 256, 4096).astype(np.uint8)))
        m = int(np.searchsorted(self._err_pending, end))
        keep = self._err_pending[:m] >= start
        pos, vals = self._err_pending[:m][keep], self._err_values[:m][keep]
        self._err_pending, self._err_values = self._err_pending[m:], self._err_values[m:]
        return pos, vals

    def step(self, until: float) -> int:
        """Encode and send every frame due up to time ``until`` (at most MAX_BATCH)."""
        with self._lock:
            if self.state != "measurement":
                return 0
            n = min(max(int(math.floor((until - self._t0) * self.rate_hz + 1e-9)) + 1 - self._k, 0), MAX_BATCH)
            if n == 0:
                return 0
            k = self._k + np.arange(n)
            frames = self.encode(k)
            self._k += n        # only once encoded: see HwXsensServer._step (sim/hardware.py)
        self.port.write(frames)
        return n

    def close(self) -> None:
        self.port.close()


__all__ = ["MAX_BATCH", "StreamTwin"]
