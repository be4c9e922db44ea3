"""The Allan fit's bounded least squares (rigctl.solvers.allan_fit._nnls_cols) keeps every
coefficient in [0, its upper bound] exactly, in the caller's units, so that the admissible
completion of the self-check (_admissible_completion) clips once, there, and not again.

Before, the solver's answer was clipped on the scaled columns and then divided by the scale:
(u s) / s can round one unit in the last place above u, and on these 200 random problems with
the bound active 32 answers were above their bound (the completion clipped a second time).
The expected solution comes from scipy's bounded least squares on the unscaled problem.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

from rigctl.solvers.allan_fit import _nnls_cols


def _problems(n: int = 200):
    """Columns of scales 1e-8 .. 1e8 (the IEEE 952 terms' columns differ by decades), a target
    that wants more than the bounds allow (the bounds active)."""
    rng = np.random.default_rng(5)
    for _ in range(n):
        a = rng.standard_normal((30, 4)) * 10.0 ** rng.uniform(-8, 8, 4)
        p_true = rng.uniform(0.0, 1.0, 4) / np.linalg.norm(a, axis=0)
        yield a, a @ p_true * 3.0, p_true * rng.uniform(0.1, 1.0, 4)


def test_every_coefficient_lies_within_its_bound_exactly():
    over = under = 0
    for a, b, up in _problems():
        p = _nnls_cols(a, b, up)
        over += int(np.any(p > up))
        under += int(np.any(p < 0.0))
    assert (over, under) == (0, 0)


def test_the_solution_is_the_bounded_least_squares_one():
    """Same answer as the bounded least squares solved directly (columns scaled to unit norm
    here too, so that the reference is well conditioned): 1e-9 relative to the bound."""
    for a, b, up in _problems(40):
        s = np.linalg.norm(a, axis=0)
        ref = lsq_linear(a / s, b, bounds=(0.0, up * s), method="trf", tol=1e-14).x / s
        np.testing.assert_allclose(_nnls_cols(a, b, up), ref, rtol=0.0, atol=1e-9 * up.max())

