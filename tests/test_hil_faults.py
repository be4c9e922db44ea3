"""Fault injection through the emulator's side channel, seen through the real drivers."""
from __future__ import annotations

import time

import numpy as np
import pytest

from rigctl.clock import ScaledClock
from rigctl.config.config import load_config
from rigctl.devices import AxisStatus, DeviceFault
from rigctl.drivers.acl_table import AclTable
from rigctl.drivers.modbus_table import ModbusTable
from rigctl.drivers.novatel import MarkTime, format_mark
from rigctl.drivers.novatel_marks import NovatelMarks
from rigctl.drivers.serial_link import ReplyTimeout
from rigctl.drivers.xsens import RateDoesNotFitError
from rigctl.drivers.xsens_imu import XsensConfigError, XsensImu
from rigctl.sim.hardware import start_hardware

from hil_support import (RunPoints, affordable_speed, hardware, pull, sampling, segments, sim_config, starting,
                         wait_progress, wait_until, wired, wired_run)


def test_imu_byte_errors_1e6_frames_through_the_driver(tmp_path):
    """1e6 MTData2 frames at 2 kHz over a pty, 100x real time (500 s of rig time in ~6 s), byte
    errors at 1e-4: no crash, no bytes dropped on the pty, and the driver counts the frames hit
    (all of them, bar hit frames whose 8-bit checksum still adds up -- undetectable by design).
    On a loaded machine the emulator runs slower (affordable_speed: as fast as its physics keeps
    up) and the waits last as long as frames keep coming (wait_progress)."""
    cfg, _ = sim_config(tmp_path, rate_hz=2000)
    n_frames = 1_000_000
    hw_kw = {"imu_baudrate": 4_000_000, "tick_s": 0.02}
    speed = affordable_speed(cfg, tmp_path, 100.0, **hw_kw)
    with start_hardware(cfg, speed, link_dir=tmp_path / "ports", **hw_kw) as hw:
        # the emulated port waits for its client as long as it reads at all: at 2 kHz x 100x a
        # host that holds the driver's reader thread off for the port's default 1.5 s (three
        # busy loops on 2 cores: 0.5-1.0 MB dropped, 2 runs in 4, 'no progress ... waiting for
        # the last frames') measures the host, not the driver's error counting; a driver that
        # stops reading for good still fails (overflow_bytes, the waits)
        hw.slots["imu"].endpoint.write_timeout_s = 30.0
        # a start-up stall of the physics is behind it before the device starts measuring (its
        # frames are due from then on, and come only once the physics has reached it)
        wait_progress(lambda: hw.lag_s < 0.1 * speed, lambda: hw.table._t(), "the physics to reach the clock")
        imu = XsensImu(hw.endpoints["imu_xsens_pty"], 2000, ScaledClock(speed), baudrate=4_000_000,
                       align_wait_s=0.0)
        imu.connect()
        try:
            rows = 0

            def read() -> dict:
                nonlocal rows
                rows += len(imu.read())
                return imu.counters

            def decoded() -> int:
                c = imu.counters
                return c["frames"] + c["bad_frames"] + c["truncated_frames"]

            hw.set_imu_byte_errors(1e-4, seed=11)
            f0 = hw.xsens.frames_sent
            wait_progress(lambda: read() and hw.xsens.frames_sent - f0 >= n_frames,
                          lambda: (hw.xsens.frames_sent, decoded()), f"{n_frames} frames sent")
            hw.set_imu_byte_errors(0.0)
            sent = hw.xsens.frames_sent
            wait_progress(lambda: read() and decoded() >= sent + 100, decoded, "the driver to catch up")
            with hw.xsens._lock:
                hw.xsens.state = "config"                       # stop the stream (side channel)
            final = hw.xsens.frames_sent
            # every frame sent is decoded (or counted lost) and handed out
            wait_progress(lambda: read() and decoded() >= final, decoded, "the last frames")
            c = read()
            assert sent - f0 >= n_frames
            hit, invisible = hw.xsens.frames_hit, hw.xsens.frames_hit_undetectable
            assert hit > 4000                                   # ~61 bytes x 1e6 x 1e-4 = 6100 errors
            assert hw.slots["imu"].endpoint.overflow_bytes == 0
            # every hit frame is counted, except (possibly) hit frames whose checksum still adds
            # up and whose structure survived: those no receiver can detect (the error positions
            # depend only on the seed). Never more: a frame's payload can hold a header whose
            # false frame passes the 8-bit checksum; with its frame hit, the decoder took it and
            # lost the next good frame too, depending on the read boundaries (bad 6156 > hit 6155
            # in a clean-clone CI run): test_frame_resync tries every corrupted byte. (No parser
            # can settle one case, ~2e-4 per run with random payload bytes: a hit preamble or
            # length byte and a whole false frame inside the payload; that frame counts twice.)
            bad = c["bad_frames"] + c["truncated_frames"]
            assert hit - invisible <= bad <= hit
            assert c["dropped_samples"] == bad                  # each lost frame is a counter gap
            assert c["out_of_order"] == 0 and c["link_losses"] == 0
            # every decoded frame is handed out, bar those dropped when the offset was lowered
            # (a lower latency than the learning window's minimum: counted, restamp_dropped)
            assert rows == c["frames"] - c["incomplete_frames"] - c["restamp_dropped"]
        finally:
            imu.close()


