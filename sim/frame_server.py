"""Emulated IMU that streams the frames of a declarative description (rigctl.config.frame_spec) on a
pty, from the moment it is powered (it takes no commands), at ``rate_hz`` on the world's grid.

Field values: ``counter`` = sample number since power-up (wraps at its type), ``time`` = device
time (t - t_origin + ``time_offset_s``) in the field's unit (wraps at its integer type),
accelerations / rates / temperature from the world, quantised by the field's type and scale as
a real sensor's output is.

:data:`EXAMPLE` is the binary frame docs/hardware.md shows (and ``rigctl sim up --imu frame``
serves); :data:`EXAMPLE_CSV` the CSV-line example.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rigctl.drivers import frame_decl
from rigctl.config.frame_spec import FrameSpec
from rigctl.sensor_axes import ACCEL_AXES, GYRO_AXES

from .stream_twin import StreamTwin

#: the binary example of docs/hardware.md, as a config mapping (the ``frame:`` of an imu section)
EXAMPLE = {
    "sync": "AA 55",
    "endian": "little",
    "fields": [
        {"name": "length", "type": "B"},
        {"name": "counter", "type": "H"},
        {"name": "time", "type": "I", "scale": 1.0e-6, "unit": "s"},
        {"name": "gx", "type": "i", "scale": 1.0e-8, "unit": "rad/s"},
        {"name": "gy", "type": "i", "scale": 1.0e-8, "unit": "rad/s"},
        {"name": "gz", "type": "i", "scale": 1.0e-8, "unit": "rad/s"},
        {"name": "ax", "type": "i", "scale": 1.0e-7, "unit": "m/s^2"},
        {"name": "ay", "type": "i", "scale": 1.0e-7, "unit": "m/s^2"},
        {"name": "az", "type": "i", "scale": 1.0e-7, "unit": "m/s^2"},
        {"name": "temperature", "type": "h", "scale": 0.01, "unit": "degC"},
        {"name": "status", "type": "B"},
    ],
    "length": {"field": "length", "counts": "frame"},
    "checksum": {"type": "crc16-ccitt", "init": 0xFFFF},
}
EXAMPLE_CSV = {
    "format": "csv",
    "prefix": "$IMU",
    "fields": [
        {"name": "counter"},
        {"name": "gx", "unit": "deg/s"}, {"name": "gy", "unit": "deg/s"},
        {"name": "gz", "unit": "deg/s"},
        {"name": "ax", "unit": "g"}, {"name": "ay", "unit": "g"}, {"name": "az", "unit": "g"},
        {"name": "temperature", "unit": "degC"},
    ],
    "checksum": "nmea",
}


class FrameServer(StreamTwin):
    def __init__(self, spec: FrameSpec, source, clock: Callable[[], float], *, rate_hz: float = 100.0,
                 time_offset_s: float = 3600.0, seed: int = 0) -> None:
        self.spec = spec
        self.time_offset_s = float(time_offset_s)
        self.sample = 0
        super().__init__(source, clock, rate_hz, seed=seed, streaming=True, name="frame-pty")

    def power_cycle(self) -> None:
        """The sensor restarts (its power lost and back): its time since power-up and its sample
        counter begin again from 0 now, and it streams at once (it takes no commands)."""
        with self._lock:
            self._enter_measurement()
            self.t_origin, self.time_offset_s, self.sample = self._t0, 0.0, 0

    def _frames(self, k: np.ndarray, t: np.ndarray, src: dict) -> np.ndarray:
        n = len(k)
        v: dict[str, np.ndarray] = {"counter": self.sample + np.arange(n)}
        self.sample += n
        tf = self.spec.field("time")
        if tf is not None:
            dev = t - self.t_origin + self.time_offset_s
            v["time"] = np.rint(dev / tf.factor).astype(np.int64) if tf.wrap else dev
        acc, gyr = np.asarray(src["acceleration"]), np.asarray(src["rate_of_turn"])
        for j, (a, g) in enumerate(zip(ACCEL_AXES, GYRO_AXES)):
            v[a], v[g] = acc[:, j], gyr[:, j]
        v["temperature"] = np.asarray(src["temperature"])
        if self.spec.format == "binary":
            return frame_decl.encode_binary(self.spec, v)
        # CSV lines differ in length: one row, with the end of each line for the error count
        data = np.frombuffer(frame_decl.encode_csv(self.spec, v), np.uint8)
        self._line_ends = np.flatnonzero(data == 0x0A) + 1
        return data.reshape(1, -1)


__all__ = ["EXAMPLE", "EXAMPLE_CSV", "FrameServer"]
