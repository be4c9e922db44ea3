"""Sensor front end: internal-rate low-pass, decimation, ADC quantization (LSB), range and saturation.

Signal path for one 3-axis sensor (gyro or accelerometer)::

    x (internal rate fi = L * fs) --Butterworth low-pass (order n, -3 dB at bandwidth_hz)-->
    keep every L-th sample (the last of each group of L) --> [noise added by the caller] -->
    ADC: y_q = lsb * round(y / lsb), clipped to [-range, +range]  (saturation)

The filter state (scipy ``sosfilt`` zi) is carried across blocks, and initialised on the first
block to the steady state for its first sample (no start-up transient), so the output is the same
whether a record is processed in one block or many (blocks must hold a multiple of L samples).
scipy.signal (~0.65 s of CPU to import) is imported only by a front end with a low-pass.
Bandwidth None means no filter (pure decimation); lsb 0/None means no quantization; range
None/inf means no saturation. Units are those of the signal (rad/s or m/s^2).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np


class FrontEnd:
    """Low-pass + decimation + ADC for one 3-axis sensor.

    Parameters: output_rate_hz (fs), internal_rate_hz (fi, an integer multiple of fs; default fs),
    bandwidth_hz (-3 dB corner of a Butterworth low-pass at fi, must be < fi/2), order (filter
    order), lsb (ADC step per axis, signal unit), full_scale (saturation level per axis, signal unit).
    """

    def __init__(self, output_rate_hz: float, internal_rate_hz: float | None = None,
                 bandwidth_hz: float | None = None, order: int = 2,
                 lsb: float | Sequence[float] | None = None,
                 full_scale: float | Sequence[float] | None = None):
        self.output_rate_hz = float(output_rate_hz)
        self.internal_rate_hz = float(internal_rate_hz or output_rate_hz)
        ratio = self.internal_rate_hz / self.output_rate_hz
        self.decimation = int(round(ratio))
        if self.decimation < 1 or abs(ratio - self.decimation) > 1e-9:
            raise ValueError("internal_rate_hz must be an integer multiple of output_rate_hz")
        self.bandwidth_hz = None if bandwidth_hz in (None, 0) else float(bandwidth_hz)
        self.order = int(order)
        self._sos = None
        if self.bandwidth_hz is not None:
            if not 0 < self.bandwidth_hz < self.internal_rate_hz / 2:
                raise ValueError("bandwidth_hz must lie in (0, internal_rate_hz/2)")
            from scipy import signal

            self._sos = signal.butter(self.order, self.bandwidth_hz, fs=self.internal_rate_hz, output="sos")
        self.lsb = np.broadcast_to(np.asarray(lsb if lsb is not None else 0.0, dtype=float), (3,)).copy()
        fsc = np.inf if full_scale is None else full_scale
        self.full_scale = np.broadcast_to(np.asarray(fsc, dtype=float), (3,)).copy()
        self._zi: np.ndarray | None = None
        self.saturated_count = np.zeros(3, dtype=np.int64)

    # ------------------------------------------------------------------------------------------
    def filter_decimate(self, x: np.ndarray) -> np.ndarray:
        """Low-pass at the internal rate and decimate: (n*L, 3) -> (n, 3)."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] % self.decimation:
            raise ValueError(f"expected (n*{self.decimation}, 3) samples at the internal rate")
        if self._sos is not None and x.shape[0]:
            from scipy import signal

            xt = np.ascontiguousarray(x.T)
            if self._zi is None:
                self._zi = self.steady_state(xt[:, 0])
            xt, self._zi = signal.sosfilt(self._sos, xt, axis=-1, zi=self._zi)
            x = xt.T
        return x[self.decimation - 1 :: self.decimation]

    def steady_state(self, x0: np.ndarray) -> np.ndarray:
        """The low-pass' state (n_sections, 3, 2) at rest on the input x0 (3,): scipy's
        ``sosfilt_zi`` (the state for a unit step) times x0 per axis."""
        from scipy import signal

        return signal.sosfilt_zi(self._sos)[:, None, :] * np.asarray(x0)[None, :, None]

    def digitize(self, y: np.ndarray) -> np.ndarray:
        """ADC: round to the LSB per axis, then clip to +-full_scale (counts saturations)."""
        y = np.array(y, dtype=np.float64)
        for ax in range(3):
            if self.lsb[ax] > 0:
                y[:, ax] = np.round(y[:, ax] / self.lsb[ax]) * self.lsb[ax]
        if np.all(np.isfinite(self.full_scale)):
            over = np.abs(y) > self.full_scale
            self.saturated_count += over.sum(axis=0)
            np.clip(y, -self.full_scale, self.full_scale, out=y)
        return y

    def quantization_white_var(self) -> np.ndarray:
        """Per-sample variance LSB^2/12 the ADC adds (white when the input spans several LSB)."""
        return self.lsb**2 / 12.0

    def frequency_response(self, f_hz: np.ndarray) -> np.ndarray:
        """Complex response of the low-pass at frequencies f_hz (1 when there is no filter)."""
        f_hz = np.asarray(f_hz, dtype=float)
        if self._sos is None:
            return np.ones_like(f_hz, dtype=complex)
        from scipy import signal

        return signal.sosfreqz(self._sos, worN=f_hz, fs=self.internal_rate_hz)[1]

    def truth(self, prefix: str, unit: str) -> dict:
        """JSON-serialisable description, keys carry units."""
        return {
            f"{prefix}_internal_rate_hz": self.internal_rate_hz,
            f"{prefix}_output_rate_hz": self.output_rate_hz,
            f"{prefix}_lowpass_bandwidth_hz": self.bandwidth_hz,
            f"{prefix}_lowpass_order": self.order if self.bandwidth_hz else None,
            f"{prefix}_lowpass_type": "butterworth" if self.bandwidth_hz else None,
            f"{prefix}_lsb_{unit}": self.lsb.tolist(),
            f"{prefix}_full_scale_{unit}": [None if not np.isfinite(v) else float(v) for v in self.full_scale],
        }