#: the drivers' reply timeout in the two stall tests, wall s. The stalled replies are held until
#: the test releases them, so every timeout these tests expect happens whatever the timeout;
#: every reply they expect must come within it, and at 0.3 s a loaded host did not always
#: deliver one (the reply after a dropped one timed out, 1 in 6 runs at load 19)
REPLY_TIMEOUT_S = 2.0


def test_acl_stalled_reply_times_out_then_recovers(tmp_path):
    with hardware(tmp_path, 10.0) as (hw, _):
        cfg = load_config(tmp_path / "physics.yaml")
        table = AclTable(hw.endpoints["table_acl_pty"], cfg.limits, ScaledClock(10.0), timeout_s=REPLY_TIMEOUT_S)
        table.connect()
        core = hw.acl.core
        try:
            # every line of the connect answered (the driver can have a reply before the
            # emulator's thread has counted it)
            wait_until(lambda: core.answered == len(core.received), 30, "the connect's last reply")
            hw.stall("acl")                        # held until released
            with pytest.raises(ReplyTimeout, match=r"no reply to ':READ:ALL\? 1;ALL\? 2;ALL\? 3'.*within 2 s"):
                table.read()
            # the driver gave up on its own: the request and the resynchronisation's *IDN? of its
            # retry each waited one timeout, while the controller still held its reply
            assert core.stalls.held == 1 and table.counters.timeouts == 2
            hw.release_stall("acl")
            # the late replies to both lines may reach the driver's port before, during or after
            # the next request's resync drains it (the kernel passes what the emulator wrote on
            # asynchronously): the resync matches only the reply to its own identity query, so
            # a late *IDN? reply is never taken for it (tests/test_wire_acl.py, which orders them)
            state = table.read()                   # resynchronised: the late reply is not misread
            assert len(state.status) == 3 and table.counters.resyncs >= 1
            hw.drop_replies(1)
            table.read()                           # retried once after a timeout
            hw.garble_replies(1)
            table.read()
            assert table.counters.timeouts == 3 and table.counters.bad_replies == 1
        finally:
            table.close()


def test_modbus_stalled_reply_times_out_then_recovers(tmp_path):
    with hardware(tmp_path, 10.0) as (hw, _):
        cfg = load_config(tmp_path / "physics.yaml")
        host, port = hw.modbus_tcp
        table = ModbusTable(cfg.limits, ScaledClock(10.0), host=host, tcp_port=port, timeout_s=REPLY_TIMEOUT_S,
                            retries=0)
        table.connect()
        try:
            hw.stall("modbus")                     # held until released
            with pytest.raises(ReplyTimeout, match=r"no reply to read input registers 100\.\.113 .* within 2 s"):
                table.read()
            assert hw.modbus.stalls.held == 1      # it gave up on its own
            hw.release_stall("modbus")
            # the driver dropped the connection; it reconnects once its back-off has passed
            wait_until(lambda: table.backoff.ready() and hw.modbus.stalls.held == 0, 30, "the reconnect back-off")
            assert len(table.read().status) == 3 and table.counters.timeouts == 1
            assert table.counters.reconnects == 1
        finally:
            table.close()


@pytest.mark.parametrize("protocol", ["acl", "modbus"])
def test_interlock_and_following_error_trips(tmp_path, protocol):
    with hardware(tmp_path, 10.0) as (hw, _):
        cfg = load_config(tmp_path / "physics.yaml")
        clock = ScaledClock(10.0)
        if protocol == "acl":
            table = AclTable(hw.endpoints["table_acl_tcp"], cfg.limits, clock)
        else:
            table = ModbusTable(cfg.limits, clock, host=hw.modbus_tcp[0], tcp_port=hw.modbus_tcp[1])
        table.connect()
        try:
            table.move(np.radians([10.0, 0.0, 0.0]))
            hw.trip_following_error(2)
            hw.trip_interlock(3)
            time.sleep(0.05)
            s = table.read().status
            assert s[1] & AxisStatus.FAULT and s[1] & AxisStatus.FOLLOWING_ERROR
            assert s[2] & AxisStatus.FAULT and s[2] & AxisStatus.INTERLOCK_OPEN
            assert not s[2] & AxisStatus.FOLLOWING_ERROR and not s[0] & AxisStatus.FAULT
            with pytest.raises(DeviceFault):
                table.move(np.radians([0.0, 5.0, 0.0]))
        finally:
            table.close()


