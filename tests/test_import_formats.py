"""`rigctl import` of the text exports labs hand over as they are, without editing them first:
a European spreadsheet export (semicolons, decimal commas), a time column of ISO 8601
date-times (the Astro Pi's `time_stamp`, a logger's `...T...Z`), a units line under the header,
and a column whose unit is wrong by orders of magnitude (a frequency counter's 10 MHz readings
taken as rad/s: refused at the import, naming the column and how to scale it). Expected values
are computed here with numpy and the standard library from what the test wrote."""
from __future__ import annotations

import datetime as dt
import math
from pathlib import Path

import h5py
import numpy as np

from helpers import run_rigctl
from rigctl import cli

D2R = math.pi / 180.0
G0 = 9.80665
COLS = "time=t,gyr_x=gx,gyr_y=gy,gyr_z=gz,acc_x=ax,acc_y=ay,acc_z=az"


def _data(n: int = 2000, seed: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(0, 0.02, (n, 3)), rng.normal(0, 1e-3, (n, 3)) + [0.0, 0.0, 1.0]


def _read(rec: Path) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    with h5py.File(rec, "r") as f:
        return (float(f["imu"].attrs["sample_rate_hz"]), f["imu/time"][()], f["imu/counter"][()],
                f["imu/angular_rate"][()], f["imu/specific_force"][()])


def test_semicolons_and_decimal_commas_with_and_without_a_header(tmp_path: Path, capsys) -> None:
    g, a = _data()
    n = len(g)
    lines = [";".join(f"{v:.7f}".replace(".", ",") for v in (k * 0.01, *g[k], *a[k])) for k in range(n)]
    with_header = tmp_path / "export.csv"
    with_header.write_text("t;gx;gy;gz;ax;ay;az\n" + "\n".join(lines) + "\n")
    bare = tmp_path / "bare.csv"  # no header: the comma must not be taken for the separator
    bare.write_text("\n".join(lines) + "\n")
    for src, cols in ((with_header, COLS), (bare, "time=0,gyr_x=1,gyr_y=2,gyr_z=3,acc_x=4,acc_y=5,acc_z=6")):
        rec = tmp_path / (src.stem + ".h5")
        assert cli.main(["import", str(src), "-o", str(rec), "--columns", cols,
                         "--units", "gyr=deg/s,acc=g,time=s"]) == 0
        assert "numbers with a decimal comma: the comma read as the decimal point" in capsys.readouterr().out
        rate, t, counter, w, f = _read(rec)
        assert len(t) == n and abs(rate - 100.0) < 1e-6 and np.array_equal(counter, np.arange(n))
        np.testing.assert_allclose(w, np.round(g, 7) * D2R, rtol=0, atol=1e-12)
        np.testing.assert_allclose(f, np.round(a, 7) * G0, rtol=0, atol=1e-9)


def test_iso_datetime_time_column_with_a_gap(tmp_path: Path, capsys) -> None:
    """Date-times with microseconds and a zone, one stretch of 7 samples missing: the rate from
    its intervals over its span, the gap a counter jump, the stamps exact to the microsecond."""
    g, a = _data(1500, seed=5)
    fs = 50.0
    keep = np.ones(len(g), bool)
    keep[700:707] = False
    t0 = dt.datetime(2015, 8, 20, 23, 58, 30, 250000, tzinfo=dt.timezone.utc)
    csv = tmp_path / "logger.csv"
    with open(csv, "w") as fh:
        fh.write("stamp,gx,gy,gz,ax,ay,az\n")
        for k in np.flatnonzero(keep):
            stamp = (t0 + dt.timedelta(microseconds=int(k * 1e6 / fs))).isoformat().replace("+00:00", "Z")
            fh.write(stamp + "," + ",".join(f"{v:.7g}" for v in (*g[k], *a[k])) + "\n")
    rec = tmp_path / "logger.h5"
    assert cli.main(["import", str(csv), "-o", str(rec), "--columns", COLS.replace("time=t", "time=stamp"),
                     "--units", "gyr=rad/s,acc=m/s^2"]) == 0
    out = capsys.readouterr().out
    assert "time column 'stamp': ISO 8601 date-times" in out
    assert "1 gaps, 7 samples missing" in out
    rate, t, counter, w, _ = _read(rec)
    assert abs(rate - fs) < 1e-9
    np.testing.assert_allclose(t, np.flatnonzero(keep) / fs, rtol=0, atol=1e-9)
    assert np.array_equal(counter, np.flatnonzero(keep))
    np.testing.assert_allclose(w, g[keep], rtol=1e-6)


def test_units_line_under_the_header_is_skipped_and_said(tmp_path: Path, capsys) -> None:
    g, a = _data(800, seed=6)
    tsv = tmp_path / "units.tsv"
    with open(tsv, "w") as fh:
        fh.write("t\tgx\tgy\tgz\tax\tay\taz\nms\tdeg/s\tdeg/s\tdeg/s\tg\tg\tg\n")
        for k in range(len(g)):
            fh.write("\t".join(f"{v:.7g}" for v in (k * 10.0, *g[k], *a[k])) + "\n")
    rec = tmp_path / "units.h5"
    assert cli.main(["import", str(tsv), "-o", str(rec), "--columns", COLS,
                     "--units", "gyr=deg/s,acc=g,time=ms"]) == 0
    assert "taken for a units line under the header and skipped" in capsys.readouterr().out
    rate, t, _, w, f = _read(rec)
    assert len(t) == len(g) and abs(rate - 100.0) < 1e-6
    np.testing.assert_allclose(w, g * D2R, rtol=1e-6)
    np.testing.assert_allclose(f, a * G0, rtol=1e-6)


def test_a_frequency_counter_file_needs_its_scale(tmp_path: Path) -> None:
    """A counter's readings of a 10 MHz oscillator (Hz, header comments) taken as rad/s are
    refused by the import itself (exit 2, one line naming the column, no file written); with
    the scale to fractional frequency they import with float64 resolution intact."""
    rng = np.random.default_rng(7)
    hz = 1e7 + 0.127 + np.cumsum(rng.normal(0, 2e-4, 3000)) * 1e-3 + rng.normal(0, 5e-4, 3000)
    src = tmp_path / "ocxo.txt"
    src.write_text("# 10 MHz OCXO, 53230A counter, 1 s gate\n" + "\n".join(f"{v:.15f}" for v in hz) + "\n")
    out = tmp_path / "o.h5"
    p = run_rigctl("import", str(src), "-o", str(out), "--columns", "gyr_x=0", "--units", "gyr=rad/s",
                   "--rate", "1")
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert "column '0' (gx) reads 1e+07 rad/s" in p.stderr and "counts:1e-7 rad/s" in p.stderr, p.stderr
    assert not out.exists()
    assert cli.main(["import", str(src), "-o", str(out), "--columns", "gyr_x=0",
                     "--units", "gyr=counts:1e-7 rad/s", "--rate", "1"]) == 0
    _, _, _, w, _ = _read(out)
    expect = np.array([float(f"{v:.15f}") for v in hz]) * 1e-7
    np.testing.assert_allclose(w[:, 0], expect, rtol=1e-15)
    # the fractional-frequency fluctuations (~5e-11) survive: differences exact to ~1e-16
    np.testing.assert_allclose(np.diff(w[:, 0]), np.diff(expect), rtol=0, atol=5e-16)


def test_epoch_seconds_with_a_fraction_keep_their_steps(tmp_path: Path, capsys) -> None:
    """Stamps like 1700000000.010 (seconds since 1970, ms digits): as float64 each is off by up
    to 1.2e-7 s, which put the rate at 100.0001 Hz; read as integer + fraction, the steps and the
    rate are exact."""
    g, a = _data(3000, seed=8)
    csv = tmp_path / "epoch.csv"
    with open(csv, "w") as fh:
        fh.write("t,gx,gy,gz,ax,ay,az\n")
        for k in range(len(g)):
            fh.write(f"{1_700_000_000 + k // 100}.{k % 100 * 10:03d}," + ",".join(f"{v:.7g}" for v in (*g[k], *a[k])) + "\n")
    rec = tmp_path / "epoch.h5"
    assert cli.main(["import", str(csv), "-o", str(rec), "--columns", COLS, "--units", "gyr=rad/s,acc=m/s^2"]) == 0
    assert "sample rate 100 Hz (the time column: its intervals over its span); no gaps" in capsys.readouterr().out
    rate, t, counter, _, _ = _read(rec)
    assert abs(rate - 100.0) < 1e-9 and np.array_equal(counter, np.arange(len(g)))
    np.testing.assert_allclose(t, np.arange(len(g)) * 0.01, rtol=0, atol=1e-12)


def test_stable32_two_column_file_with_mjd_tags(tmp_path: Path, capsys) -> None:
    """A Stable32 two-column frequency file: MJD time tags (days, 1 s apart) and fractional
    frequency, one tag missing: rate 1 Hz exactly, the gap a counter jump, values unchanged."""
    rng = np.random.default_rng(9)
    n = 4000
    y = rng.normal(0, 3e-12, n)
    keep = np.ones(n, bool)
    keep[1234] = False
    src = tmp_path / "clock.frq"
    with open(src, "w") as fh:
        for k in np.flatnonzero(keep):
            sec = 3600 + int(k)  # from 01:00:00 of MJD 57000
            fh.write(f"{57000 + sec // 86400}.{round(sec % 86400 / 86400 * 1e12):012d} {y[k]:.6e}\n")
    rec = tmp_path / "clock.h5"
    assert cli.main(["import", str(src), "-o", str(rec), "--columns", "time=0,gyr_x=1",
                     "--units", "gyr=rad/s,time=d"]) == 0
    assert "sample rate 1 Hz (the time column: its intervals over its span); 1 gaps, 1 samples missing" in capsys.readouterr().out
    rate, t, counter, w, _ = _read(rec)
    # the tags' 12 decimals of a day resolve 86 ns: the rate within 1e-7 of 1 Hz (as
    # float64, MJD 57000 resolves only 0.6 us: 6e-7)
    assert abs(rate - 1.0) < 1e-7 and np.array_equal(counter, np.flatnonzero(keep))
    np.testing.assert_allclose(t, np.flatnonzero(keep).astype(float), rtol=0, atol=1e-7)
    np.testing.assert_allclose(w[:, 0], np.array([float(f"{v:.6e}") for v in y[keep]]), rtol=1e-15)


def test_metadata_lines_before_the_header_name_the_skip(ref_data: Path, tmp_path: Path) -> None:
    """The MPU-6050 tool's static record starts with four `key,value` lines (Fs,100 ...): the
    error names the line that holds the columns and the --skip-rows that reaches it, which
    then imports the record."""
    src = ref_data / "mpu6050-multipos" / "results_test_data_imu_static_test.csv"
    lines = src.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.strip() == "ax,ay,az,gx,gy,gz")
    cols = "acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz"
    units = "acc=counts:1/16384 g,gyr=counts:1/131 deg/s"
    out = tmp_path / "mpu.h5"
    p = run_rigctl("import", str(src), "-o", str(out), "--columns", cols, "--units", units, "--rate", "100")
    assert p.returncode == 2 and f"line {k + 1} holds every named column: give --skip-rows {k}" in p.stderr, p.stderr
    assert cli.main(["import", str(src), "-o", str(out), "--columns", cols, "--units", units, "--rate", "100",
                     "--skip-rows", str(k)]) == 0
    counts = np.array([[float(v) for v in ln.split(",")] for ln in lines[k + 1:] if ln.strip()])
    _, t, _, w, f = _read(out)
    assert len(t) == len(counts)
    np.testing.assert_allclose(w, counts[:, 3:] / 131 * D2R, rtol=1e-12)
    np.testing.assert_allclose(f, counts[:, :3] / 16384 * G0, rtol=1e-12)


