"""Covariance of segment means under time-correlated noise (rigctl.solvers.segment_cov).

The kernels are checked three ways: against brute-force double integrals of the autocovariance,
against Monte Carlo of the emulator's own noise generator (rigctl.sim.noise.NoiseGenerator,
public API only: NoiseGenerator(coefficients, rate_hz, seed).next(n)), and through the property the
calibration relies on: a constant added to every segment changes only the biases' variance.

Monte-Carlo error of a sample covariance from n independent zero-mean Gaussian vectors:
Var(c_ij) = (C_ii C_jj + C_ij^2) / n, so each element is compared with its own standard error.
"""
from __future__ import annotations

import numpy as np
import pytest

from rigctl.sim.noise import NoiseGenerator
from rigctl.solvers.noise_coefficients import NoiseCoefficients, triad
from rigctl.solvers import segment_cov as sc
from rigctl.solvers.calibration_result import fit_linear

# windows [a, b] (s, run time) like a calibration: 30-s positions, shorter rate windows, far apart
A = np.array([100.0, 135.0, 400.0, 1000.0, 1500.0, 1950.0])
B = A + np.array([30.0, 30.0, 10.0, 30.0, 20.0, 30.0])


def _brute(a, b, kernel, n=1201):
    ts = [np.linspace(ai, bi, n) for ai, bi in zip(a, b)]
    out = np.empty((len(a), len(a)))
    for i in range(len(a)):
        for j in range(len(a)):
            k = kernel(ts[i][:, None], ts[j][None, :])
            out[i, j] = np.trapezoid(np.trapezoid(k, ts[j], axis=1), ts[i]) / ((b[i] - a[i]) * (b[j] - a[j]))
    return out


@pytest.mark.parametrize("tau", [0.7, 12.0, 400.0, 1e5])
def test_ou_window_covariance_is_the_double_integral(tau):
    a, b = np.array([10.0, 25.0, 300.0]), np.array([40.0, 35.0, 320.0])  # includes overlapping windows
    C = sc.cov_ou(a, b, tau)
    brute = _brute(a, b, lambda s, t: np.exp(-np.abs(s - t) / tau))
    np.testing.assert_allclose(C, brute, rtol=3e-4, atol=1e-9)  # trapezoid error at the kink s = t
    # the diagonal in closed form: Var(mean of T) = (2 tau/T) [1 - (tau/T)(1 - e^{-T/tau})]
    T = b - a
    np.testing.assert_allclose(np.diag(C), 2 * tau / T * (1 - tau / T * -np.expm1(-T / tau)), rtol=1e-9)


def test_random_walk_window_covariance_is_the_double_integral():
    a, b = np.array([10.0, 25.0, 300.0]), np.array([40.0, 35.0, 320.0])
    for t0 in (0.0, -250.0):
        exact = _brute(a, b, lambda s, t: np.minimum(s, t) - t0)
        np.testing.assert_allclose(sc.cov_random_walk(a, b, t0), exact, rtol=1e-6)
    # moving the origin adds a constant to every element (absorbed by the bias, see below)
    d = sc.cov_random_walk(A, B, -500.0) - sc.cov_random_walk(A, B, 0.0)
    np.testing.assert_allclose(d, 500.0, rtol=1e-12)
    # variance of a T-second mean of Brownian motion from its start: T/3
    assert np.isclose(sc.cov_random_walk([0.0], [30.0])[0, 0], 10.0)


def test_flicker_bank_gives_the_ieee_plateau():
    bank = sc.flicker_bank(1.0, 1.0e4)
    tau = np.geomspace(1.0, 1.0e4, 17)
    adev_over_b = np.sqrt(bank.avar(tau))
    np.testing.assert_allclose(adev_over_b, np.sqrt(2 * np.log(2) / np.pi), rtol=0.015)  # 0.664 B
    assert np.isclose(np.sqrt(2 * np.log(2) / np.pi), 0.664, atol=1e-3)
    # 1/f over [1/(2 pi tau_max)/10, 10/tau_min]: variance ~ ln(f_hi/f_lo)/pi per B^2
    assert abs(bank.stationary_var_per_b2 / (np.log(10.0 * 2 * np.pi * 1e5) / np.pi) - 1) < 0.1


def _mc(params, fs, reps, seed0):
    idx = [(int(round(a * fs)), int(round(b * fs))) for a, b in zip(A, B)]
    n = idx[-1][1] + 1
    out = []
    for r in range(reps):
        x = NoiseGenerator(triad(**params), fs, seed0 + r).next(n)  # 3 independent axes
        out.append(np.array([x[i:j].mean(axis=0) for i, j in idx]).T)
    return np.concatenate(out)  # (3 reps, K)


