"""The console is not the run (issue 16, items 1-3): the cases without a wall-clock deadline
(moved verbatim from tests/test_cli_console.py, whose runs on a scaled clock and devices that
reply in wall time are REALTIME_FILES, on the real-time worker; these run on any worker).

* ``validate | head -1`` prints no traceback;
* devices are asked before a run starts: a missing serial port, a refused TCP port and a port
  without permission give one line each, exit 1 (README), and no run directory;
* a run that fails later (configs/sim.yaml: the virtual clock) keeps its directory with status
  ``failed``, the error in run.log.jsonl and in /events, the traceback only in the run log, one
  line on stderr;
* the daemon answers an invalid submission as ``rigctl run`` exits: 2.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest
import yaml

from helpers import ROOT, rigctl_cmd
from test_cli_console import WARMUP, final_state


def test_validate_into_head_prints_no_traceback():
    p = subprocess.Popen([*rigctl_cmd(), "validate", str(ROOT / "procedures" / "full-calibration.yaml")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    assert p.stdout.readline().startswith(b"procedure full-calibration")
    p.stdout.close()
    _, err = p.communicate(timeout=120)
    assert err == b"" and p.returncode == 0


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
