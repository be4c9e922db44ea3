"""`rigctl allan` on real HDF5 recordings written with h5py (layout of schema_version 1)."""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest

import recording_helpers
from rigctl.analysis import allan as AA
from rigctl.commands import allan_cmd
from rigctl import cli
from rigctl.solvers.noise_coefficients import as_coefficients, in_field_units


def fu(fit: dict, term: str):
    """A fitted term in its field unit (value, ci95, upper95, resolved)."""
    return in_field_units(as_coefficients(fit["coefficients"]), term)[0]


def write_recording(path: Path, n: int, fs: float = 100.0, seed: int = 0,
                    with_accel: bool = True) -> dict:
    rng = np.random.default_rng(seed)
    arw = 0.3 * math.pi / 180 / 60  # rad/sqrt(s)
    vrw = 0.04 / 60  # m/s/sqrt(s)
    cols = {"angular_rate": rng.standard_normal((n, 3)) * arw * math.sqrt(fs) + 7.29e-5}
    if with_accel:
        a = rng.standard_normal((n, 3)) * vrw * math.sqrt(fs) + [0.0, 0.0, 9.80665]
        cols["specific_force"] = a.astype(np.float32)
    recording_helpers.write_recording(path, fs, chunk_rows=4096, **cols)
    return {"arw_deg_rt_h": 0.3, "vrw_m_s_rt_h": 0.04}


def _args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="rigctl")
    sub = parser.add_subparsers()
    allan_cmd.register(sub)
    return parser.parse_args(["allan", *argv])


def test_allan_command_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rec = tmp_path / "rec.h5"
    truth = write_recording(rec, 200_000)
    png = tmp_path / "allan.png"
    args = _args([str(rec), "--plot", str(png), "--taus", "40"])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "== gx (gyro" in out and "== az (accel" in out and "angle_random_walk" in out
    assert png.stat().st_size > 10_000
    with h5py.File(rec, "r") as f:
        g = f["results/allan"]
        assert g.attrs["schema_version"] == 2 and "T" in g.attrs["created_utc"]  # 2: fit["coefficients"]
        summary = json.loads(g.attrs["json"])
        tau = f["results/allan/gx/tau_s"][:]
        assert f["results/allan/gx/tau_s"].attrs["units"] == "s"
        assert f["results/allan/az/adev_mg"].attrs["units"] == "mg"
        lo, hi = f["results/allan/gx/lo68_deg_per_h"][:], f["results/allan/gx/hi68_deg_per_h"][:]
        dev = f["results/allan/gx/adev_deg_per_h"][:]
    assert np.all(np.diff(tau) > 0) and np.all(lo < dev) and np.all(dev < hi)
    n_gx = fu(summary["axes"]["gx"]["fit"], "N").value  # deg/sqrt(h)
    n_az = fu(summary["axes"]["az"]["fit"], "N").value  # m/s/sqrt(h)
    assert abs(n_gx / truth["arw_deg_rt_h"] - 1) < 0.05
    assert abs(n_az / truth["vrw_m_s_rt_h"] - 1) < 0.05  # float32 with 1 g on the axis
    # white noise only: K is an upper bound, with the capture length that could resolve it
    k = summary["axes"]["gx"]["fit"]["terms"]["K"]
    assert not fu(summary["axes"]["gx"]["fit"], "K").resolved and k["capture_h_for_25pct"] > 200_000 / 100.0 / 3600
    assert "rate_random_walk: <" in out and "+-25 % would need at least" in out
    from rigctl.report.report_html import _need_cell
    assert _need_cell(k, False).startswith(">= ") and _need_cell(summary["axes"]["gx"]["fit"]["terms"]["N"], True) == ""
    # running again replaces the results group
    args = _args([str(rec), "--axes", "gz", "--taus", "octave"])
    assert args.func(args) == 0
    with h5py.File(rec, "r") as f:
        assert list(json.loads(f["results/allan"].attrs["json"])["axes"]) == ["gz"]


def test_stream_matches_in_memory(tmp_path: Path) -> None:
    rec = tmp_path / "rec.h5"
    write_recording(rec, 150_000, seed=3)
    res = AA.compute(str(rec), ["gy"], "octave", exact=True)
    from rigctl.solvers import allan as A

    with h5py.File(rec, "r") as f:
        y = f["imu/angular_rate"][:, 1]
    ref = A.oadev(y, 0.01, "octave", data_type="rate", mode="exact")
    np.testing.assert_allclose(res["axes"]["gy"]["adev_rad/s"], ref.dev, rtol=1e-10)


