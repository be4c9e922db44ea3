"""The results database: every calibration and Allan result of every unit, across runs.

SQLAlchemy 2 (ORM, declarative); SQLite by default (``runs/results.sqlite``: the folder that
holds the run directories) or PostgreSQL (``postgresql+psycopg://user@host/db``) or any URL
SQLAlchemy accepts. The schema is versioned with Alembic (``rigctl/recording/db_migrations``): opening a
database upgrades it to the newest revision first, so an old file keeps working.

Tables (docs/production.md):

* ``analyses``: one row per analysed recording and kind (calibration / allan): unit ID (/meta
  imu_serial, else imu_device_id), run (the run directory's name), recording path, recorded
  (/meta started_utc) and analysed times (UTC), procedure, lot, software version, spec, decision
  rule and overall verdict. Analysing the same recording again replaces its rows.
* ``results``: one row per published parameter (:mod:`rigctl.analysis.results`): display name,
  SI name, value and standard uncertainty in SI and in the display unit, the unit, coverage
  factor k, dof, 95 % interval, verdict and conformance probability (NULL without a spec).
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

from sqlalchemy import (Engine, Float, ForeignKey, Integer, String, Text, create_engine, delete,
                        event, inspect, select, text)
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, relationship

from .results_place import DEFAULT_NAME, default_path  # noqa: F401 - the database's place, re-exported
from .shield import shielded

if TYPE_CHECKING:  # annotations only: the application layer imports this module, not the reverse
    from alembic.config import Config

    from ..analysis.production import RunInfo
    from ..analysis.results import Measured


#: the newest schema revision (rigctl/recording/db_migrations/versions; tests/test_results_db_concurrency.py
#: checks it is Alembic's head): a database already there is used without loading Alembic
HEAD = "0001"


class Base(DeclarativeBase):
    pass


class Analysis(Base):
    __tablename__ = "analyses"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    unit_id: Mapped[str] = mapped_column(String(128), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    run: Mapped[str] = mapped_column(String(256))
    recording: Mapped[str] = mapped_column(Text)
    recorded_utc: Mapped[str | None] = mapped_column(String(40))
    analysed_utc: Mapped[str] = mapped_column(String(40))
    procedure: Mapped[str | None] = mapped_column(String(128))
    lot: Mapped[str | None] = mapped_column(String(128), index=True)
    software_version: Mapped[str] = mapped_column(String(64))
    spec: Mapped[str | None] = mapped_column(Text)
    decision_rule: Mapped[str | None] = mapped_column(String(16))
    overall_verdict: Mapped[str | None] = mapped_column(String(16))
    results: Mapped[list["Result"]] = relationship(back_populates="analysis", cascade="all, delete-orphan",
                                                  order_by="Result.id")


class Result(Base):
    __tablename__ = "results"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    analysis_id: Mapped[int] = mapped_column(ForeignKey("analyses.id", ondelete="CASCADE"), index=True)
    parameter: Mapped[str] = mapped_column(String(128), index=True)
    name_si: Mapped[str] = mapped_column(String(128))
    value_si: Mapped[float] = mapped_column(Float(53))
    u_si: Mapped[float] = mapped_column(Float(53))
    value: Mapped[float] = mapped_column(Float(53))
    u: Mapped[float] = mapped_column(Float(53))
    unit: Mapped[str] = mapped_column(String(32))
    k: Mapped[float | None] = mapped_column(Float(53))
    dof: Mapped[float | None] = mapped_column(Float(53))
    ci95_low: Mapped[float | None] = mapped_column(Float(53))
    ci95_high: Mapped[float | None] = mapped_column(Float(53))
    verdict: Mapped[str | None] = mapped_column(String(16))
    p_conform: Mapped[float | None] = mapped_column(Float(53))
    analysis: Mapped[Analysis] = relationship(back_populates="results")


def url_for(target: str | Path) -> str:
    """A database URL from what the user gave: a URL (contains '://') or a SQLite file path."""
    t = str(target)
    return t if "://" in t else f"sqlite:///{Path(t).resolve()}"


def prepare(target: str | Path | None) -> None:
    """Do beforehand what the first :func:`open_db` and :func:`write` of a process would
    otherwise do on the caller's critical path, opening nothing: import the dialect of
    ``target``'s URL and its DB-API module (None: SQLite's, as :func:`default_path` gives;
    ``sqlalchemy.dialects.sqlite`` and ``sqlite3``: ~0.02 s of CPU) and configure the ORM
    mappers (~0.01 s). Raises what SQLAlchemy raises for an unknown dialect or a missing
    driver (:func:`open_db` then says so again)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.orm import configure_mappers

    make_url(url_for(target) if target else "sqlite://").get_dialect().import_dbapi()
    configure_mappers()


def _alembic_config(engine: Engine) -> Config:
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(Path(__file__).with_name("db_migrations")))
    cfg.set_main_option("sqlalchemy.url", engine.url.render_as_string(hide_password=False))
    return cfg


