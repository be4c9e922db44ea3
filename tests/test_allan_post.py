"""What ``rigctl allan`` does after the last chunk: the collector paused for the whole command
(no young-generation walk of the objects made beside the stream), the results database
prepared beside the stream (its dialect, driver and mappers)."""
from __future__ import annotations

import argparse
import gc
import subprocess
import sys
import weakref
from pathlib import Path

import numpy as np
import pytest

from recording_helpers import write_recording
from rigctl.analysis import allan as AA
from rigctl.commands import allan_cmd


def _recording(path: Path, n: int = 20_000, seed: int = 3, gaps: bool = False) -> Path:
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.standard_normal((n, 6)), 0) * 1e-6
    idx = np.arange(n, dtype=np.uint64)
    if gaps:
        idx[60_000:] += 5
        idx[123_457:] += 1
    return write_recording(path, 100.0, counter=idx,
                           angular_rate=rng.standard_normal((n, 3)) * 1e-3 + walk[:, :3],
                           specific_force=rng.standard_normal((n, 3)) * 1e-3 + walk[:, 3:]
                           + [0, 0, 9.8], chunk_rows=4096)


class _Cycle:
    def __init__(self) -> None:
        self.me = self


def test_the_command_runs_no_collection_and_leaves_none_frozen(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture) -> None:
    """Through the whole command (stream, analyses, store, database write) no collection runs
    (on the code before, the first allocations after compute's pause started one walking
    every object made during it); afterwards the collector is on again, nothing is left
    frozen, the objects made meanwhile are in the oldest generation (gen 0 near empty), and
    a cycle made inside the pause is garbage the next full collection frees."""
    rec = _recording(tmp_path / "r.h5")
    parser = argparse.ArgumentParser(prog="rigctl")
    allan_cmd.register(parser.add_subparsers())
    args = parser.parse_args(["allan", str(rec), "--taus", "octave", "--db",
                              str(tmp_path / "results.sqlite")])
    runs: list[int] = []

    def seen(phase: str, info: dict) -> None:
        if phase == "start":
            runs.append(info["generation"])

    was = gc.isenabled()
    gc.enable()
    gc.collect()
    gc.callbacks.append(seen)
    try:
        assert args.func(args) == 0
        assert runs == []
        assert gc.isenabled() and gc.get_freeze_count() == 0
        assert len(gc.get_objects(0)) < 2_000
        with AA.collector_paused_for_command():
            ref = weakref.ref(_Cycle())
            assert not gc.isenabled()
        assert gc.isenabled() and ref() is not None  # promoted, not collected ...
        gc.collect()
        assert ref() is None  # ... and not frozen: the next full collection frees it
    finally:
        gc.callbacks.remove(seen)
        if not was:
            gc.disable()
    assert "results database:" in capsys.readouterr().out


def test_objects_frozen_by_the_caller_stay_frozen(tmp_path: Path) -> None:
    """A caller that froze objects itself (gc.freeze) keeps them frozen: the command then
    only pauses the collector."""
    keep = [_Cycle() for _ in range(10)]
    gc.freeze()
    try:
        frozen = gc.get_freeze_count()
        with AA.collector_paused_for_command():
            _Cycle()
        assert gc.get_freeze_count() == frozen
    finally:
        gc.unfreeze()
    del keep


_PRELOAD = """
import sys
from pathlib import Path
from rigctl.analysis import production as P
from rigctl.recording import results_db as db
t = P.preload_database(sys.argv[1] if sys.argv[1] != "default" else None)
t.join(120)
print(int(t.is_alive()), int("sqlalchemy.dialects.sqlite" in sys.modules),
      int("sqlite3" in sys.modules), int(db.Analysis.__mapper__.configured),
      int(any(Path(".").iterdir())))
"""


@pytest.mark.parametrize("target,expect", [("default", "0 1 1 1 0"),
                                           ("nosuchdialect://host/db", "0 0 0 0 0")])
def test_preload_prepares_the_database_write(tmp_path: Path, target: str, expect: str) -> None:
    """The preload (beside the stream) imports the target's dialect and driver and
    configures the mappers -- on the code before, the first write imported SQLite's dialect
    after the analysis -- and opens nothing (no file appears); a URL SQLAlchemy cannot load
    leaves the write to say so (no error on the thread)."""
    p = subprocess.run([sys.executable, "-c", _PRELOAD, target], cwd=tmp_path,
                       capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split()[-5:] == expect.split(), p.stdout
    assert "Traceback" not in p.stderr


def _values(r: dict) -> dict:
    """An axis' result, every number of it (arrays, the fit's coefficients and check)."""
    out = {k: np.asarray(v) for k, v in r.items() if isinstance(v, np.ndarray)}
    out["fit"] = repr(r["fit"])
    return out


@pytest.mark.parametrize("lead,gaps", [(True, False), (True, True), (False, False)])
def test_split_noise_ids_same_results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                      lead: bool, gaps: bool) -> None:
    """The noise IDs on the decimated copy taken as tasks of their own before the analyses of
    the axes that finish together (AA.SPLIT_NOISE_IDS) are the ones each analysis took
    itself, and the analyses find them (no lag-1 sums of their own): every number of every
    axis the same, with the lead dataset analysed beside the other's last chunks or all six
    after the stream, with gaps skipped."""
    rec = _recording(tmp_path / "r.h5", 160_000, gaps=gaps)
    monkeypatch.setattr(AA, "CHUNK_ROWS", 20_000)
    monkeypatch.setattr(AA, "HEAD_POINTS", 1 << 14)
    monkeypatch.setattr(AA, "DEC_POINTS", 1 << 12)
    monkeypatch.setattr(AA, "LEAD_DATASET", lead)
    found: list = []
    orig = AA.analyse_axis

    def spy(stream, *args):
        assert stream.dec == 64
        found.append((sum(1 for m, _ in stream._nid if m % stream.dec == 0),
                      sum(1 for m in stream.ms.tolist() if m % stream.dec == 0)))
        return orig(stream, *args)

    monkeypatch.setattr(AA, "analyse_axis", spy)
    got = {}
    for split in (False, True):
        monkeypatch.setattr(AA, "SPLIT_NOISE_IDS", split)
        found.clear()
        res = AA.compute(str(rec), list(AA.AXES), 95)
        got[split] = {a: _values(r) for a, r in res["axes"].items()}
        assert len(found) == 6 and min(f[1] for f in found) >= 1, found
        assert all(f[0] == (f[1] if split else 0) for f in found), found
    for a, r in got[False].items():
        assert r.keys() == got[True][a].keys()
        for k, v in r.items():
            w = got[True][a][k]
            assert (np.array_equal(v, w, equal_nan=v.dtype.kind == "f")
                    if isinstance(v, np.ndarray) else v == w), (a, k)
