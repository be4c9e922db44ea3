"""Tap matching and the clock model on two real, independently clocked IMUs (no taps).

tests/data/mikov-mpu9150 holds five MPU-9150s recorded together on one body, each on its own
sample clock ("100 Hz" nominal). imu1's clock runs about 0.24 % slow against imu0's: its lag
grows from ~4 to ~36 samples over the 160 s session (the folder's README). This is the only
real pair of drifting IMU clocks found with a licence that allows it here; there is no tap,
no hammer pulse and no time reference better than imu0's own crystal, so what it checks is the
matching (tap_match) and the clock fit (clock_model) on real events with a large real drift,
not the tap detector (tap_detect: the events are hand rotations, not impacts).

Events: the start of each of the ~22 hand rotations (|w| above a threshold after >= 1 s of
rest), found the same simple way in both files -- imu1's play the taps (its counter), imu0's
the logged pulses (imu0's clock = the reference timescale).

Independent analysis (plain numpy, no rigctl): the lag of imu1's |w| behind imu0's in
non-overlapping 8 s windows by cross-correlation with a parabolic sub-sample peak, and a
straight line through lag vs time (np.polyfit with its covariance): the drift.

Before tap_match removed a robust line from the offsets, its local-median prediction of the
pulse time was off by up to drift x window = 2400 ppm x 120 s = 0.29 s near a window's edge:
6 to 8 of 22 events matched and the fitted drift came out at 234 to 1783 ppm, its 95 %
interval excluding the truth.
"""
from __future__ import annotations

import gzip

import numpy as np
import pytest
from scipy import stats

from rigctl.solvers import clock_model, tap_match

FS = 100.0  # nominal sample rate of every file, Hz
THRESHOLD = 0.5  # rad/s: |w| above this after >= 1 s below it is a rotation's start
#: timing error of one pair from whole-sample event times on two clocks: U(0, T) each
SIGMA_Q = np.sqrt(2.0) * (1.0 / FS) / np.sqrt(12.0)


@pytest.fixture(scope="module")
def rates(ref_data):
    """|w| (rad/s) of imu0 ... imu4."""
    return [np.linalg.norm(np.loadtxt(gzip.open(ref_data / "mikov-mpu9150" / f"imu{i}.log.gz"))[:, 3:6], axis=1)
            for i in range(5)]


@pytest.fixture(scope="module")
def pair(rates):
    return rates[0], rates[1]


def rotation_starts(w: np.ndarray, threshold: float = THRESHOLD, rest_s: float = 1.0) -> np.ndarray:
    """Sample indices where |w| first exceeds ``threshold`` after ``rest_s`` below it."""
    out, quiet = [], 0
    for k, moving in enumerate(w > threshold):
        if moving:
            if quiet >= rest_s * FS:
                out.append(k)
            quiet = 0
        else:
            quiet += 1
    return np.array(out)


def xcorr_drift(w0: np.ndarray, w1: np.ndarray, half: int = 400) -> dict:
    """Lag (s) of imu1 behind imu0 per non-overlapping window, and a line through it."""
    pos, lag = [], []
    lags = np.arange(-10, 60)
    for k in range(half + 60, w1.size - half - 60, 2 * half):
        seg = w1[k - half:k + half]
        if seg.std() < 0.3:  # a window at rest: nothing to correlate
            continue
        c = np.array([np.corrcoef(seg, w0[k + L - half:k + L + half])[0, 1] for L in lags])
        j = int(np.argmax(c))
        frac = 0.5 * (c[j - 1] - c[j + 1]) / (c[j - 1] - 2 * c[j] + c[j + 1]) if 0 < j < lags.size - 1 else 0.0
        pos.append(k / FS)
        lag.append((lags[j] + frac) / FS)
    x, y = np.array(pos), np.array(lag)
    p, cov = np.polyfit(x, y, 1, cov=True)
    return {"x": x, "y": y, "drift": p[0], "drift_sigma": float(np.sqrt(cov[0, 0])), "offset": p[1],
            "resid": y - np.polyval(p, x), "dof": x.size - 2}


@pytest.fixture(scope="module")
def solved(pair):
    w0, w1 = pair
    taps, pulses = rotation_starts(w1) / FS, rotation_starts(w0) / FS
    m = tap_match.match_taps(taps, pulses)
    ti, pj = m.tap_index[m.inlier], m.pulse_index[m.inlier]
    fit = clock_model.fit_clock(taps[ti] * FS, pulses[pj], FS, detect_steps=False, sigma_floor_s=SIGMA_Q)
    return taps, pulses, m, fit, xcorr_drift(w0, w1)


def test_independent_lag_line_is_quantization_limited(solved):
    """The numpy reference itself: ~2360 ppm, and its residual scatter is what two 100 Hz
    samplers give (each event known to U(0, T): std T/sqrt(12), two clocks: x sqrt(2))."""
    *_, xc = solved
    assert 2200e-6 < xc["drift"] < 2500e-6
    chi2 = float(np.sum((xc["resid"] / SIGMA_Q) ** 2))
    lo, hi = stats.chi2.ppf([0.005, 0.995], xc["dof"])
    assert lo <= chi2 <= hi, (chi2, xc["dof"], lo, hi)


