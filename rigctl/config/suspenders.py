"""Suspenders: conditions that pause a procedure, and resume it once they clear and stay clear.

After Bluesky's suspenders: the engine hands every poll's observation to a
:class:`SuspenderSet`; when any suspender *trips* the engine stops the table, marks the step in
flight incomplete and waits; it resumes when every suspender has been clear continuously for
``hold_s`` seconds of rig time, and re-runs the interrupted step from its start (segments are
all-or-nothing).

Suspenders (names as written to the recording's ``/events``):

* ``imu-link``    -- the IMU driver raised :class:`rigctl.devices.LinkLost`; it stays tripped
  while the driver reports the device not configured again (:func:`rigctl.devices.imu_reconnecting`)
  and until a read brings samples received after that (the second read after it reports
  configured; a device without that report: its first samples): frames a reconnecting driver
  hands out before its reconfiguration do not clear it, so a pause does not end before the
  stream is back.
* ``imu-gap``     -- samples missing: a sample-counter gap larger than ``max_counter_gap``, or no
  sample for ``imu_timeout_s`` s of rig time -- on a clock faster than the wall (an emulated rig
  at 100x), for at least :data:`IMU_SILENCE_WALL_S` of wall time (:attr:`SuspenderSet.clock_speed`).
* ``table``       -- a table axis reports FAULT, INTERLOCK_OPEN or FOLLOWING_ERROR, or the
  table link is lost, or the drive refused a command (:class:`rigctl.devices.DeviceFault`).
* ``temperature`` -- an IMU temperature sample outside ``[temperature_min_c, temperature_max_c]``.
* ``chamber``     -- the climatic chamber reports a fault, its link is lost, or its air or
  product temperature is outside the config's ``chamber.band_c`` (docs/thermal.md).
* ``disk``        -- free space on the run directory's filesystem below ``min_free_bytes``
  (``shutil.disk_usage``), checked at most every ``disk_check_interval_s`` of wall time.
* ``operator``    -- ``rigctl pause`` (cleared by ``rigctl resume``).
"""
from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import schema as S
from ..devices import AxisStatus, ImuBlock, TableState
from ..settings import Settings, duration, internal, number, setting
from ..yamlio import LocDict

TABLE_TRIP_BITS = (AxisStatus.FAULT, AxisStatus.INTERLOCK_OPEN, AxisStatus.FOLLOWING_ERROR)
_TABLE_TRIP_MASK = sum(int(b) for b in TABLE_TRIP_BITS)  # (distinct single bits)

#: On a clock faster than the wall, "no IMU sample" trips the ``imu-gap`` suspender only after at
#: least this much wall time as well, s: the samples' delay between the device and the engine is
#: the host's (scheduling, a reader thread waiting for the interpreter), in wall time, and the
#: default 2 s of rig time at 100x is 20 ms -- one scheduling delay of a loaded host. Wired
#: 24-position runs at 100x on a 2-core host at load 11-14 paused on 'IMU data gap: no samples
#: for 2.2 s' (22 ms of wall time) with no sample missing, and re-ran their warm-up; at load
#: 17-23 the host held samples back for more than 0.5 s. Samples really missing are a counter
#: gap, whatever the clock. The same allowance as the engine's window wait
#: (rigctl.engine.engine.WINDOW_WAIT_WALL_S) and the emulated IMU port's flow control.
IMU_SILENCE_WALL_S = 1.5


def _mib_as_bytes(d: LocDict, key: str, default: int) -> int:
    """``min_free_mib`` (MiB = 2**20 bytes) as bytes."""
    mib = S.get_number(d, key, default / 2**20, minimum=0.0, maximum=2.0**30)
    return int(round(mib * 2**20))


