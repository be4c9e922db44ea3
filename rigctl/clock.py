"""Clocks for the engine: virtual (as fast as the emulator computes), real, or scaled."""
from __future__ import annotations

import time
from datetime import datetime, timezone


def utc_now() -> str:
    """Wall-clock UTC as the recordings, logs and checkpoints write it (ISO 8601, microseconds, Z)."""
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


class VirtualClock:
    """Simulated time that advances only when the engine sleeps: a run costs compute, not time."""

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)

    def now(self) -> float:
        return self._t

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self._t += seconds


class ScaledClock:
    """Wall time multiplied by ``speed`` (1.0 = real time), starting at zero."""

    def __init__(self, speed: float = 1.0) -> None:
        if speed <= 0:
            raise ValueError("speed must be positive")
        self.speed = float(speed)
        self._t0 = time.monotonic()

    def now(self) -> float:
        return (time.monotonic() - self._t0) * self.speed

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds / self.speed)


class RealClock(ScaledClock):
    """Wall time since the run started, s."""

    def __init__(self) -> None:
        super().__init__(1.0)


def make_clock(kind: str, speed: float = 1.0) -> VirtualClock | ScaledClock:
    if kind == "virtual":
        return VirtualClock()
    if kind == "real":
        return RealClock()
    if kind == "scaled":
        return ScaledClock(speed)
    raise ValueError(f"unknown clock {kind!r}")
