"""A run whose IMU stream, not the table, falls behind says so with numbers that mean something.

Before: the emulated rig's physics waits for a flow-controlled IMU stream its client does not
take (sim/links.py FlowPtyEndpoint: it waits instead of dropping), so the table's time stands
still; the pace was measured on the table's time alone, and the run stopped with 'the rig's
devices keep time at about 4.7e-12x real time ... restart it with --speed 1e-09' (tests/
test_daemon_wire.py's ten link drops at load 17-30 on 2 cores). Here the host's stall is made
deterministic: output on the IMU pty's master is suspended (tcflow TCOOFF) for 6 s of wall
time after 200 s of a warm-up at 100x: the old code said 'about 2.4e-12x ... --speed 1e-09',
now 'about 35x ... the IMU stream lagged 405 s behind the clock ... --speed 20'. ~20 s.
"""
from __future__ import annotations

import io
import json
import re
import termios
import threading

from helpers import ROOT
from test_sim_speed import _round_speed
from rigctl.sim.links import FlowPtyEndpoint

#: wall time the IMU port's host moves no byte, s
STALL_S = 6.0


def test_a_stalled_imu_stream_names_the_frozen_table_clock_and_a_sensible_speed(tmp_path):
    """The end-to-end speed (the slower of the table's and the IMU stream's own), the stream's
    lag as the cause, and a --speed of at least 1 below it."""
    from hil_support import RunPoints, hardware, sampling
    from rigctl.config.config import load_config
    from rigctl.engine.procedure import load_procedure
    from rigctl.run.runner import RunOptions, run_procedure
    from rigctl.sim.wire_config import write_wire_config

    with hardware(tmp_path, 100.0) as (hw, raw):
        cfg = load_config(write_wire_config(tmp_path / "wired.yaml", raw, hw, table="acl", link="pty"))
        master = hw.slots["imu"].endpoint.master
        resume = threading.Timer(STALL_S, termios.tcflow, (master, termios.TCOON))

        def stall() -> None:
            termios.tcflow(master, termios.TCOOFF)
            resume.start()
        # the stall after 200 s of warm-up samples (2 s of wall time at 100x): the stream kept the
        # clock's speed that long, then stood still
        points = RunPoints([(sampling("warmup", after_samples=int(200 * cfg.imu_rate_hz)), stall)])
        proc = load_procedure(ROOT / "procedures" / "24pos.yaml", {"warmup": "300 s", "sample": "3 s"}, cfg.limits)
        try:
            res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False,
                                options=RunOptions(progress=points, on_engine=points.on_engine))
        finally:
            resume.cancel()
            termios.tcflow(master, termios.TCOON)
    assert points.fired, "the stall was never applied"
    lines = [json.loads(ln)["message"] for ln in (res.run_dir / "run.log.jsonl").read_text().splitlines()
             if "keep time at about" in ln]
    assert len(lines) == 1, lines       # said once
    m = re.fullmatch(r"the rig's devices keep time at about ([\d.e+-]+)x real time, slower than the 100x of "
                     r"the run's clock: the emulator \('rigctl sim up --speed 100'\) cannot run the rig that "
                     r"fast: (?:the table's clock did not advance in (\d+) reads while )?the IMU stream lagged "
                     r"(\d+) s behind the clock \(.*\) on this machine, so its devices fall ever further behind "
                     r"the clock; restart it with --speed ([\d.e+-]+) or less and run with the wired config "
                     r"it writes", lines[0])
    assert m, lines[0]
    said, lag, suggest = float(m.group(1)), float(m.group(3)), float(m.group(4))
    # the physics waits once the stream is this far behind it (sim/hardware.py _loop): the stream
    # lags the clock by at least that, less the table's own lag
    backlog_s = 100.0 * (FlowPtyEndpoint.write_timeout_s + 0.5)
    assert lag >= 0.5 * backlog_s, lines[0]
    # the stream's time advanced at 100x before the stall and not at all during it: end to end,
    # less than the clock's speed and not nothing; the advice a round speed of at least 1 below it
    assert 1.0 <= said < 100.0, lines[0]
    assert 1.0 <= suggest <= 0.8 * said and _round_speed(suggest), lines[0]


def test_the_advice_is_never_below_real_time():
    """A rig that kept less than 1.25x real time (80 % of it below 1) is told the host is too
    slow for real time, not to restart at --speed 0.5 or 1e-09; from 1.25x on, a round speed of
    at least 1 at or below 80 % of what it kept."""
    from rigctl.engine.engine import slow_rig_message

    for achieved in (0.0, 2.4e-12, 0.3, 1.2):
        line = slow_rig_message(100.0, achieved)
        assert "--speed 1)" in line and "too slow to run the emulated rig even at real time" in line, line
        assert "restart it with" not in line, line
    for achieved in (1.25, 3.0, 35.0, 81.0):
        m = re.search(r"restart it with --speed ([\d.e+-]+) or less", slow_rig_message(100.0, achieved))
        suggest = float(m.group(1))
        assert 1.0 <= suggest <= 0.8 * achieved + 1e-12 and _round_speed(suggest), (achieved, suggest)
    assert "\n" not in slow_rig_message(100.0, 35.0, still=(579, 270.0))
    assert "did not advance in 579 reads while the IMU stream lagged 270 s" in \
        slow_rig_message(100.0, 35.0, still=(579, 270.0))