@dataclass(frozen=True, kw_only=True)
class SuspenderSettings(Settings):
    """Thresholds (SI units; times in rig seconds unless stated), and the ``suspenders:``
    section of a rig config (docs/daemon.md), read by :func:`rigctl.settings.parse`.

    hold_s: every suspender clear for this long (s of rig time, or a duration such as '5 s')
    before a paused run resumes; imu_timeout_s: no IMU sample for this long (rig time) is a data
    gap; max_counter_gap: IMU samples that may go missing (counter gap) before it counts as a
    gap; temperature_min_c / temperature_max_c: the IMU temperature band, degC;
    ``min_free_mib``: free space (MiB) the run directory's filesystem must keep (0 = no check),
    held in bytes as ``min_free_bytes``."""

    hold_s: float = duration(5.0)
    imu_timeout_s: float = duration(2.0, positive=True)
    max_counter_gap: int = number(0, minimum=0, maximum=10**9, integer=True)
    temperature_min_c: float = number(-40.0, minimum=-273.15, maximum=1000.0)
    temperature_max_c: float = number(85.0, minimum=-273.15, maximum=1000.0)
    min_free_bytes: int = setting(64 * 2**20, read=_mib_as_bytes, key="min_free_mib")
    disk_check_interval_s: float = internal(0.25)  # wall time

    def check(self, d: LocDict) -> None:
        if not 0.0 <= self.hold_s <= 86400.0:
            raise S.error(d, "hold_s", f"'hold_s' = {self.hold_s:g} s must be between 0 s and 24 h")
        if self.imu_timeout_s > 3600.0:
            raise S.error(d, "imu_timeout_s",
                          f"'imu_timeout_s' = {self.imu_timeout_s:g} s is above its maximum 3600 s")
        if not self.temperature_min_c < self.temperature_max_c:
            raise S.error(d, "temperature_max_c" if "temperature_max_c" in d else "temperature_min_c",
                          f"the temperature band [{self.temperature_min_c:g}, {self.temperature_max_c:g}] "
                          "degC is empty", "temperature_min_c must be below temperature_max_c")

    @classmethod
    def from_mapping(cls, m: dict[str, Any] | None) -> "SuspenderSettings":
        """From a config mapping with the same keys (unknown keys raise ValueError)."""
        if not m:
            return cls()
        known = set(cls.__dataclass_fields__)
        bad = set(m) - known
        if bad:
            raise ValueError(f"unknown suspender settings {sorted(bad)}; known: {sorted(known)}")
        return cls(**m)


@dataclass
class Observation:
    """What one engine poll saw. ``imu`` is None when the IMU read failed (``imu_error``)."""

    t: float
    imu: ImuBlock | None = None
    imu_error: str | None = None
    table: TableState | None = None
    table_error: str | None = None
    #: why the chamber trips (fault, link lost, out of band), None when fine or absent
    chamber_reason: str | None = None
    #: the IMU's driver reported its link lost and the device not configured again yet
    #: (:func:`rigctl.devices.imu_reconnecting`), asked just BEFORE the read: a read after a
    #: poll that found it configured again holds only frames received since
    imu_reconnecting: bool = False


def describe_table_trip(state: TableState) -> str | None:
    """A readable reason when any axis reports a fault bit, else None."""
    names = ("outer", "middle", "inner")
    for i, word in enumerate(state.status):
        if not int(word) & _TABLE_TRIP_MASK:  # (plain ints first: this runs at every poll)
            continue
        bits = [b.name.lower().replace("_", " ") for b in TABLE_TRIP_BITS if int(word) & b]
        if bits:
            return (f"table {names[i]} axis reports {' and '.join(bits)} (status 0x{int(word):04x}); "
                    "clear the fault / close the interlock at the table")
    return None