def _z(emp, C, n):
    return (emp - C) / np.sqrt((np.outer(np.diag(C), np.diag(C)) + C**2) / n)


def test_random_walk_covariance_matches_the_emulator_generator():
    fs = 10.0
    M = _mc({"K": 1.0}, fs, 150, 7000)
    emp = M.T @ M / len(M)  # zero mean by construction
    C = sc.cov_random_walk(A, B, t0=-1.0 / fs)  # the generator's walk has one step at sample 0
    z = _z(emp, C, len(M))
    assert np.max(np.abs(z)) < 4.0, np.round(z, 2)
    # the covariance of the differences between windows (what a calibration sees) as well
    D = np.eye(6)[1:] - np.eye(6)[:-1]
    zd = _z(D @ emp @ D.T, D @ C @ D.T, len(M))
    assert np.max(np.abs(zd)) < 4.0, np.round(zd, 2)


def test_flicker_covariance_matches_the_emulator_generator():
    """Bias instability B = 1 with the plateau over [4 s, 1e4 s] at 10 Hz (the generator's band
    then ends at 10/tau_min = fs/4, as the bank's)."""
    fs = 10.0
    M = _mc({"B": 1.0, "flicker_tau_min_s": 4.0, "flicker_tau_max_s": 1.0e4}, fs, 120, 9000)
    n = len(M)
    emp = M.T @ M / n
    C = sc.cov_flicker(A, B, sc.flicker_bank(4.0, 1.0e4))
    D = np.eye(6)[1:] - np.eye(6)[:-1]
    zd = _z(D @ emp @ D.T, D @ C @ D.T, n)
    assert np.max(np.abs(zd)) < 4.0, np.round(zd, 2)
    # the common (slow) part: mean of all elements; its estimate has ~n independent samples
    level = emp.mean() / C.mean()
    assert abs(level - 1.0) < 4.0 * np.sqrt(2.0 / n), level
    # and the diagonal: each window's own variance
    zd = _z(emp, C, n)
    assert np.max(np.abs(np.diag(zd))) < 4.0, np.round(np.diag(zd), 2)


def test_expected_batch_variance():
    """E[var(8 batch means)/8] for white noise is the variance of the window mean, N^2/T; for a
    slow process it is far below the window's true variance (the batch means move together)."""
    ba, bb = sc.batch_windows(np.array([0.0, 100.0]), np.array([30.0, 110.0]), 8)
    white = sc.expected_batch_var(np.stack([np.diag(8.0 / np.array([30.0] * 8)), np.diag(8.0 / np.array([10.0] * 8))]))
    np.testing.assert_allclose(white, [1 / 30.0, 1 / 10.0])
    rw = sc.expected_batch_var(sc.cov_random_walk(ba, bb))
    assert np.all(rw < 0.2 * np.diag(sc.cov_random_walk([0.0, 100.0], [30.0, 110.0])))


def test_gls_equals_closed_form_and_ignores_a_common_constant():
    rng = np.random.default_rng(3)
    K = len(A)
    X = np.column_stack([np.ones(K), rng.normal(size=K), rng.normal(size=K)])  # bias + 2 regressors
    C = NoiseCoefficients(N=0.3, B=0.2, K=0.01).cov(A, B)
    y = X @ [1.0, 2.0, -1.0] + np.linalg.cholesky(C) @ rng.normal(size=K)
    res = fit_linear(X, y, np.sqrt(np.diag(C)), ["b", "c", "d"], cov=C, rescale_if_poor=False)
    Ci = np.linalg.inv(C)
    cov = np.linalg.inv(X.T @ Ci @ X)
    np.testing.assert_allclose(res.covariance, cov, rtol=1e-8)
    np.testing.assert_allclose(res.values, cov @ X.T @ Ci @ y, rtol=1e-8)
    r = y - X @ res.values
    assert np.isclose(res.chi2, r @ Ci @ r) and res.dof == K - 3
    # Sigma + c 1 1^T: same estimates (except the bias' variance, + c) and the same chi2
    c = 7.0
    res2 = fit_linear(X, y, np.sqrt(np.diag(C) + c), ["b", "c", "d"], cov=C + c, rescale_if_poor=False)
    np.testing.assert_allclose(res2.values, res.values, rtol=1e-8)
    assert np.isclose(res2.chi2, res.chi2, rtol=1e-8)
    expect = res.covariance.copy()
    expect[0, 0] += c
    np.testing.assert_allclose(res2.covariance, expect, rtol=1e-7, atol=1e-12)
