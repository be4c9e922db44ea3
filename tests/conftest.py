"""Shared pytest fixtures."""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REF_DATA = ROOT / "tests" / "data"


@pytest.fixture(scope="session")
def ref_data() -> Path:
    """Path to tests/data: real data and reference results from other labs (README there)."""
    return REF_DATA


@pytest.fixture(scope="session")
def full_calibration_run(tmp_path_factory) -> tuple[Path, str]:
    """A short emulated full calibration run once per session as ``rigctl run`` (a subprocess):
    its solve steps calibrate and write the report. Returns (run directory, stdout)."""
    from helpers import run_rigctl

    out = tmp_path_factory.mktemp("runs")
    r = run_rigctl("run", "procedures/full-calibration.yaml", "-p", "warmup=1 min", "-p", "sample=5 s",
                   "--out", str(out), timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return next(out.glob("*-full-calibration")), r.stdout


@pytest.fixture
def small_fs(tmp_path):
    """A 6 MiB tmpfs (a disk that fills up); skips unless this process may mount one (root)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"mount -t tmpfs is not permitted here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """Lines a test left in ``config._rigctl_summary`` (e.g. the hostile-input case count)."""
    for line in getattr(config, "_rigctl_summary", []):
        terminalreporter.write_line(line)
