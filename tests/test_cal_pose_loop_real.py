"""The closed loop on real table-less sessions from other labs, each checked against an
independent analysis written here in plain numpy (not the solver's functions).

* imu_tk's Xsens MTi session (tests/data/imutk-xsens, 38 hand-placed poses): the gyro's static
  means depend on the direction of gravity (g-sensitivity). A plain least-squares regression of
  each gyro axis' pose means on the pose's specific force finds the same matrix and the same
  significance; the scale factors agree with the MTi's raw-data scales (~415 counts per m/s^2,
  ~4770 counts per rad/s); the poses themselves drift (half-split test), so the accelerometer
  fit stays above its band and the status is UNEXPLAINED RESIDUAL, never OK.
* The MPU-6050 session (tests/data/mpu6050-multipos, 10 poses): the gyro hit its +-250 deg/s
  range during some motions; counted here from the samples.
* imucal's six-face session (tests/data/imucal-ferraris): no g-sensitivity is significant in the
  six faces (an F test in numpy agrees).
"""
from __future__ import annotations

import gzip
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.stats

from helpers import rigctl_in_process

G_XSENS = 9.81744


# imports and calibrations through rigctl.cli.main in this process (helpers.rigctl_in_process: the
# same commands and arguments without a new interpreter's imports); these tests are about the
# numbers, not the process
def _calibrate(rec: Path) -> tuple[str, dict]:
    proc = rigctl_in_process("calibrate", str(rec), "--explain", "--json", str(rec.with_suffix(".json")))
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    return proc.stdout, json.loads(rec.with_suffix(".json").read_text())


def _poses(rec: Path) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    with h5py.File(rec, "r") as f:
        acc, gyr = f["imu/specific_force"][()], f["imu/angular_rate"][()]
        s = f["segments"]
        iv = [(int(a), int(b)) for a, b, k in zip(s["first_sample"][()], s["last_sample"][()], s["kind"][()])
              if k == b"orientation"]
    return acc, gyr, iv


@pytest.fixture(scope="module")
def xsens(ref_data, tmp_path_factory):
    d = ref_data / "imutk-xsens"
    a = np.loadtxt(gzip.open(d / "xsens_acc.mat.gz"))
    g = np.loadtxt(gzip.open(d / "xsens_gyro.mat.gz"))
    assert np.array_equal(a[:, 0], g[:, 0])
    tmp = tmp_path_factory.mktemp("xsens")
    csv = tmp / "xsens.csv"
    np.savetxt(csv, np.column_stack([a[:, 0], a[:, 1:] - 32768, g[:, 1:] - 32768]), delimiter=",",
               header="t,ax,ay,az,gx,gy,gz", comments="", fmt="%.6f")
    rec = tmp / "xsens.h5"
    proc = rigctl_in_process("import", str(csv), "-o", str(rec), "--rate", "100", "--columns",
                      "time=t,acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz",
                      "--units", "acc=counts:1/415 m/s^2,gyr=counts:1/4770 rad/s,time=s",
                      "--t-init", "50", "--gravity", str(G_XSENS))
    assert proc.returncode == 0, proc.stderr
    out, cal = _calibrate(rec)
    return rec, out, cal


