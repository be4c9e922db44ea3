"""Production line on emulated units: verdicts, the results database, batch on Dask, history.

Eight emulated units (configs/sim.yaml, declared model, each with its own accelerometer x bias
and seed: eight unit IDs) recorded once per session as short 24-position runs (warm-up 1 min,
2 s per orientation) in two lots. The expected verdicts are computed here from the printed value
and uncertainty with the guarded rule written out (|y - limit| against U = 1.96 u: the biases
keep normal intervals); the batch results must equal the serial ``rigctl calibrate`` results
row by row, on the local scheduler and on a 2-worker dask.distributed cluster.
"""
from __future__ import annotations

import json
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from helpers import ROOT, rigctl_in_process, run_rigctl

#: (lot, accel x bias mg, seed); 5.005 mg: outside +-5 mg by less than its uncertainty (0.01-0.1 mg)
UNITS = [("A", 1.0, 11), ("A", 2.0, 12), ("A", 5.005, 13), ("A", -3.0, 14),
         ("B", 8.0, 15), ("B", 0.5, 16), ("B", -2.0, 17), ("B", 3.5, 18)]
SPEC = """spec: test accelerometer bias
decision_rule: guarded
parameters:
  accel_bias_[xyz]: {within: 5 mg}
  gyro_bias_x: {within: 100 deg/h}
"""
Z95 = 1.959964


#: `rigctl run procedures/24pos.yaml --config CFG -p warmup=1 min -p sample=2 s --out OUT` for each
#: (CFG, OUT) pair of the arguments in turn, through rigctl.cli.main in one fresh interpreter: a
#: JSON list of {code, out}
RUN_SCRIPT = r"""
import contextlib, io, json, sys
from rigctl.cli import main
runs = []
for cfg, out in zip(sys.argv[1::2], sys.argv[2::2]):
    text = io.StringIO()
    with contextlib.redirect_stdout(text), contextlib.redirect_stderr(text):
        code = main(["run", "procedures/24pos.yaml", "--config", cfg, "-p", "warmup=1 min", "-p", "sample=2 s",
                     "--out", out])
    runs.append({"code": code, "out": text.getvalue()})
print(json.dumps(runs))
"""


