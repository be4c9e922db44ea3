"""rigctl.solvers.distributions against scipy.stats: every method the solvers call, bit for bit,
on grids that cover the solvers' arguments (probabilities 1e-300 .. 1 - 1e-16, degrees of
freedom 0.5 .. 1e7 and inf, statistics 0 .. 1e6), the ends of the support, q = 0 and 1, NaN,
invalid degrees of freedom and arrays broadcast against each other."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from rigctl.solvers import distributions as D

Q = np.array([0.0, 1e-300, 1e-30, 1e-12, 1e-6, 0.001, 0.0125, 0.025, 0.05, 0.1, 0.25, 0.5,
              0.6, 0.75, 0.9, 0.95, 0.975, 0.9875, 0.999, 1 - 1e-9, 1 - 1e-16, 1.0, -0.1, 1.1,
              np.nan])
X = np.array([-np.inf, -1e6, -40.0, -5.0, -1.0, -1e-300, -0.0, 0.0, 1e-300, 1e-8, 0.01, 0.5,
              1.0, 1.96, 3.0, 7.5, 40.0, 300.0, 1e4, 1e6, np.inf, np.nan])
DF = np.array([0.5, 1.0, 2.0, 3.0, 7.0, 12.5, 39.0, 100.0, 1e3, 1e5, 1e7, np.inf, 0.0, -1.0,
               np.nan])


def same(a, b) -> None:
    """Equal bit for bit (NaN where NaN, the sign of zero too), same type and shape."""
    assert type(a) is type(b), (type(a), type(b))
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype
    assert np.array_equal(a.view(np.int64), b.view(np.int64)), np.stack([a.ravel(), b.ravel()])


@pytest.mark.parametrize("method", ["cdf", "sf", "pdf"])
def test_norm_at_x(method: str) -> None:
    same(getattr(D.norm, method)(X), getattr(stats.norm, method)(X))
    for x in X:
        same(getattr(D.norm, method)(float(x)), getattr(stats.norm, method)(float(x)))


@pytest.mark.parametrize("method", ["ppf", "isf"])
def test_norm_at_q(method: str) -> None:
    same(getattr(D.norm, method)(Q), getattr(stats.norm, method)(Q))
    for q in Q:
        same(getattr(D.norm, method)(q), getattr(stats.norm, method)(q))


@pytest.mark.parametrize("name, methods", [("t", ("cdf", "sf")), ("chi2", ("sf",))])
def test_one_shape_at_x(name: str, methods: tuple[str, ...]) -> None:
    ours, ref = getattr(D, name), getattr(stats, name)
    xx, dd = np.meshgrid(X, DF)
    for m in methods:
        same(getattr(ours, m)(xx, dd), getattr(ref, m)(xx, dd))
        same(getattr(ours, m)(X, 7.0), getattr(ref, m)(X, 7.0))
        same(getattr(ours, m)(1.5, DF), getattr(ref, m)(1.5, DF))
        same(getattr(ours, m)(2.5, 4), getattr(ref, m)(2.5, 4))  # Python scalars, integer df


@pytest.mark.parametrize("name, methods", [("t", ("ppf",)), ("chi2", ("ppf", "isf"))])
def test_one_shape_at_q(name: str, methods: tuple[str, ...]) -> None:
    ours, ref = getattr(D, name), getattr(stats, name)
    qq, dd = np.meshgrid(Q, DF)
    for m in methods:
        same(getattr(ours, m)(qq, dd), getattr(ref, m)(qq, dd))
        same(getattr(ours, m)([0.025, 0.975], 9), getattr(ref, m)([0.025, 0.975], 9))
        same(getattr(ours, m)(0.975, 5), getattr(ref, m)(0.975, 5))
        same(getattr(ours, m)(0.975, np.int64(5)), getattr(ref, m)(0.975, np.int64(5)))
    for df in DF:
        same(D.chi2.median(df), stats.chi2.median(df))


def test_f() -> None:
    xx, d1, d2 = np.meshgrid(X, DF[:9], DF)
    same(D.f.sf(xx, d1, d2), stats.f.sf(xx, d1, d2))
    qq, d1, d2 = np.meshgrid(Q, DF[:9], DF)
    same(D.f.ppf(qq, d1, d2), stats.f.ppf(qq, d1, d2))
    same(D.f.isf(qq, d1, d2), stats.f.isf(qq, d1, d2))
    same(D.f.sf(2.5, 3, 17), stats.f.sf(2.5, 3, 17))
    same(D.f.ppf(0.05, 3, 17), stats.f.ppf(0.05, 3, 17))