def test_xsens_g_sensitivity_named_and_matches_numpy(xsens):
    rec, out, cal = xsens
    gl = cal["closed_loop"]["gyro_static"]
    assert "gyro_g_sensitivity" in gl["effects_claimed"]
    assert "gyro_static | 1 | gyro_g_sensitivity" in out and "| added" in out
    # --- independent analysis: pose means, an ellipsoid-free specific force (nominal scale; a 1 %
    # scale error changes G by 1 %), and per gyro axis w = b + G_i . f by plain least squares
    acc, gyr, iv = _poses(rec)
    fa = np.array([acc[s:e].mean(axis=0) for s, e in iv])
    wg = np.array([gyr[s:e].mean(axis=0) for s, e in iv])
    f = G_XSENS * fa / np.linalg.norm(fa, axis=1)[:, None]
    X = np.column_stack([np.ones(len(f)), f])
    P = len(f)
    ours = {q["name"]: q for q in gl["final"]["parameters"]}
    n_sig = 0
    for i, ax in enumerate("xyz"):
        beta, rss1, *_ = np.linalg.lstsq(X, wg[:, i], rcond=None)
        rss0 = np.sum((wg[:, i] - wg[:, i].mean()) ** 2)
        F = ((rss0 - rss1[0]) / 3) / (rss1[0] / (P - 4))
        n_sig += scipy.stats.f.sf(F, 3, P - 4) < 1e-4
        cov = np.linalg.inv(X.T @ X) * rss1[0] / (P - 4)
        for j, bx in enumerate("xyz"):
            q = ours[f"gyro_g_sens_{ax}{bx}_rad_s_per_m_s2"]
            # Earth rate's vertical part is collinear with G's diagonal: rigctl fits it with a prior,
            # numpy does not; compare off-diagonal terms tightly and the diagonal within Omega/g
            tol = 3 * np.hypot(q["sigma"], np.sqrt(cov[j + 1, j + 1])) + (7.3e-5 / 9.8 if i == j else 0)
            assert abs(q["value"] - beta[j + 1]) < tol, (ax, bx, q, beta[j + 1])
    assert n_sig >= 2  # numpy also finds the dependence on at least two gyro axes
    # before/after: the g-sensitivity takes the gyro at rest down to near its noise floor
    rows = {r["channel"]: r for r in cal["before_after"]}
    for ax in "xyz":
        r = rows[f"g{ax} at rest"]  # the one spelling of the axes (rigctl.sensor_axes)
        assert r["final"] < r["declared"] and r["final"] < 1.6 * r["noise_floor"], r


def test_xsens_scales_match_the_mti_and_status_is_not_ok(xsens):
    rec, out, cal = xsens
    M = np.array(cal["model"]["accel"]["M"])
    Mg = np.array(cal["model"]["gyro"]["M"])
    # counts per unit = nominal * M_ii (u = counts / nominal = b + M a)
    assert np.all(np.abs(415 * np.diag(M) / np.array([415, 413, 415]) - 1) < 0.01), np.diag(M) * 415
    assert np.all(np.abs(4770 * np.diag(Mg) / np.array([4778, 4758, 4766]) - 1) < 0.01), np.diag(Mg) * 4770
    # the poses drift within themselves: half-split test in numpy, per accelerometer axis
    acc, _, iv = _poses(rec)
    z = []
    for s, e in iv:
        m = (s + e) // 2
        v = acc[s:e].var(axis=0)
        z.append((acc[s:m].mean(axis=0) - acc[m:e].mean(axis=0)) / np.sqrt(v / (m - s) + v / (e - m)))
    chi = np.sum(np.array(z) ** 2, axis=0)
    assert np.any(scipy.stats.chi2.sf(chi, len(iv)) < 1e-6)
    assert cal["closed_loop"]["accel"]["status"] == "UNEXPLAINED RESIDUAL"
    assert "drift within the poses" in out
    assert cal["status"] == "UNEXPLAINED RESIDUAL" and "STATUS: UNEXPLAINED RESIDUAL" in out
    assert "STATUS: OK" not in out
    # three columns and the floor for every channel, accelerometer raw error far above calibrated
    rows = {r["channel"]: r for r in cal["before_after"]}
    for ax in "xyz":
        r = rows[f"a{ax}"]
        assert r["raw"] > 100 * r["final"] and r["unit"] == "mg"
    assert "before/after" in out and "noise floor" in out


