"""Uncertainty of segment means: Allan variance at T, not sigma/sqrt(n), under coloured noise."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from rigctl.solvers.noise_coefficients import NoiseCoefficients, triad
from rigctl.solvers.segment_stats import (AllanCurve, allan_curve_from_samples,
                                          gauss_markov_avar, mean_sigma_from_model,
                                          overlapping_avar, segment_mean, self_noise_sigma)

FS = 100.0


def _gm(rng, shape, sigma, tc):
    phi = np.exp(-1 / (FS * tc))
    burn = int(8 * tc * FS)
    e = rng.normal(0, sigma * np.sqrt(1 - phi**2), (shape[0] + burn,) + shape[1:])
    return lfilter([1.0], [1.0, -phi], e, axis=0)[burn:]


def test_white_noise_model_equals_sigma_over_sqrt_n():
    n_white = 2e-3  # unit*sqrt(s)
    model = triad(N=n_white)
    T = 20.0
    s = mean_sigma_from_model(T, model)
    np.testing.assert_allclose(s, n_white / np.sqrt(T))
    # sample std of white noise at FS is N sqrt(FS): sigma/sqrt(n) = N/sqrt(T)
    assert np.isclose(n_white * np.sqrt(FS) / np.sqrt(T * FS), s[0])


def test_ieee952_terms_at_their_read_off_points():
    q, n, b, k, r = 1e-4, 2e-3, 5e-4, 3e-5, 1e-6
    assert np.isclose(np.sqrt(NoiseCoefficients(Q=q).avar(np.sqrt(3.0))), q)
    assert np.isclose(np.sqrt(NoiseCoefficients(N=n).avar(1.0)), n)
    assert np.isclose(np.sqrt(NoiseCoefficients(B=b).avar(123.0)), 0.664 * b, rtol=1e-3)
    assert np.isclose(np.sqrt(NoiseCoefficients(K=k).avar(3.0)), k)
    assert np.isclose(np.sqrt(NoiseCoefficients(R=r).avar(np.sqrt(2.0))), r)
    both = NoiseCoefficients(N=n, K=k).avar(10.0)
    assert np.isclose(both, n**2 / 10 + k**2 * 10 / 3)  # the terms add


def test_overlapping_avar_matches_allantools():
    allantools = pytest.importorskip("allantools")
    rng = np.random.default_rng(1)
    x = rng.normal(size=4000) + _gm(rng, (4000,), 1.0, 0.3)
    m = np.array([1, 2, 4, 16, 64, 256])
    ours = overlapping_avar(x, m)[:, 0]
    taus, adev, _, _ = allantools.oadev(x, rate=FS, data_type="freq", taus=m / FS)
    np.testing.assert_allclose(np.sqrt(ours), adev, rtol=1e-9)


def test_coloured_noise_mean_uncertainty_from_allan_curve():
    """Monte Carlo: scatter of 20 s means of white + Gauss-Markov noise."""
    rng = np.random.default_rng(2)
    n_white, gm, tc, T = 1e-3, 5e-3, 0.5, 20.0
    tau = np.logspace(-2, 3, 60)
    curve = AllanCurve(tau, np.sqrt(n_white**2 / tau + gauss_markov_avar(tau, gm, tc))[:, None] * np.ones(3))
    n = int(T * FS)
    x = rng.normal(0, n_white * np.sqrt(FS), (n, 600)) + _gm(rng, (n, 600), gm, tc)
    empirical = x.mean(axis=0).std(ddof=1)
    sm = segment_mean(x[:, :3], FS, curve)
    predicted = sm.sigma[0]
    naive = np.mean(x.std(axis=0, ddof=1)) / np.sqrt(n)
    assert sm.method == "allan_curve"
    assert abs(predicted / empirical - 1) < 0.12, (predicted, empirical)  # SE of std ~3 %
    assert empirical / naive > 2.0  # sigma/sqrt(n) would be overconfident by > 2x


def test_self_estimate_grows_under_coloured_noise():
    rng = np.random.default_rng(3)
    n = 2000
    white = rng.normal(0, 0.02, (n, 300))
    col = white * 0.2 + _gm(rng, (n, 300), 0.02, 0.5)
    for x, lo, hi in ((white, 0.9, 1.3), (col, 0.8, 1.25)):
        emp = x.mean(axis=0).std(ddof=1)  # SE of this std over 300 columns ~4 %
        est = np.sqrt(np.mean(self_noise_sigma(x, FS) ** 2))
        assert lo < est / emp < hi, (est, emp)
    naive = np.mean(col.std(axis=0, ddof=1)) / np.sqrt(n)
    est = np.sqrt(np.mean(self_noise_sigma(col, FS) ** 2))
    assert est > 5.0 * naive  # sigma/sqrt(n) would be ~10x overconfident here


def test_segment_mean_without_model_and_curve_from_samples():
    rng = np.random.default_rng(4)
    x = rng.normal(5.0, 0.1, (3000, 3))
    sm = segment_mean(x, FS)
    assert sm.method == "self" and sm.n == 3000 and np.isclose(sm.duration_s, 30.0)
    np.testing.assert_allclose(sm.mean, x.mean(axis=0))
    assert np.all(sm.sigma >= sm.naive_sigma * 0.999)
    curve = allan_curve_from_samples(x, FS)
    assert np.isclose(curve.avar(1.0)[0], 0.1**2 / FS / 1.0, rtol=0.3)
    with pytest.raises(ValueError):
        segment_mean(x[:1], FS)


def test_segment_table_from_samples_moments():
    from rigctl.solvers.segments import segment_table_from_samples

    rng = np.random.default_rng(5)
    t = np.arange(400) / FS
    w_ramp = np.stack([np.zeros_like(t), np.zeros_like(t), 0.5 * t], axis=1)  # 0.5 rad/s^2 about z
    f_static = np.array([0.0, 0.0, 9.8])
    acc = [rng.normal(f_static, 0.01, (400, 3)), rng.normal(f_static, 0.01, (400, 3))]
    gyr = [rng.normal(0, 0.001, (400, 3)), w_ramp + rng.normal(0, 0.001, (400, 3))]
    st = segment_table_from_samples(["orientation", "ramp"], acc, gyr, FS, [f_static, f_static],
                                    [np.zeros(3), w_ramp], acc_noise=triad(N=0.01 / np.sqrt(FS)),
                                    time=np.array([10.0, 20.0]))
    np.testing.assert_allclose(st.ang_accel[1], [0, 0, 0.5], atol=1e-9)
    np.testing.assert_allclose(st.ang_accel[0], 0.0)
    assert np.isclose(st.w_ref_outer[1, 2, 2], np.mean(w_ramp[:, 2] ** 2))
    assert st.w_ref_outer[1, 2, 2] > st.w_ref[1, 2] ** 2 * 1.3  # mean of w^2 is not (mean w)^2
    np.testing.assert_allclose(st.f_sigma[0], 0.01 / np.sqrt(400))  # white: N / sqrt(T)
    assert np.all(st.w_sigma > 0) and st.time[1] == 20.0
