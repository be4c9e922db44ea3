"""Several processes opening one new results database at once (two `rigctl resume`, batch
workers): each must get a usable database; none may fail creating the schema."""
from __future__ import annotations

import multiprocessing as mp
from pathlib import Path

import sqlalchemy as sa

from rigctl.recording.results_db import open_db


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


def test_head_is_alembics_head_and_an_open_database_is_not_migrated_again(tmp_path: Path) -> None:
    """results_db.HEAD names the newest migration (a new one must move it), and a database
    already at HEAD is opened without Alembic (its import alone costs ~1 s per command)."""
    import subprocess
    import sys

    from alembic.config import Config
    from alembic.script import ScriptDirectory

    from rigctl.recording import results_db

    cfg = Config()
    cfg.set_main_option("script_location", str(Path(results_db.__file__).with_name("db_migrations")))
    assert ScriptDirectory.from_config(cfg).get_heads() == [results_db.HEAD]
    path = tmp_path / "results.sqlite"
    open_db(str(path)).dispose()  # created and migrated
    code = ("import sys; from rigctl.recording.results_db import open_db; open_db(sys.argv[1]).dispose(); "
            "print('alembic' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False"
    with sa.create_engine(f"sqlite:///{path}").connect() as c:
        assert c.execute(sa.text("SELECT version_num FROM alembic_version")).scalar() == "0001"
