"""Where the results database lives by default, without the database itself.

Kept apart from :mod:`rigctl.recording.results_db` (which needs the ``db`` extra: SQLAlchemy,
Alembic) so that what only needs the place -- ``rigctl batch`` finding the folder that holds
the run directories, for its summary -- works without the extra.
"""
from __future__ import annotations

from pathlib import Path

DEFAULT_NAME = "results.sqlite"


def default_path(recording: str | Path) -> Path:
    """``results.sqlite`` in the folder that holds the run directories: for
    runs/<run>/recording.h5 that is runs/ (a run directory has the run's log or config);
    for a recording elsewhere, its own folder."""
    rec = Path(recording).resolve()
    run_dir = rec.parent
    if (run_dir / "run.log.jsonl").exists() or (run_dir / "config.yaml").exists():
        return run_dir.parent / DEFAULT_NAME
    return run_dir / DEFAULT_NAME
