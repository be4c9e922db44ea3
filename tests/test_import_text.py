"""`rigctl import` of the text forms a stranger's static capture comes in, then `rigctl allan`:
comma, tab, semicolon or whitespace columns, with or without a header, `#` comment lines, a
time column in s or ns (rate from its intervals over its span, dropped samples from its jumps) or none
(--rate), rad/s or deg/s and m/s^2 or g given by --units, a gyro-only file (the other columns
stored as NaN, rigctl allan analyses the columns present); one error line for what it cannot
read. Expected values are computed here with numpy from the written text."""
from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import run_rigctl
from rigctl import cli

D2R = math.pi / 180.0


def _ok(*args: str) -> None:
    assert cli.main(["import", *args]) == 0


def test_whitespace_no_header_counts_and_rate(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    counts = np.round(rng.normal(0, 4, (5000, 6))) + [0, 0, 0, 0, 0, -300]
    txt = tmp_path / "static.txt"
    with open(txt, "w") as fh:
        fh.write("# logger v2, unit 17\n# gx gy gz ax ay az (counts)\n")
        for row in counts.astype(int):
            fh.write("  ".join(str(v) for v in row) + "\n")
    rec = tmp_path / "s.h5"
    _ok(str(txt), "-o", str(rec), "--rate", "100",
        "--columns", "gyr_x=0,gyr_y=1,gyr_z=2,acc_x=3,acc_y=4,acc_z=5",
        "--units", "gyr=counts:0.05 deg/s,acc=counts:0.00333 g")
    with h5py.File(rec, "r") as f:
        np.testing.assert_allclose(f["imu/angular_rate"][()], counts[:, :3] * 0.05 * D2R)
        np.testing.assert_allclose(f["imu/specific_force"][()], counts[:, 3:] * 0.00333 * 9.80665)
        np.testing.assert_allclose(f["imu/time"][()], np.arange(5000) / 100.0)
        assert np.array_equal(f["imu/counter"][()], np.arange(5000))


def test_tsv_header_time_in_ns_gyro_only_with_a_gap(tmp_path: Path,
                                                    capsys) -> None:
    """A one-gyro TSV with nanosecond stamps and 25 dropped samples: the rate comes from the
    stamps, the gap becomes a counter jump, and rigctl allan analyses gx alone, skipping the
    terms across the gap (its white noise level checked against numpy)."""
    rng = np.random.default_rng(2)
    fs, n_grid = 200.0, 40_000
    y = rng.normal(0.0, 2e-3, n_grid) + 1e-3  # rad/s
    keep = np.ones(n_grid, bool)
    keep[10_000:10_025] = False
    t_ns = (np.arange(n_grid) * (1e9 / fs)).astype(np.int64) + 1_700_000_000_000_000_000
    txt = tmp_path / "gyro.tsv"
    with open(txt, "w") as fh:
        fh.write("stamp_ns\tgyro_x_rad_s\n")
        for t, v in zip(t_ns[keep], y[keep]):
            fh.write(f"{t}\t{v:.9g}\n")
    rec = tmp_path / "g.h5"
    _ok(str(txt), "-o", str(rec), "--columns", "time=stamp_ns,gyr_x=gyro_x_rad_s",
        "--units", "gyr=rad/s,time=ns")
    out = capsys.readouterr().out
    assert "sample rate 200 Hz (the time column: its intervals over its span); 1 gaps, 25 samples missing" in out
    assert "not in the file, stored as NaN: ax, ay, az, gy, gz" in out
    with h5py.File(rec, "r") as f:
        assert abs(f["imu"].attrs["sample_rate_hz"] / fs - 1) < 1e-9
        c = f["imu/counter"][()]
        assert c[-1] == n_grid - 1 and np.count_nonzero(np.diff(c) != 1) == 1
        np.testing.assert_allclose(f["imu/angular_rate"][:, 0], y[keep], rtol=1e-8)
    assert cli.main(["allan", str(rec), "--taus", "octave", "--json", str(tmp_path / "a.json")]) == 0
    cap = capsys.readouterr()
    assert "== gx (gyro" in cap.out and "== gy" not in cap.out
    assert "25 samples missing in 1 gap(s): the Allan terms touching a gap are skipped" in cap.err
    res = json.loads((tmp_path / "a.json").read_text())
    n_fit = res["axes"]["gx"]["fit"]["coefficients"]["N"]["value"]  # rad/sqrt(s), as stored
    # white noise: N = sd * sqrt(tau0)
    n_np = float(np.std(y[keep])) * math.sqrt(1.0 / fs)
    assert abs(n_fit / n_np - 1) < 0.03


def test_semicolon_header_seconds_deg_s_and_g(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 3000
    g = rng.normal(0, 0.1, (n, 3))
    a = rng.normal(0, 1e-3, (n, 3)) + [0, 0, 1]
    csv = tmp_path / "log.csv"
    with open(csv, "w") as fh:
        fh.write("% exported\ntime_s;ax_g;ay_g;az_g;wx_dps;wy_dps;wz_dps\n")
        for k in range(n):
            fh.write(f"{k * 0.01:.2f};" + ";".join(f"{v:.7g}" for v in (*a[k], *g[k])) + "\n")
    rec = tmp_path / "o.h5"
    _ok(str(csv), "-o", str(rec), "--columns",
        "time=time_s,acc_x=ax_g,acc_y=ay_g,acc_z=az_g,gyr_x=wx_dps,gyr_y=wy_dps,gyr_z=wz_dps",
        "--units", "acc=g,gyr=deg/s")
    with h5py.File(rec, "r") as f:
        assert abs(f["imu"].attrs["sample_rate_hz"] - 100.0) < 1e-6
        np.testing.assert_allclose(f["imu/specific_force"][()], a * 9.80665, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(f["imu/angular_rate"][()], g * D2R, rtol=1e-6, atol=1e-12)


def test_a_gzipped_table_imports_as_the_plain_one(tmp_path: Path) -> None:
    import gzip

    rng = np.random.default_rng(5)
    rows = "t,temp,ax,ay,az,gx,gy,gz,pose\n" + "".join(
        f"{k * 60},{20 + 0.01 * k:.3f}," + ",".join(f"{v:.7g}" for v in (*rng.normal(0, 1e-3, 2), -9.8,
                                                                          *rng.normal(0, 1e-3, 3))) + ",z down\n"
        for k in range(200))
    plain, packed = tmp_path / "log.csv", tmp_path / "log.csv.gz"
    plain.write_text(rows)
    packed.write_bytes(gzip.compress(rows.encode()))
    cols = "time=t,temp=temp,acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz,section=pose"
    for src in (plain, packed):
        _ok(str(src), "-o", str(tmp_path / f"{src.name}.h5"), "--columns", cols, "--units", "acc=m/s^2,gyr=mrad/s")
    with h5py.File(tmp_path / "log.csv.h5", "r") as a, h5py.File(tmp_path / "log.csv.gz.h5", "r") as b:
        for k in ("imu/time", "imu/temperature", "imu/specific_force", "imu/angular_rate"):
            assert np.array_equal(a[k][()], b[k][()]), k
    bad = tmp_path / "cut.csv.gz"
    bad.write_bytes(packed.read_bytes()[:40])
    p = run_rigctl("import", str(bad), "--columns", cols, "--units", "acc=m/s^2,gyr=mrad/s", "-o", str(tmp_path / "x.h5"))
    assert p.returncode == 2 and "gzip" in p.stderr and "Traceback" not in p.stderr, p.stderr


def test_unreadable_input_is_one_error_line(tmp_path: Path) -> None:
    blob = tmp_path / "capture.bin"
    blob.write_bytes(bytes(range(256)) * 8)
    txt = tmp_path / "t.txt"
    txt.write_text("1 2 3\n4 5 6\n")
    cases = [
        ([str(blob), "--columns", "gyr_x=0", "--units", "gyr=rad/s", "--rate", "100"], "text table (CSV, TSV or whitespace-separated columns)"),
        ([str(txt), "--columns", "gyr_x=7", "--units", "gyr=rad/s", "--rate", "100"], "column 7 (for gx) does not exist"),
        ([str(txt), "--columns", "gyr_x=0", "--units", "gyr=rad/s"], "--rate HZ is required without a time column"),
        ([str(txt), "--columns", "gyr_x=0,time=1", "--units", "gyr=rad/s,time=fortnights"], "time units"),
    ]
    for argv, what in cases:
        p = run_rigctl("import", *argv, "-o", str(tmp_path / "o.h5"))
        lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
        assert p.returncode == 2 and what in p.stderr, p.stderr
        assert "Traceback" not in p.stderr and len(lines) <= 2, p.stderr  # message (+ hint)
        assert not (tmp_path / "o.h5").exists()


def _table(path: Path) -> np.ndarray:
    """Rows (AF, Tau, #, Alpha, Min Sigma, Sigma, Max Sigma) of a Stable32 result file."""
    return np.array([[float(v) for v in ln.split()] for ln in path.read_text().splitlines()
                     if ln.strip() and not ln.lstrip().startswith("#")])


def test_stable32_phase_files_through_import_and_allan(ref_data: Path, tmp_path: Path) -> None:
    """A Stable32 phase file (one column of phase in s, # comments, tau0 = 1 s) goes through
    `rigctl import --units gyr=rad --integrated --rate 1` (the phase differenced into
    fractional frequency) and `rigctl allan --exact`: the overlapping deviations and term
    counts are Stable32's (its tables: 5 significant digits)."""
    cases = [("phasedat/PHASE.DAT", "phasedat/phase_dat_oadev_octave.txt", "octave"),
             ("Cs5071A/5071A_phase.txt.gz", "Cs5071A/oadev_decade.txt", "decade")]
    for src, tab, taus in cases:
        d = ref_data / "stable32-reference"
        txt = d / src
        if txt.suffix == ".gz":
            import gzip

            plain = tmp_path / txt.stem
            plain.write_bytes(gzip.decompress(txt.read_bytes()))
            txt = plain
        rec = tmp_path / (Path(src).stem + ".h5")
        _ok(str(txt), "-o", str(rec), "--columns", "gyr_x=0", "--units", "gyr=rad",
            "--integrated", "--rate", "1")
        js = tmp_path / (Path(src).stem + ".json")
        assert cli.main(["allan", str(rec), "--taus", taus, "--exact", "--json", str(js)]) == 0
        r = json.loads(js.read_text())["axes"]["gx"]
        ref = _table(d / tab)
        m = np.asarray(r["m"])
        dev = np.asarray(r["adev_rad/s"])
        n_terms = np.asarray(r["n_terms"])
        hits = 0
        for af, _, count, _, _, sigma, _ in ref:
            k = np.flatnonzero(m == int(af))
            if not k.size:
                continue
            hits += 1
            assert abs(dev[k[0]] / sigma - 1) < 1e-4, (src, af, dev[k[0]], sigma)
            assert n_terms[k[0]] == int(count), (src, af)
        assert hits >= min(len(ref), 8), (src, hits, len(ref))


def _cycle_file(path: Path, t0_s: float, n: int) -> np.ndarray:
    """A clock comparison's two-column file as a Stable32 data file holds it: `#` header lines,
    then time tag (s) and fractional frequency; the instrument reports in a cycle of three
    1.31-s readings and a 6.57-s pause (the real Sr87 record of tests/data/sr87-stable32-frequency)."""
    rng = np.random.default_rng(11)
    steps = np.tile([1.31, 1.31, 1.31, 6.57], n)[: n - 1]
    t = t0_s + np.concatenate(([0.0], np.cumsum(steps)))
    y = rng.normal(0.0, 1e-16, n)
    with open(path, "w") as fh:
        fh.write("# Type: Freq\n# Tau: 2.500000e+00\n# Header End\n")
        for a, b in zip(t, y):
            fh.write(f"{a:.15e} {b:.15e}\n")
    return t


def test_a_cycling_cadence_is_said_and_not_taken_for_gaps_silently(tmp_path: Path, capsys) -> None:
    """Stamps in a 3 + 1 cycle: read with the short step as the interval, a quarter of the
    steps become 'gaps' (Allan stretches of 4 samples, a curve of 2 taus). The import says so
    in one warning with the mean step and the way to read the samples as equally spaced; a
    record with one real gap gets no such warning."""
    src = tmp_path / "clock.txt"
    t = _cycle_file(src, 1000.0, 800)
    _ok(str(src), "-o", str(tmp_path / "c.h5"), "--columns", "time=0,gyr_x=1", "--units", "gyr=rad/s")
    out = capsys.readouterr().out
    mean = float(np.mean(np.diff(t)))
    warn = [ln for ln in out.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1, out
    assert "199 of 799 steps of the time column (25 %) are longer than 1.5 intervals" in warn[0]
    assert f"1 / mean step = {1.0 / mean:.8g} Hz" in warn[0], warn[0]  # the one rate form (units.format_rate)
    # one dropped sample in a regular record: a gap, no warning
    reg = tmp_path / "regular.txt"
    stamps = np.delete(np.arange(1000) * 0.01, 500)
    reg.write_text("".join(f"{s:.2f},{v:.6g}\n" for s, v in zip(stamps, np.ones(999) * 1e-3)))
    _ok(str(reg), "-o", str(tmp_path / "r.h5"), "--columns", "time=0,gyr_x=1", "--units", "gyr=rad/s")
    out = capsys.readouterr().out
    assert "1 gaps, 1 samples missing" in out and "warning:" not in out, out


def test_stamps_from_another_epoch_do_not_date_the_capture_in_the_future(tmp_path: Path,
                                                                          capsys) -> None:
    """Time tags in seconds since 1900 (NTP, a Stable32 file's tags: 3.66e9 s in 2016) read
    as Unix seconds are a date in 2086: the recording is not dated by them (it was), and the
    line says why."""
    src = tmp_path / "clock.txt"
    _cycle_file(src, 3_661_957_841.37, 400)
    rec = tmp_path / "c.h5"
    _ok(str(src), "-o", str(rec), "--columns", "time=0,gyr_x=1", "--units", "gyr=rad/s")
    out = capsys.readouterr().out
    assert "not dated by the time column" in out and "2086" not in out, out
    with h5py.File(rec, "r") as f:
        meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f["meta"].attrs.items()}
    assert not str(meta.get("started_utc", "")).startswith("2086"), meta.get("started_utc")
    assert "import_stamp_zero_ns" not in meta


@pytest.mark.parametrize("fs, drop", [(400.0, ()), (300.0, (5000, 5001))])
def test_stamps_rounded_to_whole_milliseconds_give_the_rate(tmp_path: Path, capsys, fs: float,
                                                            drop: tuple[int, ...]) -> None:
    """A logger stamping in whole ms (millis()): at 400 Hz the steps are 2, 3, 2, 3 ms, whose
    median said 500 Hz (25 % off, every tau with it); at 300 Hz 3, 3, 4 ms said 333.3 Hz. The
    rate is the intervals over the stamps' span (read here: the true rate to one tick over the
    span), and two dropped samples are still one gap of two."""
    n = 40_000
    keep = np.ones(n, bool)
    keep[list(drop)] = False
    stamps = (np.floor(np.arange(n) * 1000.0 / fs).astype(np.int64) + 1_700_000_000_000)[keep]
    y = np.random.default_rng(7).normal(0.0, 1e-3, n)[keep]
    src = tmp_path / "millis.csv"
    src.write_text("t_ms,gx\n" + "".join(f"{a},{b:.6e}\n" for a, b in zip(stamps, y)))
    rec = tmp_path / "m.h5"
    _ok(str(src), "-o", str(rec), "--columns", "time=t_ms,gyr_x=gx", "--units", "gyr=rad/s,time=ms")
    out = capsys.readouterr().out
    span_s = (stamps[-1] - stamps[0]) * 1e-3
    with h5py.File(rec, "r") as f:
        rate = float(f["imu"].attrs["sample_rate_hz"])
        counter = f["imu/counter"][()]
    # one 1-ms tick over the span bounds the error
    assert abs(rate - fs) <= fs * 1e-3 / span_s * 1.01, (rate, fs)
    assert np.array_equal(counter, np.flatnonzero(keep)), np.flatnonzero(np.diff(counter) != 1)
    assert ("no gaps" in out) if not drop else ("1 gaps, 2 samples missing" in out), out


def test_a_stable32_header_is_read_for_what_the_options_miss(tmp_path: Path, capsys) -> None:
    """A Stable32 data file says its own Type and Tau in its `#` header (the Sr-87 file of
    tests/data/sr87-stable32-frequency). Without --rate the error names the header's rate; a
    phase file imported as rates, a frequency file differenced as phase, or a --rate other
    than 1 / Tau each get one warning; the right options none."""
    rng = np.random.default_rng(12)
    phase = np.cumsum(rng.normal(0.0, 1e-16, 600)) * 2.5
    src = tmp_path / "phase.dat"
    src.write_text("# File: phase.dat\n# Type: Phase\n# Points: 600\n# Tau: 2.500000e+00\n"
                   "# Header End\n" + "".join(f"{v:.12e}\n" for v in phase))
    out_h5 = str(tmp_path / "p.h5")
    assert cli.main(["import", str(src), "-o", out_h5, "--columns", "gyr_x=0", "--units", "gyr=rad"]) == 2
    err = capsys.readouterr().err
    assert "--rate HZ is required" in err and "Tau: 2.5 s: --rate 0.4" in err, err
    cases = [(["--units", "gyr=rad/s", "--rate", "0.4"], "Type: Phase"),
             (["--units", "gyr=rad", "--integrated", "--rate", "1"], "Tau: 2.5 s (--rate 0.4); --rate 1 was given"),
             (["--units", "gyr=rad", "--integrated", "--rate", "0.4"], None)]
    for opts, said in cases:
        _ok(str(src), "-o", out_h5, "--force", "--columns", "gyr_x=0", *opts)
        warn = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("warning:")]
        assert (warn == []) if said is None else (len(warn) == 1 and said in warn[0]), (opts, warn)
    freq = tmp_path / "freq.dat"
    freq.write_text("# Type: Freq\n# Tau: 1\n" + "".join(f"{v:.6e}\n" for v in rng.normal(0, 1e-12, 600)))
    _ok(str(freq), "-o", out_h5, "--force", "--columns", "gyr_x=0", "--units", "gyr=rad", "--integrated",
        "--rate", "1")
    assert "header says Type: Freq" in capsys.readouterr().out
