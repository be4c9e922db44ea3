"""Shared pytest fixtures."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to ../shared/data (reference data from other labs); skips when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not present beside the checkout")
    return SHARED_DATA


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
