"""The calibration's sensor model, inverted: true inputs from measured outputs, per sample (SI).

The model ``rigctl calibrate`` fits (docs/calibration.md), with ``o`` element-wise::

    accelerometer  A = b_a + M_a a + k2 o (a o a)
    gyro           W = b_g + M_g w + G a

and the thermal model (:mod:`rigctl.solvers.thermal`), where b and M are functions of each
sample's temperature (one b and M per sample) and only the accelerometer has a k2 term.

:func:`invert_quadratic` solves ``y = b + M u + k2 o u^2`` for u by Newton's method, vectorised
over samples::

    u_0 = M^-1 (y - b),   u_{k+1} = u_k - J_k^-1 r_k,
    r_k = b + M u_k + k2 o u_k^2 - y,   J_k = M + diag(2 k2 o u_k)

(k2 |u| ~ 1e-4 at most, so a few iterations reach float64 precision; the iteration stops when the
largest step is below 1e-12 in the unit of u). :func:`invert_gyro` is then w = M_g^-1 (W - b_g - G a)
with the accelerometer's a. Used by ``rigctl apply-cal`` (:mod:`rigctl.analysis.apply_cal`) and
the thermal correction (:func:`rigctl.solvers.thermal.correct`).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def invert_quadratic(y: NDArray[np.float64], b: NDArray[np.float64], M: NDArray[np.float64],
                     k2: NDArray[np.float64], max_iter: int = 20) -> NDArray[np.float64]:
    """True input u (n, 3) from measured y (n, 3) (module docstring). M: (3, 3), the same for
    every sample, or (n, 3, 3), one per sample; b: (3,) or (n, 3); k2: (3,), zeros for none."""
    per_sample = M.ndim == 3
    if per_sample:
        u = np.linalg.solve(M, (y - b)[..., None])[..., 0]
    else:
        u = (y - b) @ np.linalg.inv(M).T
    if not np.any(k2):
        return u
    J0 = M if per_sample else np.broadcast_to(M, (len(u), 3, 3))
    for _ in range(max_iter):
        Mu = (M @ u[..., None])[..., 0] if per_sample else u @ M.T
        r = b + Mu + k2 * u * u - y
        J = J0.copy()
        J[:, [0, 1, 2], [0, 1, 2]] += 2.0 * k2 * u
        step = np.linalg.solve(J, r[..., None])[..., 0]
        u = u - step
        if np.max(np.abs(step), initial=0.0) < 1e-12:
            break
    return u


def invert_gyro(W: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64],
                M: NDArray[np.float64], G: NDArray[np.float64]) -> NDArray[np.float64]:
    """True rate w = M^-1 (W - b - G a), (n, 3), from measured W and true specific force a."""
    return (W - b - a @ G.T) @ np.linalg.inv(M).T
