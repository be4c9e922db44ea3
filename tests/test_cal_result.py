"""CalibrationResult and the weighted least-squares core."""
from __future__ import annotations

import json

import numpy as np
import scipy.stats

from rigctl.solvers.calibration_result import CalibrationResult, fit_linear, format_table


def test_fit_linear_matches_closed_form_and_reports_everything():
    rng = np.random.default_rng(0)
    n = 50
    x = np.linspace(-1, 1, n)
    X = np.stack([np.ones(n), x], axis=1)
    s = rng.uniform(0.5, 2.0, n)
    y = X @ [1.0, -2.0] + rng.normal(0, s)
    res = fit_linear(X, y, s, ["offset_m", "slope_m_per_s"])
    W = np.diag(1 / s**2)
    cov = np.linalg.inv(X.T @ W @ X)
    np.testing.assert_allclose(res.values, cov @ X.T @ W @ y, rtol=1e-10)
    np.testing.assert_allclose(res.covariance, cov, rtol=1e-10)
    assert res.dof == 48 and res.interval == "normal"
    np.testing.assert_allclose(res.chi2, np.sum(((y - X @ res.values) / s) ** 2))
    np.testing.assert_allclose(res.ci95[:, 1] - res.values, 1.959964 * res.sigma, rtol=1e-6)
    c = res.correlation
    assert np.allclose(np.diag(c), 1) and np.isclose(c[0, 1], cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1]))
    d = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert [p["name"] for p in d["parameters"]] == ["offset_m", "slope_m_per_s"]
    assert d["dof"] == 48 and len(d["residuals"]) == n
    assert "slope_m_per_s" in format_table(res)


def test_poor_fit_inflates_covariance_and_uses_t():
    rng = np.random.default_rng(1)
    n = 12
    X = np.stack([np.ones(n), np.arange(n)], axis=1)
    y = X @ [0.0, 1.0] + rng.normal(0, 10.0, n)  # the claimed sigma (1.0) is 10x too small
    res = fit_linear(X, y, np.ones(n), ["a_1", "b_1"])
    assert res.status == "poor_fit" and res.interval == "t" and res.warnings
    raw = np.linalg.inv(X.T @ X)
    np.testing.assert_allclose(res.covariance, raw * res.chi2 / res.dof, rtol=1e-9)
    assert np.isclose(res.coverage_factor, scipy.stats.t.ppf(0.975, 10))


def test_rank_deficient_design_is_flagged():
    X = np.stack([np.ones(6), np.ones(6) * 2.0, np.arange(6.0)], axis=1)
    res = fit_linear(X, np.arange(6.0), np.ones(6), ["a", "b", "c"])
    assert res.status == "underdetermined" and "rank 2 < 3" in res.warnings[0]
    assert np.isnan(res.values).sum() == 1


def test_result_validates_shapes():
    try:
        CalibrationResult("m", ["a"], np.zeros(2), np.eye(2), 1, 0.0)
    except ValueError:
        pass
    else:  # pragma: no cover
        raise AssertionError("shape mismatch accepted")


def test_truth_from_emulator_names_match_the_solvers():
    from rigctl.solvers.closed_loop import declared_design
    from rigctl.solvers.segments import truth_from_emulator
    from test_cal_synth import make_session

    params = {"accel_bias_m_per_s2": [0.01, 0.02, 0.03], "accel_turn_on_bias_m_per_s2": [0.001, 0, 0],
              "accel_scale_misalignment_matrix": np.eye(3).tolist(), "accel_quadratic_per_m_per_s2": [1e-5] * 3,
              "gyro_bias_rad_per_s": [1e-4, 0, 0], "gyro_turn_on_bias_rad_per_s": None,
              "gyro_scale_misalignment_matrix": (np.eye(3) * 1.001).tolist()}
    t = truth_from_emulator(params)
    st, _ = make_session(0, ramps=False)
    _, names = declared_design(st)
    assert set(t) == set(names)
    assert np.isclose(t["accel_bias_x_m_s2"], 0.011) and t["gyro_M_zz_ratio"] == 1.001
