"""The thermal solver on real data: a static record of a Raspberry Pi Sense HAT (LSM9DS1 IMU)
over 58 h at room temperature, board temperature 25.6 .. 32.4 degC (tests/data/
astropi-sensehat-static, recorded by the Raspberry Pi Foundation, CC BY-SA 4.0).

One orientation (x axis up): only the bias terms are identifiable, so the solver must refuse
the full model and fit with scale and misalignment held. The record goes in as any foreign log
does (``rigctl import`` with a temperature column), then the application layer cuts it into
30-min windows (rigctl.analysis.thermal.static_windows) and the solver fits the bias against
temperature by generalised least squares with the noise of the window means estimated from the
record.

Every expected value comes from an analysis written here with plain numpy on the CSV itself:
the 30-min window means, and the slope of the accelerometer output against temperature from
the *differences* of consecutive window means (the bias of a MEMS accelerometer wanders like a
random walk over hours; differencing removes it, so this is the estimator that suits that
noise, independent of the solver's covariance model), with its own residual check. Numbers
measured when this was written are in the comments.
"""
from __future__ import annotations

import csv
import datetime as dt
import gzip
import hashlib
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import run_rigctl
from rigctl.analysis import thermal as AT
from rigctl.solvers import thermal as th

SET = "astropi-sensehat-static"
CSV = "astro_pi_data_20150824_085954.csv.gz"
#: sha256 of the source's CSV (raspberrypilearning/astro-pi-flight-data-analysis, in the zip
#: data/astro_pi_data_20150824_085954.zip and as the CSV at commit 69b8bb0)
SHA256 = "da2726843cd6844f8b845012e1f057fa7f8bcd9378fedec89b229bef4ee68eb1"
#: the record's second static section: after the reset in row 3902 (0-based data row) the board
#: lies with its x axis up for 58 h; before it, 11 h with z up and a knock at 9 h
FIRST_ROW = 3902
G0 = 9.80665
MG = G0 * 1e-3
WINDOW_S = 1800.0


