"""Time offsets learnt while the emulator lags at connect.

Seen in wired 24-position runs at 100x on a loaded 2-core host: the table and IMU times came out
14-29 s (rig time) late for a whole run, because the drivers learnt their offsets while the
emulator's hardware loop stood still in a pty write that waited up to 0.5 s (wall) for a slow
client. Here the stall is injected deterministically (:meth:`Hardware.pause_physics`)."""
from __future__ import annotations

import time

import pytest

from rigctl.drivers.acl_table import AclTable
from rigctl.drivers.modbus_table import ModbusTable

from hil_support import hardware, sim_config

SPEED = 100.0
PAUSE_WALL_S = 1.0                  # 100 s of rig time


@pytest.mark.parametrize("kind", ["acl_pty", "modbus_tcp"])
def test_a_physics_stall_at_connect_does_not_shift_the_table_times(tmp_path, kind):
    """The hardware loop stands still (100 s of rig time) while the table driver connects, so
    every connect probe sees a stale controller time; the next on-time reads correct the offset.
    The driver runs on the emulator's own clock, where the controller time IS the run time:
    the true offset is 0 (the old driver kept ~+100 s: the whole run's table times late)."""
    cfg, _ = sim_config(tmp_path)
    with hardware(tmp_path, SPEED) as (hw, _raw):
        if kind == "acl_pty":
            table = AclTable(hw.endpoints["table_acl_pty"], cfg.limits, hw.clock, timeout_s=0.5)
        else:
            host, port = hw.endpoints["table_modbus_tcp"].split(":")
            table = ModbusTable(cfg.limits, hw.clock, host=host, tcp_port=int(port), timeout_s=0.5)
        time.sleep(0.1)
        hw.pause_physics(PAUSE_WALL_S)
        time.sleep(0.2)
        try:
            table.connect()
            lag_at_connect = hw.lag_s
            learnt = table.time_offset
            assert lag_at_connect > 10.0, "the stall did not cover the connect (host too slow?)"
            assert learnt > 10.0                                # what the connect probes alone give
            time.sleep(PAUSE_WALL_S)                            # the stall is over
            states = [table.read() for _ in range(10)]
            now = hw.clock.now()
            times = [s.time for s in states]
            assert all(b > a for a, b in zip(times, times[1:]))
            assert times[-1] <= now
            # on time: within the state's age (one tick, 2 ms wall = 0.2 s rig) plus a read's
            # round trip (a few ms wall) -- not 100 s late
            assert abs(table.time_offset) < 2.0, table.time_offset
            assert now - times[-1] < 5.0
            assert table.time_base.corrections >= 1
        finally:
            table.close()


@pytest.mark.parametrize("protocol", ["frame", "xsens"])
def test_a_slow_imu_client_does_not_stall_the_physics(tmp_path, protocol):
    """A client that drains the IMU port slowly (as a driver starved of CPU at connect does):
    the emulator's stream waits for it (flow control), the physics -- the table's controller
    time -- goes on. The old hardware loop wrote the stream itself and stood still in each write
    for up to 0.5 s of wall time (50 s of rig time at 100x)."""
    import serial

    from rigctl.drivers.xsens import go_to_measurement

    with hardware(tmp_path, SPEED, imu_protocol=protocol) as (hw, _raw):
        port = serial.serial_for_url(hw.endpoints[f"imu_{protocol}_pty"], baudrate=921600, timeout=0)
        try:
            if protocol == "xsens":
                port.write(go_to_measurement())
            worst, got = 0.0, 0
            end = time.monotonic() + 1.5
            while time.monotonic() < end:
                got += len(port.read(256))                     # 256 bytes per 20 ms: far too slow
                time.sleep(0.02)
                worst = max(worst, hw.lag_s)
            assert got > 0
            # the physics keeps up within a few ticks of a loaded host (0.2 s wall = 20 s rig);
            # a write waiting for this client held it 0.5 s (50 s of rig time) at a time
            assert worst < 20.0, worst
        finally:
            port.close()
