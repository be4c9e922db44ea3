"""Clocks for the engine: virtual (as fast as the emulator computes), real, or scaled."""
from __future__ import annotations

import math
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
    """Wall time multiplied by ``speed`` (1.0 = real time), starting at zero.

    An in-process emulator that cannot compute as fast as this clock runs sets it back
    (:meth:`slip_to`) to the time it has reached, instead of falling further behind at every
    call: rig time then runs slower than ``speed`` x wall time. :attr:`slipped` adds up those
    set-backs (rig time, s): zero on a host that keeps up. :meth:`now` never goes back: after a
    set-back it holds at the latest time it returned until the clock passes it again."""

    def __init__(self, speed: float = 1.0) -> None:
        if speed <= 0:
            raise ValueError("speed must be positive")
        self.speed = float(speed)
        self._t0 = time.monotonic()
        self.slipped = 0.0
        self._high = 0.0  # the latest time now() returned

    def running_now(self) -> float:
        """The time the clock has run to, without the hold of :meth:`now` after a set-back
        (the emulator's catch-up target: reading it does not hold the clock)."""
        return (time.monotonic() - self._t0) * self.speed

    def now(self) -> float:
        t = (time.monotonic() - self._t0) * self.speed
        if t < self._high:  # set back (slip_to) and not yet past what it returned before
            return self._high
        self._high = t
        return t

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds / self.speed)

    def restart(self) -> None:
        """Zero now (before anyone has read the clock: an in-process emulator, once built)."""
        self._t0 = time.monotonic()
        self._high = 0.0

    def slip_to(self, t: float) -> None:
        """Set the clock back to ``t`` (rig time, s) if it is ahead of it: it goes on from there
        at ``speed`` (:meth:`now` holds meanwhile at the latest time it returned)."""
        ahead = (time.monotonic() - self._t0) * self.speed - t
        if ahead > 0:
            self._t0 += ahead / self.speed
            self.slipped += ahead


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


def suggested_speed(achieved: float) -> float:
    """A round clock speed (1, 2 or 5 x a power of ten) at or below 80 % of ``achieved``, the
    speed a host was measured to keep up with: what to ask for instead."""
    m = 10 ** math.floor(math.log10(max(0.8 * achieved, 1e-9)))
    return max(x * m for x in (1, 2, 5) if x * m <= max(0.8 * achieved, m))
