"""The results database is an extra (rigctl[db]): without it an analysis that was not asked for a
database says nothing about one; one given ``--db`` says, once, what to install.

The extra's absence is made real for this process by making its module unimportable
(``sys.modules[name] = None`` makes ``import`` raise ImportError, as a missing SQLAlchemy does).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from recording_helpers import write_recording
from rigctl.analysis import production
from rigctl.errors import InputError


@pytest.fixture
def without_db_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    import rigctl.recording

    monkeypatch.setitem(sys.modules, "rigctl.recording.results_db", None)
    # ``from rigctl.recording import results_db`` takes the package's attribute before
    # sys.modules: once another test in this process imported the module, it must go too
    monkeypatch.delattr(rigctl.recording, "results_db", raising=False)
    with pytest.raises(ImportError):
        from rigctl.recording import results_db  # noqa: F401


def test_the_default_database_says_nothing_without_the_extra(without_db_extra, tmp_path) -> None:
    """The audit: every analysis printed 'results database not written: install rigctl[db]'."""
    assert production.to_database(tmp_path / "recording.h5", "allan", {}, None) == ""


def test_an_explicit_database_says_what_to_install(without_db_extra, tmp_path) -> None:
    """An explicit --db without the extra is invalid input (exit 2), not a printed line after
    which the command exited 0 (the audit)."""
    target = str(tmp_path / "lab.sqlite")
    with pytest.raises(InputError) as e:
        production.to_database(tmp_path / "recording.h5", "allan", {}, target)
    line = str(e.value)
    assert "\n" not in line and target in line and "pip install -e '.[db]'" in line, line
    assert production.to_database(tmp_path / "recording.h5", "allan", {}, "none") == ""
    production.check_database_option(None, "rigctl allan")  # the default needs no extra
    production.check_database_option("none", "rigctl allan")


def _rigctl_without_db_extra(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """rigctl in a real subprocess whose results-database module cannot be imported."""
    code = ("import sys; sys.modules['rigctl.recording.results_db'] = None\n"
            "from rigctl.cli import main; sys.exit(main(sys.argv[1:]))")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60,
                          cwd=cwd)


def test_history_without_the_extra_says_what_to_install(tmp_path) -> None:
    """`rigctl history` needs the database: it said 'internal error: ModuleNotFoundError ...
    (a bug in rigctl: please report it ...)'; now one line naming the extra, exit 2."""
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "results.sqlite").write_bytes(b"")
    r = _rigctl_without_db_extra("history", "SN-1", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install -e '.[db]'" in lines[0] and "internal error" not in lines[0], r.stderr


def _white_recording(path: Path) -> Path:
    """A 200 s, 100 Hz still record of white noise (no segments: Allan analysis only)."""
    rng = np.random.default_rng(3)
    path.parent.mkdir(parents=True)
    return write_recording(path, 100.0, angular_rate=1e-3 * rng.standard_normal((20000, 3)),
                           specific_force=np.array([0.0, 0.0, 9.81]) + 1e-3 * rng.standard_normal((20000, 3)))


def test_batch_without_the_extra_runs(tmp_path) -> None:
    """`rigctl batch` needs the database module only to find its output folder: without the
    extra it stopped with 'rigctl batch needs the results database' (exit 2) before analysing
    anything; now it analyses, writes its summary and says nothing of a database. (The
    recording has no 24-position segments: its calibration fails at once, exit 1, which keeps
    the test fast; the batch and its summary run as for any other.)"""
    _white_recording(tmp_path / "runs" / "a" / "recording.h5")
    r = _rigctl_without_db_extra("batch", "runs/*/recording.h5", "--workers", "1", "--out", "summary",
                                 cwd=tmp_path)
    out = r.stdout + r.stderr
    assert r.returncode == 1 and "0 of 1 analysed" in r.stdout, out
    assert "[db]" not in out and "database" not in out, out
    summary = json.loads((tmp_path / "summary" / "summary.json").read_text())
    assert summary["summary"][next(iter(summary["summary"]))]["recordings"] == 1
    assert not list(tmp_path.rglob("*.sqlite"))


@pytest.mark.parametrize("command", [("allan",), ("calibrate",), ("batch",)])
def test_explicit_db_without_the_extra_exits_2_first(tmp_path, command) -> None:
    """`--db URL` without the extra: the analysis ran, a line said what to install and the
    command exited 0; now one line naming the extra, exit 2, before any analysis output."""
    rec = _white_recording(tmp_path / "run" / "recording.h5")
    r = _rigctl_without_db_extra(command[0], str(rec), *command[1:], "--db", "sqlite:///lab.sqlite",
                                 cwd=tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install -e '.[db]'" in lines[0] and "sqlite:///lab.sqlite" in lines[0], r.stderr
    assert r.stdout == "", r.stdout  # nothing analysed, nothing printed before the error
    with __import__("h5py").File(rec, "r") as f:
        assert "results" not in f
