"""Orientation-free multi-position calibration (Tedaldi et al. 2014): synthetic truth and real MPU-6050."""
from __future__ import annotations

import numpy as np
import scipy.stats
from scipy.spatial.transform import Rotation

from rigctl.solvers.calibration_result import format_table
from rigctl.solvers.multipos import (_tg, _tk, calibrate_accel_apply, calibrate_accel_multipos,
                                     calibrate_gyro_multipos, detect_static_intervals, pose_means)

FS = 100.0
G = 9.80665


def _session(n_poses: int, seed: int):
    """Raw counts of a hand-held-like session: 10 s initial rest, then poses 3 s apart by 1.5 s moves."""
    rng = np.random.default_rng(seed)
    pa = np.array([0.01, -0.008, 0.012, 6.0e-4, 5.9e-4, 6.1e-4, 300.0, -200.0, 500.0])
    pg = np.concatenate([rng.normal(0, 0.01, 6), 1.33e-4 * (1 + rng.normal(0, 0.02, 3))])
    bg = np.array([-400.0, 150.0, -80.0])
    ma_inv, mg_inv = np.linalg.inv(_tk(pa)), np.linalg.inv(_tg(pg))
    poses = Rotation.random(n_poses, random_state=seed)
    poses = Rotation.concatenate([Rotation.identity(1), poses[1:]])
    acc, gyr, true_iv = [], [], []
    n_rest, n_pose, n_move = int(10 * FS), int(3 * FS), int(1.5 * FS)
    t0 = 0
    for k in range(n_poses):
        n_static = n_rest if k == 0 else n_pose
        f = poses[k].inv().apply([0, 0, G])
        acc.append(np.tile(f, (n_static, 1)))
        gyr.append(np.zeros((n_static, 3)))
        true_iv.append((t0, t0 + n_static))
        t0 += n_static
        if k + 1 < n_poses:
            rv = (poses[k].inv() * poses[k + 1]).as_rotvec()
            w = rv / (n_move / FS)
            att = poses[k] * Rotation.from_rotvec(np.outer(np.arange(n_move) / n_move, rv))
            acc.append(att.inv().apply([0, 0, G]))
            gyr.append(np.tile(w, (n_move, 1)))
            t0 += n_move
    acc, gyr = np.vstack(acc), np.vstack(gyr)
    raw_a = acc @ ma_inv.T + pa[6:9] + rng.normal(0, 10.0, acc.shape)
    raw_g = gyr @ mg_inv.T + bg + rng.normal(0, 5.0, gyr.shape)
    return raw_a, raw_g, pa, pg, true_iv


def _z_check(res, truth):
    z = (res.values - truth) / res.sigma
    assert np.all(np.abs(z) < 4.0), dict(zip(res.names, z))
    assert z @ z < scipy.stats.chi2.ppf(0.999, len(z)), z


def test_synthetic_30_poses_recovers_truth_with_intervals():
    raw_a, raw_g, pa, pg, true_iv = _session(30, seed=1)
    iv = detect_static_intervals(raw_a, FS, t_init_s=8.0)
    assert len(iv) == 30
    for (s, e), (ts, te) in zip(iv, true_iv):  # detected intervals lie inside the true rests
        assert ts <= s < e <= te and e - s > 0.5 * (te - ts)
    means, sig = pose_means(raw_a, iv, FS, None)
    acc = calibrate_accel_multipos(means, sig, G)
    assert acc.status == "ok" and acc.dof == 21, acc.warnings
    assert 1e-3 < acc.chi2_p_value < 1 - 1e-3
    _z_check(acc, pa)
    gyr = calibrate_gyro_multipos(raw_g, calibrate_accel_apply(acc.values, raw_a), iv, FS,
                                  scale_guess=np.radians(1 / 131.0))
    assert gyr.status == "ok" and gyr.dof == 2 * 29 - 9, gyr.warnings
    _z_check(gyr, pg)