def test_a_stable32_result_table_is_not_taken_for_samples(ref_data: Path, tmp_path: Path) -> None:
    """Stable32's output (AF, Tau, #, Alpha, sigmas per line) has the shape of a numeric table;
    imported as samples it would give a meaningless curve. Refused, pointing to the data."""
    for src in (ref_data / "ocxo-frequency-stable32" / "stable32_oadev_alltau.txt",
                ref_data / "stable32-reference" / "phasedat" / "phase_dat_oadev_octave.txt"):
        out = tmp_path / "t.h5"
        p = run_rigctl("import", str(src), "-o", str(out), "--columns", "gyr_x=5", "--units", "gyr=rad/s",
                       "--rate", "1")
        assert p.returncode == 2 and "a Stable32 result table" in p.stderr and "Traceback" not in p.stderr, p.stderr
        assert not out.exists()


def _gyro_only_bag(path: Path, gx: np.ndarray, fs: float) -> None:
    """A rosbag2 (mcap) of sensor_msgs/Imu from a gyro-only sender: linear_acceleration and the
    other two rates left at 0 in every message (rigctl.sim.imu_bag: rosbags' writer, as a
    robot's recorder)."""
    from rigctl.sim.imu_bag import write_imu_bag

    n = len(gx)
    stamps = [1_700_000_000_000_000_000 + int(i * 1e9 / fs) for i in range(n)]
    write_imu_bag(path, np.array(stamps, dtype=np.int64),
                  np.column_stack([np.asarray(gx, dtype=float), np.zeros((n, 2))]), np.zeros((n, 3)),
                  topic="/gyro", frame_id="gyro")


