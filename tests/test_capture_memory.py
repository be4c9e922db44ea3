"""Flat memory through a 12-hour capture on the emulator in virtual time (a subprocess of its own):
resident memory and the interpreter's allocated blocks after 1 h vs at 12 h. Virtual time, so no
wall-clock deadline: it runs beside other test files (tests/conftest.py)."""
from __future__ import annotations

import json
import subprocess
import sys

import h5py
import pytest

from helpers import ROOT

MEMORY_SCRIPT = r"""
import io, json, sys, resource
from contextlib import contextmanager
from pathlib import Path
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.engine.rig import open_rig
from rigctl.run.runner import RunOptions, run_procedure
from rigctl.config.suspenders import SuspenderSettings

def rss_kib():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1])

marks = []
@contextmanager
def opener(cfg):
    with open_rig(cfg) as (rig, truth):
        for h in range(1, 13):
            rig.table.world.faults.call_at(h * 3600.0, lambda h=h: marks.append(
                (h, rss_kib(), sys.getallocatedblocks())))
        yield rig, truth

out, root = Path(sys.argv[1]), Path(sys.argv[2])
cfg = load_config(root / "configs" / "sim.yaml")
p = out / "cap.yaml"
p.write_text("procedure: cap12\nsteps:\n  - capture:\n      duration: 12 h\n      discard: 0 s\n")
proc = load_procedure(p, limits=cfg.limits)
res = run_procedure(proc, cfg, out, console=io.StringIO(), install_signals=False,
                    options=RunOptions(suspenders=SuspenderSettings(min_free_bytes=0), rig_opener=opener,
                                       sample_poll_s=float(sys.argv[3])))
print(json.dumps({"status": res.status, "marks": marks, "recording": str(res.recording)}))
"""


@pytest.mark.slow
def test_12h_capture_memory_flat(tmp_path):
    """Resident memory after 1 h of a 12-hour capture (caches warm) vs at 12 h: at most +10 %.
    Polls every 2 s of rig time (21,600 polls in the window); a per-poll leak of even one
    object would show in the interpreter's allocated-block count, which must stay flat too."""
    r = subprocess.run([sys.executable, "-c", MEMORY_SCRIPT, str(tmp_path), str(ROOT), "2.0"],
                       capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["status"] == "complete"
    marks = {h: (rss, blocks) for h, rss, blocks in res["marks"]}
    assert sorted(marks) == list(range(1, 13))
    rss1, blocks1 = marks[1]
    rss12, blocks12 = marks[12]
    assert rss12 <= 1.10 * rss1, f"RSS grew from {rss1} KiB to {rss12} KiB"
    assert blocks12 - blocks1 < 10_000, f"allocated blocks grew by {blocks12 - blocks1}"
    with h5py.File(res["recording"], "r") as f:
        assert f["imu/time"].shape[0] >= 12 * 3600 * 100
        assert f["segments/last_sample"][0] - f["segments/first_sample"][0] == 12 * 3600 * 100