@pytest.fixture(scope="session")
def lot_runs(tmp_path_factory) -> tuple[Path, list[Path]]:
    """runs/<lot>/<run>/recording.h5 for the eight units, recorded by `rigctl run` (rigctl.cli.main)
    in two fresh processes side by side, four runs each one after another (RUN_SCRIPT: the same
    recordings as eight `rigctl run` processes -- every dataset and attribute but the run's times
    compared -- without six more interpreters, imports and numba start-ups, ~2 s of CPU each)."""
    root = tmp_path_factory.mktemp("production")
    base = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    argv: list[list[str]] = [[], []]
    for i, (lot, bias, seed) in enumerate(UNITS):
        cfg = json.loads(json.dumps(base))
        cfg["seed"] = seed
        cfg["imu"]["sim"]["accel_bias_mg"] = [bias, -1.5, 3.0]
        path = root / f"unit{i}.yaml"
        path.write_text(yaml.safe_dump(cfg))
        argv[i % 2] += [str(path), str(root / "runs" / lot)]
    procs = [subprocess.Popen([sys.executable, "-c", RUN_SCRIPT, *a], cwd=ROOT, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for a in argv]
    for p in procs:
        text = p.communicate(timeout=600)[0]
        assert p.returncode == 0, text[-2000:]
        runs = json.loads(text.strip().splitlines()[-1])
        assert len(runs) == len(UNITS) // 2
        for r in runs:
            assert r["code"] == 0, r["out"][-2000:]
    (root / "spec.yaml").write_text(SPEC)
    seeds = [seed for _, _, seed in UNITS]

    def seed_of(rec: Path) -> int:
        with h5py.File(rec, "r") as f:
            return int(yaml.safe_load(f["meta"].attrs["config_yaml"])["seed"])
    recs = sorted((root / "runs").glob("*/*/recording.h5"), key=lambda p: seeds.index(seed_of(p)))
    assert len(recs) == 8
    return root, recs


def _rows(db: Path) -> dict[tuple[str, str], tuple]:
    con = sqlite3.connect(db)
    try:
        q = ("SELECT a.unit_id, r.parameter, r.value_si, r.u_si, r.value, r.u, r.unit, r.verdict, a.overall_verdict, "
             "a.software_version FROM results r JOIN analyses a ON a.id = r.analysis_id WHERE a.kind = 'calibration'")
        return {(row[0], row[1]): row[2:] for row in con.execute(q)}
    finally:
        con.close()


#: `rigctl calibrate REC --spec SPEC --db DB` for each REC in turn, through rigctl.cli.main in one
#: fresh interpreter: a JSON list of {code, out, err}
SERIAL_SCRIPT = r"""
import contextlib, io, json, sys
from rigctl.cli import main
runs = []
for rec in sys.argv[3:]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["calibrate", rec, "--spec", sys.argv[1], "--db", sys.argv[2]])
    runs.append({"code": code, "out": out.getvalue(), "err": err.getvalue()})
print(json.dumps(runs))
"""


@pytest.fixture(scope="session")
def serial(lot_runs) -> tuple[Path, list[str]]:
    """Eight serial `rigctl calibrate REC --spec S` calls into serial.sqlite, one after another
    in one fresh process (SERIAL_SCRIPT: rigctl.cli.main, as the command runs it, without seven
    more interpreters and imports); their outputs. The batch runs below must equal all eight row
    by row, exactly: the batch's own worker processes (Dask's multiprocessing scheduler, fresh
    processes) calibrate several recordings each in the same way. (Not rigctl.cli.main in the
    test worker: in a clean-clone CI run its results differed from the batch's in the last bits
    -- 0.01989879399944967 against 0.019898793999449455 mg -- where fresh processes agree
    exactly; the cause is not traced.)"""
    root, recs = lot_runs
    db = root / "serial.sqlite"
    r = subprocess.run([sys.executable, "-c", SERIAL_SCRIPT, str(root / "spec.yaml"), str(db), *map(str, recs)],
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stdout[-1500:] + r.stderr[-1500:]
    runs = json.loads(r.stdout.strip().splitlines()[-1])
    assert len(runs) == len(recs)
    for c in runs:
        assert c["code"] == 0, c["out"][-1500:] + c["err"][-1500:]
    return db, [c["out"] for c in runs]


def _shown(out: str, name: str) -> tuple[float, float, str]:
    """(value, u, verdict) of a parameter in the printed verdict table."""
    m = re.search(rf"^\s+{name}\s+mg\s+(\S+)\s+(\S+)\s+\[.*?\]\s+\[-5, 5\] mg\s+\S+\s+(PASS|FAIL|INDETERMINATE)",
                  out, re.M)
    assert m, out[-3000:]
    return float(m.group(1)), float(m.group(2)), m.group(3)


def test_verdicts_pass_indeterminate_fail(serial):
    _, outs = serial
    for (lot, bias, _), out in zip(UNITS, outs):
        y, u, verdict = _shown(out, "accel_bias_x")
        assert abs(y - bias) < 4 * u, (bias, y, u)   # the calibration finds the emulated bias
        U = Z95 * u                                  # biases: normal intervals, k = 1.96
        expected = ("PASS" if abs(y) + U <= 5.0 else "FAIL" if abs(y) - U > 5.0 else "INDETERMINATE")
        assert verdict == expected, (bias, y, u, verdict)
        overall = re.search(r"^OVERALL: (\S+)", out, re.M).group(1)
        assert overall == expected  # the other biases are well inside
    verdicts = [_shown(o, "accel_bias_x")[2] for o in outs]
    # the three cases the issue asks for, on these units
    assert verdicts[0] == "PASS" and verdicts[2] == "INDETERMINATE" and verdicts[4] == "FAIL"
    y, u, _ = _shown(outs[2], "accel_bias_x")
    assert 0 < 5.005 - 5.0 < u  # the emulated bias is outside by less than its uncertainty


def test_verdicts_stored_with_the_results(lot_runs, serial):
    _, recs = lot_runs
    with h5py.File(recs[4], "r") as f:
        payload = json.loads(f["results/calibration"].attrs["json"])
    v = payload["verdicts"]
    assert v["overall"] == "FAIL" and v["rule"] == "guarded"
    row = next(r for r in v["parameters"] if r["parameter"] == "accel_bias_x")
    assert row["unit"] == "mg" and row["verdict"] == "FAIL"
    assert json.loads(recs[4].with_name("recording.calibration.json").read_text())["verdicts"]["overall"] == "FAIL"


def test_database_rows(lot_runs, serial):
    db, _ = serial
    rows = _rows(db)
    units = {k[0] for k in rows}
    assert len(units) == 8
    import rigctl

    for (unit, param), (v_si, u_si, v, u, unit_d, verdict, overall, version) in rows.items():
        assert version == rigctl.__version__
        if param == "accel_bias_x":
            assert unit_d == "mg" and v == pytest.approx(v_si * 1000 / 9.80665, rel=1e-12)
            assert u == pytest.approx(u_si * 1000 / 9.80665, rel=1e-12) and verdict in ("PASS", "FAIL", "INDETERMINATE")
        if param == "gyro_scale_error_x":
            assert verdict is None and unit_d == "ppm"  # not in the spec


def _compare(a: Path, b: Path, rel: float = 0.0) -> None:
    """Same rows; numbers identical (rel = 0) or within ``rel``; units, verdicts, versions equal."""
    ra, rb = _rows(a), _rows(b)
    assert ra.keys() == rb.keys() and len(ra) > 8 * 20
    for k in ra:
        if rel == 0.0:
            assert ra[k] == rb[k], (k, ra[k], rb[k])
        else:
            assert ra[k][4:] == rb[k][4:], (k, ra[k], rb[k])
            assert ra[k][:4] == pytest.approx(rb[k][:4], rel=rel, abs=0.0), (k, ra[k], rb[k])


def test_batch_local_equals_serial_and_reports_a_broken_file(lot_runs, serial, tmp_path):
    root, recs = lot_runs
    bad = root / "runs" / "B" / "broken-run" / "recording.h5"
    bad.parent.mkdir(parents=True, exist_ok=True)
    bad.write_bytes(b"not hdf5")
    try:
        r = run_rigctl("batch", str(root / "runs" / "*" / "*" / "recording.h5"), str(bad),
                       "--spec", str(root / "spec.yaml"), "--workers", "2", "--db", str(tmp_path / "batch.sqlite"),
                       "--out", str(tmp_path / "summary"), timeout=300)
    finally:
        shutil.rmtree(bad.parent)
    assert r.returncode == 1, r.stdout[-2000:] + r.stderr[-2000:]  # one failed, the rest analysed
    assert "8 of 9 analysed" in r.stdout and "FAILED" in r.stdout and "broken" in r.stdout
    _compare(serial[0], tmp_path / "batch.sqlite")
    s = json.loads((tmp_path / "summary" / "summary.json").read_text())["summary"]
    assert s["A"]["verdicts"] == {"PASS": 3, "FAIL": 0, "INDETERMINATE": 1} and s["A"]["yield"] == 0.75
    assert s["B"]["verdicts"] == {"PASS": 3, "FAIL": 1, "INDETERMINATE": 0}
    assert s["B"]["analysed"] == 4 and len(s["B"]["failed"]) == 1
    xs = [b for lot, b, _ in UNITS if lot == "A"]
    assert s["A"]["parameters"]["accel_bias_x"]["mean"] == pytest.approx(np.mean(xs), abs=0.2)
    assert (tmp_path / "summary" / "batch.png").stat().st_size > 10_000


def test_batch_on_a_distributed_cluster_equals_serial(lot_runs, serial, tmp_path):
    distributed = pytest.importorskip("distributed")
    root, _ = lot_runs
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        # the batch's client in this process (the calibrations run on the cluster's worker processes)
        r = rigctl_in_process("batch", str(root / "runs" / "*" / "*" / "recording.h5"), "--spec",
                              str(root / "spec.yaml"), "--scheduler", cluster.scheduler_address,
                              "--db", str(tmp_path / "dist.sqlite"), "--out", str(tmp_path / "s"))
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
        workers = {w["host"] for w in cluster.scheduler_info["workers"].values()}
    assert "dask.distributed at tcp://127.0.0.1" in r.stdout and workers == {"127.0.0.1"}
    # dask.distributed's nanny starts workers with OMP/OPENBLAS_NUM_THREADS=1; before rigctl
    # calibrate ran its solvers single-threaded too (docs/calibration.md section 7) the 2-thread
    # serial run's last bits differed (seen: 6e-13 relative); since then identical (checked
    # once with rel=0)
    _compare(serial[0], tmp_path / "dist.sqlite", rel=1e-9)


def test_history_drift_against_numpy(lot_runs, serial, tmp_path):
    """Three recordings labelled as one unit (imu_serial), dated 0, 100 and 400 days apart:
    the drift is the weighted line through (t, value +- u), checked with numpy's polyfit."""
    root, recs = lot_runs
    db = tmp_path / "h.sqlite"
    dates = ("2025-01-01T00:00:00+00:00", "2025-04-11T00:00:00+00:00", "2026-02-05T00:00:00+00:00")
    for i, (src, date) in enumerate(zip((recs[0], recs[1], recs[5]), dates)):
        run = tmp_path / "runs" / f"cal{i}"
        shutil.copytree(src.parent, run)
        with h5py.File(run / "recording.h5", "r+") as f:
            f["meta"].attrs["started_utc"] = date
            f["meta"].attrs["imu_serial"] = "SN-TEST-1"
        r = rigctl_in_process("calibrate", str(run / "recording.h5"), "--db", str(db))
        assert r.returncode == 0, r.stderr[-1500:]
    con = sqlite3.connect(db)
    unit = con.execute("SELECT DISTINCT unit_id FROM analyses").fetchall()
    assert len(unit) == 1
    rows = con.execute("SELECT a.recorded_utc, r.value, r.u FROM results r JOIN analyses a ON a.id = r.analysis_id "
                       "WHERE r.parameter = 'accel_bias_x' ORDER BY a.recorded_utc").fetchall()
    con.close()
    r = rigctl_in_process("history", unit[0][0], "--db", str(db))
    assert r.returncode == 0, r.stderr
    block = r.stdout.split("accel_bias_x [mg]")[1].split("\n\n")[0]
    m = re.search(r"drift: (?:not resolved: )?(\S+) \+- (\S+) mg/year(, its 95 % interval includes zero)? "
                  r"\(dof 1, chi2/dof ([0-9.e+-]+)", block)
    assert m, block
    import datetime as dt

    t = np.array([dt.datetime.fromisoformat(x[0]).timestamp() for x in rows]) / (365.25 * 86400)
    v, u = np.array([x[1] for x in rows]), np.array([x[2] for x in rows])
    coef, cov = np.polyfit(t - t.mean(), v, 1, w=1 / u, cov="unscaled")
    chi2 = float(np.sum(((v - np.polyval(coef, t - t.mean())) / u) ** 2))
    assert float(m.group(1)) == pytest.approx(coef[0], abs=float(m.group(2)) * 0.06)
    assert float(m.group(4)) == pytest.approx(chi2, rel=2e-3)
    # the slope's standard uncertainty; scaled by sqrt(chi2/dof) when chi2 is improbable (p < 0.001)
    scale = np.sqrt(chi2) if chi2 > 10.828 else 1.0
    assert ("scaled by sqrt(chi2/dof)" in block) == (scale > 1.0)
    assert float(m.group(2)) == pytest.approx(np.sqrt(cov[0, 0]) * scale, rel=0.06)
    # "not resolved" exactly when the 95 % interval (Student t on 1 dof when scaled) holds zero
    from scipy.stats import t as student_t
    k95 = student_t.ppf(0.975, 1) if scale > 1.0 else Z95
    assert (m.group(3) is not None) == (abs(coef[0]) <= k95 * np.sqrt(cov[0, 0]) * scale)
    assert block.split("drift:")[1].startswith(" not resolved: ") == (m.group(3) is not None)
    r = rigctl_in_process("history", "no-such-unit", "--db", str(db))
    assert r.returncode == 2 and "no results for unit" in r.stderr and unit[0][0] in r.stderr


def _pg_bin(name: str) -> str:
    found = sorted(Path("/usr/lib/postgresql").glob(f"*/bin/{name}"))
    if not found:
        pytest.fail(f"PostgreSQL's {name} not found: apt-get install postgresql (.ci/run installs it)")
    return str(found[-1])


@pytest.fixture
def postgres(tmp_path_factory):
    """A real PostgreSQL server (Debian's binaries) in a temporary directory, on a free
    loopback port, run as the 'postgres' user (the server refuses to run as root); yields its URL."""
    import os
    import pwd
    import socket
    import tempfile

    if os.geteuid() == 0:
        try:
            pw = pwd.getpwnam("postgres")
        except KeyError:
            pytest.fail("no 'postgres' user: apt-get install postgresql creates it")
        as_user = ["runuser", "-u", "postgres", "--"]
    else:
        pw, as_user = pwd.getpwuid(os.geteuid()), []
    base = Path(tempfile.mkdtemp(prefix="rigctl-pg-"))
    os.chown(base, pw.pw_uid, pw.pw_gid)
    data, sock = base / "data", base
    r = subprocess.run([*as_user, _pg_bin("initdb"), "-D", str(data), "-U", "rigctl", "--auth=trust", "-E", "UTF8"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    # The server cannot be handed a bound socket: the port is looked up (bind to 0, close) and
    # PostgreSQL binds it a moment later, when another process (the other xdist worker, any
    # client's outgoing connection) may have taken it. Only that case -- the server's own log
    # says the address is in use -- is tried again, on another port.
    for attempt in range(5):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        log = base / f"log{attempt}"
        r = subprocess.run([*as_user, _pg_bin("pg_ctl"), "-D", str(data), "-l", str(log), "-w", "-t", "60",
                            "-o", f"-h 127.0.0.1 -p {port} -k {sock}", "start"], capture_output=True, text=True,
                           timeout=120)
        if r.returncode == 0 or "Address already in use" not in (log.read_text() if log.exists() else ""):
            break
    assert r.returncode == 0, r.stdout + r.stderr + (log.read_text() if log.exists() else "")
    try:
        r = subprocess.run([*as_user, _pg_bin("createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", "rigctl",
                            "results"], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        yield f"postgresql+psycopg://rigctl@127.0.0.1:{port}/results"
    finally:
        subprocess.run([*as_user, _pg_bin("pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop"],
                       capture_output=True, timeout=120)
        shutil.rmtree(base, ignore_errors=True)


def test_postgresql_holds_the_same_rows(lot_runs, serial, postgres):
    """The same calibrations written to a real PostgreSQL server (schema by the Alembic
    migration) read back equal to the SQLite rows; history reads from it too."""
    import sqlalchemy as sa

    _, recs = lot_runs
    for rec in recs[:3]:
        # in this process: the rows are compared to 1e-9, not exactly (the serial ones are subprocesses)
        r = rigctl_in_process("calibrate", str(rec), "--db", postgres, "--noise", "auto")
        assert r.returncode == 0, r.stderr[-1500:]
        assert "results database: postgresql+psycopg://rigctl@127.0.0.1" in r.stdout
    eng = sa.create_engine(postgres)
    with eng.connect() as c:
        version = c.execute(sa.text("SELECT version_num FROM alembic_version")).scalar_one()
        pg = {(u, p): (v, s) for u, p, v, s in c.execute(sa.text(
            "SELECT a.unit_id, r.parameter, r.value_si, r.u_si FROM results r JOIN analyses a ON a.id = r.analysis_id"))}
        assert c.execute(sa.text("SELECT count(*) FROM analyses")).scalar_one() == 3
    eng.dispose()
    assert version == "0001"
    lite = _rows(serial[0])
    units = {u for u, _ in pg}
    assert len(units) == 3
    mine = {k: v[:2] for k, v in lite.items() if k[0] in units}
    assert mine.keys() == pg.keys()
    for k in pg:  # the serial rows were calibrated with the same spec-free pipeline: numbers equal
        # the same pipeline recalibrated: equal up to BLAS summation order (seen: 2e-12 relative)
        assert pg[k] == pytest.approx(mine[k], rel=1e-9, abs=0.0), k
    r = rigctl_in_process("history", sorted(units)[0], "--db", postgres)
    assert r.returncode == 0 and "accel_bias_x [mg]" in r.stdout, r.stderr