def test_bag_fields_nobody_filled_are_left_out(tmp_path: Path, capsys) -> None:
    """A bag whose sender fills only one rate: the five constant fields are stored as NaN and
    rigctl allan analyses the filled axis alone (before: exit 1, an internal error from the fit
    of a constant axis). Asking for a constant axis of a recording is one error line naming it."""
    rng = np.random.default_rng(10)
    gx = rng.normal(0, 1e-3, 4000)
    bag = tmp_path / "gyro_bag"
    _gyro_only_bag(bag, gx, 100.0)
    rec = tmp_path / "bag.h5"
    assert cli.main(["import", str(bag), "-o", str(rec)]) == 0
    assert ("not filled in any message (the same value throughout), stored as NaN: ax, ay, az, "
            "gy, gz; rigctl allan analyses the others (gx)") in capsys.readouterr().out
    with h5py.File(rec, "r") as f:
        assert f["meta"].attrs["import_axes"] == "gx"
        w = f["imu/angular_rate"][()]
        assert np.isnan(f["imu/specific_force"][()]).all() and np.isnan(w[:, 1:]).all()
        np.testing.assert_array_equal(w[:, 0], gx)
    assert cli.main(["allan", str(rec), "--db", "none", "--taus", "octave"]) == 0
    out = capsys.readouterr().out
    assert "== gx (gyro" in out and "== gy" not in out
    # a CSV maps its columns explicitly: a constant one is kept, and rigctl allan names it
    csv = tmp_path / "const.csv"
    csv.write_text("gx,gy\n" + "\n".join(f"{v:.9g},0.25" for v in gx) + "\n")
    rec2 = tmp_path / "const.h5"
    assert cli.main(["import", str(csv), "-o", str(rec2), "--columns", "gyr_x=gx,gyr_y=gy",
                     "--units", "gyr=rad/s", "--rate", "100"]) == 0
    p = run_rigctl("allan", str(rec2), "--db", "none", "--axes", "gx,gy")
    assert p.returncode == 2 and "axis gy: every sample is the same value" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr and "internal error" not in p.stderr


