"""apply-cal's per-sample inversion of the sensor model, against the forward model."""
from __future__ import annotations

import numpy as np

from rigctl.solvers.sensor_model import invert_gyro, invert_quadratic


def test_newton_inverts_the_accelerometer_model_with_quadratic_terms():
    rng = np.random.default_rng(7)
    a = rng.normal(0, 15.0, (5000, 3))  # up to ~5 g
    b = rng.normal(0, 0.05, 3)
    M = np.eye(3) + rng.normal(0, 3e-3, (3, 3))
    k2 = rng.normal(0, 3e-4, 3)  # 3 mg/g^2: far above real parts, to exercise the iteration
    A = b + a @ M.T + k2 * a * a
    back = invert_quadratic(A, b, M, k2)
    np.testing.assert_allclose(back, a, atol=1e-10)
    linear = (A - b) @ np.linalg.inv(M).T
    assert np.max(np.abs(linear - a)) > 1e-3  # the quadratic term matters, Newton removes it


def test_gyro_inversion_removes_g_sensitivity():
    rng = np.random.default_rng(8)
    w, a = rng.normal(0, 1.0, (1000, 3)), rng.normal(0, 9.8, (1000, 3))
    b, M, G = rng.normal(0, 1e-3, 3), np.eye(3) + rng.normal(0, 1e-3, (3, 3)), rng.normal(0, 1e-5, (3, 3))
    W = b + w @ M.T + a @ G.T
    np.testing.assert_allclose(invert_gyro(W, a, b, M, G), w, atol=1e-12)
