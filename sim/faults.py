"""Fault injection for the in-process emulated rig.

The emulated devices (:mod:`rigctl.sim.world`) consult a :class:`FaultInjector` on every read
and command, so the engine sees injected faults exactly as it would see real ones:

* ``imu_link`` -- the IMU link is down: ``SimImuDevice.read`` raises
  :class:`rigctl.devices.LinkLost`; the samples produced meanwhile are lost (a counter gap).
* ``imu_power`` -- the IMU is without power (a power cycle, not a cable pull): the link is down
  as for ``imu_link``, and when the window ends the unit restarts -- its device time begins
  again, counted in ``SimImuDevice.counters["device_restarts"]`` as a streaming driver counts it
  (drivers/stream_imu.py).
* ``table_fault`` -- every axis reports ``AxisStatus.FAULT`` and the table stops (mode off);
  motion commands are refused with :class:`rigctl.devices.DeviceFault` until the fault clears.
* ``interlock`` -- the interlock is open: ``AxisStatus.INTERLOCK_OPEN`` and the table stops.
* ``temperature`` -- the IMU temperature reads ``offset_c`` degC off (a thermal excursion).
* ``chamber_fault`` -- the climatic chamber's controller reports a fault and stops regulating
  (its air drifts towards ambient) until the window ends.

Faults are windows of rig time ``[start, start + duration)`` (duration ``inf`` = until
:meth:`FaultInjector.clear` is called), so a run in virtual time is deterministic. Arbitrary
actions (e.g. filling a small filesystem) run through :meth:`FaultInjector.call_at` when the
emulator's time passes ``t``. Times are seconds on the emulator's clock.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

KINDS = ("imu_link", "table_fault", "interlock", "temperature", "chamber_fault", "imu_power")


@dataclass
class FaultWindow:
    kind: str
    start: float
    duration: float = math.inf
    offset_c: float = 0.0

    @property
    def end(self) -> float:
        return self.start + self.duration

    def active(self, t: float) -> bool:
        return self.start <= t < self.end


@dataclass
class FaultInjector:
    """Scheduled faults and timed actions, consulted by the emulated devices."""

    windows: list[FaultWindow] = field(default_factory=list)
    _actions: list[tuple[float, Callable[[], None]]] = field(default_factory=list)
    #: (time, kind, "on"/"off") edges seen by the devices, for tests and logs
    history: list[tuple[float, str, str]] = field(default_factory=list)
    _state: dict[str, bool] = field(default_factory=dict)

    def schedule(self, kind: str, start: float, duration: float = math.inf,
                 offset_c: float = 0.0) -> FaultWindow:
        """Inject ``kind`` from rig time ``start`` for ``duration`` s (inf: until cleared)."""
        if kind not in KINDS:
            raise ValueError(f"unknown fault {kind!r}; one of {', '.join(KINDS)}")
        w = FaultWindow(kind, float(start), float(duration), float(offset_c))
        self.windows.append(w)
        return w

    def clear(self, kind: str, t: float) -> None:
        """End every open window of ``kind`` at rig time ``t`` (an operator reset)."""
        for w in self.windows:
            if w.kind == kind and w.active(t):
                w.duration = max(0.0, t - w.start)

    def call_at(self, t: float, action: Callable[[], None]) -> None:
        """Run ``action()`` once, the first time the emulator's time reaches ``t``."""
        self._actions.append((float(t), action))
        self._actions.sort(key=lambda a: a[0])

    def tick(self, t: float) -> None:
        """Run due actions and note fault edges (called by the devices on every access)."""
        while self._actions and self._actions[0][0] <= t:
            _, action = self._actions.pop(0)
            action()
        for kind in KINDS[:3]:
            on = self.active(kind, t)
            if on != self._state.get(kind, False):
                self._state[kind] = on
                self.history.append((t, kind, "on" if on else "off"))

    def active(self, kind: str, t: float) -> bool:
        return any(w.kind == kind and w.active(t) for w in self.windows)

    def temperature_offset(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """Temperature offset, degC, at each time of ``t``."""
        out = np.zeros_like(t, dtype=float)
        for w in self.windows:
            if w.kind == "temperature":
                out += np.where((t >= w.start) & (t < w.end), w.offset_c, 0.0)
        return out

    def count(self, kind: str) -> int:
        """How many times ``kind`` went on, as seen by the devices."""
        return sum(1 for _, k, edge in self.history if k == kind and edge == "on")