def test_synthetic_10_poses_is_flagged_not_confident():
    raw_a, raw_g, pa, pg, _ = _session(10, seed=2)
    iv = detect_static_intervals(raw_a, FS, t_init_s=8.0)
    means, sig = pose_means(raw_a, iv, FS, None)
    acc = calibrate_accel_multipos(means, sig, G)
    assert acc.status == "insufficient_poses" and acc.dof == 1
    assert "10 poses for 9 parameters" in acc.warnings[0]
    assert "NOT TRUSTWORTHY" in format_table(acc)
    assert acc.to_dict()["status"] == "insufficient_poses"


def _mpu(ref_data):
    d = ref_data / "mpu6050-multipos"
    path = d / "calibration_data_example_data_calibration.csv"
    meta = dict(line.strip().split(",")[:2] for line in path.read_text().splitlines()[:4])
    raw = np.loadtxt(path, delimiter=",", skiprows=5)
    ref_iv = np.loadtxt(d / "optmization_result_data_static_intervals.csv", delimiter=",").astype(int)
    ref_acc = np.loadtxt(d / "optmization_result_data_params_acc.csv")
    return float(meta["Fs"]), float(meta["Initialization time"]), raw, ref_iv, ref_acc


def test_mpu6050_session_flagged_as_too_few_poses(ref_data):
    fs, t_init, raw, ref_iv, ref_acc = _mpu(ref_data)
    iv = detect_static_intervals(raw[:, :3], fs, t_init)
    assert len(iv) == 10  # initial rest + 9 hand-held poses, as the original tool found
    for s, e in ref_iv.T[1:]:  # each of the tool's intervals overlaps one of ours
        assert any(a < e + 1 and s < b for a, b in iv), (s, e)
    means, sig = pose_means(raw[:, :3], iv, fs, None)
    acc = calibrate_accel_multipos(means, sig, G)
    assert acc.status == "insufficient_poses" and acc.dof == 1
    assert "10 poses for 9 parameters" in acc.warnings[0]
    assert "NOT TRUSTWORTHY" in format_table(acc)
    # the numbers themselves resemble the original tool's (same method, same few poses) ...
    np.testing.assert_allclose(acc.values[3:6], ref_acc[3:6], rtol=0.01)
    np.testing.assert_allclose(-acc.values[6:9], ref_acc[6:9], atol=20.0)  # its bias sign is opposite
    # ... and the gyro step, resting on the same 10 poses, is flagged too
    gyr = calibrate_gyro_multipos(raw[:, 3:], calibrate_accel_apply(acc.values, raw[:, :3]), iv, fs,
                                  scale_guess=np.radians(1 / 131.0))
    assert gyr.status == "insufficient_poses"


def test_correlated_pose_means_are_whitened():
    """With IEEE 952 coefficients holding slow terms, the pose means are correlated: the fit
    whitens |a_p| - g by their covariance. Same truth, same data: the estimate stays consistent,
    and with a flicker/random-walk model the chi2 differs from the independent one."""
    from rigctl.solvers.multipos import pose_cov
    from rigctl.solvers.noise_coefficients import triad

    raw_a, _, pa, _, _ = _session(30, seed=3)
    iv = detect_static_intervals(raw_a, FS, t_init_s=8.0)
    means, sig = pose_means(raw_a, iv, FS, None)
    white = triad(N=10.0 / np.sqrt(FS))  # the generator's white noise, 10 counts per sample
    pc = pose_cov(iv, FS, white)
    np.testing.assert_allclose(np.sqrt(np.diagonal(pc, axis1=1, axis2=2)).T, 10.0 / np.sqrt(
        [[e - s] * 3 for s, e in iv]), rtol=1e-2)
    ind = calibrate_accel_multipos(means, np.sqrt(np.diagonal(pc, axis1=1, axis2=2)).T, G)
    whit = calibrate_accel_multipos(means, sig, G, pose_cov=pc)  # diagonal: the same fit
    np.testing.assert_allclose(whit.values, ind.values, rtol=1e-6)
    assert np.isclose(whit.chi2, ind.chi2, rtol=1e-6)
    slow = pose_cov(iv, FS, triad(N=10.0 / np.sqrt(FS), B=3.0, K=0.3))
    corr = calibrate_accel_multipos(means, sig, G, pose_cov=slow)
    assert corr.status == "ok" and not np.isclose(corr.chi2, ind.chi2, rtol=1e-3)
    _z_check(corr, pa)
