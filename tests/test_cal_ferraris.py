"""Real hand-held Ferraris session (imucal): static faces -> accelerometer, compared with imucal.

imucal models raw = K_a R_a a + b_a (counts, a in m/s^2 with g = 9.81) and
raw_g = K_g R_g w + K_ga a + b_g. The faces x_p/x_a, ... put +-g on one axis; our full A2 form
without the quadratic term, f = b + M a, is the same model with M = K_a R_a.

Differences, stated and explained:

1. M (9 numbers): the unweighted least-squares estimate on six +-g faces is algebraically
   imucal's (U_p - U_a) / (2 g) (checked to 1e-9 below). Ours weights each face by its
   uncertainty, so it differs slightly, well inside the interval.
2. b_a (3 numbers): imucal takes b_i from the two faces of axis i only, (U_ip + U_ia)/2; least
   squares uses all six faces: b_i = mean over the three pairs of (U_jp,i + U_ja,i)/2. The faces
   are held by hand, not exactly opposite, so the pair sums differ -- which is also why chi2/dof
   is ~100-5000 here: the residuals are pose errors, not sensor noise. We say so (status
   "poor_fit") and inflate the covariance by chi2/dof with t intervals (2 dof per axis); with
   that honest interval imucal's b_a lies inside.
3. gyro bias: imucal averages all static samples (each face weighted by its length); we weight
   the face means by their uncertainty. Both ignore the Earth rate (unknown heading; at most
   15 deg/h = 0.07 count, below the 0.05-deg/s-per-count resolution).
4. K_g, R_g, K_ga: not compared (K_ga is the gyro g-sensitivity, which our closed loop adds only
   when the data demand it; K_g R_g needs the rotation integration, covered by the synthetic
   multi-position tests).
"""
from __future__ import annotations

import csv
import json

import numpy as np

from rigctl.solvers.accel24 import calibrate_accel, calibrate_gyro_bias_static
from rigctl.solvers.segment_stats import segment_mean

G_IMUCAL = 9.81
FS = 204.8
ACC_LSB = G_IMUCAL / 2048.0  # nominal m/s^2 per count (values compared in counts, so exact value moot)
GYR_LSB = np.radians(1.0 / 16.4)  # nominal rad/s per count
FACES = ["x_p", "x_a", "y_p", "y_a", "z_p", "z_a"]
REF = G_IMUCAL * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


def _load(ref_data):
    d = ref_data / "imucal-ferraris"
    with open(d / "example_data_annotated_session.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    part = np.array([r["part"] for r in rows])
    cols = ("acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z")
    data = np.array([[float(r[c]) for c in cols] for r in rows])
    snap = json.loads((d / "tests_snapshots_example_cal.json").read_text())
    return part, data, snap


def test_ferraris_accelerometer_agrees_with_imucal(ref_data):
    part, data, snap = _load(ref_data)
    acc_si = data[:, :3] * ACC_LSB  # nominal SI, so the parameter names' units hold
    means = [segment_mean(acc_si[part == f], FS) for f in FACES]  # no noise model: from the data
    f = np.array([m.mean for m in means])
    s = np.array([m.sigma for m in means])
    res = calibrate_accel(f, s, REF, quadratic=False)
    assert res.dof == 6 and res.status == "poor_fit" and res.interval == "t"
    assert res.chi2_per_dof > 50  # the hand-held faces are far from the noise model, and we say so
    M_counts = res.extra["M"] / ACC_LSB
    b_counts = res.extra["bias_m_s2"] / ACC_LSB
    M_im = np.array(snap["K_a"]) @ np.array(snap["R_a"])
    b_im = np.array(snap["b_a"])
    half = (res.ci95[:, 1] - res.ci95[:, 0]) / 2 / ACC_LSB
    assert np.all(np.abs(M_counts - M_im).ravel() <= half[3:12]), (M_counts - M_im) / half[3:12].reshape(3, 3)
    assert np.all(np.abs(b_counts - b_im) <= half[0:3]), (b_counts - b_im) / half[0:3]
    # explanation 1 and 2, exactly: unweighted least squares = imucal's M; our bias = mean of pair sums
    uw = calibrate_accel(f, np.ones_like(f), REF, quadratic=False)
    np.testing.assert_allclose(uw.extra["M"] / ACC_LSB, M_im, rtol=1e-9)
    pair_sums = (f[0::2] + f[1::2]) / 2 / ACC_LSB  # rows: face pairs x, y, z; columns: axes
    np.testing.assert_allclose(np.diag(pair_sums), b_im, rtol=1e-9)  # imucal: own pair only
    np.testing.assert_allclose(uw.extra["bias_m_s2"] / ACC_LSB, pair_sums.mean(axis=0), rtol=1e-9)


def test_ferraris_gyro_bias_agrees_with_imucal(ref_data):
    part, data, snap = _load(ref_data)
    gyr_si = data[:, 3:] * GYR_LSB
    means = [segment_mean(gyr_si[part == f], FS) for f in FACES]
    gb = calibrate_gyro_bias_static(np.array([m.mean for m in means]), np.array([m.sigma for m in means]),
                                    np.zeros((6, 3)))
    assert gb.status == "ok"  # a constant bias over the faces is consistent with the noise
    half = (gb.ci95[:, 1] - gb.ci95[:, 0]) / 2 / GYR_LSB
    b_counts = gb.values / GYR_LSB
    assert np.all(np.abs(b_counts - np.array(snap["b_g"])) <= half), (b_counts, snap["b_g"], half)
