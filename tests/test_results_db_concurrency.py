"""Several processes opening one new results database at once (two `rigctl resume`, batch
workers): each must get a usable database; none may fail creating the schema."""
from __future__ import annotations

import multiprocessing as mp
from pathlib import Path

import sqlalchemy as sa

from rigctl.results_db import open_db


def _open(args: tuple[str, object]) -> str:
    path, barrier = args
    barrier.wait(timeout=60)  # type: ignore[attr-defined]
    try:
        open_db(path)
    except Exception as exc:  # reported to the parent, which asserts on it
        return f"{type(exc).__name__}: {exc}"
    return "ok"


def test_processes_creating_one_new_database_at_once(tmp_path: Path) -> None:
    path = str(tmp_path / "results.sqlite")
    ctx = mp.get_context("fork")
    n = 8
    with ctx.Manager() as mgr:
        barrier = mgr.Barrier(n)
        with ctx.Pool(n) as pool:
            outcomes = pool.map(_open, [(path, barrier)] * n)
    assert outcomes == ["ok"] * n, outcomes
    with sa.create_engine(f"sqlite:///{path}").connect() as c:
        assert c.execute(sa.text("SELECT count(*) FROM alembic_version")).scalar() == 1
