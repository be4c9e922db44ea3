"""The console is not the run (issue 16, items 1-3), with real pipes, ptys, signals and ports.

* a pipe closed by its reader (``| head -2``), a pty whose master is closed under the process
  (with and without it being the controlling terminal), and SIGHUP: the run goes on and its
  recording, /run/status and checkpoint end ``complete``;
* devices are asked before a run starts: on the emulated hardware's ports every device answers.

These runs are on a scaled clock or ask devices that reply in wall time (REALTIME_FILES,
tests/conftest.py). The console cases without a wall-clock deadline (``validate | head -1``,
missing devices, a run that fails later, the daemon's answer to an invalid submission) are in
tests/test_cli_console_offline.py.
"""
from __future__ import annotations

import json
import os
import pty
import select
import signal
import subprocess
import time
from pathlib import Path

import h5py
import yaml

from helpers import ROOT, rigctl_cmd

WARMUP = str(ROOT / "procedures" / "warmup.yaml")


def scaled_config(tmp: Path, speed: float = 10.0) -> Path:
    """configs/sim.yaml on a scaled clock: a 20 s warm-up lasts ~2 s of wall time, long enough
    for the console to go away while the run is going."""
    d = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    d["clock"], d["speed"] = "scaled", speed
    p = tmp / "scaled.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def run_argv(tmp: Path) -> list[str]:
    return [*rigctl_cmd(), "run", WARMUP, "--config", str(scaled_config(tmp)), "-p", "warmup=20 s",
            "--out", str(tmp / "runs")]


def final_state(tmp: Path) -> tuple[str, str, list[dict]]:
    """(/run/status, checkpoint status, run log records) of the one run under tmp/runs."""
    (run_dir,) = list((tmp / "runs").iterdir())
    with h5py.File(run_dir / "recording.h5", "r") as f:
        status = f["run/status"][0].decode()
    ck = json.loads((run_dir / "checkpoint.json").read_text())["status"]
    log = [json.loads(line) for line in (run_dir / "run.log.jsonl").read_text().splitlines()]
    return status, ck, log


def read_until(fd: int, needle: bytes, timeout: float = 60.0) -> bytes:
    buf, end = b"", time.monotonic() + timeout
    while needle not in buf:
        left = end - time.monotonic()
        assert left > 0, f"no {needle!r} within {timeout} s: {buf[-500:]!r}"
        r, _, _ = select.select([fd], [], [], left)
        if r:
            chunk = os.read(fd, 4096)
            assert chunk, f"EOF before {needle!r}: {buf[-500:]!r}"
            buf += chunk
    return buf


def test_a_pipe_closed_by_its_reader_does_not_change_the_run(tmp_path):
    """`rigctl run ... | head -2`: the reader exits after two lines, the run goes on."""
    p = subprocess.Popen(run_argv(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    lines = [p.stdout.readline() for _ in range(2)]
    assert all(lines), lines
    p.stdout.close()  # the reader goes away while the run is going (~2 s of wall time left)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 0, err.decode()
    assert b"Traceback" not in err and b"BrokenPipe" not in err
    status, ck, log = final_state(tmp_path)
    assert (status, ck) == ("complete", "complete")
    assert any("console (stdout) lost: broken pipe" in r["message"] for r in log), log[-5:]
    assert log[-1]["message"].startswith("recording: ")


def test_a_pty_closed_under_the_run_without_a_controlling_terminal(tmp_path):
    """stdout and stderr on a pty (not the process's controlling terminal): closing the master
    makes every later write fail with EIO; the run goes on."""
    master, slave = os.openpty()
    p = subprocess.Popen(run_argv(tmp_path), stdin=subprocess.DEVNULL, stdout=slave, stderr=slave,
                         cwd=ROOT, start_new_session=True)
    os.close(slave)
    try:
        read_until(master, b"steps, about")
    finally:
        os.close(master)
    assert p.wait(timeout=120) == 0
    status, ck, log = final_state(tmp_path)
    assert (status, ck) == ("complete", "complete")
    assert any("terminal gone" in r["message"] for r in log), log[-5:]


def test_the_controlling_terminal_closed_under_the_run(tmp_path):
    """pty.fork: the pty is the run's controlling terminal; closing the master hangs it up
    (SIGHUP from the kernel, then EIO); the run goes on."""
    argv = run_argv(tmp_path)
    pid, master = pty.fork()
    if pid == 0:  # the child: exec at once
        os.chdir(ROOT)
        os.execv(argv[0], argv)
    try:
        read_until(master, b"steps, about")
    finally:
        os.close(master)
    end = time.monotonic() + 120
    while True:
        done, st = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        assert time.monotonic() < end, "the run did not end"
        time.sleep(0.05)
    assert os.waitstatus_to_exitcode(st) == 0
    status, ck, log = final_state(tmp_path)
    assert (status, ck) == ("complete", "complete")
    assert any("hang-up (SIGHUP)" in r["message"] or "terminal gone" in r["message"] for r in log), log[-5:]


def test_sighup_does_not_end_the_run(tmp_path):
    p = subprocess.Popen(run_argv(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    assert b"steps, about" in p.stdout.readline() + p.stdout.readline()
    p.send_signal(signal.SIGHUP)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err.decode()
    assert b"Traceback" not in err
    status, ck, log = final_state(tmp_path)
    assert (status, ck) == ("complete", "complete")
    assert any("hang-up (SIGHUP)" in r["message"] for r in log), log[-5:]
    assert b"complete:" not in out  # the console was detached: the last lines went to the log only


# -- devices checked before a run starts: the emulated hardware answers (ports, wall-clock replies)
def test_validate_devices_on_emulated_hardware_says_ok(tmp_path):
    """`validate --devices` against `rigctl sim up`'s wire peers (the HIL fixtures): every
    device answers with its identity."""
    from hil_support import wired

    with wired(tmp_path, 20.0) as (_hw, cfg_path):
        r = subprocess.run([*rigctl_cmd(), "validate", WARMUP, "--config", str(cfg_path), "--devices"],
                           capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert any(ln.startswith("table: ") and ": ok (SIM,TT3-SIM" in ln for ln in lines), lines
    assert any(ln.startswith("imu: ") and ": ok (Xsens MT, device ID " in ln for ln in lines), lines
    assert any(ln.startswith("pulses: ") and ": ok (NovAtel receiver answers" in ln for ln in lines), lines
