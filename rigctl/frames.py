"""Reference model: table gimbal kinematics, normal gravity and Earth rate.

Frames (see docs/frames.md):

* **n** -- local East-North-Up (ENU) navigation frame at the site.
* **b** -- IMU body frame. The IMU's x, y, z input axes are parallel to the table's inner,
  middle and outer gimbal axes, and the table is levelled and north-found, so at zero angles
  the body frame *is* ENU (x East, y North, z Up).

Gimbal order: the outer axis is vertical (about n-z), it carries the middle axis (about y of the
outer gimbal), which carries the inner axis (about x of the middle gimbal). The body-to-nav
direction cosine matrix is

    C_b^n = R_z(outer) @ R_y(middle) @ R_x(inner)

with R_a(theta) the right-handed (active) rotation about axis a by theta.

At rest the accelerometers sense the specific force f^n = (0, 0, +g) (reaction to gravity, up)
and the gyros the Earth rate Omega^n = Omega_E (0, cos L, sin L). In the body frame

    f^b = (C_b^n)^T f^n,    w^b = (C_b^n)^T Omega^n + w_table^b.

All functions are pure and vectorised over leading dimensions. Angles in rad, rates in rad/s,
specific force in m/s^2.
"""
from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Earth rotation rate, rad/s (WGS-84).
EARTH_RATE_RAD_S: float = 7.292115e-5
#: WGS-84 semi-major axis (m), flattening, and the Somigliana constants.
_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563
_WGS84_GE = 9.7803253359  # normal gravity at the equator, m/s^2
_WGS84_K = 0.00193185265241  # Somigliana constant
_WGS84_E2 = 0.00669437999013  # first eccentricity squared
_WGS84_M = 0.00344978650684  # omega^2 a^2 b / GM

#: Gimbal axes in order [outer, middle, inner] and the body axes they rotate about.
GIMBAL_AXES: tuple[str, str, str] = ("z", "y", "x")


