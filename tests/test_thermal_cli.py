"""``rigctl thermal`` end to end on a real record: the CATS tag held still in three poses for
74.5 h, 4.8 .. 27.8 degC (tests/data/cats-tag-thermal, AGPL-3.0), imported as a user would
(tests/cats_support.py), and the command's one-line errors.

Two runs of the command, side by side (each ~20 s of CPU, nearly all the noise estimate):

* the import *without* its pose column, the poses given by ``--poses FILE`` (time ranges written
  here from the CSV's pose column), ``--settle-s 3600 --no-loop --json --csv``: every number
  against numpy on the CSV itself -- the windows, the temperature range, each pose's gravity
  direction, and the bias and scale per K and per K^2 from the *differences* of consecutive
  window means within a pose (which removes the pose offsets and a bias that wanders like a
  random walk; independent of the solver's covariance model), converted to mg/K, ppm/K and
  deg/h/K with the constants written here; the printed table against the JSON; the chi-square
  bands against scipy's chi-square quantiles.
* the import *with* its pose column (the recording's segments), no settle, 60-min windows (4 s
  of CPU against 48 s with 30-min windows): the accelerometer's chi-square falls below its band
  (docs/thermal.md: the first hour of each pose, a fast temperature fall counted as noise) and
  the command must say so as a finding, never "ok".
"""
from __future__ import annotations

import json
import math
import re
import subprocess
import csv as csvmod
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy import stats

import cats_support as cats
from helpers import rigctl_cmd, run_rigctl

G0 = 9.80665
FIELD = {"mg/K": 1e3 / G0, "mg/K^2": 1e3 / G0, "ppm/K": 1e6, "ppm/K^2": 1e6,
         "deg/h/K": 180.0 / math.pi * 3600.0, "deg/h/K^2": 180.0 / math.pi * 3600.0}
SETTLE_ROWS = 60  # --settle-s 3600 on 60-s rows


def _pose_file(rows: list[dict[str, str]], path: Path) -> Path:
    """The three poses' time ranges from the CSV's pose column: first row's start .. last row's
    end (60-s rows)."""
    t = np.array([float(r["t_s"]) for r in rows])
    pose = np.array([r["pose"] for r in rows])
    items = []
    for p in cats.POSES:
        i = np.flatnonzero(pose == p)
        items.append(f"- {{label: {p}, from_s: {t[i[0]]:g}, to_s: {t[i[-1]] + 60.0:g}}}")
    path.write_text("# the poses of the CATS tag record, s on its time axis\n" + "\n".join(items) + "\n")
    return path