def test_pty_disconnect_mid_run_is_reconnected(tmp_path):
    """Pull the IMU's and the table's pty in the middle of a run: the drivers reconnect (same
    symlink, new pty), the engine pauses on the gap and re-runs the step, the run completes.
    The cables are pulled at defined points of the run (not after wall-clock delays, which on a
    loaded host could fall before the run had started or between its steps): the IMU's 10 s
    (1000 samples at 100 Hz) into the warm-up's window, the table's 1 s into the third
    orientation's window, in the engine's thread (the port is gone at its next poll); each
    cuts its step off. The windows are 10 s: the 100th sample of one must arrive while the
    window is still open on the run's clock (sampling()), and at 100x a 3 s window left 20 ms
    of wall time for the samples' latency and the host's scheduling -- 2 of 18 runs at load 9-11
    fired only in the next orientation's window or not at all in the third's."""
    params = {"warmup": "2 min", "sample": "10 s"}
    rec, cfg, info = wired_run(tmp_path, "24pos.yaml", params, "acl", "pty", 100.0,
                               at=[(sampling("warmup", after_samples=1000), pull("imu")),
                                   (sampling("orientation", after_samples=100, finished=2), pull("table-acl"))])
    assert None not in info["fired"]
    assert info["reconnects"]["imu"] == 1 and info["reconnects"]["table-acl"] == 1
    seg = segments(rec)
    done = seg["status"] == b"complete"
    assert done.sum() == 25 and list(seg["kind"][done]).count(b"orientation") == 24
    # the steps cut off by the outages, then re-run: the warm-up and the third orientation
    cut = list(zip(seg["kind"][~done], seg["step"][~done]))
    assert (b"warmup", seg["step"][done][0]) in cut and (b"orientation", seg["step"][done][3]) in cut, cut
    import h5py
    with h5py.File(rec, "r") as f:
        c = f["imu/counter"][()].astype(np.int64)
        kinds = set(f["events/kind"][()])
    assert np.any(np.diff(c) > 1)             # the samples of the outage are a counter gap
    assert kinds & {b"suspend", b"resume"}


#: three orientations with the settle of procedures/24pos.yaml (its 60 s timeout)
STALL_PROC = """procedure: settle-through-a-stall
description: three orientations; the emulator stalls while the second settles
defaults:
  settle: {position_window_deg: 0.01, rate_window_dps: 0.02, hold: 2 s, timeout: 60 s}
  sample: 2 s
  discard: 0.5 s
steps:
  - orientations: {angles_deg: [[0, 0, 0], [90, 0, 0], [90, 90, 0]]}
"""


def test_settle_is_timed_on_the_table_through_an_emulator_stall(tmp_path):
    """The emulator's physics stands still for 1 s of wall time (100 s of rig time, as when the
    host starves it or it waits for the IMU stream's client) from the start of the second
    orientation, so the table gets its command and cannot move yet: the table has not had the time to settle, and the settle's 60 s timeout (on the
    table's own time) must not fail it, though the run's clock passes it. Before, the timeout on
    the run's clock failed the step ('did not settle within 60 s', the table's time frozen), as
    the wired soaks and 24-position runs did at 100x under load. The IMU silence allowance is
    raised beyond the stall, so that the stall does not pause the run instead."""
    proc = tmp_path / "stall.yaml"
    proc.write_text(STALL_PROC)
    rec, cfg, info = wired_run(tmp_path, proc, {}, "acl", "pty", 100.0,
                               at=[(starting("orientation", finished=1), lambda hw: hw.pause_physics(1.0))],
                               suspenders={"imu_timeout_s": "10 min"})
    assert info["fired"][0] is not None
    seg = segments(rec)
    assert list(seg["status"]) == [b"complete"] * 3 and list(seg["kind"]) == [b"orientation"] * 3
    # the second settle spanned the stall: longer than the timeout on the run's clock
    assert seg["settle_time"][1] > 60.0
    np.testing.assert_allclose(np.degrees(seg["measured_angle"]), [[0, 0, 0], [90, 0, 0], [90, 90, 0]], atol=0.01)


