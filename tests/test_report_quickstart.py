"""Every command of docs/quickstart.md, in order, in a copy of the checkout (issue 9).

The ```sh blocks are run as one bash script (as a user types them) in a temporary copy of the
working tree (tracked and untracked, not ignored, files: what a fresh clone holds plus the work
in progress), install lines included: the script creates its own venv and pip-installs the
project into it (about 25 s with pip's cache warm, as it is after `.ci/run`'s own install).
"""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from helpers import ROOT, assert_k_lines_cover_truth

pytest.importorskip("matplotlib")
QUICKSTART = ROOT / "docs" / "quickstart.md"


def sh_commands(text: str) -> list[str]:
    """Non-empty, non-comment lines of the ```sh blocks, in order."""
    out = []
    for block in re.findall(r"^```sh\n(.*?)^```", text, flags=re.S | re.M):
        out += [ln.strip() for ln in block.splitlines() if ln.strip() and not ln.strip().startswith("#")]
    return out


def copy_checkout(dest: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT,
                           capture_output=True, check=True, timeout=60).stdout.decode().split("\0")
    for rel in filter(None, files):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)


def test_quickstart_commands_work_in_order(tmp_path: Path) -> None:
    if shutil.which("bash") is None or shutil.which("git") is None:
        pytest.skip("needs bash and git")
    run = sh_commands(QUICKSTART.read_text())
    assert run[:3] == ["python3 -m venv .venv", ". .venv/bin/activate", "pip install -e '.[report]'"], run
    assert any(c.startswith("rigctl run procedures/full-calibration.yaml") for c in run)
    assert any(c.startswith("rigctl report ") for c in run)
    work = tmp_path / "clone"
    copy_checkout(work)
    assert not (work / "runs").exists()
    script = tmp_path / "quickstart.sh"
    script.write_text("set -euo pipefail\n" + "\n".join(run) + "\n")
    # the user's shell: no venv active (drop this test run's venv from PATH), and Python writing
    # its bytecode caches (__pycache__) as it does by default. pip does not byte-compile what it
    # installs (PIP_COMPILE=no, pip's --no-compile): Python compiles each module the commands
    # import at its first import and keeps it, the same compiler on the same files; compiling the
    # ~2,400 installed modules up front (most never imported here: scipy's, matplotlib's, the build
    # environment's setuptools) was ~14 s of the test's ~97 s of CPU, ~10 s of it for nothing
    venv_bin = str(Path(sys.executable).parent)
    path = os.pathsep.join(p for p in os.environ.get("PATH", "").split(os.pathsep) if p != venv_bin)
    env = {k: v for k, v in os.environ.items()
           if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONDONTWRITEBYTECODE")}
    env.update(PATH=path, PYTHONUNBUFFERED="1", PIP_COMPILE="no")
    r = subprocess.run(["bash", str(script)], cwd=work, env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, f"quickstart failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    runs = sorted((work / "runs").glob("*-full-calibration"))
    assert len(runs) == 1
    assert f"report written: runs/{runs[0].name}/report.html" in r.stdout
    page = (runs[0] / "report.html").read_text()
    for sid in ("summary", "table", "calibration", "closed-loop", "allan", "sync", "events", "provenance"):
        assert f'<section id="{sid}">' in page
    assert 'id="plot-table_timeline"' in page and 'id="plot-cal_residuals_orientation"' in page
    allan = sorted((work / "runs").glob("*-allan-overnight"))
    assert len(allan) == 1 and 'id="plot-allan"' in (allan[0] / "report.html").read_text()
    # the default emulator has B and K: the 5-minute capture shows B as an estimate with its
    # interval on most axes, and K as a bound (what docs/quickstart.md says it shows)
    b_est = re.findall(r"allan [ga][xyz]: N [^;]+; B [0-9.e+-]+ (?:deg/h|mg) \[", r.stdout)
    k_bound = re.findall(r"allan [ga][xyz]: .*; K < [0-9.e+-]+ ", r.stdout)
    assert len(b_est) >= 4 and len(k_bound) == 6, r.stdout[-3000:]
    # calibrate's noise-model lines (the run's own, from the session, and with --noise NIGHT.h5):
    # K (0.05 m/s/h/sqrt(h), 3 deg/h/sqrt(h) on the emulator) as a bound or interval holding it
    with h5py.File(runs[0] / "recording.h5", "r") as f:
        p = json.loads(f["truth"].attrs["params_json"])
    assert_k_lines_cover_truth(r.stdout, p.get("imu", p), blocks=2)
