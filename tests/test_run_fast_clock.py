"""``rigctl run`` on the in-process emulator with a scaled clock faster than the host computes.

Before: the emulator caught up with the clock at every device read, each catch-up took longer
than the rig time it covered, so the next had more to do: one poll ran hours of rig time ahead
(a 30 s warm-up at 500x on a loaded 2-core host: 7.5 min of wall time, 560 MB), and SIGTERM,
noticed at the end of a poll, waited for it. Now the emulator gives up a catch-up after 0.05 s of
wall time and sets the clock back (rigctl.clock.ScaledClock.slip_to): rig time runs as fast as
the host computes, the run says so once, and a signal is noticed within a poll.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import ROOT, derived_config, rigctl_cmd

#: far beyond what any host computes (the config allows up to 1e4): with the IMU at RATE_HZ, ten
#: million samples per wall second, 7x the emulator's full model on one core (benchmarks/emulator.py:
#: 1.4e6). At configs/sim.yaml's 100 Hz a quiet 2-core host computed 5390x, above the 0.5 x SPEED
#: this file asserts: a clean-clone CI failed on it
SPEED = 10000.0
RATE_HZ = 1000
WARMUP = str(ROOT / "procedures" / "warmup.yaml")


def _start(args: list[str], tmp_path: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1", RIGCTL_SOCKET=str(tmp_path / "no-daemon.sock"))
    return subprocess.Popen([*rigctl_cmd(), *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


class _Lines:
    """The stdout lines of ``proc``, read by a thread as they come."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self.proc = proc
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, needle: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while not any(needle in ln for ln in self.lines):
            assert time.monotonic() < deadline and self.proc.poll() is None, self.lines
            time.sleep(0.05)


def _terminate(proc: subprocess.Popen) -> tuple[float, str]:
    """SIGTERM; (seconds until the process exited, its stderr)."""
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    took = time.monotonic() - t0
    print(f"SIGTERM to exit: {took:.2f} s")
    return took, proc.stderr.read()


def _check_interrupted(rec: Path, n_resume_events: int) -> None:
    """The recording opens with plain h5py, says interrupted, and holds one unbroken series of
    IMU samples no longer than the rig time the run reached (no backlog, no duplicates)."""
    with h5py.File(rec, "r") as f:
        assert f["run/status"][0] == b"interrupted"
        kinds = list(f["events/kind"][()])
        assert b"safe-state" in kinds and kinds.count(b"resume") == n_resume_events
        t = f["imu/time"][()]
        c = f["imu/counter"][()].astype(np.int64)
        rate = float(f["imu"].attrs["sample_rate_hz"])
        t_table = float(f["table/time"][-1])  # the last table reading: the rig time reached
    steps = np.diff(c)
    assert np.all(steps >= 1) and np.count_nonzero(steps != 1) == n_resume_events  # a gap per resume
    assert t[-1] <= t_table + 1e-6
    assert len(t) <= (t_table + 1.0) * rate  # IMU rows: at most the rig time's worth


def test_sigterm_stops_a_run_that_the_host_cannot_keep_up_with(tmp_path):
    cfg = derived_config(tmp_path, clock="scaled", speed=SPEED, imu__rate_hz=RATE_HZ)
    runs = tmp_path / "runs"
    proc = _start(["run", WARMUP, "--config", str(cfg), "-p", "warmup=24 h", "--out", str(runs)], tmp_path)
    out = _Lines(proc)
    try:
        out.wait_for("started: warmup")
        out.wait_for("cannot keep up", timeout=30)  # measured over 2 s of wall time
        time.sleep(0.5)
    finally:
        took, err = _terminate(proc)
    time.sleep(0.2)  # the reader thread: the last lines
    lines = out.lines
    text = "\n".join(lines)
    assert proc.returncode == 130, text + err
    assert took < 10.0, f"{took:.1f} s from SIGTERM to exit"  # measured 0.7-1.6 s (load 2-15, 2 cores)
    assert "Traceback" not in text + err
    err_lines = err.splitlines()
    assert len(err_lines) == 1 and err_lines[0].startswith("rigctl run: interrupted: interrupted by SIGTERM; "
                                                           "recording "), err
    (run_dir,) = runs.iterdir()
    # the command the line names, exactly (the run is outside ./runs: with --runs)
    assert f"(rigctl resume {run_dir} --runs {runs} continues it)" in err_lines[0], err_lines[0]
    warn = [ln for ln in lines if "cannot keep up" in ln]
    assert len(warn) == 1 and warn[0].startswith(f"warning: the host cannot keep up with clock speed {SPEED:g}x")
    assert json.loads((run_dir / "checkpoint.json").read_text())["status"] == "interrupted"
    _check_interrupted(run_dir / "recording.h5", 0)

    # resumable: the resume starts, and a SIGTERM ends it the same way
    named = err_lines[0].split("(rigctl ", 1)[1].split(" continues it)")[0].split()
    assert named == ["resume", str(run_dir), "--runs", str(runs)], named
    proc = _start(named, tmp_path)
    out = _Lines(proc)
    try:
        out.wait_for("resuming")
        out.wait_for("started: warmup")
    finally:
        took, err = _terminate(proc)
    assert proc.returncode == 130, "\n".join(out.lines) + err
    assert took < 10.0, f"{took:.1f} s from SIGTERM to exit"
    assert len(err.splitlines()) == 1 and "interrupted by SIGTERM" in err and "Traceback" not in err
    _check_interrupted(run_dir / "recording.h5", 1)


