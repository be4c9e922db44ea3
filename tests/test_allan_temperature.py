"""The Allan pipeline's check of the residual drift against a recorded temperature
(rigctl.analysis.allan_drift.temperature_check), on the real Astro Pi record
(tests/data/astropi-sensehat-static: a Sense HAT's LSM9DS1, 58 h static with its x axis up,
board temperature 25.6 - 32.5 degC, a reading every ~10 s; README there). Its accelerometer
follows the room's temperature by ~0.5 mg/K, a drift outside IEEE 952 (once taken for the cause
of --taus octave and all disagreeing there; that was the covariance across taus ignoring the
gaps, test_allan_gapcov.py): the pipeline must name the temperature, give its coefficient with an
interval that an independent plain-numpy estimate (30-min windows by time from the CSV,
differences of consecutive window means regressed on the temperature's) agrees with, and with
--temperature remove analyse the samples without the term.
"""
from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from astropi_support import import_xup, xup_rows
from rigctl.analysis import allan as AA

WINDOW_S = 1800.0


@pytest.fixture(scope="module")
def astro(ref_data, tmp_path_factory) -> tuple[list[dict], Path]:
    rows = xup_rows(ref_data)
    rec = import_xup(rows, tmp_path_factory.mktemp("astro_t"),
                     ("temp_h", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z"))
    return rows, rec


def _numpy_coefficient(rows: list[dict], col: str) -> tuple[float, float, float]:
    """mg/K of ``col`` on temp_h: 30-min windows by time (kept with at least 90 readings),
    least squares of the differences of consecutive window means, Student-t 95 % interval."""
    t = np.array([dt.datetime.fromisoformat(r["time_stamp"]).timestamp() for r in rows])
    t -= t[0]
    T = np.array([float(r["temp_h"]) for r in rows])
    y = np.array([float(r[col]) for r in rows]) * 1000.0  # g -> mg
    k = np.floor(t / WINDOW_S).astype(int)
    n = np.bincount(k)
    keep = n >= 90
    ym = np.bincount(k, y)[keep] / n[keep]
    Tm = np.bincount(k, T)[keep] / n[keep]
    dy, dT = np.diff(ym), np.diff(Tm)
    c = float(dT @ dy / (dT @ dT))
    r = dy - c * dT
    se = float(np.sqrt(r @ r / (dy.size - 1) / (dT @ dT)))
    q = float(stats.t.ppf(0.975, dy.size - 1))
    return c, c - q * se, c + q * se


def _apart(ra: dict, rb: dict) -> list[str]:
    """Terms on which two fits disagree beyond their 95 % intervals / bounds."""
    bad = []
    for t in ("N", "B", "K"):
        a, b = getattr(ra["fit"]["coefficients"], t), getattr(rb["fit"]["coefficients"], t)
        if a.resolved and b.resolved:
            if a.ci95[0] > b.ci95[1] or b.ci95[0] > a.ci95[1]:
                bad.append(t)
        elif a.resolved != b.resolved:
            s, u = (a, b) if a.resolved else (b, a)
            if s.ci95[0] > u.upper95:
                bad.append(t)
    return bad


@pytest.fixture(scope="module")
def results(astro) -> dict:
    _, rec = astro
    # every tau ("all") is ~10x the work of the octaves: x only (the axis of the issue)
    return {(taus, mode): AA.compute(str(rec), ["gx", "ax", "ay", "az"] if taus == "octave"
                                     else ["ax"], taus, temperature=mode)
            for taus in ("octave", "all") for mode in ("report", "remove")}


@pytest.mark.parametrize("axis,col", [("ax", "accel_x"), ("ay", "accel_y"), ("az", "accel_z")])
def test_temperature_named_and_coefficient_matches_numpy(astro, results, axis, col) -> None:
    rows, _ = astro
    t = results[("octave", "report")]["axes"][axis]["temperature"]
    assert t["found"] and t["p_value"] < 1e-10, t
    assert t["coef_unit"] == "mg/K"
    lo, hi = t["coef_ci95_field"]
    c_np, lo_np, hi_np = _numpy_coefficient(rows, col)
    # each estimate inside the other's 95 % interval (measured on ax: pipeline 0.521 [0.479,
    # 0.563] mg/K over 128 blocks of 1610 s; numpy 0.530 [0.491, 0.570] over 116 30-min windows)
    assert lo <= c_np <= hi, (axis, t["coef_field"], lo, hi, c_np)
    assert lo_np <= t["coef_field"] <= hi_np, (axis, t["coef_field"], c_np, lo_np, hi_np)
    text = "\n".join(AA.screening_notes(results[("octave", "report")]["axes"][axis])[0])
    assert "follows the recorded temperature" in text and "--temperature remove" in text


def test_gyro_not_put_down_to_temperature(results) -> None:
    # RTIMULib tracks the gyro bias (100 s): nothing of the temperature is left on gx
    t = results[("octave", "report")]["axes"]["gx"]["temperature"]
    assert not t["found"] and t["p_value"] > 1e-3, t
    assert not any(o.get("cause") == "temperature"
                   for o in results[("octave", "report")]["axes"]["gx"]["fit"]["check"]["outside"])


def test_remove_takes_the_term_out_and_octave_and_all_then_agree(results) -> None:
    for taus in ("octave", "all"):
        r = results[(taus, "remove")]
        assert r["temperature"] == "remove"
        for a in r["axes"]:
            if a == "gx":
                assert "temperature_removed" not in r["axes"]["gx"]
                continue
            rm = r["axes"][a]["temperature_removed"]
            assert rm["before"]["found"]
            # the second pass finds no temperature dependence left
            after = r["axes"][a]["temperature"]
            assert not after["found"] and abs(after["coef"]) < 0.1 * abs(rm["before"]["coef"]), after
    # ax: octave and all agree with the temperature in and without it. (With the covariance of
    # one continuous record they were apart with it in -- all: B < 0.031 mg, K 8.0 [7.4, 8.7]
    # m/s/h/sqrt(h), chi-square 7561 for 36 dof -- and that was put down to the drift; with the
    # covariance of the gap-free stretches (issue 15, test_allan_gapcov.py) the all-tau fit with
    # the temperature in is within its statistics: N 0.144, B 0.044 mg, 25.2 / 37)
    assert not _apart(results[("octave", "report")]["axes"]["ax"],
                      results[("all", "report")]["axes"]["ax"])
    assert not _apart(results[("octave", "remove")]["axes"]["ax"],
                      results[("all", "remove")]["axes"]["ax"])
    ck = results[("all", "report")]["axes"]["ax"]["fit"]["check"]
    assert ck["ok"] and stats.chi2.sf(ck["chi2"], ck["dof"]) >= 0.01, ck
    # (with it removed, the all-tau fit drops K at z = 1.94 -- unselected 2.61 [1.75, 5.14]
    # m/s/h/sqrt(h), octave 2.79 [1.91, 5.11] -- and its check names 520-720 s, data 1.19x
    # above the total: docs/allan.md, not asserted either way)


def test_no_temperature_channel_no_check(tmp_path: Path) -> None:
    """A recording without /imu/temperature: said so, nothing named."""
    import importlib.util

    root = Path(__file__).resolve().parent.parent
    spec = importlib.util.spec_from_file_location("allan_profiles", root / "benchmarks" / "allan_profiles.py")
    b = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(b)
    rec = tmp_path / "d.h5"
    b.emulated_recording("default", rec, 0.25, seed=3)
    r = AA.compute(str(rec), ["gx"], "octave", temperature="remove")
    assert r["axes"]["gx"]["temperature"] == {"found": False, "skipped": "no usable /imu/temperature"}
    assert "temperature_removed" not in r["axes"]["gx"]
