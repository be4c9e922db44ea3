"""The results database is an extra (rigctl[db]): without it an analysis that was not asked for a
database says nothing about one; one given ``--db`` says, once, what to install.

The extra's absence is made real for this process by making its module unimportable
(``sys.modules[name] = None`` makes ``import`` raise ImportError, as a missing SQLAlchemy does).
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from rigctl.analysis import production


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
    target = str(tmp_path / "lab.sqlite")
    line = production.to_database(tmp_path / "recording.h5", "allan", {}, target)
    assert "\n" not in line and target in line and "pip install -e '.[db]'" in line, line
    assert production.to_database(tmp_path / "recording.h5", "allan", {}, "none") == ""


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
