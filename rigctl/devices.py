"""Device protocols the engine talks to, and the records they return.

Devices are small duck-typed objects (after Bluesky's ``Movable`` / ``Readable``): the engine
never cares whether a turntable is emulated in-process, emulated behind a serial line, or real.

* :class:`Turntable` -- ``move``, ``set_rate``, ``stop``, ``read``, ``check_value``
* :class:`Imu` -- ``read`` returns the samples that arrived since the last call
* :class:`PulseSource` -- ``read`` returns the pulse edges time-stamped since the last call
* :class:`Clock` -- ``now`` and ``sleep`` (virtual, real or scaled)

Table angles and rates are ordered [outer, middle, inner] and are in rad and rad/s.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntFlag
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from .errors import DeviceError


class AxisStatus(IntFlag):
    """Per-axis 16-bit status word (CiA-402 flavoured; docs/modbus-map.md)."""

    READY = 1 << 0
    SERVO_ON = 1 << 1
    OPERATION_ENABLED = 1 << 2
    FAULT = 1 << 3
    INTERLOCK_OPEN = 1 << 4
    QUICK_STOP = 1 << 5
    WARNING = 1 << 7
    PROFILE_COMPLETE = 1 << 8
    AT_RATE = 1 << 9
    TARGET_REACHED = 1 << 10
    LIMIT_ACTIVE = 1 << 11
    SETPOINT_ACK = 1 << 12
    FOLLOWING_ERROR = 1 << 13
    MOVING = 1 << 15
    # aliases used by the register map (rigctl.drivers.modbus_map.StatusBit is this class)
    INTERNAL_LIMIT = LIMIT_ACTIVE
    FOLLOWING_ERROR_TRIP = FOLLOWING_ERROR


@dataclass(frozen=True)
class TableState:
    """A coherent snapshot of the table.

    Attributes:
        time: controller time of the snapshot, s (run time base).
        angle: (3,) measured gimbal angles [outer, middle, inner], rad.
        rate: (3,) measured gimbal rates, rad/s.
        status: (3,) per-axis :class:`AxisStatus` words.
    """

    time: float
    angle: NDArray[np.float64]
    rate: NDArray[np.float64]
    status: tuple[int, int, int]

    def all_have(self, flag: AxisStatus) -> bool:
        return all(int(s) & flag for s in self.status)

    def any_has(self, flag: AxisStatus) -> bool:
        return any(int(s) & flag for s in self.status)

    @property
    def status_word(self) -> int:
        """The three 16-bit axis words packed into one integer: outer | middle << 16 | inner << 32."""
        return int(self.status[0]) | int(self.status[1]) << 16 | int(self.status[2]) << 32


@dataclass
class ImuBlock:
    """IMU samples: ``n`` rows.

    Attributes:
        time: (n,) IMU sample time, s (counter / nominal rate, run time base).
        counter: (n,) sample counter (gaps mean dropped samples).
        specific_force: (n, 3) m/s^2.
        angular_rate: (n, 3) rad/s.
        temperature: (n,) degC.
    """

    time: NDArray[np.float64]
    counter: NDArray[np.uint64]
    specific_force: NDArray[np.float64]
    angular_rate: NDArray[np.float64]
    temperature: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @classmethod
    def empty(cls) -> "ImuBlock":
        return cls(np.empty(0), np.empty(0, np.uint64), np.empty((0, 3)), np.empty((0, 3)),
                   np.empty(0))


@dataclass
class Pulses:
    """Pulse edges time-stamped by a reference clock.

    Attributes:
        time: (p,) reference time of each edge, s (run time base).
        gps_week: (p,) GPS week, -1 where the source gives none.
        gps_seconds: (p,) GPS seconds of week, NaN where none.
        source: label of the source (``gnss``, ``gpio``, ``modem``, ``sim``).
    """

    time: NDArray[np.float64]
    gps_week: NDArray[np.int32] = field(default_factory=lambda: np.empty(0, np.int32))
    gps_seconds: NDArray[np.float64] = field(default_factory=lambda: np.empty(0))
    source: str = "sim"

    def __len__(self) -> int:
        return int(self.time.shape[0])


@runtime_checkable
class Clock(Protocol):
    def now(self) -> float:
        """Current time, s, on the run's time base."""

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of run time pass."""


@runtime_checkable
class Turntable(Protocol):
    def move(self, angles: NDArray[np.float64]) -> None:
        """Position mode on all axes, go to ``angles`` [outer, middle, inner] rad."""

    def set_rate(self, rates: NDArray[np.float64]) -> None:
        """Rate mode on the axes with a non-NaN entry, rad/s; NaN axes hold position."""

    def stop(self) -> None:
        """Controlled stop: rate zero, then mode off. Must return within 1 s."""

    def read(self) -> TableState:
        """A coherent snapshot of angles, rates and status."""

    def check_value(self, angles: NDArray[np.float64] | None, rates: NDArray[np.float64] | None) -> None:
        """Raise ValueError if a demand is outside the table's limits."""


