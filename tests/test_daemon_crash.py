"""Crash safety with real processes: kill -9 at random moments of an accelerated overnight
capture, then ``rigctl resume``. (Flat memory through a 12-hour capture: tests/test_capture_memory.py.)

"At most 1 s of data at risk" is measured in wall seconds: the recording stores the Unix time
at which the run's scaled clock read zero (``/meta clock_zero_unix_s``), so the last flushed
IMU sample (rig time T) was produced at wall time ``clock_zero + T / speed``. Data at risk =
wall time of the kill - that instant; it must be <= 1 s.

The resume is what completes a run's solve steps (Allan, report): a whole run took 6.9 s of CPU
with them and 2.5 s without (so most of the resumes' time was the solvers); the first
:data:`SOLVED` runs keep the shipped procedure's solve step, so a resumed run's solvers still run
and are checked on a stitched recording; the others run the same procedure without it (the kills
fall in the capture either way: they hit the writer, not the solvers).
"""
from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor

import h5py
import numpy as np
import pytest
import yaml

from helpers import DURATION_EPS, ROOT, derived_config, rigctl_cmd, run_rigctl

SPEED = 500.0
KILLS = 20
#: the runs (of KILLS) whose resume also runs the procedure's solve step (allan, report)
SOLVED = 2
#: rig time of the capture, s: the run lasts (30 s + CAPTURE_S) / SPEED = 1.5 s of wall time, so
#: that a kill (at most 1 s after the recording appears) still finds the run in its capture
#: when the run has no solve step after it
CAPTURE_S = 720.0


def _procedure_without_solve(tmp) -> str:
    """procedures/allan-overnight.yaml without its solve step (and its include beside it)."""
    d = tmp / "procedures"
    d.mkdir()
    proc = yaml.safe_load((ROOT / "procedures" / "allan-overnight.yaml").read_text())
    kinds = [next(iter(step)) for step in proc["steps"]]
    assert kinds == ["include", "capture", "solve"], kinds
    proc["steps"] = proc["steps"][:-1]
    (d / "allan-overnight.yaml").write_text(yaml.safe_dump(proc, sort_keys=False))
    (d / "warmup.yaml").write_text((ROOT / "procedures" / "warmup.yaml").read_text())
    return str(d / "allan-overnight.yaml")


def _new_recording(runs, known, deadline):
    while time.monotonic() < deadline:
        for p in runs.glob("*/recording.h5"):
            if p not in known:
                return p
        time.sleep(0.01)
    return None


@pytest.mark.slow
def test_kill9_at_20_random_moments_files_open_lose_under_1s_and_resume_completes(tmp_path):
    cfg = derived_config(tmp_path, clock="scaled", speed=SPEED)
    runs = tmp_path / "runs"
    runs.mkdir()
    rng = random.Random(20240608)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    known: set = set()
    killed = []
    errlog = tmp_path / "stderr.txt"
    no_solve = _procedure_without_solve(tmp_path)
    for i in range(KILLS):
        procedure = "procedures/allan-overnight.yaml" if i < SOLVED else no_solve
        proc = subprocess.Popen([*rigctl_cmd(), "run", procedure, "--config", str(cfg),
                                 "-p", "warmup=30 s", "-p", f"capture={CAPTURE_S:g} s", "--out", str(runs)],
                                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=errlog.open("w"), env=env)
        try:
            rec = _new_recording(runs, known, time.monotonic() + 30)
            assert rec is not None, f"run {i}: no recording appeared: {errlog.read_text()[-2000:]}"
            known.add(rec)
            time.sleep(rng.uniform(0.0, 1.0))  # the run lasts ~1.5 s of wall time at 500x
            t_kill = time.time()
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == -signal.SIGKILL
        # the file opens with h5py as cut off (SWMR read: the writer's flags are still set)
        with h5py.File(rec, "r", libver="latest", swmr=True) as f:
            assert f["run/status"][0] == b"running"
            t0 = float(f["meta"].attrs["clock_zero_unix_s"])
            n = f["imu/time"].shape[0]
            last_t = float(f["imu/time"][-1]) if n else 0.0
            counters = f["imu/counter"][()].astype(np.int64)
            assert np.all(np.diff(counters) == 1)  # everything flushed is intact
            for g in ("imu", "table", "segments", "events"):
                lengths = {f[g][k].shape[0] for k in f[g]}
                assert len(lengths) == 1, f"{g} columns of unequal length {lengths}"
        at_risk = t_kill - (t0 + last_t / SPEED)
        assert at_risk <= 1.0, f"kill {i}: {at_risk:.3f} s of data at risk ({n} IMU rows flushed)"
        killed.append((rec, n, at_risk))
    assert len(killed) == KILLS
    # every cut-off run completes with `rigctl resume` into the same recording (two at a time)
    before = {}
    for rec, n, _ in killed:
        with h5py.File(rec, "r", libver="latest", swmr=True) as f:
            before[rec] = f["imu/specific_force"][:n]
    with ThreadPoolExecutor(max_workers=2) as pool:
        done_runs = list(pool.map(lambda k: run_rigctl("resume", str(k[0].parent), "--runs", str(runs),
                                                       timeout=120), killed))
    for i, ((rec, n, _), r) in enumerate(zip(killed, done_runs)):
        assert r.returncode == 0, r.stdout + r.stderr
        # the solve step ran in the resumed session (its report), and only where the run had one
        assert (rec.parent / "report.html").is_file() == (i < SOLVED), r.stdout
        with h5py.File(rec, "r") as f:  # plain open: flags cleared, closed properly
            assert f["run/status"][0] == b"complete"
            np.testing.assert_array_equal(f["imu/specific_force"][:n], before[rec])
            seg = {k: f["segments"][k][()] for k in ("kind", "status", "first_sample", "last_sample",
                                                     "t_start", "t_end")}
            done = seg["status"] == b"complete"
            assert sorted(seg["kind"][done].tolist()) == [b"capture", b"warmup"]
            cap = int(np.flatnonzero(done & (seg["kind"] == b"capture"))[0])
            # the sampling window spans the full capture (with a scaled clock it is wall-timed, so
            # the sample count follows the polls: see the report on heavily loaded machines).
            # t_end - t_start is CAPTURE_S only to float rounding (t_end = t_start + CAPTURE_S,
            # offsets of a resumed session added to both ends: 1113.10... - 513.10... = 599.99...)
            assert seg["t_end"][cap] - seg["t_start"][cap] >= CAPTURE_S - DURATION_EPS
            assert seg["last_sample"][cap] - seg["first_sample"][cap] >= 0.99 * CAPTURE_S * 100
            c = f["imu/counter"][seg["first_sample"][cap]:seg["last_sample"][cap]].astype(np.int64)
            assert np.all(np.diff(c) == 1)
            # the data of the step in flight are marked and not in any complete segment
            ev = [m for k, m in zip(f["events/kind"][()], f["events/message"][()]) if k == b"resume"]
            assert any(b"session 2 after a cut-off" in m for m in ev)
            for i in np.flatnonzero(~done):
                a, z = seg["first_sample"][i], seg["last_sample"][i]
                for j in np.flatnonzero(done):
                    assert z <= seg["first_sample"][j] or a >= seg["last_sample"][j]
        ck = json.loads((rec.parent / "checkpoint.json").read_text())
        assert ck["status"] == "complete" and ck["sessions"] == 2
