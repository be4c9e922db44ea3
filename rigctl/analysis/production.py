"""From one analysed recording to the production record: verdicts and the results database.

The commands (calibrate, allan, batch) call :func:`verdicts_for` before they store their
results (so the verdicts are stored with them) and :func:`to_database` after. The unit under
test is identified by /meta ``imu_serial`` (the lab's label, rig config ``imu.serial``), else
``imu_device_id`` (what the IMU reports), else the recording's run name.
"""
from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py

from .. import __version__
from ..recording.recording_reader import open_recording
from ..config.spec import Spec
from . import results as R
from .verdicts import evaluate
from ..errors import InputError

KINDS = ("calibration", "allan")


@dataclass(frozen=True)
class RunInfo:
    """What identifies an analysed recording in the results database."""

    unit_id: str
    kind: str
    run: str
    recording: str
    recorded_utc: str | None
    procedure: str | None
    software_version: str
    lot: str | None = None


def _text(v: Any) -> str:
    return (v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)).strip()


def unit_id_of(meta: dict[str, Any], fallback: str) -> str:
    """The unit under test: /meta imu_serial, else imu_device_id, else ``fallback``."""
    for key in ("imu_serial", "imu_device_id"):
        v = _text(meta.get(key, ""))
        if v:
            return v
    return fallback


def run_name(recording: str | Path) -> str:
    """The run's name: its directory (runs/<UTC>-<procedure>) for recording.h5, else the file stem."""
    p = Path(recording).resolve()
    return p.parent.name if p.name == "recording.h5" else p.stem


def read_meta(recording: str | Path) -> dict[str, Any]:
    """/meta attributes of a recording (text decoded); {} when absent."""
    with open_recording(recording, need=()) as f:
        return {k: (_text(v) if isinstance(v, (bytes, str)) else v)
                for k, v in (f["meta"].attrs.items() if "meta" in f else [])}


def measured(kind: str, results: dict[str, Any]) -> list[R.Measured]:
    """The published parameters of a calibration payload or an Allan summary."""
    return R.from_calibration(results) if kind == "calibration" else R.from_allan(results)


def verdicts_for(spec: Spec | None, kind: str, results: dict[str, Any]) -> dict[str, Any] | None:
    """The verdicts of one command's results (entries it cannot measure do not count)."""
    if spec is None:
        return None
    return evaluate(spec, measured(kind, results), (kind,))


def run_info(recording: str | Path, kind: str, lot: str | None = None) -> RunInfo:
    """The database's identification of an analysed recording."""
    meta = read_meta(recording)
    return RunInfo(unit_id=unit_id_of(meta, run_name(recording)), kind=kind, run=run_name(recording),
                   recording=str(Path(recording).resolve()), recorded_utc=meta.get("started_utc") or None,
                   procedure=meta.get("procedure_name") or None, software_version=__version__, lot=lot)


def preload_database(target: str | None) -> threading.Thread | None:
    """Import the results database's modules (SQLAlchemy and the ORM classes: ~0.6 s of CPU,
    all of it Python holding the GIL) on a background thread, for a command that writes to
    the database after a long computation in compiled code (``rigctl allan``: the streamed
    sums run without the GIL, so the import costs the command no wall time of its own), and
    there also the target's dialect and driver and the ORM mappers
    (:func:`rigctl.recording.results_db.prepare`: without it ~0.03 s of the write after the
    analysis). :func:`to_database` then finds the modules imported (or waits for the import
    to finish, by Python's import lock). Returns the thread (a daemon); None, and nothing
    happens, for ``target == "none"``."""
    if target == "none":
        return None

    def load() -> None:
        try:
            from ..recording import results_db
        except ImportError:
            return  # to_database says what to install
        try:
            results_db.prepare(target)
        except Exception:  # noqa: BLE001 - a bad URL or driver: to_database raises it
            pass

    thread = threading.Thread(target=load, name="preload-results-db", daemon=True)
    thread.start()
    return thread


def results_db_module(command: str) -> Any:
    """The results database module (rigctl.recording.results_db) for ``command``, which needs
    it; without the ``db`` extra an InputError saying what to install (one line, exit 2)."""
    try:
        from ..recording import results_db as db  # optional dependency (rigctl[db])
    except ImportError as exc:
        raise InputError(f"{command} needs the results database: {exc}",
                         hint="install the db extra: pip install -e '.[db]'") from None
    return db


def check_database_option(target: str | None, command: str) -> None:
    """Refuse, before any analysis, a ``--db`` given explicitly (not None, not 'none') without
    the ``db`` extra installed: one line saying what to install, exit 2. The default database
    (``target`` None) needs no extra: without it nothing is written and nothing said."""
    if target is not None and target != "none":
        results_db_module(f"{command} --db {target}")


def to_database(recording: str | Path, kind: str, results: dict[str, Any], target: str | None,
                lot: str | None = None, engine: Any = None) -> str:
    """Write one analysed recording to the results database; returns the line to print.

    ``target``: a URL or SQLite path; None = the default (rigctl.recording.results_db.default_path);
    "none" = do not write. ``engine``: an open engine (batch: one for all recordings).
    Without the ``db`` extra the default writes nothing and says nothing (the user asked for
    no database); an explicit ``target`` is an InputError saying what to install (the commands
    check it first, :func:`check_database_option`, so that it comes before the analysis).
    """
    if target == "none":
        return ""
    try:
        from ..recording import results_db as db  # optional dependency (rigctl[db])
    except ImportError:
        if target is None:
            return ""
        check_database_option(target, "rigctl")
    where = target or str(db.default_path(recording))
    eng = engine or db.open_db(where)
    try:
        db.write(eng, run_info(recording, kind, lot), measured(kind, results), results.get("verdicts"))
    finally:
        if engine is None:
            eng.dispose()
    return f"results database: {eng.url.render_as_string(hide_password=True)}"


def _allan_summary(path: Path) -> dict[str, Any] | None:
    try:
        with h5py.File(path, "r") as f:
            g = f.get("results/allan")
            return None if g is None or "json" not in g.attrs else json.loads(g.attrs["json"])
    except OSError:
        return None


def latest_allan(recording: str | Path, search: int = 2) -> tuple[Path, dict[str, Any]] | None:
    """The Allan results of the unit recorded in ``recording``: its own /results/allan, else
    those of the same unit's latest recording (by /meta started_utc) among the recordings of
    the runs directory (``runs/*/recording.h5``; with ``search`` = 2 also one folder deeper,
    ``runs/LOT/*/recording.h5``). Same unit: equal /meta imu_serial or imu_device_id."""
    rec = Path(recording).resolve()
    own = _allan_summary(rec)
    if own is not None:
        return rec, own
    meta = read_meta(rec)
    ids = {k: _text(meta.get(k, "")) for k in ("imu_serial", "imu_device_id")}
    ids = {k: v for k, v in ids.items() if v}
    if not ids:
        return None
    runs = rec.parent.parent if rec.name == "recording.h5" else rec.parent
    cands = list(runs.glob("*/recording.h5")) + (list(runs.glob("*/*/recording.h5")) if search > 1 else [])
    best: tuple[str, Path, dict[str, Any]] | None = None
    for c in cands:
        if c.resolve() == rec:
            continue
        try:
            m = read_meta(c)
        except OSError:
            continue
        if not all(_text(m.get(k, "")) == v for k, v in ids.items()):
            continue
        s = _allan_summary(c)
        if s is not None and (best is None or str(m.get("started_utc", "")) > best[0]):
            best = (str(m.get("started_utc", "")), c, s)
    return None if best is None else (best[1], best[2])