def _meta(rec: Path) -> dict:
    with h5py.File(rec, "r") as f:
        return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f["meta"].attrs.items()}


def test_a_csv_is_dated_by_its_own_wall_clock_stamps(tmp_path: Path, capsys) -> None:
    """/meta started_utc and ended_utc of an imported CSV are the capture's own first and last
    stamp where its time column holds wall-clock times -- ISO 8601 date-times, Unix seconds with
    a fraction, Unix milliseconds as integers -- not the import's (as a bag's are); the import's
    time is kept in import_utc. A time column counting from 0, or none (--rate), leaves the
    import's times and says in capture_time that the capture's start is unknown. Expected ISO
    strings written here with datetime from what the test wrote."""
    g, a = _data(600, seed=8)
    fs = 20.0
    t0 = dt.datetime(2019, 3, 4, 5, 6, 7, 125000, tzinfo=dt.timezone.utc)
    iso = lambda t: t.strftime("%Y-%m-%dT%H:%M:%S.%fZ")  # noqa: E731  (the recorder's form)
    start, end = iso(t0), iso(t0 + dt.timedelta(seconds=(len(g) - 1) / fs))
    unix = (t0 - dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc)).total_seconds()
    stamps = {
        "iso": ([(t0 + dt.timedelta(microseconds=int(k * 1e6 / fs))).isoformat() for k in range(len(g))], ""),
        "unix_s": ([f"{unix + k / fs:.6f}" for k in range(len(g))], ",time=s"),
        "unix_ms": ([str(int(round(unix * 1000)) + k * 50) for k in range(len(g))], ",time=ms"),
        "from_zero": ([f"{k / fs:.3f}" for k in range(len(g))], ",time=s"),
    }
    today = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d")
    for name, (col, unit) in stamps.items():
        csv = tmp_path / f"{name}.csv"
        csv.write_text("t,gx,gy,gz,ax,ay,az\n" + "".join(
            f"{col[k]}," + ",".join(f"{v:.7g}" for v in (*g[k], *a[k])) + "\n" for k in range(len(g))))
        rec = tmp_path / f"{name}.h5"
        assert cli.main(["import", str(csv), "-o", str(rec), "--columns", COLS,
                         "--units", "gyr=rad/s,acc=m/s^2" + unit]) == 0
        out = capsys.readouterr().out
        m = _meta(rec)
        assert m["import_utc"].startswith(today), (name, m)
        if name == "from_zero":
            assert m["capture_time"].startswith("unknown") and m["started_utc"].startswith(today), (name, m)
            assert "the capture's start is unknown" in out
        else:
            assert (m["started_utc"], m["ended_utc"]) == (start, end), (name, m["started_utc"], m["ended_utc"])
            assert m["capture_time"] == "the file's own time stamps (wall clock)"
            assert abs(m["clock_zero_unix_s"] - unix) < 1e-6
            assert f"dated by the time column: {start} to {end}" in out
    # no time column: --rate, the start unknown
    csv = tmp_path / "rate.csv"
    csv.write_text("".join(",".join(f"{v:.7g}" for v in (*g[k], *a[k])) + "\n" for k in range(len(g))))
    rec = tmp_path / "rate.h5"
    assert cli.main(["import", str(csv), "-o", str(rec), "--columns",
                     "gyr_x=0,gyr_y=1,gyr_z=2,acc_x=3,acc_y=4,acc_z=5", "--units", "gyr=rad/s,acc=m/s^2",
                     "--rate", str(fs)]) == 0
    m = _meta(rec)
    assert m["capture_time"].startswith("unknown") and m["started_utc"].startswith(today)
