"""The normal, Student t, chi-square and F distribution functions the solvers use, without
importing scipy.stats.

``import scipy.stats`` costs ~0.45 s of CPU per process beyond scipy.linalg (its ~100
distributions, scipy.interpolate, scipy.spatial, ...), paid by every ``rigctl calibrate``,
``allan``, ``report``, ``history`` and ``batch`` process, while the solvers need only a few
functions of four distributions. This module gives them with scipy.stats' own arithmetic: each
method is the scipy.special function that scipy.stats' distribution calls (scipy 1.17,
``scipy/stats/_continuous_distns.py``), wrapped as ``rv_continuous`` wraps it for loc = 0,
scale = 1 (``_distn_infrastructure.py``): the same values at the same arguments, bit for bit,
including the support's ends, q = 0 and 1, NaN and invalid shapes (NaN); a 0-d result is a numpy
scalar, as there. tests/test_distributions.py compares every method with scipy.stats.

    norm:  cdf = ndtr(x), sf = ndtr(-x), ppf = ndtri(q), isf = -ndtri(q),
           pdf = exp(-x^2 / 2) / sqrt(2 pi)
    t:     cdf = stdtr(df, x), sf = stdtr(df, -x), ppf = stdtrit(df, q)
    chi2:  sf = chdtrc(df, x), ppf = 2 gammaincinv(df / 2, q), isf = chdtri(df, q),
           median = ppf(0.5)
    f:     sf = fdtrc(dfn, dfd, x), ppf = fdtri(dfn, dfd, q), isf = ppf(1 - q)
"""
from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
from scipy import special as sc

_NORM_PDF_C = np.sqrt(2 * np.pi)  # scipy.stats' _norm_pdf_C


class _Continuous:
    """One distribution on the support (a, b) with positive shape parameters: the generic
    wrappers of scipy.stats' rv_continuous (loc 0, scale 1) around the kernels below."""

    def __init__(self, a: float, b: float, nshapes: int,
                 cdf: Callable | None = None, sf: Callable | None = None,
                 ppf: Callable | None = None, isf: Callable | None = None,
                 pdf: Callable | None = None) -> None:
        self.a, self.b, self.nshapes = a, b, nshapes
        self._cdf, self._sf, self._ppf, self._isf, self._pdf = cdf, sf, ppf, isf, pdf

    def _shapes_ok(self, args: tuple) -> Any:
        assert len(args) == self.nshapes, f"{self.nshapes} shape parameters expected"
        ok = np.asarray(True)
        for s in args:
            ok = ok & (np.asarray(s) > 0)
        return ok

    @staticmethod
    def _result(out: np.ndarray) -> Any:
        return out[()] if out.ndim == 0 else out

    def _at_x(self, kernel: Callable, x: Any, args: tuple, below: float, above: float) -> Any:
        """cdf / sf: the kernel inside the open support, ``below`` at x <= a (sf: 1), ``above``
        at x >= b (cdf: 1), else 0; NaN for NaN x or invalid shapes."""
        x = np.asarray(x)
        x = np.asarray(x - 0, dtype=np.promote_types(x.dtype, np.float64))
        args = tuple(np.asarray(s) for s in args)
        ok = self._shapes_ok(args)
        inside = ok & (self.a < x) & (x < self.b)
        shape = np.broadcast_shapes(np.shape(inside), np.shape(x))
        out = np.zeros(shape, x.dtype)
        with np.errstate(all="ignore"):
            val = np.broadcast_to(kernel(x, *args), shape) if np.any(inside) else out
        out = np.where(~ok | np.isnan(x), np.nan, out)
        if below:
            out = np.where(ok & (x <= self.a), below, out)
        if above:
            out = np.where(ok & (x >= self.b), above, out)
        return self._result(np.asarray(np.where(inside, val, out), dtype=x.dtype))

    def _at_q(self, kernel: Callable, q: Any, args: tuple, at0: float, at1: float) -> Any:
        """ppf / isf: kernel(q) * 1 + 0 for 0 < q < 1 (scipy.stats' scale and loc), ``at0`` at
        q = 0, ``at1`` at q = 1, else NaN."""
        q = np.asarray(q)
        args = tuple(np.asarray(s) for s in args)
        ok = self._shapes_ok(args)
        inside = ok & (0 < q) & (q < 1)
        shape = np.shape(inside)
        out = np.full(shape, np.nan)
        out = np.where(ok & (q == 0), at0, out)
        out = np.where(ok & (q == 1), at1, out)
        if np.any(inside):
            with np.errstate(all="ignore"):
                val = np.broadcast_to(np.asarray(kernel(q, *args) * 1 + 0, dtype=float), shape)
            out = np.where(inside, val, out)
        return self._result(np.asarray(out, dtype=float))

    def cdf(self, x: Any, *args: Any) -> Any:
        return self._at_x(self._cdf, x, args, 0.0, 1.0)

    def sf(self, x: Any, *args: Any) -> Any:
        return self._at_x(self._sf, x, args, 1.0, 0.0)

    def ppf(self, q: Any, *args: Any) -> Any:
        return self._at_q(self._ppf, q, args, self.a, self.b)

    def isf(self, q: Any, *args: Any) -> Any:
        return self._at_q(self._isf, q, args, self.b, self.a)

    def median(self, *args: Any) -> Any:
        return self.ppf(0.5, *args)

    def pdf(self, x: Any, *args: Any) -> Any:
        """The density on the closed support, 0 outside, NaN for NaN x or invalid shapes."""
        x = np.asarray(x)
        x = np.asarray(x - 0, dtype=np.promote_types(x.dtype, np.float64))
        args = tuple(np.asarray(s) for s in args)
        ok = self._shapes_ok(args)
        inside = ok & (self.a <= x) & (x <= self.b)
        shape = np.broadcast_shapes(np.shape(inside), np.shape(x))
        with np.errstate(all="ignore"):
            val = np.broadcast_to(self._pdf(x, *args) / 1, shape)
        out = np.where(~ok | np.isnan(x), np.nan, np.zeros(shape, x.dtype))
        return self._result(np.asarray(np.where(inside, val, out), dtype=x.dtype))


#: the standard normal distribution (scipy.stats.norm)
norm = _Continuous(-math.inf, math.inf, 0, cdf=sc.ndtr, sf=lambda x: sc.ndtr(-x), ppf=sc.ndtri,
                   isf=lambda q: -sc.ndtri(q), pdf=lambda x: np.exp(-x**2 / 2.0) / _NORM_PDF_C)
#: Student's t distribution, t.<method>(x or q, df) (scipy.stats.t)
t = _Continuous(-math.inf, math.inf, 1, cdf=lambda x, df: sc.stdtr(df, x),
                sf=lambda x, df: sc.stdtr(df, -x), ppf=lambda q, df: sc.stdtrit(df, q))
#: the chi-square distribution, chi2.<method>(x or q, df) (scipy.stats.chi2)
chi2 = _Continuous(0.0, math.inf, 1, sf=lambda x, df: sc.chdtrc(df, x),
                   ppf=lambda q, df: 2 * sc.gammaincinv(df / 2, q),
                   isf=lambda q, df: sc.chdtri(df, q))
#: the F distribution, f.<method>(x or q, dfn, dfd) (scipy.stats.f)
f = _Continuous(0.0, math.inf, 2, sf=lambda x, dfn, dfd: sc.fdtrc(dfn, dfd, x),
                ppf=lambda q, dfn, dfd: sc.fdtri(dfn, dfd, q),
                isf=lambda q, dfn, dfd: sc.fdtri(dfn, dfd, 1.0 - q))
