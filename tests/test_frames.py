"""Reference model against hand-worked cases (docs/methods.md A3)."""
import math

import numpy as np
import pytest

from rigctl.frames import (EARTH_RATE_RAD_S, body_references, gimbal_dcm, gimbal_rate_body,
                           normal_gravity, north_pointing_angles)

LAT = math.radians(40.0)


@pytest.mark.parametrize("phi_deg", [0, 45, 90, 135, 180, 225, 270, 315])
def test_x_north_rotation_about_x_matches_methods_a3(phi_deg):
    # docs/methods.md A3: X north, rotation phi about X: f = g (0, sin phi, cos phi),
    # Earth rate (W cos L, W sin L sin phi, W sin L cos phi).
    phi = math.radians(phi_deg)
    g = 9.8
    f, w = body_references(north_pointing_angles("x", phi), latitude_rad=LAT, g=g)
    np.testing.assert_allclose(f, g * np.array([0.0, math.sin(phi), math.cos(phi)]), atol=1e-12)
    W = EARTH_RATE_RAD_S
    expected = [W * math.cos(LAT), W * math.sin(LAT) * math.sin(phi), W * math.sin(LAT) * math.cos(phi)]
    np.testing.assert_allclose(w, expected, atol=1e-18)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_named_axis_points_north_and_is_the_rotation_axis(axis):
    col = "xyz".index(axis)
    for phi in np.radians(np.arange(0, 360, 45)):
        c = gimbal_dcm(north_pointing_angles(axis, phi))
        np.testing.assert_allclose(c[:, col], [0.0, 1.0, 0.0], atol=1e-12)  # axis -> North
        f, _ = body_references(north_pointing_angles(axis, phi), g=1.0)
        assert abs(f[col]) < 1e-12  # horizontal axis senses no gravity
        np.testing.assert_allclose(np.linalg.norm(f), 1.0)


def test_24_positions_put_0707g_on_two_axes():
    g = 9.8
    fs = np.array([body_references(north_pointing_angles(a, math.radians(p)), g=g)[0]
                   for a in "xyz" for p in range(0, 360, 45)])
    assert fs.shape == (24, 3)
    diag = np.sum(np.isclose(np.abs(fs), g * math.sqrt(0.5)).all(axis=1) |
                  (np.isclose(np.abs(fs), g * math.sqrt(0.5)).sum(axis=1) == 2))
    assert diag == 12  # the odd-multiple-of-45 positions excite two axes at once
    # every axis sees +g and -g exactly once per rotation about another axis
    for col in range(3):
        assert np.sum(np.isclose(fs[:, col], g)) == 2 and np.sum(np.isclose(fs[:, col], -g)) == 2


def test_dcm_is_orthonormal_and_zero_is_enu():
    rng = np.random.default_rng(0)
    a = rng.uniform(-np.pi, np.pi, (100, 3))
    c = gimbal_dcm(a)
    np.testing.assert_allclose(c @ np.swapaxes(c, -1, -2), np.broadcast_to(np.eye(3), c.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(c), 1.0)
    np.testing.assert_allclose(gimbal_dcm([0, 0, 0]), np.eye(3))


def test_gimbal_rate_body_matches_numerical_derivative():
    rng = np.random.default_rng(1)
    a0 = rng.uniform(-1, 1, 3)
    rates = rng.uniform(-1, 1, 3)
    h = 1e-6
    c0, c1 = gimbal_dcm(a0 - rates * h), gimbal_dcm(a0 + rates * h)
    cdot = (c1 - c0) / (2 * h)
    omega_skew = gimbal_dcm(a0).T @ cdot  # C^T Cdot = [w x] in the body frame
    w_num = np.array([omega_skew[2, 1], omega_skew[0, 2], omega_skew[1, 0]])
    np.testing.assert_allclose(gimbal_rate_body(a0, rates), w_num, atol=1e-8)


def test_normal_gravity_known_values():
    # WGS-84 normal gravity on the ellipsoid: equator 9.7803253 m/s^2, pole 9.8321849 m/s^2
    assert normal_gravity(0.0) == pytest.approx(9.7803253359, abs=1e-9)
    assert normal_gravity(math.pi / 2) == pytest.approx(9.8321849378, abs=1e-7)
    # free-air gradient about -3.086e-6 s^-2
    assert (normal_gravity(LAT, 1000.0) - normal_gravity(LAT)) == pytest.approx(-3.086e-3, rel=2e-3)


def test_rotation_matrices_are_the_row_formula_bit_for_bit():
    """frames._rot fills its matrices in place (the emulator builds them at every poll); it must
    give the values and the memory layout (hence the matmul path and its rounding) of the plain
    formula: the rows as nested lists, moved to the last two axes."""
    from rigctl.frames import _rot

    rng = np.random.default_rng(5)
    for shape in ((), (1,), (7,), (4, 3)):
        th = rng.uniform(-7.0, 7.0, shape)
        c, s = np.cos(th), np.sin(th)
        one, zero = np.ones_like(th), np.zeros_like(th)
        rows = {"x": [[one, zero, zero], [zero, c, -s], [zero, s, c]],
                "y": [[c, zero, s], [zero, one, zero], [-s, zero, c]],
                "z": [[c, -s, zero], [s, c, zero], [zero, zero, one]]}
        for axis, r in rows.items():
            want = np.moveaxis(np.array(r, dtype=np.float64), (0, 1), (-2, -1))
            got = _rot(axis, th)
            assert got.shape == want.shape and got.strides == want.strides
            assert got.tobytes() == want.tobytes()