def _rows(ref_data: Path) -> list[dict[str, str]]:
    with gzip.open(ref_data / SET / CSV, "rt", newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def record(ref_data, tmp_path_factory):
    """(rows of the source CSV, the imported recording of the x-up section)."""
    raw = gzip.open(ref_data / SET / CSV).read()
    assert hashlib.sha256(raw).hexdigest() == SHA256
    rows = _rows(ref_data)
    d = tmp_path_factory.mktemp("astropi")
    t0 = dt.datetime.fromisoformat(rows[FIRST_ROW]["time_stamp"]).timestamp()
    src = d / "xup.csv"
    with src.open("w") as fh:  # numeric time (the source's is a date), the columns unchanged
        fh.write("t,temp_h,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z\n")
        for r in rows[FIRST_ROW:]:
            t = dt.datetime.fromisoformat(r["time_stamp"]).timestamp() - t0
            fh.write(f"{t:.0f},{r['temp_h']},{r['accel_x']},{r['accel_y']},{r['accel_z']},"
                     f"{r['gyro_x']},{r['gyro_y']},{r['gyro_z']}\n")
    seg = d / "sections.json"
    seg.write_text(json.dumps({"x up": {"start": 0, "end": len(rows) - FIRST_ROW}}))
    rec = d / "xup.h5"
    proc = run_rigctl("import", str(src), "-o", str(rec), "--columns",
                      "time=t,temp=temp_h,acc_x=accel_x,acc_y=accel_y,acc_z=accel_z,"
                      "gyr_x=gyro_x,gyr_y=gyro_y,gyr_z=gyro_z",
                      "--units", "acc=g,gyr=rad/s,time=s", "--segments", str(seg))
    assert proc.returncode == 0, proc.stderr
    return rows, rec


def _numpy_windows(rows: list[dict[str, str]]) -> dict[str, np.ndarray]:
    """30-min windows of the x-up section from the CSV: edges every WINDOW_S from its first
    sample, a window kept with at least half its 180 nominal samples."""
    sub = rows[FIRST_ROW:]
    t = np.array([dt.datetime.fromisoformat(r["time_stamp"]).timestamp() for r in sub])
    t -= t[0]
    T = np.array([float(r["temp_h"]) for r in sub])
    acc = np.array([[float(r[f"accel_{a}"]) for a in "xyz"] for r in sub]) * G0
    k = np.floor(t / WINDOW_S).astype(int)
    n = np.bincount(k)
    keep = np.flatnonzero(n >= 90)
    return {"T": np.bincount(k, T)[keep] / n[keep], "n": n[keep], "index": keep, "t": t, "temp": T,
            "acc": np.column_stack([np.bincount(k, acc[:, i])[keep] / n[keep] for i in range(3)])}


@pytest.fixture(scope="module")
def fits(record):
    """Windows of the imported record and the solver's fits: accelerometer with the bias degree
    1 that select_degrees chooses here, gyro likewise; noise of the window means from the record."""
    _, rec = record
    wins = AT.static_windows(rec, WINDOW_S)
    for w in wins.values():
        th.estimate_noise(w)
    deg = {"bias": 1, **th.BIAS_ONLY}
    return wins, {s: th.fit_thermal(w, deg, loop=False) for s, w in wins.items()}, \
        {s: th.fit_thermal(w, deg, loop=True) for s, w in wins.items()}


def test_the_record_spans_several_kelvin_and_imports_with_its_temperature(record):
    rows, rec = record
    assert len(rows) == 24604
    with h5py.File(rec, "r") as f:
        T = f["imu/temperature"][()]
        acc = f["imu/specific_force"][()]
        assert T.size == len(rows) - FIRST_ROW == 20702
        assert T.max() - T.min() > 6.5  # 25.60 .. 32.46 degC
        # one orientation: x up, within 3 deg of the vertical throughout
        assert np.all(acc[:, 0] > np.cos(np.radians(3.0)) * np.linalg.norm(acc, axis=1))


def test_the_application_layer_windows_match_numpy(record, fits):
    rows, _ = record
    ref = _numpy_windows(rows)
    w = fits[0]["accel"]
    assert len(w) == len(ref["T"]) == 116
    assert np.allclose(w.temperature, ref["T"], rtol=0, atol=1e-9)
    assert np.allclose(w.y, ref["acc"], rtol=1e-12, atol=1e-12)
    assert np.all(w.t_end - w.t_start <= WINDOW_S + 1e-6)
    # one orientation: the same reference input in every window
    assert th.one_orientation(w.ref)


def test_one_orientation_the_solver_refuses_scale_and_misalignment(fits):
    w = fits[0]["accel"]
    with pytest.raises(ValueError, match="only the bias terms are identifiable"):
        th.fit_thermal(w)  # the default degrees 2, 2, 1
    with pytest.raises(ValueError, match="one orientation"):
        th.fit_thermal(w, {"bias": 1, "scale": 1, "misalignment": -1})
    assert th.select_degrees(w)["scale"] == th.HELD


def test_without_window_times_the_fit_is_numpy_weighted_least_squares(record):
    """The means treated as independent (no times, no covariance): the solver's bias fit is the
    weighted polynomial fit of the window means against the window-mean temperature (degree 1:
    <dT> is the mean temperature less 25 degC)."""
    rows, rec = record
    ref = _numpy_windows(rows)
    w = AT.static_windows(rec, WINDOW_S)["accel"]
    w.t_start = w.t_end = None
    w.set_cov(None)
    fit = th.fit_thermal(w, {"bias": 1, **th.BIAS_ONLY}, loop=False)
    for i, a in enumerate(fit.axes):
        c = np.polyfit(ref["T"] - 25.0, ref["acc"][:, i] - w.ref[:, i], 1, w=1.0 / w.sigma[:, i])
        assert np.allclose(a.values, c[::-1], rtol=1e-7, atol=1e-10)
    # and treating the means as independent is wrong on this record: the chi-square is far out
    # of its band (measured 674; per axis 501, 110, 1412) -- the bias wanders between windows
    assert fit.chi2 / fit.dof > 20 * fit.band()[1]


def test_bias_per_kelvin_agrees_with_the_differenced_window_means(record, fits):
    """Solver (GLS, noise from the record) against numpy's slope of the differences of
    consecutive window means on the differences of their temperatures. Measured: solver
    0.537 +- 0.019, 0.457 +- 0.015, -0.341 +- 0.026 mg/K; numpy 0.530 +- 0.020, 0.460 +- 0.018,
    -0.341 +- 0.024 mg/K. Each 95 % interval holds the other's value."""
    rows, _ = record
    ref = _numpy_windows(rows)
    _, plain, _ = fits
    params = {q["name"]: q for q in plain["accel"].parameters()}
    consecutive = np.diff(ref["index"]) == 1
    dT = np.diff(ref["T"])[consecutive]
    for i, a in enumerate("xyz"):
        dy = np.diff(ref["acc"][:, i])[consecutive]
        b = (dT @ dy) / (dT @ dT)
        r = dy - b * dT
        s = np.sqrt((r @ r) / (dT.size - 1) / (dT @ dT))
        # numpy's own check: the temperature explains most of the window-to-window changes
        # (measured: residual RMS 0.057, 0.050, 0.067 mg against 0.150, 0.131, 0.112 mg)
        assert np.std(r) < 0.65 * np.std(dy)
        q = params[f"accel_bias_{a}_m_s2_per_K"]
        assert q["ci95"][0] <= b <= q["ci95"][1], (a, b / MG, q["value"] / MG, q["sigma"] / MG)
        assert abs(q["value"] - b) <= 1.96 * s, (a, b / MG, q["value"] / MG, s / MG)
        assert abs(b) > 10 * s  # a real effect of 0.3 - 0.5 mg/K, not noise


def test_accel_chi_square_inside_its_band_and_the_loop(fits):
    """With the noise of the window means from the record the accelerometer fit's chi-square
    is inside its 99 % band (measured 0.960 in 0.814 .. 1.208; with the means' uncertainties
    from within the windows alone it is 674: the bias wanders). The loop: the temperature rate
    adds nothing (p_adj 0.68); a heating/cooling difference ('hysteresis', 0.1 - 0.15 mg) is
    accepted at bias degree 1 (F = 6.5, p_adj 6e-4; at degree 2 p_adj 0.003, not accepted): the
    temperature is the board's humidity sensor, centimetres from the IMU's die, and a lag
    between them cannot be told from a hysteresis of the sensor (docs/thermal.md)."""
    _, plain, looped = fits
    f = plain["accel"]
    lo, hi = f.band()
    assert lo <= f.chi2 / f.dof <= hi
    fl = looped["accel"]
    rate = [e for e in fl.explain if e["candidate"] == "temperature_rate"]
    assert rate and all(e["decision"] == "rejected" and e["p_adj"] > 0.05 for e in rate)
    assert fl.accepted == ["hysteresis"]
    lo, hi = fl.band()
    assert lo <= fl.chi2 / fl.dof <= hi


def test_gyro_the_loop_names_the_temperature_rate_and_chi_square_is_below_its_band(fits):
    """The Sense HAT's library (RTIMULib) subtracts a gyro bias it keeps learning while the
    board is still (first-order, time constant 1 / 0.01 = 100 s): what is left of a bias that
    moves with temperature is its lag, tau dB/dT dT/dt. Measured: no bias slope (all |b| below
    2 sigma), the loop accepts the temperature rate (F = 9.8, p_adj 6e-6; z: -0.076 +- 0.018
    rad/s per K/s, i.e. dB/dT ~ -7.6e-4 rad/s/K behind the 100 s tracker), and the chi-square
    is *below* its 99 % band (0.72 against 0.81 .. 1.21): the covariance from the record's
    noise estimate over-predicts the scatter of a tracker's output -- a finding, reported by
    the fit's band, not hidden."""
    _, plain, looped = fits
    for q in plain["gyro"].parameters():
        if q["name"].endswith("_per_K"):
            assert abs(q["value"]) < 2 * q["sigma"], q
    g = looped["gyro"]
    assert g.accepted[:1] == ["temperature_rate"]
    first = [e for e in g.explain if e["step"] == 1 and e["candidate"] == "temperature_rate"][0]
    assert first["p_adj"] < 1e-4
    z = {q["name"]: q for q in g.parameters()}["gyro_temp_rate_z_rad_s_per_K_per_s"]
    assert z["ci95"][1] < 0
    lo, _ = g.band()
    assert g.chi2 / g.dof < lo


def test_noise_model_against_the_allan_deviation_of_the_record(record, fits):
    """The covariance of the window means rests on the noise the solver estimated from the record
    (white N, bias instability B, rate random walk K per axis). Against it: the overlapping Allan
    deviation of the record itself in numpy, less numpy's temperature slope (differenced window
    means), on the 10-s grid, with the IEEE 952 terms N^2/tau + (2 ln2/pi) B^2 + K^2 tau/3
    written out here. Measured ratio data/model: x 0.90 .. 1.06 and z 0.92 .. 1.07 from 10 s to
    3000 s, y 0.93 .. 1.04 from 100 s to 10000 s. Two findings, asserted as such: on y the
    estimate put no white noise at all (N^2 3e-11 against 7e-6 on x and z), and at 10 s the data
    are 2.1 times the model; over 3 - 8 h x and z wander more than the model (1.4 - 2.2 times):
    what the temperature slope leaves (the heating/cooling difference the loop finds, a lag of
    the board's sensor behind the die) on top of a random walk."""
    rows, _ = record
    sub = rows[FIRST_ROW:]
    t = np.array([dt.datetime.fromisoformat(r["time_stamp"]).timestamp() for r in sub])
    T = np.array([float(r["temp_h"]) for r in sub])
    acc = np.array([[float(r[f"accel_{a}"]) for a in "xyz"] for r in sub]) * G0
    ref = _numpy_windows(rows)
    consecutive = np.diff(ref["index"]) == 1
    dT = np.diff(ref["T"])[consecutive]
    grid = np.arange(t[0], t[-1], 10.0)  # 236 single-sample gaps: the next sample stands in
    idx = np.clip(np.searchsorted(t, grid), 0, t.size - 1)
    w = fits[0]["accel"]

    def ratios(i: int, taus: list[int]) -> np.ndarray:
        dy = np.diff(ref["acc"][:, i])[consecutive]
        y = (acc[:, i] - (dT @ dy) / (dT @ dT) * (T - 25.0))[idx]
        x = np.concatenate([[0.0], np.cumsum(y)]) * 10.0
        m = w.noise[i]
        out = []
        for tau in taus:
            k = tau // 10
            d = x[2 * k:] - 2 * x[k:-k] + x[:-2 * k]
            adev2 = np.mean(d**2) / (2.0 * tau**2)
            model = (sum(v**2 for v in m.white_by_group.values()) / tau + 2 * np.log(2) / np.pi * m.B.value**2
                     + m.K.value**2 * tau / 3)
            out.append(np.sqrt(adev2 / model))
        return np.array(out)

    for i in (0, 2):
        assert np.all(np.abs(ratios(i, [10, 30, 100, 300, 1000, 3000]) - 1) < 0.2), ratios(i, [10, 3000])
        assert np.all(ratios(i, [10000, 30000]) > 1.3)  # the slow excess (finding)
    assert np.all(np.abs(ratios(1, [100, 300, 1000, 3000, 10000]) - 1) < 0.2)
    assert (sum(v**2 for v in w.noise[1].white_by_group.values())
            < 1e-3 * sum(v**2 for v in w.noise[0].white_by_group.values()))
    assert ratios(1, [10])[0] > 1.8  # white level lost on y (finding)
