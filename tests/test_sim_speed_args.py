"""``rigctl sim up --speed X`` with a bad X: one line each, exit 2, before any emulator starts (no
wall-clock deadline: any worker; the speeds a host cannot keep up with are in
tests/test_sim_speed.py, REALTIME_FILES)."""
from __future__ import annotations

import subprocess

from helpers import ROOT, rigctl_cmd


def test_bad_speeds_are_one_line_each(tmp_path):
    bad = ["abc", "0", "-1", "nan", "inf", "1e6", "1001"]
    procs = {v: subprocess.Popen([*rigctl_cmd(), "sim", "up", "--speed", v], cwd=ROOT, text=True,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE) for v in bad}
    for v, p in procs.items():
        out, err = p.communicate(timeout=60)
        assert p.returncode == 2 and out == "", (v, out, err)
        assert err.splitlines() == [
            f"rigctl sim: error: --speed {v!r}: the emulated rig's clock runs 0.01 to 1000 times real time "
            "(give a number in that range, 1 = real time; above what this machine computes, the clock runs "
            "slower and 'rigctl sim up' says how fast)"], (v, err)
