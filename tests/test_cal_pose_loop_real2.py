"""The closed loop on a second lab's real table-less session: an MPU-9150 turned by hand through
23 static poses (tests/data/mikov-mpu9150, sensor #1 = imu0.log), with a second MPU-9150 on the
same body (#5 = imu4.log) read here in numpy only. What the loop finds, each checked against an
independent analysis written here in plain numpy (not rigctl's functions):

* accel: OK, no effect claimed; biases, scales and misalignments agree with the source's own
  published calibration of this sensor (Mikov et al., ICINS 2020) within rigctl's 3 sigma.
* gyro_static: UNEXPLAINED RESIDUAL (chi2/dof ~3), no library effect claimed (g-sensitivity
  rejected), the poses drift within themselves. numpy: no g-sensitivity (F test per axis), the
  half-split test is far outside chance on the loop's poses and inside it once 0.5 s is cut from
  each pose's ends (the excess is settling of the hand at the pose edges), and the angular rate
  at rest is > 98 % the same as the second sensor's on that body: real motion, not the sensor.
* gyro_rotation: UNEXPLAINED RESIDUAL (chi2/dof ~3.5), nothing claimed. Its noise is the gyro's
  white noise measured on the longest rest plus each held pose's wander; numpy shows why the
  at-rest scatter of the held poses must not be used instead: it is the shared hand motion
  (the sensor-only noise left after removing it gives a floor more than 10 times lower).
* No sample at either range limit (+-16 g, +-2000 deg/s); the session STATUS is UNEXPLAINED
  RESIDUAL, never OK.
"""
from __future__ import annotations

import gzip
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.stats

from helpers import run_rigctl

G_SRC = 9.81  # the source converts counts with g = 9.81 and fits |a| = 9.81
FS = 100.0
# the source's calibration of sensor #1 (images/real_imu.png; README): a_meas = M a + b, M upper
# triangular, 1 + s on the diagonal; misalignments in degrees, gyro biases in deg/s
SRC_ACC_S = np.array([0.363, 0.315, 0.647]) / 100
SRC_ACC_M = {(0, 1): 0.02, (0, 2): 0.317, (1, 2): 0.123}  # m_xy, m_xz, m_yz
SRC_ACC_B = np.array([0.103, 0.097, 0.344])
SRC_GYR_S = np.array([0.041, 0.457, 0.826]) / 100
SRC_GYR_B = np.radians([1.146, -0.401, 1.261])


def _log(ref_data: Path, i: int) -> np.ndarray:
    return np.loadtxt(gzip.open(ref_data / "mikov-mpu9150" / f"imu{i}.log.gz"))


