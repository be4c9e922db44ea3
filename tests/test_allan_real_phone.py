"""A real 6-hour static capture of a phone's MEMS gyro through the user's path: `rigctl import`
of the CSV (tests/data/galaxy-s5-static: a Samsung Galaxy S5 lying still on a table, decimated
by its publisher from 100 Hz to 10 Hz with a zero-phase filter; AGPL-3.0, see its README),
then `rigctl allan` with its defaults and with `--taus octave`.

It is a hard case, and the reason it is here: the curve is not IEEE 952 anywhere short. Below
~2 s it lies under the white-noise line and rises (the decimation filter, and a raw output
that dwells for seconds on 0.061 deg/s steps); between ~3 and ~80 s it stands above any
IEEE 952 total (a bump); it reaches its minimum (12-23 deg/h) between 400 and 1300 s, at or
near the end of the taus whose 95 % band is informative.

Every expected value is computed here: the fully overlapping Allan deviation in plain numpy,
the EDF of each tau from NIST SP 1065's simple approximations (the smaller of white FM's and
flicker FM's, so the band is not made too narrow), the 95 % band from scipy's chi-square, the
floor read off the curve (its minimum over the taus whose band is informative, hi95/lo95 <= 2)
and the IEEE 952 total sigma^2 = 3Q^2/tau^2 + N^2/tau + (2 ln 2/pi) B^2 + K^2 tau/3 +
R^2 tau^2/2 written out here. No datasheet check: the publisher does not name the phone's
gyro part.

Three tests were findings of issue 15 on this capture (xfail, strict) and pass now: spikes
judged against the data's spread; the default and octave tau sets agreeing once the rising
front is left out of the fit; B no larger than the curve allows (B held to min sigma / 0.664
where the fit needs a model error).
"""
from __future__ import annotations

import gzip
import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from rigctl import cli

SET = "galaxy-s5-static"
FS = 10.0
TAU0 = 1.0 / FS
AXES = ("gx", "gy", "gz")
B_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)  # 0.664: flicker FM's Allan deviation / B
DEG_H = 180.0 / math.pi * 3600.0  # rad/s -> deg/h
DEG_RT_H = 180.0 / math.pi * 60.0  # rad/sqrt(s) -> deg/sqrt(h)
#: the column limit of each term: its sigma^2 part at tau is c^2 * A(tau) (written out here)
COLUMNS = {"Q": lambda t: 3.0 / t ** 2, "N": lambda t: 1.0 / t, "B": lambda t: np.full(t.shape, B_FACTOR ** 2),
           "K": lambda t: t / 3.0, "R": lambda t: t ** 2 / 2.0}


def oadev(y: np.ndarray, ms: np.ndarray) -> np.ndarray:
    """Fully overlapping Allan deviation of rate samples y (tau0 apart) at factors ms."""
    x = np.concatenate(([0.0], np.cumsum(y - y.mean()))) * TAU0
    return np.array([math.sqrt(np.mean((x[2 * m:] - 2 * x[m:-m] + x[:-2 * m]) ** 2) / (2 * (m * TAU0) ** 2))
                     for m in ms])


def edf_simple(n_phase: int, m: int) -> float:
    """NIST SP 1065 (5.2.x) simple EDF of the overlapping ADEV: the smaller of white FM's and
    flicker FM's (the noise of the -1/2 stretch and of a floor)."""
    n = float(n_phase)
    wfm = (3 * (n - 1) / (2 * m) - 2 * (n - 2) / n) * 4 * m * m / (4 * m * m + 5)
    ffm = 2 * (n - 2) ** 2 / (2.3 * n - 4.9) if m == 1 else 5 * n * n / (4 * m * (n + 3 * m))
    return min(wfm, ffm)


def read_curve(y: np.ndarray, ms: np.ndarray) -> dict:
    """The curve read here: deviations, 95 % band, informative taus, the floor (minimum over
    the informative taus), the local slope around it and how far the informative taus reach
    past it."""
    dev = oadev(y, ms)
    tau = ms * TAU0
    edf = np.array([edf_simple(len(y) + 1, int(m)) for m in ms])
    lo, hi = dev * np.sqrt(edf / chi2.ppf(0.975, edf)), dev * np.sqrt(edf / chi2.ppf(0.025, edf))
    ok = hi / lo <= 2.0
    i = int(np.argmin(np.where(ok, dev, np.inf)))
    near = ok & (tau >= tau[i] / 2.5) & (tau <= tau[i] * 2.5)
    return {"tau": tau, "dev": dev, "lo": lo, "hi": hi, "ok": ok, "i": i, "floor": float(dev[i]),
            "tau_floor": float(tau[i]), "reach": float(tau[ok].max() / tau[i]),
            "slope_floor": float(np.polyfit(np.log(tau[near]), np.log(dev[near]), 1)[0])}


