"""`rigctl serve` as a real process with a wired config, against the emulated hardware running
in this test's process (ACL table and Xsens IMU on ptys, NovAtel receiver on a pty, scaled
clock): a table fault in the middle of a rate step, SIGTERM mid-step, and a daemon killed with
SIGKILL that resumes its own job when started again. The table's state is read on the
emulator's side (the controller's own mode, rate and status words)."""
from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import time
from contextlib import contextmanager
from pathlib import Path

import h5py

from rigctl.service import control
from rigctl.devices import AxisStatus

from helpers import ROOT, rigctl_cmd

from hil_support import commands_since, table_snapshot, wait_until, wired

SPEED = 50.0
RATE_JOB = """procedure: rate-job
steps:
  - warmup:
      duration: 5 s
  - rates:
      axes: [z]
      rates_dps: [100]
      directions: [forward]
      dwell: 30 s
      discard: 0.5 s
      settle: {hold: 1 s, timeout: 60 s}
"""


@contextmanager
def serve(cfg: Path, runs: Path, sock: Path, log: Path):
    """`rigctl serve` as a subprocess; yields the Popen once its socket answers."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with log.open("a") as out:
        p = subprocess.Popen([*rigctl_cmd(), "serve", "--config", str(cfg), "--runs", str(runs),
                              "--socket", str(sock)], cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        assert control.wait_for_socket(sock, 30), log.read_text()[-3000:]
        yield p
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(timeout=10)


def spinning(hw, rate_dps: float = 100.0) -> bool:
    """The emulated controller reports its outer axis at rate ``rate_dps``."""
    r = hw.table.read(1)
    return bool(r["status"] & AxisStatus.AT_RATE) and abs(math.degrees(r["rate"]) - rate_dps) < 0.05


def stopped(hw) -> bool:
    """Every axis of the emulated controller off and standing still (< 0.01 deg/s)."""
    snap = table_snapshot(hw)
    return snap["mode"] == ["off"] * 3 and max(abs(r) for r in snap["rate_dps"]) < 0.01


def time_until(pred, timeout: float = 10.0) -> float:
    t0 = time.monotonic()
    wait_until(pred, timeout, "the condition", poll=0.001)
    return time.monotonic() - t0


def job(sock: Path, jid: int) -> dict:
    return next(j for j in control.request(sock, "queue")["jobs"] if j["id"] == jid)


def test_table_fault_mid_rate_step_through_the_daemon(tmp_path, sock_dir):
    """While the outer axis spins at 100 deg/s, the emulated controller trips its middle axis
    (following error: FAULT, INTERLOCK_OPEN and FOLLOWING_ERROR status bits; that axis alone
    stops). The daemon stops the whole table within 1 s, pauses with a message naming the axis
    and the fault in `rigctl status` and in the run log, and resumes only after the operator
    cleared the fault at the table; the rate step then re-runs and the job completes."""
    proc = tmp_path / "rate.yaml"
    proc.write_text(RATE_JOB)
    sock = sock_dir / "rigctl.sock"
    with wired(tmp_path, SPEED, suspenders={"hold_s": "3 s"}) as (hw, cfg), \
            serve(cfg, tmp_path / "runs", sock, tmp_path / "daemon.log") as daemon:
        reply = control.request(sock, "submit", {"procedure": str(proc)})
        assert reply["ok"], reply
        wait_until(lambda: spinning(hw), 30, "the outer axis at 100 deg/s")
        time.sleep(0.1)                                   # 5 s of rig time into the rate step
        assert control.request(sock, "status")["step"].startswith("rate")
        t_fault = time.monotonic()
        hw.trip_following_error(2)
        stop_s = time_until(lambda: stopped(hw))          # the engine stopped the spinning axis
        cmds = [c for t, c in commands_since(hw, t_fault)]
        assert ":MODE:OFF ALL" in cmds
        st = wait_until(lambda: (s := control.request(sock, "status"))["state"] == "paused" and s, 10, "paused")
        reason = st["suspenders"]["table"]
        assert reason.startswith("table middle axis reports fault and interlock open and following error")
        assert "clear the fault / close the interlock at the table" in reason
        assert st["reason"].startswith("table middle axis reports fault")  # why the daemon is paused
        cli = subprocess.run([*rigctl_cmd(), "status", "--socket", str(sock)], capture_output=True, text=True,
                             timeout=30, cwd=ROOT)
        assert cli.returncode == 0 and re.search(r"(?m)^state:\s+paused since", cli.stdout), cli.stdout
        assert re.search(r"(?m)^suspended:\s+table: table middle axis reports fault", cli.stdout), cli.stdout
        run_dir = Path(st["job"]["run_dir"])
        logged = [json.loads(line) for line in (run_dir / "run.log.jsonl").read_text().splitlines()]
        assert any(r["kind"] == "warning" and "suspended (table)" in r["message"]
                   and "middle axis reports fault" in r["message"] for r in logged)
        time.sleep(0.3)                                   # 15 s of rig time: still paused, still stopped
        assert control.request(sock, "status")["state"] == "paused" and stopped(hw)
        t_clear = time.monotonic()
        hw.clear_fault()                                  # the operator resets it at the table
        wait_until(lambda: job(sock, reply["job"])["state"] not in ("queued", "running"), 60, "the job to end")
        assert job(sock, reply["job"])["state"] == "complete"
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(timeout=30) == 0
    resumed = [t for t, c in commands_since(hw, t_clear) if c.startswith(":MODE:RATE")]
    assert resumed, "the rate step was not commanded again after the clear"
    with h5py.File(run_dir / "recording.h5", "r") as f:
        assert f["run/status"][0] == b"complete"
        seg = {k: f["segments"][k][()] for k in ("kind", "status", "t_start", "measured_rate")}
        ev = list(zip(f["events/time"][()], f["events/kind"][()], f["events/message"][()]))
    assert list(zip(seg["kind"], seg["status"])) == [(b"warmup", b"complete"), (b"rate", b"incomplete"),
                                                      (b"rate", b"complete")]
    assert abs(math.degrees(seg["measured_rate"][2][0]) - 100.0) < 0.05
    t_resume = [t for t, k, m in ev if k == b"resume" and b"table clear for 3 s after" in m]  # config's hold_s
    t_suspend = [t for t, k, m in ev if k == b"suspend" and m.startswith(b"table: table middle axis")]
    assert len(t_suspend) == 1 and len(t_resume) == 1 and seg["t_start"][2] > t_resume[0]
    assert stop_s <= 1.0, f"table stopped {stop_s:.3f} s after the fault"
    print(f"\ntable fault: whole table stopped (mode off, < 0.01 deg/s) {stop_s * 1e3:.0f} ms after the trip")


def test_sigterm_stops_within_1s_then_kill9_daemon_resumes_its_job(tmp_path, sock_dir):
    """(1) SIGTERM to `rigctl serve` mid-rate-step: within 1 s the emulated controller reports
    every axis off and still, the recording is closed as interrupted, the daemon exits 0.
    (2) SIGKILL to a serving daemon mid-job: the table keeps spinning (nothing is left to stop
    it); `rigctl serve` started again resumes the crashed job into the same run directory,
    stopping the table before anything else, and completes it."""
    proc = tmp_path / "rate.yaml"
    proc.write_text(RATE_JOB)
    sock = sock_dir / "rigctl.sock"
    runs = tmp_path / "runs"
    log = tmp_path / "daemon.log"
    with wired(tmp_path, SPEED, suspenders={"hold_s": "3 s"}) as (hw, cfg):
        # -- SIGTERM ---------------------------------------------------------------------------
        with serve(cfg, runs, sock, log) as daemon:
            first = control.request(sock, "submit", {"procedure": str(proc)})["job"]
            wait_until(lambda: spinning(hw), 30, "the outer axis at 100 deg/s")
            time.sleep(0.1)
            t_term = time.monotonic()
            daemon.send_signal(signal.SIGTERM)
            term_s = time_until(lambda: stopped(hw))
            assert daemon.wait(timeout=30) == 0
        jobs = json.loads((runs / ".rigctl-daemon" / "jobs.json").read_text())
        j1 = next(j for j in jobs if j["id"] == first)
        assert j1["state"] == "interrupted" and "SIGTERM" in j1["message"]
        with h5py.File(Path(j1["run_dir"]) / "recording.h5", "r") as f:
            assert f["run/status"][0] == b"interrupted"
            assert any(k == b"safe-state" for k in f["events/kind"][()])
        assert ":MODE:OFF ALL" in [c for t, c in commands_since(hw, t_term)]
        # -- kill -9 mid-job, then serve again ---------------------------------------------------
        with serve(cfg, runs, sock, log) as daemon:
            second = control.request(sock, "submit", {"procedure": str(proc)})["job"]
            wait_until(lambda: spinning(hw), 30, "the outer axis at 100 deg/s")
            run_dir = Path(job(sock, second)["run_dir"])
            time.sleep(0.1)
            daemon.kill()
            daemon.wait(timeout=10)
            t_kill = time.monotonic()
        time.sleep(0.2)                                   # 10 s of rig time with nobody in charge
        assert spinning(hw), table_snapshot(hw)           # kill -9 cannot stop the table
        with serve(cfg, runs, sock, log) as daemon:
            jobs = control.request(sock, "queue")["jobs"]
            crashed = next(j for j in jobs if j["id"] == second)
            assert crashed["state"] == "crashed"
            again = next(j for j in jobs if j["kind"] == "resume")
            assert Path(again["run_dir"]) == run_dir
            wait_until(lambda: job(sock, again["id"])["state"] not in ("queued", "running"), 60, "the resume")
            assert job(sock, again["id"])["state"] == "complete", job(sock, again["id"])
            time.sleep(0.3)
            assert control.request(sock, "queue")["queued"] == []     # resumed once, not twice
            daemon.send_signal(signal.SIGTERM)
            assert daemon.wait(timeout=30) == 0
        assert log.read_text().count(f"job {again['id']}: resume") == 1
        after = [c for t, c in commands_since(hw, t_kill)]
        first_motion = next(i for i, c in enumerate(after) if c.startswith(":MODE:POSITION"))
        assert ":MODE:OFF ALL" in after[:first_motion]   # stopped before the re-run's first demand
    assert len([d for d in runs.iterdir() if not d.name.startswith(".")]) == 2   # no new run directory
    with h5py.File(run_dir / "recording.h5", "r") as f:
        assert f["run/status"][0] == b"complete"
        seg = {k: f["segments"][k][()] for k in ("kind", "status")}
        msgs = [(k, m.decode()) for k, m in zip(f["events/kind"][()], f["events/message"][()])]
    assert [k for k, s in zip(seg["kind"], seg["status"]) if s == b"complete"] == [b"warmup", b"rate"]
    found = [m for k, m in msgs if k == b"safe-state" and "stop commanded before any motion" in m]
    assert len(found) == 1 and "table found moving (outer +100.000 deg/s" in found[0], msgs
    ck = json.loads((run_dir / "checkpoint.json").read_text())
    assert ck["status"] == "complete" and ck["sessions"] == 2
    assert term_s <= 1.0, f"SIGTERM: table off and still after {term_s:.3f} s"
    print(f"\nSIGTERM: every axis off and still {term_s * 1e3:.0f} ms after the signal")