@pytest.fixture(scope="module")
def mpu(ref_data, tmp_path_factory):
    d = _log(ref_data, 0)
    tmp = tmp_path_factory.mktemp("mpu9150")
    csv = tmp / "imu0.csv"
    np.savetxt(csv, d, delimiter=",", header="ax,ay,az,gx,gy,gz", comments="", fmt="%.5f")
    rec = tmp / "imu0.h5"
    proc = run_rigctl("import", str(csv), "-o", str(rec), "--rate", "100", "--columns",
                      "acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz", "--units", "acc=m/s^2,gyr=rad/s",
                      "--t-init", "7", "--gravity", str(G_SRC))
    assert proc.returncode == 0, proc.stderr
    js = tmp / "imu0.json"
    proc = run_rigctl("calibrate", str(rec), "--explain", "--json", str(js), timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    with h5py.File(rec, "r") as f:
        s = f["segments"]
        iv = [(int(a), int(b)) for a, b, k in zip(s["first_sample"][()], s["last_sample"][()], s["kind"][()])
              if k == b"orientation"]
    return d, iv, proc.stdout, json.loads(js.read_text())


def _params(cal: dict, sub: str) -> dict[str, dict]:
    return {q["name"]: q for q in cal["closed_loop"][sub]["final"]["parameters"]}


def _numpy_poses(gyr: np.ndarray) -> list[tuple[int, int]]:
    """Our own static detector: 0.5 s moving mean of |w| below 0.1 rad/s for at least 1.5 s,
    0.25 s cut from each end."""
    wn = np.convolve(np.linalg.norm(gyr, axis=1), np.ones(50) / 50, mode="same")
    e = np.flatnonzero(np.diff(np.r_[0, (wn < 0.1).astype(int), 0]))
    return [(a + 25, b - 25) for a, b in zip(e[::2], e[1::2]) if b - a >= 150]


def _pooled_var(x: np.ndarray, iv: list[tuple[int, int]], nb: int = 25) -> np.ndarray:
    """Per-sample variance from batch means of nb samples, pooled over the poses."""
    num, dof = np.zeros(x.shape[1]), 0
    for a, b in iv:
        m = x[a:a + (b - a) // nb * nb].reshape(-1, nb, x.shape[1]).mean(axis=1)
        num += nb * ((m - m.mean(axis=0)) ** 2).sum(axis=0)
        dof += len(m) - 1
    return num / dof


def _half_split(x: np.ndarray, iv: list[tuple[int, int]]) -> np.ndarray:
    """p-value per axis of sum_p z_p^2 (first-half mean minus second-half mean over its noise)."""
    v = _pooled_var(x, iv)
    chi = sum((x[a:(a + b) // 2].mean(0) - x[(a + b) // 2:b].mean(0)) ** 2
              / (v * (1 / ((b - a) // 2) + 1 / (b - (a + b) // 2))) for a, b in iv)
    return scipy.stats.chi2.sf(chi, len(iv))


def _const_chi2_per_dof(x: np.ndarray, iv: list[tuple[int, int]]) -> np.ndarray:
    """Per axis: chi2/dof of the pose means about one weighted constant."""
    v = _pooled_var(x, iv)
    n = np.array([b - a for a, b in iv], float)[:, None]
    mu = np.array([x[a:b].mean(0) for a, b in iv])
    w = n / v
    c = (mu * w).sum(0) / w.sum(0)
    return ((mu - c) ** 2 * w).sum(0) / (len(iv) - 1)


def test_accel_ok_and_agrees_with_the_source_calibration(mpu):
    d, iv, out, cal = mpu
    # pose count: our own detector finds the same 23 poses, each overlapping exactly one of rigctl's
    ours = _numpy_poses(d[:, 3:])
    assert cal["n_poses"] == len(iv) == len(ours) == 23
    for a, b in ours:
        assert sum(min(b, e) > max(a, s) for s, e in iv) == 1
    acc = cal["closed_loop"]["accel"]
    assert acc["status"] == "OK" and acc["effects_claimed"] == []
    assert "accel: 0.499 -> 0.499" in out and "effects found: none" in out
    p = _params(cal, "accel")
    M = np.array(cal["model"]["accel"]["M"])
    bias = np.array(cal["model"]["accel"]["bias_m_s2"])
    for i, ax in enumerate("xyz"):
        sb = p[f"accel_bias_{ax}_m_s2"]["sigma"]
        assert abs(bias[i] - SRC_ACC_B[i]) < 3 * sb + 0.0005, (ax, bias[i], SRC_ACC_B[i])  # table: 3 decimals
        ss = p[f"accel_scale_{ax}_ratio"]["sigma"]
        assert abs(M[i, i] - (1 + SRC_ACC_S[i])) < 3 * ss + 5e-6, (ax, M[i, i], SRC_ACC_S[i])
    sm = max(q["sigma"] for n, q in p.items() if n.startswith("accel_misalign"))
    for (i, j), deg in SRC_ACC_M.items():
        assert abs(M[i, j] - np.radians(deg)) < 3 * sm + np.radians(0.0005), ((i, j), M[i, j], deg)
    rows = {r["channel"]: r for r in cal["before_after"]}
    for ax in "xyz":
        r = rows[f"a{ax}"]
        assert r["unit"] == "mg" and r["raw"] > 50 * r["final"], r


def test_gyro_static_unexplained_motion_not_a_sensor_effect(mpu, ref_data):
    d, iv, out, cal = mpu
    gs = cal["closed_loop"]["gyro_static"]
    assert gs["status"] == "UNEXPLAINED RESIDUAL" and gs["effects_claimed"] == []
    gsens = next(e for e in gs["explain"] if e["candidate"] == "gyro_g_sensitivity")
    assert gsens["decision"].startswith("rejected")
    assert any("drift within the poses" in f for f in gs["findings"])
    assert gs["final"]["chi2_per_dof"] > gs["band_chi2_per_dof"][1]
    acc, gyr = d[:, :3], d[:, 3:]
    # (1) no g-sensitivity: per axis, gyro pose means (our poses) on the gravity direction, OLS F test
    ours = _numpy_poses(gyr)
    P = len(ours)
    f = np.array([acc[a:b].mean(0) for a, b in ours])
    f = G_SRC * f / np.linalg.norm(f, axis=1)[:, None]
    X = np.column_stack([np.ones(P), f])
    for i in range(3):
        y = np.array([gyr[a:b, i].mean() for a, b in ours])
        _, rss1, *_ = np.linalg.lstsq(X, y, rcond=None)
        F = ((np.sum((y - y.mean()) ** 2) - rss1[0]) / 3) / (rss1[0] / (P - 4))
        assert scipy.stats.f.sf(F, 3, P - 4) > 0.01, (i, F)
    # (2) the loop's poses drift within themselves; cut 0.5 s from each end and they do not: the
    # excess sits at the pose edges (the hand settling), and the constant-bias fit enters its band
    assert np.all(_half_split(gyr, iv) < 1e-4)
    cut = [(a + 50, b - 50) for a, b in iv]
    assert np.all(_half_split(gyr, cut) > 1e-3)
    hi = scipy.stats.chi2.ppf(0.995, P - 1) / (P - 1)
    assert np.all(_const_chi2_per_dof(gyr, iv) > hi) and np.all(_const_chi2_per_dof(gyr, cut) < hi)
    # (3) the rate at rest is the body's: sensor #5 on the same body, lag from |w|, mapped by a 3x3
    # least-squares fit of the within-pose fluctuations, explains > 98 % of #1's
    shared = _shared_motion(d, _log(ref_data, 4), iv)
    assert np.all(shared["r2"] > 0.98), shared["r2"]
    # what is left is the two sensors' own noise (MPU-9150 datasheet: 0.06 deg/s rms each)
    assert np.all(np.degrees(np.sqrt(shared["v_resid"])) < 0.15), shared["v_resid"]
    rows = {r["channel"]: r for r in cal["before_after"]}
    for ax in "xyz":
        r = rows[f"g{ax} at rest"]
        assert r["unit"] == "deg/h" and r["final"] > 1.3 * r["noise_floor"], r


def _shared_motion(d1: np.ndarray, d5: np.ndarray, iv: list[tuple[int, int]]) -> dict[str, np.ndarray]:
    n = min(len(d1), len(d5))
    g1, g5 = np.linalg.norm(d1[:n, 3:], axis=1), np.linalg.norm(d5[:n, 3:], axis=1)
    m = n - 200
    lag = int(np.argmax([np.dot(g1[100:100 + m] - g1.mean(), g5[100 + k:100 + k + m] - g5.mean())
                         for k in range(-50, 51)])) - 50
    w1, w5 = d1[:n, 3:], np.roll(d5[:n, 3:], -lag, axis=0)
    ivs = [(a, b) for a, b in iv if a + lag >= 0 and b - lag <= n]
    f1 = np.vstack([w1[a:b] - w1[a:b].mean(0) for a, b in ivs])
    f5 = np.vstack([w5[a:b] - w5[a:b].mean(0) for a, b in ivs])
    R, *_ = np.linalg.lstsq(f5, f1, rcond=None)
    e = w1 - w5 @ R
    return {"lag": np.array(lag), "r2": 1 - ((f1 - f5 @ R) ** 2).sum(0) / (f1 ** 2).sum(0),
            "v_rest": _pooled_var(w1, ivs), "v_resid": _pooled_var(e, ivs)}


def test_gyro_rotation_noise_is_the_sensors_own_and_status_not_ok(mpu, ref_data):
    d, iv, out, cal = mpu
    rl = cal["closed_loop"]["gyro_rotation"]
    # the motions' noise is the gyro's own white noise (measured on the longest rest) plus each
    # held pose's wander; the hand-held residual (~3 mrad) is above that band and nothing in the
    # library explains it
    assert rl["status"] == "UNEXPLAINED RESIDUAL" and rl["effects_claimed"] == []
    assert rl["final"]["chi2_per_dof"] > rl["band_chi2_per_dof"][1]
    # numpy: the floor that treats the at-rest scatter of the held poses as angle random walk
    # (per-sample variance from 0.25 s batch means, mean over axes) is the shared hand motion: the
    # sensor-only noise (#1 minus the motion seen by #5) gives a floor > 10x lower, and rigctl's
    # floor sits below the at-rest-scatter one
    gyr = d[:, 3:]
    T = np.array([(iv[k + 1][0] + 1 - (iv[k][1] - 1)) / FS for k in range(len(iv) - 1)])
    floor = lambda v: np.sqrt(np.mean(np.mean(v) / FS * T)) / np.sqrt(2)  # noqa: E731
    rows = {r["channel"]: r for r in cal["before_after"]}
    theirs = rows["motion (gravity direction) x"]["noise_floor"] * 1e-6
    held = floor(_pooled_var(gyr, iv))
    assert theirs < held
    shared = _shared_motion(d, _log(ref_data, 4), iv)
    assert floor(shared["v_resid"]) < held / 10
    for ax in "xyz":
        r = rows[f"motion (gravity direction) {ax}"]
        assert r["unit"] == "urad" and r["noise_floor"] < r["final"] < r["raw"], r
    # gyro bias and scale against the source's calibration (bias: within rigctl's 3 sigma, inflated
    # by the gyro_static chi2/dof; scales: see below)
    ps, pr = _params(cal, "gyro_static"), _params(cal, "gyro_rotation")
    for i, ax in enumerate("xyz"):
        b = ps[f"gyro_bias_{ax}_rad_s"]
        assert abs(b["value"] - SRC_GYR_B[i]) < 3 * b["sigma"] + 0.0005, (ax, b, SRC_GYR_B[i])
        # rigctl's ratio maps raw to true (w = T K (u - b)); the source's 1 + s maps true to raw
        k = pr[f"gyro_scale_{ax}_ratio"]
        diff = abs(1 / k["value"] - (1 + SRC_GYR_S[i]))
        sig = k["sigma"] * np.sqrt(rl["final"]["chi2_per_dof"])  # the interval rigctl publishes (inflated)
        if ax == "y":
            assert diff < 3 * sig, (ax, k, SRC_GYR_S[i])
        else:
            # measured: x and z differ from the source's by 0.85 % and 0.59 % (3.8 and 3.0 of the
            # published sigma); the rotation model is UNEXPLAINED RESIDUAL, so rigctl does not
            # certify these scales -- same ballpark only
            assert diff < 0.01 and rl["status"] == "UNEXPLAINED RESIDUAL", (ax, k, SRC_GYR_S[i])
    # range limits: +-16 g (2048 counts/g, g = 9.81) and +-2000 deg/s, counted in the samples
    a_rail = 32767 * G_SRC / 2048
    w_rail = np.radians(32767 * 2000 / 32768)
    assert int(np.sum(np.abs(d[:, :3]) >= 0.995 * a_rail)) == 0
    assert int(np.sum(np.abs(d[:, 3:]) >= 0.995 * w_rail)) == 0
    assert "gyro_range_exceeded" not in out
    # the session: enough poses to be trustworthy, UNEXPLAINED RESIDUAL, never OK
    assert cal["trustworthy"] is True
    assert cal["status"] == "UNEXPLAINED RESIDUAL" and "STATUS: UNEXPLAINED RESIDUAL" in out
    assert "STATUS: OK" not in out
    assert "before/after" in out and "noise floor" in out