def open_db(target: str | Path) -> Engine:
    """An engine for ``target`` with the schema upgraded to the newest revision."""
    url = url_for(target)
    if url.startswith("sqlite:///"):
        Path(url[len("sqlite:///"):]).parent.mkdir(parents=True, exist_ok=True)
    sqlite = url.startswith("sqlite:///")
    # several processes (two resumes, batch workers) may open the same database at once: wait
    # for one another's writes instead of failing with "database is locked"
    engine = create_engine(url, connect_args={"timeout": 60.0} if sqlite else {})
    if engine.dialect.name == "sqlite":
        event.listen(engine, "connect", lambda c, _: c.execute("PRAGMA foreign_keys=ON"))
    with _schema_lock(url), engine.begin() as conn:
        if engine.dialect.name == "postgresql":  # held until this transaction ends
            conn.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": _SCHEMA_LOCK_KEY})
        if _revision(conn) != HEAD:
            from alembic import command  # ~1 s of imports: only when the schema must change

            cfg = _alembic_config(engine)
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, "head")
    return engine


def _revision(conn: Any) -> str | None:
    """The schema revision Alembic recorded in the database (None: none or several)."""
    if not inspect(conn).has_table("alembic_version"):
        return None
    rows = conn.execute(text("SELECT version_num FROM alembic_version")).fetchall()
    return rows[0][0] if len(rows) == 1 else None


#: pg_advisory_xact_lock key serialising schema upgrades (any constant shared by all rigctl)
_SCHEMA_LOCK_KEY = 0x72696763


@contextlib.contextmanager
def _schema_lock(url: str) -> Iterator[None]:
    """For a SQLite file, an exclusive flock on ``FILE.lock`` while the schema is created or
    upgraded: two processes creating the same new database would otherwise both try to create
    the alembic_version table and one would fail."""
    if not url.startswith("sqlite:///"):
        yield
        return
    with open(url[len("sqlite:///"):] + ".lock", "a+b") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _f(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def write(engine: Engine, info: RunInfo, measured: list[Measured],
          verdicts: dict[str, Any] | None = None) -> int:
    """Store one analysed recording (replacing an earlier analysis of the same recording and
    kind); returns the analysis id. One transaction, whole even when an interruption arrives
    meanwhile (:func:`rigctl.recording.shield.shielded`)."""
    by_param = {r["parameter"]: r for r in (verdicts or {}).get("parameters", [])}
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    with shielded(), Session(engine) as s, s.begin():
        s.execute(delete(Analysis).where(Analysis.recording == info.recording, Analysis.kind == info.kind))
        a = Analysis(unit_id=info.unit_id, kind=info.kind, run=info.run, recording=info.recording,
                     recorded_utc=info.recorded_utc, analysed_utc=now, procedure=info.procedure,
                     lot=info.lot, software_version=info.software_version,
                     spec=(verdicts or {}).get("spec"), decision_rule=(verdicts or {}).get("rule"),
                     overall_verdict=(verdicts or {}).get("overall"))
        for m in measured:
            d = m.display
            lo, hi = m.interval
            v = by_param.get(d.base)
            a.results.append(Result(parameter=d.base, name_si=m.name, value_si=m.value, u_si=m.u,
                                    value=d.value(m.value), u=d.sigma(m.u), unit=d.unit,
                                    k=_f(m.coverage_factor), dof=_f(m.dof),
                                    ci95_low=_f(d.value(lo)), ci95_high=_f(d.value(hi)),
                                    verdict=None if v is None else v["verdict"],
                                    p_conform=None if v is None else v["p_conform"]))
        s.add(a)
        s.flush()
        return a.id


def unit_history(engine: Engine, unit_id: str, kind: str | None = None) -> list[Analysis]:
    """Every analysis of a unit (results loaded), oldest first (by recording time)."""
    with Session(engine) as s:
        q = select(Analysis).where(Analysis.unit_id == unit_id)
        if kind:
            q = q.where(Analysis.kind == kind)
        rows = list(s.scalars(q))
        for a in rows:
            _ = list(a.results)
        s.expunge_all()
    return sorted(rows, key=lambda a: (a.recorded_utc or a.analysed_utc, a.id))


def all_rows(engine: Engine) -> list[dict[str, Any]]:
    """Every result joined with its analysis, as plain dicts (for comparisons and exports)."""
    with Session(engine) as s:
        q = select(Analysis, Result).join(Result).order_by(Analysis.unit_id, Analysis.kind, Result.parameter)
        out = []
        for a, r in s.execute(q):
            out.append({"unit_id": a.unit_id, "kind": a.kind, "run": a.run, "recording": a.recording,
                        "lot": a.lot, "software_version": a.software_version,
                        "overall_verdict": a.overall_verdict,
                        **{c: getattr(r, c) for c in ("parameter", "name_si", "value_si", "u_si", "value",
                                                      "u", "unit", "k", "dof", "ci95_low", "ci95_high",
                                                      "verdict", "p_conform")}})
    return out