@pytest.fixture(scope="module")
def runs(ref_data, tmp_path_factory):
    """(rows, the --poses run's stdout/stderr/JSON/CSV, the segments run's stdout/stderr/JSON, the
    unsectioned recording, the pose file), both runs started together."""
    rows = cats.rows(ref_data)
    d = tmp_path_factory.mktemp("thermal_cli")
    plain = cats.import_record(ref_data, d / "plain.h5", sections=False)
    marked = cats.import_record(ref_data, d / "marked.h5", sections=True)
    poses = _pose_file(rows, d / "poses.yaml")
    argv = {"poses": ["thermal", str(plain), "--poses", str(poses), "--settle-s", "3600", "--no-loop",
                      "--json", str(d / "a.json"), "--csv", str(d / "a.csv")],
            "segments": ["thermal", str(marked), "--no-loop", "--window-s", "3600", "--json", str(d / "b.json")]}
    procs = {k: subprocess.Popen([*rigctl_cmd(), *v], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k, v in argv.items()}
    out = {}
    for k, p in procs.items():
        so, se = p.communicate(timeout=600)
        assert p.returncode == 0, se
        out[k] = {"stdout": so, "stderr": se}
    out["poses"]["json"] = json.loads((d / "a.json").read_text())
    out["poses"]["csv"] = list(csvmod.DictReader((d / "a.csv").read_text().splitlines()))
    out["segments"]["json"] = json.loads((d / "b.json").read_text())
    return rows, out, plain, poses


def test_each_stage_of_the_fit_is_said_on_stderr(runs):
    """The fit of the 74.5 h record takes minutes (~1.5 min at load 5 on 2 cores): each stage
    is said as it starts, with the time since the command began; the command ran silent."""
    _, out, plain, _ = runs
    lines = out["poses"]["stderr"].strip().splitlines()
    stages = [re.match(rf"^thermal {plain.name}, [^:]+: (accel|gyro): (noise|generalised)", ln) for ln in lines]
    assert [(m.group(1), m.group(2)) for m in stages if m] == [
        ("accel", "noise"), ("accel", "generalised"), ("gyro", "noise"), ("gyro", "generalised")], lines
    assert "closed loop" not in out["poses"]["stderr"]  # --no-loop


def _differenced(ref: dict[str, np.ndarray], y: np.ndarray, u: np.ndarray | None):
    """numpy's least squares of the differences of consecutive window means within a pose on the
    differences of <dT>, <dT^2> (and u times them: the scale terms, u the pose's reference
    along the axis): (coefficients, standard uncertainties s^2 (A^T A)^-1)."""
    same = np.diff(ref["k"]) == 0
    cols = [np.diff(ref["p1"])[same], np.diff(ref["p2"])[same]]
    if u is not None:
        cols += [u[1:][same] * cols[0], u[1:][same] * cols[1]]
    A = np.column_stack(cols)
    d = np.diff(y)[same]
    b = np.linalg.lstsq(A, d, rcond=None)[0]
    r = d - A @ b
    return b, np.sqrt(np.diag((r @ r) / (d.size - A.shape[1]) * np.linalg.inv(A.T @ A)))


def test_windows_temperature_and_poses_match_numpy(runs):
    """141 windows (49, 48, 44 per pose after the first hour of each); the temperature range the
    command reports is numpy's over the window means (measured 4.89 .. 24.25 degC, 19.36 K); each
    pose's gravity reference points along numpy's mean specific force of the pose."""
    rows, out, _, _ = runs
    ref = cats.numpy_windows(rows, skip_rows=SETTLE_ROWS)
    r = out["poses"]["json"]
    assert r["settings"]["settle_s"] == 3600.0 and r["settings"]["poses_from"].endswith("poses.yaml")
    assert all(d["windows"] == len(ref["T"]) == 141 for d in r["sensors"].values())
    assert [p["label"] for p in r["poses"]] == cats.POSES
    assert [p["windows"] for p in r["poses"]] == [int(np.sum(ref["pose"] == p)) for p in cats.POSES] == [49, 48, 44]
    assert r["temperature_c"]["min"] == pytest.approx(ref["T"].min(), abs=1e-9)
    assert r["temperature_c"]["max"] == pytest.approx(ref["T"].max(), abs=1e-9)
    assert r["temperature_c"]["span_K"] == pytest.approx(np.ptp(ref["T"]), abs=1e-9)
    for p in r["poses"]:
        m = ref["pose"] == p["label"]
        assert p["temperature_c"] == pytest.approx([ref["T"][m].min(), ref["T"][m].max()], abs=1e-9)
        down = ref["down"][p["label"]]
        assert np.allclose(p["direction"], down / np.linalg.norm(down), atol=1e-9)
        assert np.linalg.norm(p["gravity_reference_m_s2"]) == pytest.approx(G0, rel=1e-12)
    text = out["poses"]["stdout"]
    assert f"{ref['T'].min():.2f} .. {ref['T'].max():.2f} degC, span {np.ptp(ref['T']):.2f} K" in text
    assert "the first 3600 s of every pose left out" in text


def test_bias_and_scale_per_K_agree_with_numpy_in_field_units(runs):
    """Accelerometer bias (mg/K, mg/K^2) and scale (ppm/K, ppm/K^2), gyro bias (deg/h/K,
    deg/h/K^2) per axis: the command's value within 1.96 numpy sigma of numpy's differenced
    fit and numpy's value inside the command's 95 % interval. Measured, accelerometer bias mg/K
    and scale ppm/K: x 0.915 +- 0.090, -869 +- 242; y -2.62 +- 0.16, -328 +- 181;
    z 2.95 +- 0.28, 2919 +- 1371 (numpy x 0.916, -848; y -2.61, -324; z 2.96, 2901); gyro bias
    deg/h/K: x -6.6 +- 21.5, y 117.3 +- 7.1, z 40.3 +- 14.5 (numpy -7.7 +- 20.2, 116.7 +- 8.5,
    40.4 +- 16.5)."""
    rows, out, _, _ = runs
    ref = cats.numpy_windows(rows, skip_rows=SETTLE_ROWS)
    r = out["poses"]["json"]
    for sensor, y_all, keys in (("accel", ref["acc"], ("bias_per_K", "bias_per_K2", "scale_per_K", "scale_per_K2")),
                                ("gyro", ref["gyr"], ("bias_per_K", "bias_per_K2"))):
        for i, ax in enumerate(r["sensors"][sensor]["axes"]):
            assert set(ax["coefficients"]) == set(keys)
            u = None
            if sensor == "accel":  # the pose's reference along the axis: g along its mean specific force
                u = np.array([G0 * ref["down"][p][i] / np.linalg.norm(ref["down"][p]) for p in ref["pose"]])
            b, s = _differenced(ref, y_all[:, i], u)
            for j, key in enumerate(keys):
                q = ax["coefficients"][key]
                unit = {"accel": {"bias": "mg/K", "scale": "ppm/K"}, "gyro": {"bias": "deg/h/K"}}[sensor][key.split("_")[0]]
                unit += "^2" if key.endswith("K2") else ""
                assert q["unit"] == unit
                f = FIELD[unit]
                assert q["ci95"][0] <= b[j] * f <= q["ci95"][1], (sensor, ax["axis"], key, q, b[j] * f)
                assert abs(q["value"] - b[j] * f) <= 1.96 * s[j] * f, (sensor, ax["axis"], key, q, b[j] * f, s[j] * f)
            assert ax["axis"] == ("ax", "ay", "az", "gx", "gy", "gz")[3 * (sensor == "gyro") + i]  # one spelling
            if sensor == "accel" or ax["axis"] == "gy":  # a real bias slope: accelerometer 10 - 17 sigma, gyro y
                assert abs(b[0]) > 7 * s[0]
    # the SI values behind the field units, with the constants written here
    for d in r["sensors"].values():
        for q in d["parameters"]:
            if q["unit"] in FIELD:
                assert q["value"] == pytest.approx(q["si"]["value"] * FIELD[q["unit"]], rel=1e-12)
                assert q["sigma"] == pytest.approx(q["si"]["sigma"] * FIELD[q["unit"]], rel=1e-12)


def _pairs(line: str) -> list[tuple[str, str]]:
    return re.findall(r"(-?\d+(?:\.\d+)?) \+- (\d+(?:\.\d+)?)", line)


def test_printed_table_is_the_json_rounded(runs):
    """Each axis row of the printed table: the JSON's values and sigmas rounded to two
    significant digits of the sigma; the CSV holds every coefficient of the JSON."""
    _, out, _, _ = runs
    r, text = out["poses"]["json"], out["poses"]["stdout"]
    for name, d in r["sensors"].items():
        block = text[text.index(f"\n{name}: "):]
        keys = sorted(d["axes"][0]["coefficients"], key=lambda k: (k[:4] != "bias", k))
        for ax in d["axes"]:
            line = next(ln for ln in block.splitlines() if ln.startswith(f"  {ax['axis']}   "))
            got = _pairs(line)
            assert len(got) == len(keys)
            for (v, u), k in zip(got, keys):
                q = ax["coefficients"][k]
                tol = 0.5 * 10.0 ** (math.floor(math.log10(float(u))) - 1) * 1.001
                assert abs(float(u) - q["sigma"]) <= tol and abs(float(v) - q["value"]) <= tol, (line, k, q)
    rows = out["poses"]["csv"]
    params = [(s, q) for s, d in r["sensors"].items() for q in d["parameters"]]
    assert len(rows) == len(params)
    for row, (s, q) in zip(rows, params):
        assert row["sensor"] == s and row["parameter"] == q["name"] and row["unit"] == q["unit"]
        assert float(row["value"]) == q["value"] and float(row["si_sigma"]) == q["si"]["sigma"]


def test_chi_square_bands_and_findings(runs):
    """Bands from scipy's chi-square quantiles (99 %, two-sided) for the dof the JSON states;
    the status is "ok" exactly inside. Settled (the --poses run): both sensors inside (measured
    accelerometer 1.044 in 0.828 .. 1.191). Not settled (the segments run, 60-min windows): the
    accelerometer below its band (measured 0.321 against 0.762 .. 1.276; gyro 0.881, inside),
    printed as a finding, never "ok"."""
    _, out, _, _ = runs
    for k in ("poses", "segments"):
        r = out[k]["json"]
        for name, d in r["sensors"].items():
            for x in (d, *d["axes"]):
                lo, hi = stats.chi2.ppf([0.005, 0.995], x["dof"]) / x["dof"]
                assert x["chi2_band_99"] == pytest.approx([lo, hi], rel=1e-9)
                assert x["chi2_per_dof"] == pytest.approx(x["chi2"] / x["dof"], rel=1e-12)
                inside = lo <= x["chi2_per_dof"] <= hi
                assert (x["status"] == "ok") == inside
                assert x["status"] == ("ok" if inside else "chi2_below_band" if x["chi2_per_dof"] < lo
                                       else "chi2_above_band")
    settled = out["poses"]["json"]["sensors"]
    assert settled["accel"]["status"] == "ok" and settled["gyro"]["status"] == "ok"
    assert settled["accel"]["chi2_per_dof"] == pytest.approx(1.044, abs=0.01)
    raw = out["segments"]["json"]
    acc = raw["sensors"]["accel"]
    assert acc["status"] == "chi2_below_band" and acc["chi2_per_dof"] < 0.5
    assert raw["settings"]["window_s"] == 3600.0
    line = next(ln for ln in out["segments"]["stdout"].splitlines() if ln.startswith("accel: "))
    assert "BELOW the band -- a finding" in line and "inside the band" not in line and not re.search(r"\bok\b", line)
    assert any(f.startswith("accel chi2/dof") for f in raw["findings"])
    assert out["segments"]["stdout"].rstrip().splitlines()[-2].startswith("findings: accel chi2/dof")
    assert raw["settings"]["poses_from"] == "the recording's segments" and raw["settings"]["settle_s"] == 0.0


# ------------------------------------------------------------------------------ bad input
def _one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> str:
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rigctl thermal: error: "), proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""
    for n in needles:
        assert n in lines[0], lines[0]
    return lines[0]


def test_a_recording_without_temperature_is_one_line(runs, tmp_path):
    rows, _, _, _ = runs
    src = tmp_path / "notemp.csv"
    cols = ["t_s", "acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z", "pose"]
    src.write_text(",".join(cols) + "\n" + "\n".join(",".join(r[c] for c in cols) for r in rows[:400]) + "\n")
    rec = tmp_path / "notemp.h5"
    imp = run_rigctl("import", str(src), "-o", str(rec), "--columns",
                     "time=t_s,acc_x=acc_x,acc_y=acc_y,acc_z=acc_z,gyr_x=gyr_x,gyr_y=gyr_y,gyr_z=gyr_z,section=pose",
                     "--units", cats.UNITS)
    assert imp.returncode == 0, imp.stderr
    _one_line_error(run_rigctl("thermal", str(rec)), str(rec), "temperature column (/imu/temperature holds no reading)",
                    "temp=COLUMN")


def test_one_pose_is_one_line(runs):
    """The import without its pose column and no --poses: one stretch, one pose."""
    _, _, plain, _ = runs
    _one_line_error(run_rigctl("thermal", str(plain)), "one pose", "scale per K cannot be told from bias per K",
                    "--poses FILE", "--one-pose")


def test_too_small_a_temperature_span_is_one_line(runs, tmp_path):
    """Two poses, 8 h each in the cold (rows 120 .. 600 of the z and x poses): numpy's span of
    the window means is under 5 K (measured 4.9 .. 7.5 degC)."""
    rows, _, plain, _ = runs
    t = np.array([float(r["t_s"]) for r in rows])
    pose = np.array([r["pose"] for r in rows])
    T = np.array([float(r["temp_c"]) for r in rows])
    items, means = [], []
    for p in cats.POSES[:2]:
        i = np.flatnonzero(pose == p)[120:600]
        items.append(f"- {{label: {p}, from_s: {t[i[0]]:g}, to_s: {t[i[-1]] + 60.0:g}}}")
        means += [T[i[s:s + 30]].mean() for s in range(0, i.size, 30)]
    assert np.ptp(means) < 5.0
    f = tmp_path / "cold.yaml"
    f.write_text("\n".join(items) + "\n")
    line = _one_line_error(run_rigctl("thermal", str(plain), "--poses", str(f)), "the IMU temperature spans",
                           "a thermal fit needs at least 5 K")
    assert f"spans {np.ptp(means):.2f} K over the {len(means)} windows" in line


def test_bad_pose_files_and_options_are_one_line(runs, tmp_path):
    _, _, plain, _ = runs
    f = tmp_path / "overlap.yaml"
    f.write_text("- {label: a, from_s: 0, to_s: 100}\n- {label: b, from_s: 50, to_s: 200}\n")
    _one_line_error(run_rigctl("thermal", str(plain), "--poses", str(f)), f"{f}:2:", "overlap")
    f.write_text("- {label: a, from: 0, to_s: 100}\n")
    _one_line_error(run_rigctl("thermal", str(plain), "--poses", str(f)), f"{f}:1:", "label, from_s and to_s")
    _one_line_error(run_rigctl("thermal", str(plain), "--bias-degree", "0"), "--bias-degree 0")
    _one_line_error(run_rigctl("thermal", str(plain), "--settle-s", "-5"), "--settle-s -5")


def test_a_chamber_run_is_one_line_pointing_to_calibrate(runs, tmp_path):
    """The segments import with chamber readings written into its /chamber (as a chamber run
    records them): refused, naming rigctl calibrate and --static."""
    _, _, plain, _ = runs
    rec = tmp_path / "chamber.h5"
    rec.write_bytes(plain.with_name("marked.h5").read_bytes())
    with h5py.File(rec, "a") as f:
        g = f["chamber"]
        for k in g:
            g[k].resize((3,))
            g[k][:] = [b"ok"] * 3 if g[k].dtype.kind == "S" else [0.0, 1e5, 2.7e5] if k == "time" else [20.0, 10, 20]
    _one_line_error(run_rigctl("thermal", str(rec)), str(rec), "a chamber run", "rigctl calibrate", "--static")


def test_help_names_the_options():
    r = run_rigctl("thermal", "--help")
    assert r.returncode == 0
    for w in ("--poses", "--settle-s", "--json", "--csv", "--one-pose", "--static", "from_s", "chi-square"):
        assert w in r.stdout, w


def test_one_pose_accepted_with_one_pose_is_the_apparent_bias(runs, tmp_path):
    """--one-pose on the z pose alone (--poses with one entry, 51 windows of 30 min): bias per K
    and per K^2 only (no scale: it cannot be told from the bias), each axis within 1.96 sigma of
    numpy's differenced window means of that pose, said to be the apparent bias. Measured,
    accelerometer mg/K: x 1.03 +- 0.31, y -2.50 +- 0.31, z 2.05 +- 0.63, chi2/dof 0.934 inside
    0.723 .. 1.330; gyro chi2/dof 1.862 ABOVE that band (its bias wanders beyond the noise model
    in this pose, docs/thermal.md), printed as a finding."""
    rows, _, plain, _ = runs
    ref = cats.numpy_windows(rows)
    m = ref["pose"] == cats.POSES[0]
    sub = {k: ref[k][m] for k in ("k", "p1", "p2", "acc", "gyr")}
    t = np.array([float(r["t_s"]) for r in rows])
    i = np.flatnonzero(np.array([r["pose"] for r in rows]) == cats.POSES[0])
    f = tmp_path / "one.yaml"
    f.write_text(f"- {{label: {cats.POSES[0]}, from_s: {t[i[0]]:g}, to_s: {t[i[-1]] + 60.0:g}}}\n")
    j = tmp_path / "one.json"
    r = run_rigctl("thermal", str(plain), "--poses", str(f), "--one-pose", "--no-loop", "--json", str(j), timeout=300)
    assert r.returncode == 0, r.stderr
    assert "the bias per K is the apparent one" in r.stdout
    res = json.loads(j.read_text())
    assert res["settings"]["one_pose"] and [p["windows"] for p in res["poses"]] == [int(m.sum())] == [51]
    g = res["sensors"]["gyro"]
    assert g["status"] == "chi2_above_band" and g["chi2_per_dof"] > g["chi2_band_99"][1]
    line = next(ln for ln in r.stdout.splitlines() if ln.startswith("gyro: "))
    assert "ABOVE the band -- a finding" in line and not re.search(r"\bok\b", line)
    for sensor, y_all, unit in (("accel", sub["acc"], "mg/K"), ("gyro", sub["gyr"], "deg/h/K")):
        for i_ax, ax in enumerate(res["sensors"][sensor]["axes"]):
            assert set(ax["coefficients"]) == {"bias_per_K", "bias_per_K2"}
            b, s = _differenced(sub, y_all[:, i_ax], None)
            q = ax["coefficients"]["bias_per_K"]
            assert q["unit"] == unit
            assert abs(q["value"] - b[0] * FIELD[unit]) <= 1.96 * s[0] * FIELD[unit], (sensor, ax["axis"], q, b[0])
