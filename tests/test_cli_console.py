"""The console is not the run (issue 16, items 1-3), with real pipes, ptys, signals and ports.

* a pipe closed by its reader (``| head -2``), a pty whose master is closed under the process
  (with and without it being the controlling terminal), and SIGHUP: the run goes on and its
  recording, /run/status and checkpoint end ``complete``; ``validate | head -1`` prints no
  traceback;
* devices are asked before a run starts: a missing serial port, a refused TCP port and a port
  without permission give one line each, exit 1 (README), and no run directory;
* a run that fails later keeps its directory with status ``failed``, the error in run.log.jsonl
  and in /events, the traceback only in the run log, one line on stderr;
* the daemon answers an invalid submission as ``rigctl run`` exits: 2.
"""
from __future__ import annotations

import json
import os
import pty
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest
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


def test_validate_into_head_prints_no_traceback():
    p = subprocess.Popen([*rigctl_cmd(), "validate", str(ROOT / "procedures" / "full-calibration.yaml")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    assert p.stdout.readline().startswith(b"procedure full-calibration")
    p.stdout.close()
    _, err = p.communicate(timeout=120)
    assert err == b"" and p.returncode == 0


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


# -- devices checked before a run starts ------------------------------------------------------------
def wired_config(tmp: Path, table_port: str, imu_port: str) -> Path:
    d = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    d["clock"] = "real"
    d["table"] = {"driver": "acl", "port": table_port, "limits": d["table"]["limits"]}
    d["imu"] = {"driver": "xsens", "port": imu_port, "rate_hz": 100}
    d["pulses"] = {"driver": "none"}
    p = tmp / "wired.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


@pytest.mark.parametrize("case", ["missing-serial", "refused-tcp", "no-permission"])
def test_a_missing_device_is_one_line_exit_1_and_no_run_directory(tmp_path, case):
    prefix: list[str] = []
    if case == "missing-serial":
        table, imu = "/dev/ttyUSB97", "/dev/ttyUSB98"
        want = ["table: /dev/ttyUSB97: no such device; is the adapter plugged in? ls /dev/serial/by-id",
                "imu: /dev/ttyUSB98: no such device; is the adapter plugged in? ls /dev/serial/by-id"]
    elif case == "refused-tcp":
        table = imu = "socket://127.0.0.1:9"
        want = [f"{r}: socket://127.0.0.1:9: connection refused; is rigctl sim up / the device server running?"
                for r in ("table", "imu")]
    else:  # a real pty the user may not open: another owner, mode 0600
        master, slave = os.openpty()
        path = os.ttyname(slave)
        os.chmod(path, 0o000)
        prefix = []
        if os.geteuid() == 0:  # root opens anything: chown it away and drop CAP_DAC_OVERRIDE
            os.chown(path, 65534, 65534)
            os.chmod(path, 0o600)
            prefix = ["setpriv", "--bounding-set=-dac_override,-dac_read_search"]
        table = imu = path
        want = [f"{r}: {path}: permission denied; add the user to the dialout group" for r in ("table", "imu")]
    cfg = wired_config(tmp_path, table, imu)
    cfg.chmod(0o644)
    runs = tmp_path / "runs"
    try:
        for verb in (["run", WARMUP, "--config", str(cfg), "--out", str(runs)],
                     ["validate", WARMUP, "--config", str(cfg), "--devices"]):
            r = subprocess.run([*prefix, *rigctl_cmd(), *verb], capture_output=True, text=True, timeout=120,
                               cwd=ROOT)
            assert r.returncode == 1, r.stderr
            lines = r.stderr.splitlines()
            assert len(lines) == 2 and "Traceback" not in r.stderr, r.stderr
            for line, w in zip(lines, want):
                assert line.startswith(f"rigctl {verb[0]}: failed: {w}"), (line, w)
            assert not runs.exists() or not any(runs.iterdir())
    finally:
        if case == "no-permission":
            os.close(master)
            os.close(slave)


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


# -- a run that fails later -----------------------------------------------------------------------
def test_a_failure_during_the_run_ends_failed_with_one_line(tmp_path):
    """A bug inside the run (here: the recorder's IMU writer raising): status failed in the
    recording and the checkpoint, the error in run.log.jsonl (with its traceback) and /events,
    the table stopped, one line on stderr, exit 1."""
    script = tmp_path / "failing.py"
    script.write_text(
        "import sys\n"
        "from rigctl.recording import recorder; from rigctl import cli\n"
        "orig = recorder.Recorder.append_imu\n"
        "calls = [0]\n"
        "def broken(self, block):\n"
        "    calls[0] += 1\n"
        "    if calls[0] == 50:\n"
        "        raise ZeroDivisionError('a bug in the middle of the run')\n"
        "    return orig(self, block)\n"
        "recorder.Recorder.append_imu = broken\n"
        "sys.exit(cli.main(sys.argv[1:]))\n")
    r = subprocess.run([sys.executable, str(script), "run", WARMUP, "-p", "warmup=20 s", "--out",
                        str(tmp_path / "runs")], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 1
    assert "Traceback" not in r.stderr and "Traceback" not in r.stdout
    err = r.stderr.splitlines()
    assert len(err) == 1 and err[0].startswith("rigctl run: failed: ZeroDivisionError: a bug in the middle"), err
    status, ck, log = final_state(tmp_path)
    assert (status, ck) == ("failed", "failed")
    errors = [rec for rec in log if rec["kind"] == "error"]
    assert any("ZeroDivisionError" in rec.get("traceback", "") for rec in errors), errors
    (run_dir,) = list((tmp_path / "runs").iterdir())
    with h5py.File(run_dir / "recording.h5", "r") as f:
        events = [(k.decode(), m.decode()) for k, m in zip(f["events/kind"][()], f["events/message"][()])]
    assert ("failed", "ZeroDivisionError: a bug in the middle of the run") in events, events
    assert any(k == "safe-state" for k, _ in events), events


# -- the daemon answers as `rigctl run` exits ------------------------------------------------------
def test_submit_of_an_invalid_procedure_exits_2_like_run(tmp_path):
    sock = tmp_path / "d.sock"
    serve = subprocess.Popen([*rigctl_cmd(), "serve", "--runs", str(tmp_path / "runs"), "--socket", str(sock)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT)
    try:
        end = time.monotonic() + 60
        while not sock.exists():
            assert time.monotonic() < end and serve.poll() is None, serve.stderr.read() if serve.poll() else ""
            time.sleep(0.05)
        bad = tmp_path / "bad.yaml"
        bad.write_text("steps:\n  - warmup:\n      duration: 15 parsecs\n")
        for argv in (["submit", str(bad)], ["submit", str(tmp_path / "missing.yaml")],
                     ["submit", WARMUP, "-p", "warmpu=5 s"]):
            sub = subprocess.run([*rigctl_cmd(), *argv, "--socket", str(sock)], capture_output=True, text=True,
                                 timeout=60, cwd=ROOT)
            run = subprocess.run([*rigctl_cmd(), "run", *argv[1:], "--out", str(tmp_path / "r")],
                                 capture_output=True, text=True, timeout=60, cwd=ROOT)
            assert sub.returncode == run.returncode == 2, (sub.stderr, run.stderr)
            assert sub.stderr.split(": error: ", 1)[1] == run.stderr.split(": error: ", 1)[1]
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(timeout=60)