def test_every_consistent_rotation_matched_one_to_one(solved):
    """Both files hold the same 22 rotations in the same order; the matcher must pair each
    tap with the pulse of the same rotation (checked against the cross-correlation line), and
    it must pair at least 21 of them (at 0.5 rad/s the detector finds all 22 in both files)."""
    taps, pulses, m, _, xc = solved
    assert taps.size == pulses.size == 22
    assert m.tap_index.size >= 21, (m.tap_index.size, m.unmatched_taps)
    # imu0 sample = imu1 sample + lag: imu0 time = imu1 time + lag(t); a wrong pairing is a
    # whole rotation (>= 5 s) off
    predicted = taps[m.tap_index] + xc["offset"] + xc["drift"] * taps[m.tap_index]
    assert np.max(np.abs(pulses[m.pulse_index] - predicted)) < 0.05
    assert np.array_equal(m.tap_index, m.pulse_index)


def test_clock_drift_agrees_with_cross_correlation(solved):
    """fit_clock's drift and its 95 % interval against the independent lag line."""
    *_, fit, xc = solved
    # imu0 time of imu1 counter n: n/FS + lag(n/FS) = n/FS (1 + drift_xc) + offset_xc, so the
    # model's d (t_ref = c0 + (1 + d) x) is drift_xc (positive: imu1's clock is slow)
    d_ref, s_ref = xc["drift"], xc["drift_sigma"]
    d, s = fit.drift_ppm * 1e-6, fit.drift_sigma_ppm * 1e-6
    assert abs(d - d_ref) <= 1.96 * np.hypot(s, s_ref), (fit.drift_ppm, d_ref * 1e6)
    assert fit.t95 * s < 150e-6  # a real constraint: +-150 ppm or better at 95 %


def test_clock_fit_residuals_exceed_quantization_finding(solved):
    """Finding (not OK): the clock fit's residual scatter (~9 ms) is about twice what the two
    samplers' quantization gives (4.1 ms; the cross-correlation above meets it), chi2/dof
    ~5, far above its 99 % band. The missing effect is the event timing: a threshold crossing
    on a hand rotation lands at a different point of the ramp in each sensor (different noise,
    scale and axes), jitter no tap-sync model term describes. fit_clock scales its covariance
    by the residuals (s^2 = RSS / dof), so its interval stays honest (previous test); a tap
    rig's hammer events would have to show chi2 in band before that scaling is trusted."""
    *_, fit, _ = solved
    r = fit.residual_s[fit.inlier]
    chi2 = float(np.sum((r / SIGMA_Q) ** 2))
    lo, hi = stats.chi2.ppf([0.005, 0.995], fit.dof)
    assert chi2 > hi, (chi2, fit.dof, hi)
    assert 6e-3 < fit.residual_std_s < 15e-3


def test_pipeline_on_non_taps_warns_instead_of_reporting_quietly(ref_data, pair):
    """The whole pipeline (first-difference tap detector on imu1's x accelerometer, the hand
    rotations' starts in imu0 as pulses): the detector finds 29 'taps' in hand motion, 6 of 21
    pulses match, and the drift (-150 +- 620 ppm at 95 %) misses the true ~2360 ppm. The result
    must say so: a warning that few pulses matched, printed with the summary."""
    from rigctl.analysis.sync import SyncOptions, summary_lines, synchronise

    w0, _ = pair
    d1 = np.loadtxt(gzip.open(ref_data / "mikov-mpu9150" / "imu1.log.gz"))
    pulses = rotation_starts(w0) / FS
    res = synchronise(np.arange(d1.shape[0]), d1[:, 0], FS, pulses, SyncOptions(response="none"))
    s = res.summary
    assert s["n_inliers"] < 0.5 * s["n_pulses"]
    assert abs(s["drift_ppm"] - 2360.0) > s["drift_ci95_ppm"]  # the wrong answer the warning is for
    assert len(s["warnings"]) == 1 and "pulses are matched" in s["warnings"][0]
    assert any(line.startswith("WARNING: only") for line in summary_lines(s))


@pytest.mark.parametrize("imu, drift_ppm", [(1, 2360), (2, 2190), (3, 136), (4, 3)])
def test_every_pair_drift_against_cross_correlation(rates, imu, drift_ppm):
    """imu1 ... imu4 against imu0: large (~2200-2400 ppm), small (~140 ppm) and nearly no
    drift (~3 ppm). imu4's 22 rotation starts all sit exactly 1 sample off imu0's: a fit
    without a timing floor had RSS 0 and reported 0 +- 0 ppm, an interval that excludes the
    3 +- 1 ppm of the cross-correlation; with the quantization floor sqrt(2) T / sqrt(12) the
    interval is honest (tens of ppm)."""
    taps, pulses = rotation_starts(rates[imu]) / FS, rotation_starts(rates[0]) / FS
    # whole-sample times: the outlier limit no lower than 5 x the quantization (imu4: 20 of 22
    # offsets are identical, MAD 0, and with the default 1 ms floor the rest, one sample off,
    # were outliers)
    m = tap_match.match_taps(taps, pulses, outlier_floor_s=5 * SIGMA_Q)
    assert m.inlier.sum() >= 20
    ti, pj = m.tap_index[m.inlier], m.pulse_index[m.inlier]
    fit = clock_model.fit_clock(taps[ti] * FS, pulses[pj], FS, detect_steps=False, sigma_floor_s=SIGMA_Q,
                                outlier_floor_s=5 * SIGMA_Q)
    xc = xcorr_drift(rates[0], rates[imu])
    assert abs(xc["drift"] * 1e6 - drift_ppm) < 30
    s = fit.drift_sigma_ppm * 1e-6
    assert s > 0
    assert abs(fit.drift_ppm * 1e-6 - xc["drift"]) <= 1.96 * np.hypot(s, xc["drift_sigma"]), \
        (imu, fit.drift_ppm, fit.drift_sigma_ppm, xc["drift"] * 1e6, xc["drift_sigma"] * 1e6)