@pytest.mark.parametrize("case", ["too slow", "clock stands still"])
def test_settle_on_the_table_still_fails_a_table_that_does_not_settle(tmp_path, case):
    """The settle measured on the table's time still fails: a table too slow for the timeout
    (acceleration limited to 2 deg/s^2: 90 deg take 13.4 s, the timeout is 1 s of its own time,
    counted from its first reading after the command); a table whose time
    stands still (the emulator's physics stopped for 2 s of wall time, 200 s of rig time, from
    the start of the step) once its time has not moved for ten timeouts (10 s) of the run's
    clock and the wall-time floor of that check (60 s, made 0.5 s here)."""
    import io

    from rigctl.engine.procedure import load_procedure
    from rigctl.run.runner import RunOptions, run_procedure

    proc = tmp_path / "stuck.yaml"
    proc.write_text(STALL_PROC.replace("hold: 2 s, timeout: 60 s", "hold: 0.5 s, timeout: 1 s"))
    with wired(tmp_path, 100.0, pulses="none", suspenders={"imu_timeout_s": "10 min"}) as (hw, cfg_path):
        if case == "too slow":
            import yaml
            d = yaml.safe_load(cfg_path.read_text())
            d["table"]["limits"]["accel_dps2"] = [2, 2, 4]
            cfg_path.write_text(yaml.safe_dump(d, sort_keys=False))
        cfg = load_config(cfg_path)
        def stand_still() -> None:      # the wall-time floor of the check (60 s) made 0.5 s
            points.engine.still_wall_s = 0.5
            hw.pause_physics(2.0)
        points = RunPoints([] if case == "too slow" else [(starting("orientation"), stand_still)])
        res = run_procedure(load_procedure(proc, {}, cfg.limits), cfg, tmp_path / "runs", console=io.StringIO(),
                            install_signals=False, options=RunOptions(progress=points, on_engine=points.on_engine))
    if case == "too slow":
        assert res.exit_code != 0 and "step 2 (angles [90, 0, 0] deg) did not settle within 1 s: axis 1" in res.message, \
            res.message
    else:
        assert res.exit_code != 0 and points.fired, res.message
        assert "the table's time stood still at" in res.message and "while it settled" in res.message, res.message


def test_gnss_marks_with_crc_check_and_timeguard(tmp_path):
    with hardware(tmp_path, 10.0) as (hw, _):
        clock = ScaledClock(10.0)
        marks = NovatelMarks(hw.endpoints["gnss_novatel_pty"], clock, timeguard_ms=50)
        marks.connect()
        try:
            assert hw.gnss.control.timeguard_ms == 50
            t = hw.world_clock.now()
            assert hw.pulse(t) and not hw.pulse(t + 0.01)  # inside the 50 ms timeguard: suppressed
            assert hw.pulse(t + 1.0)
            bad = bytearray(format_mark(MarkTime(week=2300, seconds=1.0)))
            bad[-5] = ord("0") if bad[-5] != ord("0") else ord("1")   # corrupt the CRC
            hw.inject("gnss", bytes(bad))
            deadline, got = time.monotonic() + 5, []
            while sum(len(p) for p in got) < 2 and time.monotonic() < deadline:
                time.sleep(0.02)
                got.append(marks.read())
            p = [x for x in got if len(x)]
            week = np.concatenate([x.gps_week for x in p])
            sec = np.concatenate([x.gps_seconds for x in p])
            want = [hw.gnss.mark_time(t), hw.gnss.mark_time(t + 1.0)]
            assert list(week) == [w for w, _ in want]
            np.testing.assert_allclose(sec, [s for _, s in want], atol=1e-8)
            times = np.concatenate([x.time for x in p])
            assert times[1] - times[0] == pytest.approx(1.0, abs=1e-6)
            time.sleep(0.2)
            marks.read()
            assert marks.counters["bad_crc"] == 1 and marks.counters["marks"] == 2
        finally:
            marks.close()


def test_imu_configuration_that_does_not_fit_is_refused(tmp_path):
    with hardware(tmp_path, 10.0, imu_baudrate=921_600) as (hw, _):
        with pytest.raises(RateDoesNotFitError, match="baud"):
            XsensImu(hw.endpoints["imu_xsens_pty"], 2000, ScaledClock(10.0), baudrate=921_600)
        imu = XsensImu(hw.endpoints["imu_xsens_pty"], 2000, ScaledClock(10.0), baudrate=4_000_000)
        with pytest.raises(XsensConfigError, match="refused the output configuration"):
            imu.connect()
        assert "921,600 baud" in hw.xsens.last_error
