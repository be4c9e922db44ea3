"""The results database is an extra (rigctl[db]): without it an analysis that was not asked for a
database says nothing about one; one given ``--db`` says, once, what to install.

The extra's absence is made real for this process by making its module unimportable
(``sys.modules[name] = None`` makes ``import`` raise ImportError, as a missing SQLAlchemy does).
"""
from __future__ import annotations

import sys

import pytest

from rigctl.analysis import production


@pytest.fixture
def without_db_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rigctl.recording.results_db", None)
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
