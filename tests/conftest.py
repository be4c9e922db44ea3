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


# -- parallel runs (opt-in: -n 2 --dist loadfile) ----------------------------------------------
# A test file is one unit of work, so its module- and session-scoped fixtures (emulated runs,
# real-data imports) are made once, as in a serial run. Not the default: the wire/HIL/daemon
# real-time tests (pty floods, 100x-200x rig clocks, kill -9 windows) missed their deadlines with a
# second worker on a 2-core machine.

#: files that share an expensive session-scoped fixture of this conftest: one worker runs them all
SHARED_FIXTURE_FILES = {
    "tests/test_production_certificate.py": "full_calibration_run",
    "tests/test_report_sections.py": "full_calibration_run",
    "tests/test_report_html.py": "full_calibration_run",
}

try:
    from xdist.scheduler import LoadFileScheduling
except ImportError:  # a venv installed before pytest-xdist joined the test extras
    LoadFileScheduling = None

if LoadFileScheduling is not None:
    class _FileScheduling(LoadFileScheduling):
        """--dist loadfile, with the files of SHARED_FIXTURE_FILES as one unit."""

        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return SHARED_FIXTURE_FILES.get(path, path)

    @pytest.hookimpl(optionalhook=True)
    def pytest_xdist_make_scheduler(config, log):
        return _FileScheduling(config, log) if config.getoption("dist") == "loadfile" else None


_SUMMARY: list[str] = []


def pytest_runtest_logreport(report):
    """Collect the lines a test left in its ``user_properties`` under ``rigctl_summary`` (e.g. the
    hostile-input case count); they travel with the report from an xdist worker."""
    if report.when == "call":
        _SUMMARY.extend(line for key, lines in report.user_properties if key == "rigctl_summary"
                        for line in lines)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """The lines tests left for the summary (pytest_runtest_logreport)."""
    for line in _SUMMARY:
        terminalreporter.write_line(line)
