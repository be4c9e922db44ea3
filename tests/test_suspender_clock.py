"""The ``imu-gap`` suspender's no-sample wait on a clock faster than the wall: at least
IMU_SILENCE_WALL_S (1.5 s) of wall time, since the samples' delay on a loaded host is wall time
(2 s of rig time at 100x is 20 ms: wired runs at 100x paused on 'no samples for 2.2 s' with no
sample missing). Real time and the virtual clock keep ``imu_timeout_s`` as configured; a counter
gap trips at once on any clock."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from rigctl.clock import RealClock, ScaledClock, VirtualClock
from rigctl.config.suspenders import Observation, SuspenderSet, SuspenderSettings
from rigctl.devices import ImuBlock
from rigctl.engine.engine import Engine


def block(t: float, counters: list[int]) -> ImuBlock:
    n = len(counters)
    return ImuBlock(time=t + 0.01 * np.arange(n), counter=np.asarray(counters, np.uint64),
                    specific_force=np.zeros((n, 3)), angular_rate=np.zeros((n, 3)),
                    temperature=np.full(n, 25.0))


def silence_trips(speed: float, silent_rig_s: float, timeout_s: float = 2.0) -> bool:
    sus = SuspenderSet(SuspenderSettings(imu_timeout_s=timeout_s, min_free_bytes=0))
    sus.clock_speed = speed
    assert sus.check(Observation(t=0.0, imu=block(0.0, [0, 1, 2]))) == {}
    return "imu-gap" in sus.check(Observation(t=silent_rig_s, imu=ImuBlock.empty()))


@pytest.mark.parametrize("speed, silent, trips", [
    (1.0, 2.1, True), (1.0, 1.9, False),            # real time: imu_timeout_s, as configured
    (100.0, 2.2, False), (100.0, 149.0, False),     # 100x: 22 ms / 1.49 s of wall time
    (100.0, 151.0, True),                           # 1.51 s of wall time
    (200.0, 10.5, False), (200.0, 301.0, True),
])
def test_no_sample_wait_has_a_wall_time_floor_on_a_fast_clock(speed, silent, trips):
    assert silence_trips(speed, silent) is trips


def test_a_timeout_longer_than_the_floor_is_kept():
    assert not silence_trips(100.0, 199.0, timeout_s=200.0) and silence_trips(100.0, 201.0, timeout_s=200.0)


def test_a_counter_gap_trips_on_any_clock():
    sus = SuspenderSet(SuspenderSettings(min_free_bytes=0))
    sus.clock_speed = 100.0
    sus.check(Observation(t=0.0, imu=block(0.0, [0, 1, 2])))
    assert "samples missing" in sus.check(Observation(t=0.03, imu=block(0.03, [4, 5])))["imu-gap"]


@pytest.mark.parametrize("clock, speed", [(ScaledClock(100.0), 100.0), (RealClock(), 1.0),
                                          (VirtualClock(), 1.0)])
def test_the_engine_gives_its_clock_speed_to_the_suspenders(clock, speed):
    engine = Engine(SimpleNamespace(clock=clock), None, suspenders=SuspenderSet())
    assert engine.suspenders.clock_speed == speed


def test_imu_link_holds_until_reads_after_the_driver_is_configured_again():
    """'imu-link' after a LinkLost, with a driver that reports its reconnect
    (Observation.imu_reconnecting, asked before each read): frames read while it reconfigures,
    and those of the first read after it reports configured (queued before), keep it tripped;
    the second read's samples, received after, clear it. A device that never reports a
    reconnect (the in-process emulator) clears on its first samples, as before."""
    def link_trips(seq: list[tuple[bool, list[int]]]) -> list[bool]:
        sus = SuspenderSet(SuspenderSettings(min_free_bytes=0))
        assert sus.check(Observation(t=0.0, imu=block(0.0, [0, 1, 2]))) == {}
        assert "imu-link" in sus.check(Observation(t=0.5, imu_error="no data for 0.1 s (reconnecting)"))
        return ["imu-link" in sus.check(Observation(t=1.0 + i, imu=block(1.0 + i, c), imu_reconnecting=r))
                for i, (r, c) in enumerate(seq)]

    # reconnecting (frames still streamed before GoToConfig), then configured: the first read
    # after holds what was queued, the second clears (with the counter gap: imu-gap trips then)
    assert link_trips([(True, [3, 4]), (True, []), (False, [5]), (False, [50, 51]), (False, [52])]) == \
        [True, True, True, False, False]
    # configured, but the first two reads after: nothing, then samples -- both after the report
    assert link_trips([(True, []), (False, []), (False, [], ), (False, [60])]) == [True, True, True, False]
    # no reconnect reported: the first samples clear it
    assert link_trips([(False, []), (False, [30, 31])]) == [True, False]