class SuspenderSet:
    """Evaluates every suspender on each observation and tracks how long all have been clear."""

    def __init__(self, settings: SuspenderSettings | None = None, run_dir: Path | None = None) -> None:
        self.s = settings or SuspenderSettings()
        self.run_dir = run_dir
        #: rig seconds per wall second of the run's clock when it runs with the wall (a scaled
        #: clock, set by the engine); 1.0 for real time and for the virtual clock (no wall time)
        self.clock_speed = 1.0
        self.operator: str | None = None
        self.last_counter: int | None = None
        self.last_sample_t: float | None = None
        self._disk_checked = -1e9
        self._disk_reason: str | None = None
        self.active: dict[str, str] = {}
        self.clear_since: float | None = None
        #: the reason 'imu-link' tripped, kept until the stream is back (see :meth:`_imu`)
        self.link_lost: str | None = None
        self._reconfigured_reads = -1   # reads since the driver reported configured again (_imu)
        #: the temperature suspender's reason at the last read that held samples (None: in band);
        #: a read without samples says nothing of the temperature and keeps it (see :meth:`check`)
        self._temp_reason: str | None = None

    def rebase(self) -> None:
        """Forget counter/time history (after a reconnect, a resume or a new session)."""
        self.last_counter = None
        self.last_sample_t = None

    def imu_silence_s(self) -> float:
        """Rig seconds without an IMU sample that trip ``imu-gap``: ``imu_timeout_s``, and on a
        clock faster than the wall at least :data:`IMU_SILENCE_WALL_S` of wall time."""
        if self.clock_speed > 1.0:
            return max(self.s.imu_timeout_s, IMU_SILENCE_WALL_S * self.clock_speed)
        return self.s.imu_timeout_s

    # -- individual checks ---------------------------------------------------------------------
    def _imu(self, obs: Observation) -> dict[str, str]:
        out: dict[str, str] = {}
        if obs.imu_error is not None:
            out["imu-link"] = self.link_lost = f"IMU link lost: {obs.imu_error}"
            self._reconfigured_reads = -1   # (-1: the driver has not reported reconnecting)
            return out
        block = obs.imu
        if self.link_lost is not None:      # tripped: clear once reconfigured and streaming
            if obs.imu_reconnecting:
                self._reconfigured_reads = 0
            elif self._reconfigured_reads >= 0:
                self._reconfigured_reads += 1
            # a driver that reported reconnecting: the first read after it reported configured
            # may still hold frames received before (queued while it configured); the next holds
            # only frames received after (see Observation.imu_reconnecting)
            stale = 0 <= self._reconfigured_reads < 2
            if obs.imu_reconnecting or stale or block is None or not len(block):
                out["imu-link"] = self.link_lost
                if block is None or not len(block):
                    return out
            else:
                self.link_lost = None
        if block is not None and len(block):
            c0 = int(block.counter[0])
            if self.last_counter is not None and c0 - self.last_counter - 1 > self.s.max_counter_gap:
                out["imu-gap"] = (f"IMU data gap: {c0 - self.last_counter - 1} samples missing "
                                  f"(counter {self.last_counter} -> {c0})")
            counters = block.counter.astype(np.int64)
            inner = np.diff(counters) - 1
            if inner.size and int(inner.max()) > self.s.max_counter_gap:
                out["imu-gap"] = f"IMU data gap: {int(inner.sum())} samples missing inside a read"
            self.last_counter = int(counters[-1])
            self.last_sample_t = obs.t
            temp = block.temperature
            lo, hi = float(np.min(temp)), float(np.max(temp))
            self._temp_reason = None
            if lo < self.s.temperature_min_c or hi > self.s.temperature_max_c:
                out["temperature"] = self._temp_reason = (
                    f"IMU temperature {hi if hi > self.s.temperature_max_c else lo:.1f} "
                    f"degC outside [{self.s.temperature_min_c:g}, {self.s.temperature_max_c:g}] degC")
        elif self.last_sample_t is None:
            self.last_sample_t = obs.t
        elif obs.t - self.last_sample_t > self.imu_silence_s():
            out["imu-gap"] = f"IMU data gap: no samples for {obs.t - self.last_sample_t:.1f} s"
        return out

    def _table(self, obs: Observation) -> dict[str, str]:
        if obs.table_error is not None:
            return {"table": obs.table_error}
        if obs.table is not None:
            reason = describe_table_trip(obs.table)
            if reason:
                return {"table": reason}
        return {}

    def _disk(self) -> dict[str, str]:
        if self.run_dir is None or self.s.min_free_bytes <= 0:
            return {}
        now = time.monotonic()
        if now - self._disk_checked >= self.s.disk_check_interval_s:
            self._disk_checked = now
            try:
                free = shutil.disk_usage(self.run_dir).free
            except OSError as exc:
                self._disk_reason = f"cannot check free disk space of {self.run_dir}: {exc}"
            else:
                self._disk_reason = None
                if free < self.s.min_free_bytes:
                    self._disk_reason = (f"disk space low: {free / 2**20:.2f} MiB free on the run "
                                         f"directory's filesystem ({self.run_dir}), need at least "
                                         f"{self.s.min_free_bytes / 2**20:.2f} MiB; free some space")
        return {"disk": self._disk_reason} if self._disk_reason else {}

    # -- all together --------------------------------------------------------------------------
    def check(self, obs: Observation) -> dict[str, str]:
        """Evaluate every suspender; returns {name: reason} of those tripped now (empty = clear).
        Also keeps :attr:`clear_since` (the rig time since which all have been clear)."""
        tripped: dict[str, str] = {}
        tripped.update(self._imu(obs))
        if self._temp_reason is not None:
            # the last read with samples (this one, or before a read without any: a table-stop
            # poll in a pause, a link down) still stands -- else one empty read cleared it, and
            # the next read's samples 'tripped' it again: a second suspend event in one pause,
            # and a pause could end on a read that saw no temperature at all
            tripped["temperature"] = self._temp_reason
        tripped.update(self._table(obs))
        tripped.update(self._disk())
        if obs.chamber_reason:
            tripped["chamber"] = obs.chamber_reason
        if self.operator:
            tripped["operator"] = self.operator
        self.active = tripped
        if tripped:
            self.clear_since = None
        elif self.clear_since is None:
            self.clear_since = obs.t
        return tripped

    def clear_for(self, t: float) -> float:
        """How long every suspender has been clear at rig time ``t``, s (0 when tripped)."""
        return 0.0 if self.clear_since is None else t - self.clear_since