@pytest.mark.parametrize("case", ["missing", "not_hdf5", "not_rigctl", "no_accel", "short",
                                  "bad_axes", "bad_taus"])
def test_bad_input_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture, case: str) -> None:
    rec = tmp_path / "rec.h5"
    argv = [str(rec)]
    if case == "not_hdf5":
        rec.write_text("hello")
    elif case == "not_rigctl":
        with h5py.File(rec, "w") as f:
            f.create_dataset("x", data=[1, 2, 3])
    elif case == "no_accel":
        write_recording(rec, 1000, with_accel=False)
    elif case == "short":
        write_recording(rec, 20)
    elif case == "bad_axes":
        write_recording(rec, 1000)
        argv += ["--axes", "gx,qq"]
    elif case == "bad_taus":
        write_recording(rec, 1000)
        argv += ["--taus", "weekly"]
    assert cli.main(["allan", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rigctl allan: error:") and "Traceback" not in err
    if case in ("missing", "not_hdf5", "not_rigctl", "no_accel", "short"):
        assert str(rec) in err


@pytest.mark.parametrize("opts, names", [
    (["--kalibr", "{d}/no-dir/imu.yaml"], "no-dir"), (["--json", "{d}/no-dir/r.json"], "no-dir"),
    (["--csv", "{d}"], "is a directory"), (["--plot", "{d}/no-dir/p.png"], "no-dir"),
    (["--kalibr-inflate", "3"], "--kalibr-inflate without --kalibr"),
    (["--kalibr-topic", "/imu"], "--kalibr-topic without --kalibr")])
def test_export_options_are_checked_before_the_analysis(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                         opts: list[str], names: str) -> None:
    """An export into a directory that does not exist failed only after the analysis (minutes
    on a long capture) with exit 1 ("failed: ...: No such file or directory"), the results
    already stored; --kalibr-inflate / --kalibr-topic without --kalibr were silently ignored.
    Now each is invalid input: exit 2, one line naming the path or the option, nothing run."""
    rec = tmp_path / "rec.h5"
    write_recording(rec, 1000)
    argv = ["allan", str(rec), "--db", "none", *[o.format(d=tmp_path) for o in opts]]
    assert cli.main(argv) == 2
    out, err = capsys.readouterr()
    assert err.startswith("rigctl allan: error:") and err.count("\n") == 1, err
    assert names in err and "Traceback" not in err
    with h5py.File(rec, "r") as f:
        assert "results/allan" not in f  # refused before the analysis
    assert not (tmp_path / "no-dir").exists()


def test_solve_recording_uses_capture_segment(tmp_path: Path) -> None:
    """The procedure hook analyses the longest capture segment, stores /results/allan and the
    results database and logs one info line per axis (plus one for counter gaps, whose
    terms are skipped)."""
    rec = tmp_path / "rec.h5"
    write_recording(rec, 120_000, seed=4)
    with h5py.File(rec, "r+") as f:
        seg = f.create_group("segments")
        seg.create_dataset("kind", data=np.array([b"warmup", b"capture", b"capture"], "S16"))
        seg.create_dataset("label", data=np.array([b"warm", b"overnight", b"short"], "S48"))
        seg.create_dataset("first_sample", data=np.array([0, 20_000, 110_000], np.int64))
        seg.create_dataset("last_sample", data=np.array([20_000, 100_000, 115_000], np.int64))
        seg.create_dataset("status", data=np.array([b"complete"] * 3, "S16"))
        counter = f["imu/counter"][:]
        counter[50_000:] += 3  # three dropped samples inside the capture
        f["imu/counter"][:] = counter
    messages: list[tuple[str, str]] = []
    AA.solve_recording(rec, lambda kind, msg, **_: messages.append((kind, msg)))
    with h5py.File(rec, "r") as f:
        summary = json.loads(f["results/allan"].attrs["json"])
    assert summary["n_samples"] == 80_000 and summary["first_sample"] == 20_000
    assert summary["dropped_samples"] == 0 and "overnight" in summary["segment"]
    info = [m for k, m in messages if k == "info"]
    assert any("capture segment 'overnight'" in m for m in info)
    assert sum(m.startswith("allan gx:") for m in info) == 1
    assert sum(m.startswith("allan: results database: ") for m in info) == 1 and len(info) == 9
    assert any("3 samples missing" in m and "skipped" in m for m in info)
    n_gx = fu(summary["axes"]["gx"]["fit"], "N").value  # deg/sqrt(h)
    assert abs(n_gx / 0.3 - 1) < 0.05


def test_warns_when_the_table_moved_in_the_analysed_range(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    rec = tmp_path / "moving.h5"
    write_recording(rec, 20_000)
    with h5py.File(rec, "r") as f:
        t_end = float(f["/imu/time"][-1])
    for rate_dps, warned in ((0.0, False), (10.0, True)):
        with h5py.File(rec, "a") as f:
            if "table" in f:
                del f["table"]
            t = np.linspace(0.0, t_end, 500)
            g = f.create_group("table")
            g["time"] = t
            g["rate"] = np.tile(np.radians([0.0, 0.0, rate_dps]), (t.size, 1))
            g["angle"] = np.outer(t, np.radians([0.0, 0.0, rate_dps]))
        args = _args([str(rec), "--axes", "gz", "--taus", "octave"])
        assert args.func(args) == 0
        cap = capsys.readouterr()
        assert "analysing the whole recording" in cap.out
        assert ("warning: the table moved during the analysed range" in cap.err) is warned, cap.err
        if warned:
            assert "up to 10 deg/s" in cap.err


def test_gaps_are_refused_or_handled_as_asked(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Dropped samples are never bridged silently: by default the Allan terms touching a gap
    are skipped (Stable32; tests/test_allan_gaps.py checks the numbers) and the output says so;
    --gaps refuse refuses, naming the gap and the ways on (exit 2, one message); --gaps longest
    analyses the longest gap-free stretch; --gaps bridge treats the samples as contiguous and
    says so. Gaps are found from /imu/counter, or from /imu/time when there is no counter."""
    rec = tmp_path / "gappy.h5"
    write_recording(rec, 60_000)
    with h5py.File(rec, "r+") as f:
        counter = f["imu/counter"][:]
        counter[40_000:] += 5
        f["imu/counter"][:] = counter
    assert cli.main(["allan", str(rec), "--axes", "gx", "--taus", "octave"]) == 0
    err = capsys.readouterr().err
    assert "note: 5 samples missing in 1 gap(s): the Allan terms touching a gap are skipped" in err
    assert cli.main(["allan", str(rec), "--axes", "gx", "--taus", "octave", "--gaps", "refuse"]) == 2
    err = capsys.readouterr().err
    assert "5 samples missing in 1 gap(s)" in err and "before row 40000" in err
    assert "--gaps longest" in err and "40000 samples" in err and "--gaps bridge" in err
    assert "Traceback" not in err
    args = _args([str(rec), "--axes", "gx", "--taus", "octave", "--gaps", "longest"])
    assert args.func(args) == 0
    assert "analysing the longest gap-free stretch, rows 0..39999" in capsys.readouterr().err
    with h5py.File(rec, "r") as f:
        s = json.loads(f["results/allan"].attrs["json"])
    assert s["n_samples"] == 40_000 and s["first_sample"] == 0 and s["dropped_samples"] == 0
    args = _args([str(rec), "--axes", "gx", "--taus", "octave", "--gaps", "bridge"])
    assert args.func(args) == 0
    assert "5 samples missing in 1 gap(s), bridged on request" in capsys.readouterr().err
    with h5py.File(rec, "r") as f:
        assert json.loads(f["results/allan"].attrs["json"])["dropped_samples"] == 5
    # no counter: the time stamps tell
    with h5py.File(rec, "r+") as f:
        del f["imu/counter"]
        t = f["imu/time"][:]
        t[30_000:] += 0.5  # a step of 0.51 s: 50 samples missing at 100 Hz
        f["imu/time"][:] = t
    assert cli.main(["allan", str(rec), "--axes", "gx", "--taus", "octave", "--gaps", "refuse"]) == 2
    assert "50 samples missing in 1 gap(s)" in capsys.readouterr().err


def test_spikes_and_quantization_on_synthetic_noise(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Known spikes injected into white noise are all found and reported; excluded, N comes
    back to the truth, left in, it is inflated (and the output says so). A rounded output's step
    is read from the samples."""
    rng = np.random.default_rng(5)
    n, fs = 100_000, 100.0
    arw = 0.3 * math.pi / 180 / 60
    y = rng.standard_normal((n, 3)) * arw * math.sqrt(fs)
    spikes = np.sort(rng.choice(np.arange(100, n - 100), 40, replace=False))
    y[spikes, 0] += 30.0 * arw * math.sqrt(fs) * np.where(np.arange(40) % 2, 1.0, -1.0)
    step = arw * math.sqrt(fs) / 4.0  # about four steps of noise per sample
    y[:, 2] = np.round(y[:, 2] / step) * step
    rec = tmp_path / "spiky.h5"
    write_recording(rec, n, with_accel=False)
    with h5py.File(rec, "r+") as f:
        f["imu/angular_rate"][:] = y
    res = AA.compute(str(rec), ["gx", "gy", "gz"], "octave")
    sp = res["axes"]["gx"]["spikes"]
    assert sp["count"] == 40 and np.allclose(sp["first_times_s"], spikes[:10] / fs)
    assert res["axes"]["gy"]["spikes"]["count"] == 0
    n_in = fu(res["axes"]["gx"]["fit"], "N").value
    clean = AA.compute(str(rec), ["gx"], "octave", outliers="exclude")["axes"]["gx"]
    n_out = fu(clean["fit"], "N").value
    # 40 spikes of 30 sd in 1e5 samples add 40 * 900 / 1e5 = 0.36 of the white variance
    assert abs(n_out / 0.3 - 1) < 0.05 and abs(n_in / (0.3 * math.sqrt(1.36)) - 1) < 0.06
    q = res["axes"]["gz"]["quantization"]
    assert abs(q["step_si"] / step - 1) < 1e-9 and res["axes"]["gx"]["quantization"] is None
    assert abs(q["white_N_si"] / (step * math.sqrt(0.01 / 12)) - 1) < 1e-9
    args = _args([str(rec), "--axes", "gx,gz", "--taus", "octave"])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "warning: 40 samples (0.04 %) more than 10 robust sd" in out and "--outliers exclude" in out
    assert "note: output quantized in steps of" in out


def test_all_taus_below_2_20_points_stay_fast_modes_set(tmp_path) -> None:
    """Below 2^20 points the sums are exact, but `--taus all` without --exact keeps fast mode's
    set (at most 8 factors per octave): every factor of a 2.8 h x 100 Hz capture was ~5e5
    taus and 6 min 21 s (the sums stay exact: stride 1)."""
    rng = np.random.default_rng(3)
    n = 200_000
    rec = recording_helpers.write_recording(tmp_path / "r.h5", 100.0,
                          angular_rate=rng.normal(0, 1e-3, (n, 3)),
                          specific_force=rng.normal(0, 1e-2, (n, 3)))
    r = AA.compute(str(rec), ["gx"], "all")["axes"]["gx"]
    m = np.asarray(r["m"])
    octaves = np.floor(np.log2(m)).astype(int)
    assert np.bincount(octaves).max() <= 8 and len(m) < 200, len(m)
    assert np.all(np.asarray(r["stride"]) == 1)


def test_kalibr_on_a_gyro_only_import_says_what_the_recording_has(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture) -> None:
    """A gyro-only log (a bag whose linear_acceleration is never filled, here a CSV without
    accelerometer columns): --kalibr was refused with "(--axes gx,gy,gz,ax,ay,az)", advice that
    then fails on the NaN accelerometer. Now the error says which axes the recording has."""
    rng = np.random.default_rng(4)
    t = np.arange(3000) / 100.0
    g = rng.standard_normal((t.size, 3)) * 1e-3
    csv = tmp_path / "gyro.csv"
    csv.write_text("time,gx,gy,gz\n" + "\n".join(f"{a:.2f},{b:.6e},{c:.6e},{d:.6e}"
                                                 for a, (b, c, d) in zip(t, g)) + "\n")
    rec = tmp_path / "gyro.h5"
    assert cli.main(["import", str(csv), "-o", str(rec), "--columns",
                     "time=time,gyr_x=gx,gyr_y=gy,gyr_z=gz", "--units", "gyr=rad/s"]) == 0
    capsys.readouterr()
    assert cli.main(["allan", str(rec), "--db", "none", "--kalibr", str(tmp_path / "imu.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(rec) in err and "has gx,gy,gz only" in err, err
    assert "--axes gx,gy,gz,ax,ay,az" not in err
    assert not (tmp_path / "imu.yaml").exists()