def test_mpu6050_gyro_range_exceeded(ref_data, tmp_path):
    d = ref_data / "mpu6050-multipos"
    rec = tmp_path / "mpu.h5"
    proc = rigctl_in_process("import", str(d / "calibration_data_example_data_calibration.csv"), "-o", str(rec),
                      "--columns", "acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz", "--skip-rows", "4",
                      "--units", "acc=counts:1/16384 g,gyr=counts:1/131 deg/s", "--rate", "100", "--t-init", "36.5")
    assert proc.returncode == 0, proc.stderr
    out, cal = _calibrate(rec)
    # independent count: raw counts at the int16 rails (+32767 / -32768) in the CSV
    raw = np.loadtxt(d / "calibration_data_example_data_calibration.csv", delimiter=",", skiprows=5)[:, 3:6]
    rails = int(np.sum((raw >= 32767) | (raw <= -32768)))
    assert rails > 0
    rl = cal["closed_loop"]["gyro_rotation"]
    assert "gyro_range_exceeded" in rl["effects_claimed"]
    assert f"gyro_range_exceeded: {rails} samples" in out
    assert cal["trustworthy"] is False and "STATUS: NOT TRUSTWORTHY" in out


def test_imucal_faces_no_g_sensitivity(ref_data, tmp_path):
    d = ref_data / "imucal-ferraris"
    rec = tmp_path / "imucal.h5"
    proc = rigctl_in_process("import", str(d / "example_data_annotated_session.csv"), "-o", str(rec), "--columns",
                      "acc_x=acc_x,acc_y=acc_y,acc_z=acc_z,gyr_x=gyr_x,gyr_y=gyr_y,gyr_z=gyr_z,section=part",
                      "--units", "acc=counts:1/2048 g,gyr=counts:1/16.4 deg/s", "--rate", "204.8",
                      "--gravity", "9.81")
    assert proc.returncode == 0, proc.stderr
    out, cal = _calibrate(rec)
    assert "gyro_g_sensitivity" not in cal["closed_loop"]["gyro_static"]["effects_claimed"]
    # numpy: six faces, gyro means against +-g along each face's axis; F test of G (9) against the
    # bias (3), with the within-face white variance of each mean
    acc, gyr, iv = _poses(rec)
    ups = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    w = np.array([gyr[s:e].mean(axis=0) for s, e in iv])
    var = np.array([gyr[s:e].var(axis=0) / (e - s) for s, e in iv])
    chi0 = np.sum((w - np.average(w, axis=0, weights=1 / var)) ** 2 / var)
    chi1 = 0.0
    for i in range(3):
        X = np.column_stack([np.ones(6), 9.81 * ups]) / np.sqrt(var[:, i])[:, None]
        _, r, *_ = np.linalg.lstsq(X, w[:, i] / np.sqrt(var[:, i]), rcond=None)
        chi1 += r[0] if len(r) else 0.0
    # 18 means, 12 parameters: F(9, 6); numpy's verdict at the loop's threshold agrees
    F = ((chi0 - chi1) / 9) / max(chi1 / 6, 1e-12)
    assert scipy.stats.f.sf(F, 9, 6) > 0.01 / 3 / 2


def test_xsens_report_shows_the_loop_and_three_columns(xsens, tmp_path):
    pytest.importorskip("matplotlib")
    import sys
    sys.path.insert(0, str(Path(__file__).parent))
    from test_report_sections import Page
    from rigctl.report import report_build

    rec, out, cal = xsens
    page = Page(report_build.build_report(rec, tmp_path).read_text())
    assert "closed-loop" not in page.not_run
    rows = page.rows["closed-loop"]
    assert ["channel", "unit", "raw", "declared model", "final model", "noise floor"] in rows
    ba = {r[0]: r for r in rows if r and r[0].endswith(" at rest")}
    for ax in "xyz":
        want = next(r for r in cal["before_after"] if r["channel"] == f"g{ax} at rest")
        got = ba[f"g{ax} at rest"]
        assert got[1] == "deg/h" and abs(float(got[4]) - want["final"]) <= 0.01 * want["final"]
    subs: dict[str, list[str]] = {}
    for r in rows:  # the sub-model table comes first (the chain's rows start with the same names)
        if r and r[0] in ("accel", "gyro_static", "gyro_rotation"):
            subs.setdefault(r[0], r)
    assert subs["gyro_static"][1] == cal["closed_loop"]["gyro_static"]["status"]
    assert "gyro_g_sensitivity" in subs["gyro_static"][-1]
