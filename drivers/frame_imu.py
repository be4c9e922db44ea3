"""Declarative frame IMU driver: any IMU whose stream the rig config describes
(:mod:`rigctl.config.frame_spec`), decoded by :mod:`rigctl.drivers.frame_decl`, behind the engine's
:class:`rigctl.devices.Imu`. The device is not commanded (it streams on its own); its identity
is what the config says (``imu: serial:``), since such a frame carries none.

Device time: the ``time`` field (x scale x unit, unwrapped at its integer type's range) when
the frame has one, else the ``counter`` (unwrapped at its type's range) / ``rate_hz``.
"""
from __future__ import annotations

import numpy as np

from rigctl.config.frame_spec import FrameSpec
from rigctl.sensor_axes import ACCEL_AXES, GYRO_AXES

from . import frame_decl
from .stream_imu import StreamImu

PROTOCOL = "declarative frame"


class _Unwrap:
    def __init__(self, wrap: int | None) -> None:
        self.wrap, self.prev_raw, self.base = wrap, None, 0

    def __call__(self, raw: np.ndarray) -> np.ndarray:
        if self.wrap is None or not raw.size:
            return raw.astype(np.float64)
        prev = self.prev_raw if self.prev_raw is not None else int(raw[0])
        d = np.diff(np.concatenate(([prev], raw))) % self.wrap
        # a step of more than half the range is a counter going backwards: keep it negative
        d = np.where(d > self.wrap // 2, d - self.wrap, d)
        ext = self.base + np.cumsum(d) if self.prev_raw is not None else int(raw[0]) + np.cumsum(d)
        self.prev_raw, self.base = int(raw[-1]), int(ext[-1])
        return ext.astype(np.float64)


class FrameImu(StreamImu):
    """An IMU streaming the frames ``spec`` describes, over ``url``."""

    protocol = PROTOCOL

    def __init__(self, url: str, spec: FrameSpec, rate_hz: float, clock, *, baudrate: int = 115_200,
                 timeout_s: float = 0.5, align_wait_s: float = 0.02, link_timeout_s: float = 2.0,
                 learn_s: float = 0.2, name: str = "imu") -> None:
        self.spec = spec
        tf, cf = spec.field("time"), spec.field("counter")
        self._time_field, self._counter_field = tf, cf
        self._unwrap = _Unwrap(tf.wrap if tf is not None else cf.wrap if cf is not None else None)
        super().__init__(url, rate_hz, clock, baudrate=baudrate, timeout_s=timeout_s, align_wait_s=align_wait_s,
                         link_timeout_s=link_timeout_s, learn_s=learn_s, name=name)
        sync = spec.sync.hex(" ").upper() if spec.format == "binary" else spec.prefix or "csv"
        self.identity = {"device_id": "", "protocol": f"{PROTOCOL} ({spec.format}, {sync})"}

    def _new_stream(self):
        return frame_decl.decoder(self.spec)

    def _device_time(self, out: dict) -> np.ndarray:
        if self._time_field is not None:
            raw = out["time"]
            if raw.dtype.kind == "i":
                return self._unwrap(raw) * self._time_field.factor
            return raw
        return self._unwrap(out["counter"]) / self.rate_hz

    def _inertial(self, out: dict):
        n = len(out["offset"])
        acc = np.stack([out[a] for a in ACCEL_AXES], axis=1)  # fields decoded under the axes' one spelling
        gyr = np.stack([out[g] for g in GYRO_AXES], axis=1)
        temp = out["temperature"] if "temperature" in out else np.full(n, np.nan)
        return acc, gyr, temp

    def _configure_device(self) -> None:
        if self.configurations == 0:
            self._discard_preconfig()
            self._unwrap = _Unwrap(self._unwrap.wrap)

    def identify(self) -> str:
        """Open the port and wait for one valid frame."""
        self.link.open()
        try:
            st = frame_decl.decoder(self.spec)
            import time
            end = time.monotonic() + max(1.0, 20.0 / self.rate_hz)
            while time.monotonic() < end:
                out = st.feed(self.link.read_some(0.05))
                if len(out["offset"]):
                    return f"{self.identity['protocol']}: frames decode"
        finally:
            self.link.close()
        from rigctl.devices import LinkLost
        raise LinkLost(self.name, f"no valid frame from {self.link.url}")


__all__ = ["FrameImu", "PROTOCOL"]
