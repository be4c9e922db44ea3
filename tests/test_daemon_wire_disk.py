"""A full disk over the wire: `rigctl run` (a real process, wired config) records onto a small
tmpfs that the test fills up in the middle of the run. The run pauses with a message saying so,
writes nothing while the disk is full, resumes when space is back and completes; nothing it
had written before is changed. Needs root (mount -t tmpfs); skipped with the reason otherwise."""
from __future__ import annotations

import os
import re
import subprocess

import h5py
import numpy as np

from helpers import DISK_PROCEDURE, ROOT, fill_disk as fill, rigctl_cmd

from hil_support import wait_until, wired

SPEED = 50.0
PROC = DISK_PROCEDURE


def test_full_disk_over_the_wire_pauses_and_damages_nothing(tmp_path, small_fs):
    proc = tmp_path / "disk.yaml"
    proc.write_text(PROC)
    out = tmp_path / "run.out"
    ballast = small_fs / "ballast"
    with wired(tmp_path, SPEED, suspenders={"hold_s": "2 s", "min_free_mib": 1}) as (hw, cfg):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        p = subprocess.Popen([*rigctl_cmd(), "run", str(proc), "--config", str(cfg), "--out", str(small_fs)],
                             cwd=ROOT, env=env, stdout=out.open("w"), stderr=subprocess.STDOUT)
        try:
            ck = wait_until(lambda: next(small_fs.glob("*/checkpoint.json"), None), 30, "the run directory")
            wait_until(lambda: '"last_step": 0' in ck.read_text(), 30, "the warm-up to complete")
            rec = ck.parent / "recording.h5"
            with h5py.File(rec, "r", libver="latest", swmr=True) as f:   # what is on disk now
                n0 = f["imu/time"].shape[0]
                before = {k: f["imu"][k][:n0] for k in f["imu"]}
                warm = {k: f["segments"][k][0] for k in f["segments"]}
            fill(ballast)
            wait_until(lambda: "suspended (disk)" in out.read_text(), 30, "the run to pause on the full disk")
            wait_until(lambda: "paused" in out.read_text().split("suspended (disk)")[1], 10, "paused")
            free_full = os.statvfs(small_fs).f_bavail
            ballast.unlink()
            assert p.wait(timeout=60) == 0, out.read_text()[-3000:]
        finally:
            if p.poll() is None:
                p.kill()
    text = out.read_text()
    # the pause names the cause, where, how much is free and what happens / what to do
    # (the suspender's disk check or the recorder's reserve check, whichever saw it first)
    line = next(ln for ln in text.splitlines() if "suspended (disk)" in ln)
    m = re.search(r"suspended \(disk\): disk space low: (\d+\.\d\d) MiB free on (the run directory's "
                  r"filesystem \()?" + re.escape(str(small_fs)), line)
    assert m, line
    assert line.endswith(("need at least 1.00 MiB; free some space",       # the config's min_free_mib
                          "reserve of 0.25 MiB; writes held until space is freed")), line
    # what was free when the check saw it: below the limit the line names (the test fills the
    # disk 64 kB at a time, so a check during the fill can see e.g. 0.99 MiB, not only 0.00)
    limit = 1.00 if line.endswith("free some space") else 0.25
    assert float(m.group(1)) < limit, line
    assert free_full == 0
    with h5py.File(rec, "r") as f:      # plain open: closed properly
        assert f["run/status"][0] == b"complete"
        for k, v in before.items():     # nothing already written is touched
            np.testing.assert_array_equal(f["imu"][k][:n0], v)
        for k, v in warm.items():
            assert f["segments"][k][0].tobytes() == np.asarray(v).tobytes()
        seg = {k: f["segments"][k][()] for k in ("kind", "status", "first_sample", "last_sample", "step")}
        ev = list(zip(f["events/kind"][()], f["events/message"][()]))
        c = f["imu/counter"][()].astype(np.int64)
    sus = [m for k, m in ev if k == b"suspend"]
    assert sus and sus[0].startswith(b"disk: disk space low")
    lost = [m for k, m in ev if k == b"data-lost"]
    assert len(lost) == 1 and b"not recorded while the disk was full" in lost[0]
    done = seg["status"] == b"complete"
    assert sorted(seg["step"][done].tolist()) == [0, 1, 2, 3]
    for a, z in zip(seg["first_sample"][done], seg["last_sample"][done]):
        assert z > a and np.all(np.diff(c[a:z]) == 1)
    print(f"\nfull disk: {n0} IMU rows on disk before the fill unchanged; {lost[0].decode()[:120]}")