def slope(c: dict, t0: float, t1: float) -> float:
    sel = (c["tau"] >= t0) & (c["tau"] <= t1)
    return float(np.polyfit(np.log(c["tau"][sel]), np.log(c["dev"][sel]), 1)[0])


def total(coef: dict, tau: np.ndarray) -> np.ndarray:
    """The fitted IEEE 952 total at tau: the estimated terms (those with an interval); a term
    known only as an upper bound is not part of the model the fit reports (no tone is reported
    on this capture, which the fixture checks)."""
    v = lambda t: float(coef[t]["value"]) if "ci95" in coef[t] else 0.0  # noqa: E731
    return np.sqrt(3 * v("Q") ** 2 / tau ** 2 + v("N") ** 2 / tau + B_FACTOR ** 2 * v("B") ** 2
                   + v("K") ** 2 * tau / 3 + v("R") ** 2 * tau ** 2 / 2)


@pytest.fixture(scope="module")
def phone(ref_data: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    d = ref_data / SET
    if not d.exists():
        pytest.skip(f"{d} not present (AGPL-3.0 data: a redistribution may leave it out, see its README)")
    tmp = tmp_path_factory.mktemp("phone")
    src = tmp / "gyro_measured_rad_s.csv"  # as stored, gunzipped: header gyr_x,gyr_y,gyr_z; rad/s
    src.write_bytes(gzip.decompress((d / "gyro_measured_rad_s.csv.gz").read_bytes()))
    rec = tmp / "phone.h5"
    assert cli.main(["import", str(src), "-o", str(rec), "--columns", "gyr_x=0,gyr_y=1,gyr_z=2",
                     "--units", "gyr=rad/s", "--rate", f"{FS:g}"]) == 0
    res = {}
    for name, extra in (("default", []), ("octave", ["--taus", "octave"])):
        out = tmp / f"{name}.json"
        assert cli.main(["allan", str(rec), "--db", "none", "--json", str(out), *extra]) == 0
        res[name] = json.loads(out.read_text())["axes"]
        for a in AXES:
            assert res[name][a]["tones"]["tones"] == []  # the total above needs no tone term
    y = np.loadtxt(src, delimiter=",", skiprows=1)
    assert y.shape == (214800, 3)  # 5.97 h at 10 Hz
    return {"y": y, "res": res}


def _cases(phone: dict):
    for run in ("default", "octave"):
        for i, a in enumerate(AXES):
            r = phone["res"][run][a]
            yield run, a, r, read_curve(phone["y"][:, i], np.asarray(r["m"]))


def test_pipeline_curve_is_plain_numpy(phone: dict) -> None:
    """The deviations the fit sees: exact where the pipeline sums every term, within their
    68 % half-width where fast mode strides."""
    for run, a, r, c in _cases(phone):
        dev = np.asarray(r["adev_rad/s"])
        exact = np.asarray(r["stride"]) == 1
        assert exact.sum() >= 10
        np.testing.assert_allclose(dev[exact], c["dev"][exact], rtol=1e-9)
        half = (np.asarray(r["hi68_deg/h"]) - np.asarray(r["lo68_deg/h"])) / 2 / np.asarray(r["adev_deg/h"])
        assert np.all(np.abs(dev / c["dev"] - 1) <= half), (run, a, np.max(np.abs(dev / c["dev"] - 1) / half))


def test_the_curve_is_the_hard_case_described(phone: dict) -> None:
    """What makes this capture hard, read here: the curve rises from 0.1 to 1 s (slope > 0:
    below the white-noise line, where white noise alone gives -1/2), and its minimum over the
    informative taus lies between 300 and 1500 s at 12-24 deg/h. Measured (default taus):
    slopes 0.18 / 0.17 / 0.18, floors 16.9 / 23.0 / 12.7 deg/h at 667 / 420 / 1191 s, the
    last at the edge of the informative taus (still falling there, slope -0.31)."""
    for run, a, r, c in _cases(phone):
        assert slope(c, 0.1, 1.0) > 0.1, (run, a)
        assert 300.0 <= c["tau_floor"] <= 1500.0 and 12.0 < c["floor"] * DEG_H < 24.0, (run, a, c["tau_floor"])


def test_no_bound_above_what_the_curve_allows(phone: dict) -> None:
    """Every term reported as a bound: at most the curve's own limit for it (the largest
    value whose sigma^2 part stays under the measured sigma^2 at every informative tau)."""
    n_bounds = 0
    for run, a, r, c in _cases(phone):
        tau, dev = c["tau"][c["ok"]], np.asarray(r["adev_rad/s"])[c["ok"]]
        for t, coef in r["fit"]["coefficients"].items():
            if t in COLUMNS and isinstance(coef, dict) and "upper95" in coef:
                lim = float(np.sqrt(np.min(dev ** 2 / COLUMNS[t](tau))))
                assert coef["upper95"] <= lim * (1 + 1e-9), (run, a, t, coef["upper95"], lim)
                n_bounds += 1
    assert n_bounds >= 12


def test_self_check_names_where_the_total_leaves_the_curve(phone: dict) -> None:
    """The fitted total is not the curve here, and the self-check says so: not ok, and every
    informative tau where the total (computed here from the reported terms) lies outside the
    reported 95 % band and more than 10 % off the curve is inside a run the check names (its
    main or its small-departure list). The band is the pipeline's (its EDF, reduced where fast
    mode strides): the numpy band of read_curve is up to 4 % narrower at 470-600 s, where the
    gx total (1.27-1.28 x the curve) sits between the two edges. With the default taus the
    first run starts at the shortest tau, on the side 'data below the fit' (the filtered front)."""
    for run, a, r, c in _cases(phone):
        check = r["fit"]["check"]
        assert not check["ok"], (run, a)
        tau = c["tau"]
        tot = total(r["fit"]["coefficients"], tau)
        lo, hi = (np.asarray(r[f"{k}95_deg/h"]) / DEG_H for k in ("lo", "hi"))
        off = c["ok"] & ((tot > hi) | (tot < lo)) & (np.abs(c["dev"] / tot - 1.0) > 0.10)
        assert off.sum() >= 5, (run, a)
        named = np.zeros(tau.size, dtype=bool)
        for o in check["outside"] + check.get("outside_small", []):
            named |= (tau >= o["tau_from_s"] - 1e-9) & (tau <= o["tau_to_s"] + 1e-9)
        assert np.all(named[off]), (run, a, tau[off & ~named])
        if run == "default":
            first = check["outside"][0]
            assert first["tau_from_s"] == pytest.approx(TAU0) and first["side"] == "data below the fit"


def test_b_is_no_larger_than_the_curve_allows(phone: dict) -> None:
    """As on the OCXO and the ADIS16405: 0.664 B never above the curve's minimum over the
    informative taus (a larger B puts the model above the data there). Was a finding (issue
    15): B came out above it on every axis, 0.664 B / floor = 1.25 / 1.31 / 1.50 (default
    taus) and 1.35 / 1.33 / 1.55 (octave), the whole 95 % interval above floor / 0.664 for gz
    (23.0-37.9 vs 19.1 deg/h, its curve still falling at its last informative tau); B is now
    held to that limit where the fit needs a model error (allan_fit._b_point_limit)."""
    for run, a, r, c in _cases(phone):
        b = r["fit"]["coefficients"]["B"]
        assert b["value"] * B_FACTOR <= c["floor"] * (1 + 1e-9), (run, a, b["value"] * B_FACTOR / c["floor"])


def test_default_and_octave_agree_within_their_intervals(phone: dict) -> None:
    """Issue 15: both tau sets give each term compatible answers: two estimates' 95 % intervals
    overlap; an estimate's interval reaches below the other run's bound. (Was a finding: the
    default run estimated N 2.18 [1.90, 2.57] / 2.37 [2.04, 2.83] deg/sqrt(h) on gx / gy while
    the octave run, fitting the rising front 0.1-1.6 s as well, bounded N by the filtered
    0.1 s point, < 0.258 / < 0.306. Both now leave the front out of the fit; measured: N 2.83
    [2.72, 2.95] / 3.11 [2.98, 3.25] / 3.57 [3.42, 3.74] default, 2.91 [2.73, 3.10] / 3.29
    [3.07, 3.54] / 3.68 [3.41, 3.99] octave.) The front is read here too: the curve rises
    from 0.1 s by more than sqrt(2) and falls by more than sqrt(2) after its top, and both
    runs name the front's taus below the fit."""
    for a in AXES:
        cd, co = (phone["res"][k][a]["fit"]["coefficients"] for k in ("default", "octave"))
        for t in ("N", "B"):
            x, z = cd[t], co[t]
            lo_x, hi_x = x["ci95"] if "ci95" in x else (0.0, x["upper95"])
            lo_z, hi_z = z["ci95"] if "ci95" in z else (0.0, z["upper95"])
            assert lo_x <= hi_z and lo_z <= hi_x, (a, t, (lo_x, hi_x), (lo_z, hi_z))
    for run, a, r, c in _cases(phone):
        dev = c["dev"][c["ok"]]
        top = int(np.argmax(dev[c["tau"][c["ok"]] < 100.0]))
        assert dev[top] > math.sqrt(2) * dev[:top + 1].min() and dev[top:].min() < dev[top] / math.sqrt(2)
        f = r["fit"]["check"]["front_excluded"]
        assert f is not None and f["tau_from_s"] == pytest.approx(TAU0), (run, a)
        # the front ends just before the curve's top, read here (within the tau spacing)
        t_top = float(c["tau"][c["ok"]][top])
        assert t_top / 1.5 <= f["top_tau_s"] <= t_top * 1.5, (run, a, f, t_top)


def test_spikes_are_judged_against_the_datas_spread(phone: dict) -> None:
    """An outlier stands out of the data's own spread: numpy counts the samples more than
    10 robust sd of the series (1.4826 MAD) from the running median of 25 neighbours; the
    pipeline may report a few more (its own scale), not thousands. (Was a finding: 5.4-5.6 %
    of the samples were reported, against the residual's MAD scale, 12-14 deg/h, which the
    output's dwell collapses; the pipeline now reads that collapse and judges against the
    samples' own spread, reported as its basis.)"""
    y = phone["y"]
    for i, a in enumerate(AXES):
        v = y[:, i]
        pad = np.concatenate((np.full(12, v[0]), v, np.full(12, v[-1])))
        med = np.median(np.lib.stride_tricks.sliding_window_view(pad, 25), axis=1)
        sd = 1.4826 * np.median(np.abs(v - np.median(v)))
        n_numpy = int(np.sum(np.abs(v - med) > 10 * sd))
        n_reported = phone["res"]["default"][a]["spikes"]["count"]
        assert n_reported <= max(10, 10 * n_numpy), (a, n_reported, n_numpy)
        # the collapse, read here: the residual's MAD scale is far below both the residual's
        # own 90 % point (/1.645) and the samples' spread; the pipeline then uses the spread
        r = v - med
        mad_r = 1.4826 * np.median(np.abs(r - np.median(r)))
        q90 = np.quantile(np.abs(r - np.median(r)), 0.9) / 1.6448536269514722
        assert q90 > 2 * mad_r and sd > 2 * mad_r, (a, mad_r, q90, sd)
        sp = phone["res"]["default"][a]["spikes"]
        assert sp["sd_from"] == "samples" and sp["sd_si"] == pytest.approx(sd, rel=1e-9), (a, sp)


def test_the_step_read_from_the_samples_is_the_files_digits(phone: dict, ref_data: Path) -> None:
    """The CSV's numbers are printed with 7 significant digits (-1.491515e-02): the samples lie
    on a grid of the last printed digit, 1e-8 rad/s for values of order 1e-2 -- the file's
    resolution, not the gyro's LSB (its 0.061 deg/s levels were smoothed by the publisher's
    filter). The step the pipeline reads must be said to be that (issue 15). Read here from
    the text: each number's last-digit value 10^(exponent - mantissa decimals)."""
    with gzip.open(ref_data / SET / "gyro_measured_rad_s.csv.gz", "rt") as fh:
        rows = [line.strip().split(",") for line in fh.readlines()[1:200_001]]
    from rigctl.analysis import allan as AA

    reported = 0
    for i, a in enumerate(AXES):
        digit = {int(v.split("e")[1]) - len(v.split("e")[0].split(".")[1]) for v in (r[i] for r in rows)}
        q = phone["res"]["default"][a]["quantization"]
        if q is None:  # mixed exponents: no single grid (gy)
            assert len(digit) > 1, (a, digit)
            continue
        reported += 1
        assert digit == {-8}, (a, digit)
        assert abs(q["step_si"] / 1e-8 - 1.0) < 1e-6, (a, q["step_si"])
        assert q["step_source"] == {"kind": "file_digits", "unit": "rad/s", "decimals": 8}, q
        _, notes = AA.screening_notes(phone["res"]["default"][a])
        assert any("1e-8 rad/s" in n and "not the sensor's LSB" in n for n in notes), notes
    assert reported >= 2
