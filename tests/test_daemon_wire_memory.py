"""Resident memory of `rigctl run` through an accelerated 12-hour capture over the wire (issue 8):
the real drivers (ACL table, Xsens IMU, NovAtel receiver on ptys) against the emulated hardware
in this process. The IMU streams at 10 Hz so that 12 h at 2000x is 20,000 frames per wall second
on the pty -- the memory question is about hours of polling, buffering and flushing, not about
the sample rate (tests/test_daemon_crash.py runs 12 h at 100 Hz in-process)."""
from __future__ import annotations

import subprocess
import time
from pathlib import Path

import h5py
import pytest

from helpers import rigctl_cmd
from hil_support import wired

SPEED = 2000.0
RATE_HZ = 10


def rss_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


@pytest.mark.slow
def test_12h_capture_over_the_wire_resident_memory_flat(tmp_path):
    proc = tmp_path / "cap12.yaml"
    proc.write_text("procedure: cap12\ndefaults:\n  settle: {timeout: 30 min}\n"
                    "steps:\n  - capture:\n      duration: 12 h\n      discard: 0 s\n")
    runs = tmp_path / "runs"
    marks: dict[int, int] = {}
    with wired(tmp_path, SPEED, imu={"rate_hz": RATE_HZ},
               suspenders={"imu_timeout_s": 600, "max_counter_gap": 1_000_000,
                           "min_free_mib": 0}) as (hw, cfg_path):
        log = (tmp_path / "run.out").open("w")
        p = subprocess.Popen([*rigctl_cmd(), "run", str(proc), "--config", str(cfg_path), "--out", str(runs)],
                             stdout=log, stderr=subprocess.STDOUT)
        t_first = None
        try:
            while p.poll() is None:
                time.sleep(0.05)
                if t_first is None:
                    if list(runs.glob("*/recording.h5")):
                        t_first = hw.clock.now()  # rig time at which the recording exists
                    continue
                h = int((hw.clock.now() - t_first) // 3600)
                if 1 <= h <= 12 and h not in marks and (r := rss_kib(p.pid)) is not None:
                    marks[h] = r
            p.wait(timeout=300)
        finally:
            if p.poll() is None:
                p.kill()
            log.close()
    out = (tmp_path / "run.out").read_text()
    assert p.returncode == 0, out[-3000:]
    assert {1, 11} <= set(marks), (marks, out[-2000:])
    last = max(marks)
    assert marks[last] <= 1.10 * marks[1], f"RSS grew from {marks[1]} KiB at 1 h to {marks[last]} KiB at {last} h"
    rec = next(runs.glob("*/recording.h5"))
    with h5py.File(rec, "r") as f:
        assert f["run/status"][0] == b"complete"
        n = int(f["segments/last_sample"][0] - f["segments/first_sample"][0])
    assert n >= 0.99 * 12 * 3600 * RATE_HZ, n
    print(f"\nRSS of rigctl run over the wire: {marks[1]} KiB at 1 h, {marks[last]} KiB at {last} h "
          f"({100 * (marks[last] / marks[1] - 1):+.1f} %); {n} IMU samples in the capture")