@runtime_checkable
class Imu(Protocol):
    """An IMU. Besides ``read`` it may carry an ``identity`` attribute (optional, duck-typed:
    read it with :func:`imu_identity`), a dict naming the unit under test, valid once the
    device is connected::

        {"device_id": "03780001",      # what the unit reports (Xsens: DeviceID, upper-case hex);
                                       # "" when it cannot tell
         "protocol": "Xsens MT"}       # how it was read ("in-process emulator", ...)

    The recording keeps it (/meta ``imu_device_id``, ``imu_identity_json``) and ``rigctl resume``
    refuses to continue a run on a unit whose non-empty ``device_id`` differs from the
    recording's."""

    def read(self) -> ImuBlock:
        """Samples that arrived since the previous call (possibly none)."""


def imu_identity(imu: object) -> dict[str, str]:
    """``imu.identity`` with a str ``device_id`` (``""`` when unknown) and ``protocol``; a device
    without the attribute (e.g. a third-party Imu) gives ``{"device_id": "", "protocol": ""}``."""
    ident = getattr(imu, "identity", None)
    out = {str(k): v for k, v in ident.items()} if isinstance(ident, dict) else {}
    out["device_id"] = str(out.get("device_id") or "")
    out["protocol"] = str(out.get("protocol") or "")
    return out


def imu_restarts(imu: object) -> int:
    """How many times the IMU itself restarted (its device time began again: it lost power) since
    it was connected, as opposed to link losses after which its time continues: its
    ``device_restarts`` attribute (optional, duck-typed; an int read on every engine poll, so no
    lock or copy: the ``counters`` snapshot carries the same number): StreamImu's rebased
    timelines (drivers/stream_imu.py), the Xsens decoder's SampleTimeFine time bases that began
    behind the last stamp (drivers/xsens_decode.py), the in-process emulator's ``imu_power``
    fault; 0 for a device without it."""
    n = getattr(imu, "device_restarts", 0)
    return int(n) if isinstance(n, (int, float)) else 0


def imu_reconnecting(imu: object) -> bool:
    """Whether the IMU's driver reports its link lost and the device not configured again yet:
    its optional ``link_down_s()`` (wall seconds since the link was lost, None once the link is
    back and the device configured again: drivers/reader_thread.py, ReconnectingReader; duck-typed)
    is not None. Meanwhile ``read`` may still hand out frames received before the
    reconfiguration (an Xsens streams until GoToConfig takes effect). False for a device without it."""
    down = getattr(imu, "link_down_s", None)
    return callable(down) and down() is not None


@runtime_checkable
class PulseSource(Protocol):
    def read(self) -> Pulses:
        """Edges time-stamped since the previous call (possibly none)."""


class LinkLost(DeviceError, ConnectionError):
    """A device link is down (cable pulled, USB reset, socket closed, reply timeout).

    Drivers raise it from ``read`` (or a command) and keep trying to reconnect themselves (with
    backoff) on later calls; the engine treats it as a suspending condition: it pauses the
    procedure, keeps calling ``read`` until data flow again, and re-runs the interrupted step.
    A run that ends on it (the rig cannot open, or the link stays down) fails with its one line
    (:class:`rigctl.errors.DeviceError`, exit code 1); it is still an ``OSError``.
    """

    def __init__(self, device: str, message: str = "link lost") -> None:
        self.device = device
        super().__init__(f"{device}: {message}")


class DeviceFault(DeviceError, RuntimeError):
    """A device reports a fault that needs an operator (e.g. the table refuses a command while
    its drive is faulted). The engine pauses on it like on the fault status bits; a run that ends
    on it fails with its one line (:class:`rigctl.errors.DeviceError`, exit code 1)."""


class NoPulses:
    """A pulse source that never fires (rig without a pulse input)."""

    def read(self) -> Pulses:
        return Pulses(np.empty(0), source="none")