def _run_warmup(tmp_path: Path, speed: float, warmup: str) -> dict:
    """A warm-up on the in-process emulator at ``speed``, the engine's own way (in-process),
    aborted once the run has said it cannot keep up: its log lines, the longest poll (wall s),
    wall time, the clock, the recording and, measured here on the table's readings (the rig time
    the devices reached, s) at the wall time of each poll: ``rig_time``, the last reading (after
    the safe state's polls), and ``measured``, the devices' speed from the first poll to the one
    that warned (None without a warning). Not ``clock.now()``: once the emulator has set it back
    it runs on at ``speed`` until the next catch-up sets it back again, and 0.1 s of wall time
    after the last poll is 1000 s of rig time at 10000x that no device reached."""
    from rigctl.config.config import load_config
    from rigctl.engine.engine import Engine, Interrupted
    from rigctl.engine.procedure import load_procedure
    from rigctl.engine.rig import open_rig
    from rigctl.recording.recorder import Recorder

    cfg = load_config(derived_config(tmp_path, clock="scaled", speed=speed, imu__rate_hz=RATE_HZ))
    proc = load_procedure(WARMUP, {"warmup": warmup}, cfg.limits)
    logged: list[tuple[str, str]] = []
    polls: list[float] = []
    seen: list[tuple[float, float]] = []    # (wall s, table time s) at the end of each poll
    warned: list[tuple[float, float]] = []  # the same, in the poll that warned

    def alarm(*_):
        raise TimeoutError("the run did not end within 60 s of wall time")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(60)
    try:
        with open_rig(cfg) as (rig, truth):
            rec = Recorder(tmp_path / f"rec-{speed:g}.h5", {}, truth, imu_rate_hz=cfg.imu_rate_hz)
            def log(kind: str, msg: str, **_) -> None:
                logged.append((kind, msg))
                if "cannot keep up" in msg:   # said in the poll that read engine.last_state
                    warned.append((time.monotonic(), float(engine.last_state.time)))
                    engine.request_abort("test: the warning came")

            engine = Engine(rig, rec, log=log)
            engine.pace_window_s = 0.5
            poll = engine.poll

            def timed(*a, **kw):
                t = time.monotonic()
                try:
                    state = poll(*a, **kw)
                    seen.append((time.monotonic(), float(state.time)))
                    return state
                finally:
                    polls.append(time.monotonic() - t)

            engine.poll = timed
            wall0 = time.monotonic()
            try:
                engine.run(proc.steps)
            except Interrupted:
                pass
            wall = time.monotonic() - wall0
            engine.safe_state()
            rec.close("complete")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    (w0, t0), rig_time = seen[0], seen[-1][1]
    measured = (warned[0][1] - t0) / (warned[0][0] - w0) if warned else None
    return {"log": logged, "longest_poll": max(polls), "rig_time": rig_time, "wall": wall,
            "measured": measured, "clock": rig.clock, "recording": tmp_path / f"rec-{speed:g}.h5"}


def test_a_run_faster_than_the_host_says_so_once_and_records_no_backlog(tmp_path):
    r = _run_warmup(tmp_path, SPEED, "24 h")
    warn = [m for k, m in r["log"] if "cannot keep up" in m]
    assert len(warn) == 1 and all(k == "warning" for k, m in r["log"] if m in warn), r["log"]
    head = f"the host cannot keep up with clock speed {SPEED:g}x: the emulator computes about "
    assert warn[0].startswith(head)
    said = float(warn[0][len(head):].split("x", 1)[0])
    # what the devices really reached, measured here: the table's time over wall time from the
    # first poll (where the run's pace window starts) to the poll that warned, the stretch the
    # stated speed was measured on (not the whole run: a loaded host computes faster and slower
    # stretches; and not on clock.now(), which runs ahead of the devices -- a run at load 9 said
    # 208x where that average was 912x); the same order as the stated speed, far below the asked one
    got = r["measured"]
    assert said < 0.5 * SPEED and got < 0.5 * SPEED
    assert got / 3 < said < got * 3, (said, got)
    assert "'clock: virtual'" in warn[0] and "'speed: " in warn[0]
    assert r["clock"].slipped > 0
    # the work per poll is bounded (before: each poll ran further behind than the last)
    assert r["longest_poll"] < 2.0, r["longest_poll"]
    with h5py.File(r["recording"], "r") as f:
        c = f["imu/counter"][()].astype(np.int64)
        t = f["imu/time"][()]
        kinds = list(f["events/kind"][()])
    # one unbroken series: every sample once, none beyond the rig time reached
    assert c[0] == 0 and np.all(np.diff(c) == 1)
    assert t[-1] <= r["rig_time"] + 1e-6
    assert len(c) <= (r["rig_time"] + 0.01) * RATE_HZ + 1
    assert kinds.count(b"clock") == 1


def test_a_run_the_host_keeps_up_with_keeps_its_speed(tmp_path):
    r = _run_warmup(tmp_path, 5.0, "5 s")  # ~1.5 s of wall time: three windows of 0.5 s
    assert not [m for _, m in r["log"] if "cannot keep up" in m], r["log"]
    assert r["clock"].slipped == 0.0
    with h5py.File(r["recording"], "r") as f:
        assert b"clock" not in list(f["events/kind"][()])