def _rot(axis: str, theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Active right-handed rotation matrices about ``axis`` for angles ``theta`` (rad)."""
    theta = np.asarray(theta)
    c, s = np.cos(theta), np.sin(theta)
    if axis == "x":
        i, j = 1, 2
    elif axis == "y":
        i, j = 2, 0
    elif axis == "z":
        i, j = 0, 1
    else:  # pragma: no cover - internal
        raise ValueError(axis)
    # the (3, 3, ...) array of rows filled in place, then viewed as (..., 3, 3): the same values
    # and the same memory layout (so the same matmul path) as np.array(rows) + np.moveaxis, at a
    # fraction of the per-call cost (the emulator builds these at every poll)
    m = np.zeros((3, 3) + c.shape)
    m[3 - i - j, 3 - i - j] = 1.0
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m.transpose(tuple(range(2, m.ndim)) + (0, 1))


def gimbal_dcm(angles: ArrayLike) -> NDArray[np.float64]:
    """Body-to-ENU direction cosine matrix C_b^n for table angles.

    Args:
        angles: (..., 3) gimbal angles [outer, middle, inner], rad.

    Returns:
        (..., 3, 3) matrix with C_b^n = R_z(outer) R_y(middle) R_x(inner).
    """
    a = np.asarray(angles, dtype=np.float64)
    if a.shape[-1] != 3:
        raise ValueError("angles must have a last dimension of 3 [outer, middle, inner]")
    return _rot("z", a[..., 0]) @ _rot("y", a[..., 1]) @ _rot("x", a[..., 2])


def normal_gravity(latitude_rad: float, height_m: float = 0.0) -> float:
    """WGS-84 normal gravity (Somigliana, with the free-air height correction), m/s^2.

        g0(L) = g_e (1 + k sin^2 L) / sqrt(1 - e^2 sin^2 L)
        g(L, h) = g0 [1 - 2/a (1 + f + m - 2 f sin^2 L) h + 3 h^2 / a^2]
    """
    s2 = np.sin(latitude_rad) ** 2
    g0 = _WGS84_GE * (1.0 + _WGS84_K * s2) / np.sqrt(1.0 - _WGS84_E2 * s2)
    corr = 1.0 - 2.0 / _WGS84_A * (1.0 + _WGS84_F + _WGS84_M - 2.0 * _WGS84_F * s2) * height_m
    return float(g0 * (corr + 3.0 * height_m**2 / _WGS84_A**2))


def earth_rate_enu(latitude_rad: float) -> NDArray[np.float64]:
    """Earth rate in ENU, rad/s: Omega_E (0, cos L, sin L)."""
    return EARTH_RATE_RAD_S * np.array([0.0, np.cos(latitude_rad), np.sin(latitude_rad)])


@functools.lru_cache(maxsize=16)
def _normal_gravity_cached(latitude_rad: float, height_m: float) -> float:
    """:func:`normal_gravity`, once per site (body_references runs at every emulator poll)."""
    return normal_gravity(latitude_rad, height_m)


@functools.lru_cache(maxsize=16)
def _earth_rate_cached(latitude_rad: float) -> NDArray[np.float64]:
    """:func:`earth_rate_enu`, once per latitude, read-only (it is shared)."""
    w = earth_rate_enu(latitude_rad)
    w.flags.writeable = False
    return w


def gimbal_rate_body(angles: ArrayLike, gimbal_rates: ArrayLike) -> NDArray[np.float64]:
    """Angular rate of the body relative to the (non-rotating) table base, in the body frame.

    With gimbal rates (d outer, d middle, d inner) in rad/s:

        w^b = R_x(i)^T R_y(m)^T (0,0,d_o) + R_x(i)^T (0,d_m,0) + (d_i,0,0)

    Args:
        angles: (..., 3) [outer, middle, inner], rad.
        gimbal_rates: (..., 3) time derivatives of the angles, rad/s.
    """
    a = np.asarray(angles, dtype=np.float64)
    r = np.asarray(gimbal_rates, dtype=np.float64)
    rx_t = np.swapaxes(_rot("x", a[..., 2]), -1, -2)
    ry_t = np.swapaxes(_rot("y", a[..., 1]), -1, -2)
    # (..., 3) vectors with one gimbal rate each (np.zeros + one column: the C-ordered arrays
    # np.stack made, cheaper)
    w_outer, w_middle, w_inner = np.zeros(r.shape), np.zeros(r.shape), np.zeros(r.shape)
    w_outer[..., 2], w_middle[..., 1], w_inner[..., 0] = r[..., 0], r[..., 1], r[..., 2]
    return (
        np.einsum("...ij,...jk,...k->...i", rx_t, ry_t, w_outer)
        + np.einsum("...ij,...j->...i", rx_t, w_middle)
        + w_inner
    )


def body_references(
    angles: ArrayLike,
    gimbal_rates: ArrayLike | None = None,
    latitude_rad: float = 0.0,
    height_m: float = 0.0,
    g: float | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """True specific force and angular rate in the body frame.

    Static or constant-rate table, IMU at the rotation centre (no lever arm):

        f^b = (C_b^n)^T (0, 0, g)
        w^b = (C_b^n)^T Omega_E (0, cos L, sin L) + w_table^b

    Args:
        angles: (..., 3) gimbal angles [outer, middle, inner], rad.
        gimbal_rates: (..., 3) gimbal angle rates, rad/s (None: static).
        latitude_rad: site latitude, rad.
        height_m: site ellipsoidal height, m.
        g: measured local gravity, m/s^2; None uses WGS-84 normal gravity.

    Returns:
        (f_b, w_b): (..., 3) specific force in m/s^2 and angular rate in rad/s.
    """
    c_bn = gimbal_dcm(angles)
    try:  # once per site (a hashable latitude and height: the usual floats)
        g_site = _normal_gravity_cached(latitude_rad, height_m)
        w_site = _earth_rate_cached(latitude_rad)
    except TypeError:
        g_site, w_site = normal_gravity(latitude_rad, height_m), earth_rate_enu(latitude_rad)
    g_val = g_site if g is None else float(g)
    c_nb = np.swapaxes(c_bn, -1, -2)
    f_b = c_nb @ np.array([0.0, 0.0, g_val])
    w_b = c_nb @ w_site
    if gimbal_rates is not None:
        w_b = w_b + gimbal_rate_body(angles, gimbal_rates)
    return f_b, w_b


def north_pointing_angles(axis: str, phi_rad: float) -> tuple[float, float, float]:
    """Gimbal angles [outer, middle, inner] (rad) pointing body ``axis`` north, rotated by phi.

    The unit is turned so that the named input axis lies horizontal and north, then rotated
    about that axis by ``phi`` (right-handed):

    * x north: outer = +90 deg, inner = phi     -> f^b = g (0, sin phi, cos phi)
    * y north: middle = phi                      -> f^b = g (-sin phi, 0, cos phi)
    * z north: inner = -90 deg, middle = phi     -> f^b = g (-sin phi, -cos phi, 0)
    """
    half_pi = np.pi / 2.0
    if axis == "x":
        return (half_pi, 0.0, phi_rad)
    if axis == "y":
        return (0.0, phi_rad, 0.0)
    if axis == "z":
        return (0.0, phi_rad, -half_pi)
    raise ValueError(f"axis must be 'x', 'y' or 'z', not {axis!r}")
