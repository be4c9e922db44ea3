"""IEEE Std 952 noise terms from an Allan deviation curve: joint weighted least squares.

Model (IEEE Std 952-1997 annex C; rate units u, e.g. rad/s or m/s^2)::

    sigma^2(tau) = 3 Q^2 / tau^2 + N^2 / tau + (2 ln2 / pi) B^2 + K^2 tau / 3 + R^2 tau^2 / 2

Q quantization (u s), N angle/velocity random walk (u sqrt(s)), B bias instability (u),
K rate/acceleration random walk (u / sqrt(s)), R rate ramp (u / s).

The model is linear in p = (Q^2, N^2, B^2, K^2, R^2) and all taus are fitted at once by
generalized non-negative least squares: the residuals are weighted with the inverse of the
full covariance of the sigma^2(tau) estimates (:mod:`rigctl.solvers.allan_cov`), computed for
the fitted noise mixture (iterated: fit -> covariance -> fit). Its diagonal is 2 sigma^4 / edf
with Greenhall's EDF for that mixture; its off-diagonal terms are the strong correlation of
overlapping estimates at neighbouring taus (0.8-0.97 between taus 1.26x apart), which a
diagonal fit ignores and so reports intervals several times too narrow. Up to ``max_taus``
(40) log-spaced taus of the curve are used (the rest add almost no information). Without
``tau0``/``n_phase`` the covariance falls back to the diagonal from the given EDF.

Model selection (backward elimination): a term is kept only if its estimate is significant
(p_j > 1.96 sd_j, i.e. its 95 % lower bound is above zero) and it reaches at least 10 % of the
fitted sigma^2 at some tau (``MIN_SHARE``; a smaller share is within the model's own
idealisation error, e.g. filters and the edges of the flicker band, and is what produced
spurious quantization terms). The weakest failing term is dropped and the rest refitted until
all pass. B must in addition pass its presence test (:func:`b_presence_test`: a likelihood
ratio at B_TEST_ALPHA = 2.5 % with every other shape and a low-pass's own 1/tau^2 term
present); a B that does not goes first. K and R likewise: the same test of K = R = 0 (a
rise at the long taus), with the covariance taken at the null's fit; where it does not find
one they go first. A dropped term is reported as a one-sided 95 % upper
bound, sqrt(max(p_j, 0) +
1.645 sd_j) from the fit with it restored (unconstrained). Parameter covariance:
(A^T Sigma^-1 A)^-1, inflated by the reduced chi-square when > 1. Intervals of a kept term:
chi-square with nu = 2 p^2 / sd(p)^2 degrees of freedom (Satterthwaite), the same form as the
intervals of the deviations, each end p solving p_j = p chi2_{q'}(nu(p)) / nu(p) with sd(p) from
the covariance at the model with the term at p (Neyman; :func:`_neyman_chi2_ci`), square-rooted.

Each Q/N/B/K entry also carries ``crb_rel_sd``: the Cramer-Rao bound of sd(c)/c for the
capture (:mod:`rigctl.solvers.allan_crb`), i.e. how well any estimator could determine that
term from these T seconds (with the Gauss-Markov term's sigma_GM and Tc as nuisance parameters
when the fit has one); this fit reaches it, so a wide bound means "capture longer".

For comparison the classic piecewise read-offs (slope -1 below 0.5 s -> Q at tau = sqrt(3),
slope -1/2 between 0.5 s and 2 s -> N at tau = 1 s, flat minimum above 20 s -> B = min/0.664,
slope +1/2 above the minimum -> K at tau = 3 s) are reported beside it.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.linalg import cholesky as _cholesky, solve_triangular as _solve_triangular
from scipy.linalg.lapack import dpotrf, dtrtrs
from scipy.optimize import nnls
from .distributions import chi2, norm

from . import allan_cov as C
from . import allan_crb as R
from . import allan_tones as TN
from . import noise_coefficients as NC
from .noise_coefficients import FIELD_UNITS, G0, SI_UNITS, TERM_NAMES  # noqa: F401 - one table, named here too
from .allan_stream import blas_single_thread

TERMS = ("Q", "N", "B", "K", "R")
_B_FACTOR = 2.0 * math.log(2.0) / math.pi
#: a term must reach this share of the fitted sigma^2 at some tau to count as identified
MIN_SHARE = 0.10
#: relative sd at which 95 % of an efficient estimator's results lie within +-25 %
TARGET_REL_SD = 0.25 / 1.96
_Z95, _Z95_ONE = float(norm.ppf(0.975)), float(norm.ppf(0.95))
_DEG = 180.0 / math.pi


def design_matrix(tau: np.ndarray) -> np.ndarray:
    """Columns d sigma^2 / d p for p = (Q^2, N^2, B^2, K^2, R^2)."""
    tau = np.asarray(tau, dtype=float)
    return np.column_stack((3.0 / tau ** 2, 1.0 / tau, np.full(tau.shape, _B_FACTOR),
                            tau / 3.0, tau ** 2 / 2.0))


def model_avar(tau: np.ndarray, coeffs: dict[str, float]) -> np.ndarray:
    """sigma^2(tau) of the IEEE 952 model from SI coefficients {Q, N, B, K, R}."""
    p = np.array([coeffs.get(t, 0.0) ** 2 for t in TERMS])
    return design_matrix(tau) @ p


#: the columns of the joint fit: the IEEE 952 terms and, where the Gauss-Markov candidate
#: (rigctl.solvers.allan_gm) found one, a first-order Gauss-Markov term (sigma_GM^2 at a fixed Tc)
COLS = TERMS + ("GM",)
GM_IDX = COLS.index("GM")


def gm_avar(tau: np.ndarray, var_gm: float, tc: float) -> np.ndarray:
    """Allan variance of a first-order Gauss-Markov rate of variance ``var_gm`` (SI^2) and
    correlation time ``tc`` (s) at averaging times ``tau`` (s) (IEEE Std 952-1997 annex C)::

        sigma^2(tau) = var_gm (Tc / tau)^2 (2 tau / Tc - 3 + 4 e^(-tau/Tc) - e^(-2 tau/Tc))

    Series below tau/Tc = 0.05 (the closed form cancels there)."""
    x = np.asarray(tau, dtype=float) / float(tc)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        closed = (2.0 * x - 3.0 + 4.0 * np.exp(-x) - np.exp(-2.0 * x)) / x ** 2
    series = x * (2.0 / 3.0 - x / 2.0 + x * x * 7.0 / 30.0 - x ** 3 / 12.0)
    return float(var_gm) * np.where(x < 0.05, series, closed)


def gm_column(tau: np.ndarray, tc: float) -> np.ndarray:
    """d sigma^2 / d sigma_GM^2 of a first-order Gauss-Markov rate of correlation time ``tc``
    (:func:`gm_avar` at unit variance)."""
    return gm_avar(np.asarray(tau, dtype=float), 1.0, float(tc))


def full_design(tau: np.ndarray, tc: float | None) -> np.ndarray:
    """:func:`design_matrix` with the Gauss-Markov column (index GM_IDX) when ``tc`` is given."""
    a = design_matrix(tau)
    return a if tc is None else np.column_stack((a, gm_column(tau, tc)))


def fitted_avar(fit_or_coeffs: Any, tau: np.ndarray) -> np.ndarray:
    """sigma^2(tau) of the model a fit reports: its resolved IEEE 952 terms
    (:func:`rigctl.solvers.noise_coefficients.resolved_values`) plus its Gauss-Markov terms
    (``coefficients.gm``, in the fit when the candidate found one). Not the tones."""
    co = fit_or_coeffs.get("coefficients") if isinstance(fit_or_coeffs, dict) else fit_or_coeffs
    co = NC.as_coefficients(co)
    tau = np.asarray(tau, dtype=float)
    out = model_avar(tau, NC.resolved_values(co))
    for g in co.gm:
        if g.sigma.resolved:
            out = out + gm_column(tau, g.tau_c_s) * g.sigma.value ** 2
    return out


def cholesky(a: np.ndarray, lower: bool = True) -> np.ndarray:
    """``scipy.linalg.cholesky(a, lower=True)`` for a square float array: its own steps -- the
    input checked finite (the same ValueError), LAPACK's dpotrf (clean: the other triangle
    zeroed), its LinAlgError / ValueError on info != 0 -- without its wrapper's batch dispatch
    (40 x 40: 22.5 -> 16.7 us; _whiten factors ~200 covariances per fit_terms call). Anything
    else (another dtype or shape, lower=False, an empty array) goes to scipy's function."""
    a1 = np.asarray_chkfinite(a)
    if not (lower and a1.dtype == np.float64 and a1.ndim == 2 and a1.size
            and a1.shape[0] == a1.shape[1]):
        return _cholesky(a, lower=lower)
    c, info = dpotrf(a1, lower=True, overwrite_a=False, clean=True)
    if info > 0:
        raise np.linalg.LinAlgError(
            f"{info}-th leading minor of the array is not positive definite")
    if info < 0:
        raise ValueError(
            f'LAPACK reported an illegal value in {-info}-th argument on entry to "POTRF".')
    return c


def solve_triangular(lw: np.ndarray, b: np.ndarray, lower: bool = True) -> np.ndarray:
    """``scipy.linalg.solve_triangular(lw, b, lower=True)`` for float arrays (lw square, b of
    its rows, 1-d or 2-d): its own steps -- the inputs checked finite (the same ValueError),
    LAPACK's dtrtrs on lw (or on lw.T as upper, transposed, where lw is not Fortran-ordered,
    as scipy hands it), its errors -- without the wrapper around them (the batch dispatch,
    the validation of array types, the lookup of the LAPACK routine), which cost more than
    the solve itself on the fits' 40 x 40 factors (~380 solves per fit_terms call; a fit's
    CPU -3 to -5 %). Anything else (another dtype or shape, lower=False, an empty b) goes to
    scipy's function."""
    a1 = np.asarray_chkfinite(lw)
    b1 = np.asarray_chkfinite(b)
    if not (lower and a1.dtype == np.float64 and b1.dtype == np.float64 and a1.ndim == 2
            and a1.shape[0] == a1.shape[1] and b1.ndim in (1, 2) and b1.size
            and a1.shape[0] == b1.shape[0]):
        return _solve_triangular(lw, b, lower=lower)
    if a1.flags.f_contiguous:
        x, info = dtrtrs(a1, b1, overwrite_b=False, lower=True, trans=0, unitdiag=False)
    else:
        x, info = dtrtrs(a1.T, b1, overwrite_b=False, lower=False, trans=True, unitdiag=False)
    if info == 0:
        return x
    if info > 0:
        raise np.linalg.LinAlgError(f"singular matrix: resolution failed at diagonal {info-1}")
    raise ValueError(f"illegal value in {-info}-th argument of internal trtrs")


def bvls(a: np.ndarray, b: np.ndarray, lb: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """``scipy.optimize.lsq_linear(a, b, bounds=(lb, ub), method="bvls").x`` (its default tol
    1e-10, the exact solver) without its wrapper: the same steps in the same order (the
    unbounded solution with lstsq(rcond=-1), returned if within the bounds; else scipy's
    bvls loop, its lstsq(rcond=None) on the free variables, its cost-change and KKT
    stopping rules), the same numbers bit for bit (tests/test_allan_fit.py compares them);
    what scipy computes only to report (step norms, messages, the result object, the
    checks of its arguments) is left out. The fits solve thousands of these 40 x 6
    problems, where the wrapper was most of the cost. ``lb``, ``ub``: float arrays, lb < ub.
    (scipy's loop itself, scipy.optimize._lsq.bvls.bvls, gives the same numbers when called
    directly, but it also computes step norms and a result object: 262 vs 224 us per bounded
    solve, 2-5 % of a fit_terms call on noise curves, where most solves are bounded.)"""
    lstsq = np.linalg.lstsq
    x = lstsq(a, b, rcond=-1)[0]
    if np.all((x >= lb) & (x <= ub)):
        return x
    tol = 1e-10
    n = a.shape[1]
    on_bound = np.zeros(n)
    mask = x <= lb
    x[mask] = lb[mask]
    on_bound[mask] = -1
    mask = x >= ub
    x[mask] = ub[mask]
    on_bound[mask] = 1
    free_set = on_bound == 0
    active_set = ~free_set
    free_set, = np.nonzero(free_set)
    r = a.dot(x) - b
    cost = 0.5 * np.dot(r, r)
    g = a.T.dot(r)
    iteration = 0
    # scipy's initialization loop: the least-squares solution on the free variables, those
    # outside their bounds set there, until it is feasible
    while free_set.size > 0:
        iteration += 1
        z = lstsq(a[:, free_set], b - a.dot(x * active_set), rcond=None)[0]
        lbv = z < lb[free_set]
        ubv = z > ub[free_set]
        v = lbv | ubv
        if np.any(lbv):
            ind = free_set[lbv]
            x[ind] = lb[ind]
            active_set[ind] = True
            on_bound[ind] = -1
        if np.any(ubv):
            ind = free_set[ubv]
            x[ind] = ub[ind]
            active_set[ind] = True
            on_bound[ind] = 1
        x[free_set[~v]] = z[~v]
        r = a.dot(x) - b
        cost = 0.5 * np.dot(r, r)
        g = a.T.dot(r)
        if np.any(v):
            free_set = free_set[~v]
        else:
            break
    max_iter = n + iteration

    def optimality() -> float:  # scipy's compute_kkt_optimality
        g_kkt = g * on_bound
        free = on_bound == 0
        g_kkt[free] = np.abs(g[free])
        return np.max(g_kkt)

    opt = optimality()
    stop = False
    for _ in range(iteration, max_iter):
        if opt < tol or stop:
            break
        on_bound[np.argmax(g * on_bound)] = 0
        while True:
            free = on_bound == 0
            active_set = ~free
            free_set, = np.nonzero(free)
            x_free = x[free_set]
            lb_free = lb[free_set]
            ub_free = ub[free_set]
            z = lstsq(a[:, free_set], b - a.dot(x * active_set), rcond=None)[0]
            lbv, = np.nonzero(z < lb_free)
            ubv, = np.nonzero(z > ub_free)
            v = np.hstack((lbv, ubv))
            if v.size > 0:
                alphas = np.hstack((lb_free[lbv] - x_free[lbv],
                                    ub_free[ubv] - x_free[ubv])) / (z[v] - x_free[v])
                i = np.argmin(alphas)
                i_free = v[i]
                alpha = alphas[i]
                x_free *= 1 - alpha
                x_free += alpha * z
                x[free_set] = x_free
                on_bound[free_set[i_free]] = -1 if i < lbv.size else 1
            else:
                x[free_set] = z
                break
        r = a.dot(x) - b
        cost_new = 0.5 * np.dot(r, r)
        if cost - cost_new < tol * cost:
            stop = True
        cost = cost_new
        g = a.T.dot(r)
        opt = optimality()
    return x


def _nnls_cols(a: np.ndarray, b: np.ndarray, upper: np.ndarray | None = None) -> np.ndarray:
    """Non-negative least squares with column scaling; with ``upper``, also p <= upper
    (bounded-variable least squares): 0 <= p_j <= upper_j exactly, in the caller's units (the
    solver's answer clipped once, after the scaling is undone; an upper of 0 is solved as
    1e-300 on the scaled column, lsq_linear needs lower < upper)."""
    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0] = 1.0
    if upper is None or not np.any(np.isfinite(upper)):
        p, _ = nnls(a / scale, b)
        return p / scale
    upper = np.asarray(upper, dtype=float)
    ub = np.maximum(np.where(np.isfinite(upper), upper * scale, np.inf), 1e-300)
    x = bvls(a / scale, b, np.zeros_like(ub), ub)
    return np.clip(x / scale, 0.0, np.where(np.isfinite(upper), np.maximum(upper, 1e-300 / scale), np.inf))


def _whiten(cov: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a covariance. A diagonal jitter on the correlation matrix keeps
    it definite: 1e-9, raised tenfold while rounding still leaves it indefinite (the
    correlations of neighbouring long taus are within 1e-9 of 1 on non-stationary data)."""
    d = np.sqrt(np.diag(cov))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(d, d)
    for jitter in 10.0 ** np.arange(-9, -1):
        try:
            return d[:, None] * cholesky(corr + jitter * np.eye(d.size), lower=True)
        except (np.linalg.LinAlgError, ValueError):
            continue
    # still indefinite (seen on a caesium clock's phase through rigctl allan: white PM over
    # five decades, correlations of the long taus within rounding of 1): the nearest
    # definite correlation (eigenvalues clipped), else none at all
    corr = np.where(np.isfinite(corr), corr, 0.0)
    np.fill_diagonal(corr, 1.0)
    try:
        w, v = np.linalg.eigh(0.5 * (corr + corr.T))
        w = np.maximum(w, 1e-6 * max(float(w.max()), 1.0))
        c = (v * w) @ v.T
        s = np.sqrt(np.diag(c))
        return d[:, None] * cholesky(c / np.outer(s, s), lower=True)
    except (np.linalg.LinAlgError, ValueError):
        return np.diag(np.where(d > 0, d, 1e-300))


#: _whiten's first diagonal jitter (the same float: 10.0 ** -9 as numpy computes it there)
_JITTER0 = float((10.0 ** np.arange(-9, -1))[0])


def _whiten_diag(var: np.ndarray) -> np.ndarray:
    """``_whiten(np.diag(var))`` without the factorization: the Cholesky factor of a diagonal
    correlation plus the jitter is the diagonal of its square roots (the same numbers: no
    off-diagonal term enters a pivot), scaled back by the sd. Variances that are not all
    finite and positive take :func:`_whiten` itself."""
    var = np.asarray(var, dtype=float)
    d = np.sqrt(var)
    if not (d.size and np.all(np.isfinite(d)) and np.all(d > 0)):
        return _whiten(np.diag(var))
    return np.diag(d * np.sqrt(var / (d * d) + _JITTER0))


def _model_cov(cov_terms: dict | None, p: np.ndarray, cols: list[int], a: np.ndarray,
               edf: np.ndarray, model_err: float = 0.0, inflate: np.ndarray | None = None
               ) -> np.ndarray:
    """Covariance of the sigma^2 estimates under the model p (see allan_cov); without factor
    information: diagonal 2 sigma^4 / edf. ``model_err`` adds the model's own idealisation
    error, (model_err * sigma^2)^2 on the diagonal (see :func:`_model_error`)."""
    cov = _stat_cov(cov_terms, p, cols, a, edf)
    if model_err > 0:
        mod = np.maximum(a @ p, 1e-300)
        cov = cov + np.diag((model_err * mod) ** 2)
    if inflate is not None:  # robust down-weighting of taus the model cannot follow
        g = np.sqrt(inflate)
        cov = cov * np.outer(g, g)
    return cov


def _stat_cov(cov_terms: dict | None, p: np.ndarray, cols: list[int], a: np.ndarray,
              edf: np.ndarray) -> np.ndarray:
    # the Gauss-Markov column (GM_IDX): its own kernel where ``cov_terms`` holds the pairs of
    # allan_cov at the column's Tc (term_covariances(..., tc=)); without them, like the ramp,
    # its part of the total takes the correlations of the Q, N, B, K terms, scaled tau by tau
    # to the total (the approximation rigctl.solvers.allan_gm makes)
    full = np.zeros(len(COLS))
    full[cols] = p
    mod = np.maximum(a @ p, 1e-300)
    if cov_terms is None:
        return np.diag(2.0 * mod ** 2 / edf)
    coeffs = dict(zip(C.TERMS4, full[:4]))
    has_g = GM_IDX in cols and ("G", "G") in cov_terms
    if has_g:
        coeffs["G"] = full[GM_IDX]
    cov = C.combine(cov_terms, coeffs)
    kern = [i for i, c in enumerate(cols) if c < 4 or (has_g and c == GM_IDX)]
    noisy = np.maximum(a[:, kern] @ p[kern], 1e-300) if kern else mod
    g = mod / noisy  # the deterministic ramp R: same correlations, scaled to the total
    # where the noise terms are ~0 beside a ramp (noisy floored at 1e-300) g**2 overflows: those
    # taus have no usable noise covariance and take the diagonal fallback below
    with np.errstate(over="ignore", invalid="ignore"):
        cov = cov * np.outer(g, g)
    bad = ~(np.isfinite(np.diag(cov)) & (np.diag(cov) > 0))
    cov[~np.isfinite(cov)] = 0.0
    if np.any(bad):  # e.g. a model with Q only beyond its exact-lag range
        cov[bad, :] = 0.0
        cov[:, bad] = 0.0
        cov[bad, bad] = 2.0 * mod[bad] ** 2 / edf[bad]
    return cov


def _gls(a: np.ndarray, s2: np.ndarray, edf: np.ndarray, cols: list[int],
         cov_terms: dict | None, p0: np.ndarray, iterations: int, model_err: float = 0.0,
         upper: np.ndarray | None = None, inflate: np.ndarray | None = None) -> tuple:
    """Iterated generalized NNLS (p <= upper if given); returns (p, whitened design,
    whitened residual)."""
    p = p0
    for _ in range(iterations):
        lw = _whiten(_model_cov(cov_terms, p, cols, a, edf, model_err, inflate))
        aw = solve_triangular(lw, a, lower=True)
        bw = solve_triangular(lw, s2, lower=True)
        p_next = _nnls_cols(aw, bw, upper)
        if not np.all(a @ p_next > 0):
            # the whitened NNLS zeroed every term (seen on a real phone gyro's 5-minute window,
            # Galaxy S5 gx rows 27000-30000, in the Gauss-Markov profile): a zero total has no
            # covariance (2 sigma^4 / edf = 0, a singular factor), so keep the last iterate
            break
        p = p_next
    lw = _whiten(_model_cov(cov_terms, p, cols, a, edf, model_err, inflate))
    aw = solve_triangular(lw, a, lower=True)
    bw = solve_triangular(lw, s2, lower=True)
    return p, aw, bw - aw @ p


def _param_cov(aw: np.ndarray) -> np.ndarray:
    """(A^T A)^-1 of a whitened design, with column scaling (the columns differ by 20+
    orders of magnitude: tau^-2 .. tau^2)."""
    d = np.linalg.norm(aw, axis=0)
    d[d == 0] = 1.0
    return np.linalg.pinv((aw / d).T @ (aw / d)) / np.outer(d, d)


def _chi2_over_nu(q: float, nu: float) -> float:
    """chi2.ppf(q, nu) / nu (Wilson-Hilferty above 1e7 degrees of freedom)."""
    if nu <= 1e7:
        return float(chi2.ppf(q, nu)) / nu
    h = 2.0 / (9.0 * nu)
    return (1.0 - h + float(norm.ppf(q)) * math.sqrt(h)) ** 3


def _chi2_ci(p: float, nu: float, conf: float) -> tuple[float, float]:
    """Two-sided interval (confidence ``conf``) of a coefficient sqrt(p) whose variance p has
    Satterthwaite dof nu: sqrt(p nu / chi2_{1-q}(nu)) .. sqrt(p nu / chi2_q(nu)), q = (1 -
    conf) / 2; [0, inf) where nu << 1 leaves nothing known."""
    q = (1.0 - conf) / 2.0
    r_hi, r_lo = _chi2_over_nu(1.0 - q, nu), _chi2_over_nu(q, nu)
    if not r_lo > 0:
        return 0.0, math.inf
    return math.sqrt(p / r_hi), math.sqrt(p / r_lo)


def _unit_reduced_chi2_eps(reduced: Callable[[float], float]) -> float:
    """The relative model error eps in [1e-4, 10] at which ``reduced(eps)`` (a fit's reduced
    chi-square with eps sigma^2 added to each sigma^2's standard deviation) falls to 1:
    bisection on log eps to 0.02 (at most 30 steps); the upper end of the last bracket."""
    lo, hi = math.log(1e-4), math.log(10.0)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if reduced(math.exp(mid)) > 1.0:
            lo = mid
        else:
            hi = mid
        if hi - lo < 0.02:
            break
    return math.exp(hi)


def _model_whitener(ct: dict | None, q_nbk: np.ndarray, mod: np.ndarray, noisy: np.ndarray,
                    e: np.ndarray, eps: float, q_gm: float | None = None) -> np.ndarray:
    """Whitener of the sigma^2 estimates at a fitted model: the covariance of the N, B, K
    terms (allan_cov, ``ct``) at their fitted values ``q_nbk``, scaled per tau by the whole
    model ``mod`` over those terms' part ``noisy`` (the other terms: the same correlations,
    scaled); the diagonal 2 mod^2 / e where there is none or it is not positive; plus the
    model error (eps mod)^2 on the diagonal. ``q_gm``: sigma_GM^2, a Gauss-Markov term whose
    kernel ``ct`` carries (its pairs with N, B, K; then ``noisy`` includes it)."""
    cov = None
    if ct is not None:
        p = {"N": max(q_nbk[0], 0.0), "B": max(q_nbk[1], 0.0), "K": max(q_nbk[2], 0.0)}
        if q_gm is not None:
            p["G"] = max(q_gm, 0.0)
        cov = C.combine(ct, p)
        g = mod / noisy
        with np.errstate(over="ignore", invalid="ignore"):
            cov = cov * np.outer(g, g)
        if not np.all(np.isfinite(cov)) or not np.all(np.diag(cov) > 0):
            cov = None
    if cov is None:
        cov = np.diag(2.0 * mod ** 2 / e)
    if eps > 0:
        cov = cov + np.diag((eps * mod) ** 2)
    return _whiten(cov)


def _sd_at(a: np.ndarray, s2: np.ndarray, edf: np.ndarray, cols: list[int],
           cov_terms: dict | None, p: np.ndarray, i: int, value: float, chi2_red: float,
           model_err: float = 0.0, inflate: np.ndarray | None = None) -> float:
    """sd of the GLS estimate of column i's coefficient when that coefficient is ``value``
    (the others at ``p``): the covariance of the sigma^2 estimates at that model, the
    parameter covariance (A^T Sigma^-1 A)^-1 of the columns with a positive coefficient,
    inflated by the reduced chi-square when > 1 (as the fit's own sd)."""
    model = np.maximum(np.array(p, dtype=float), 0.0)
    model[i] = max(float(value), 0.0)
    pos = model > 0
    if not pos[i]:
        return 0.0
    lw = _whiten(_model_cov(cov_terms, model, cols, a, edf, model_err, inflate))
    aw = solve_triangular(lw, a[:, pos], lower=True)
    k = int(np.count_nonzero(pos[:i]))
    return float(np.sqrt(max(_param_cov(aw)[k, k], 0.0) * max(1.0, chi2_red)))


def _neyman_chi2_ci(p_hat: float, sd_at: Callable[[float], float], conf: float,
                    steps: int = 8) -> tuple[float, float]:
    """Two-sided interval (confidence ``conf``) of a coefficient sqrt(p) from its estimate
    ``p_hat`` whose spread depends on p (Neyman's construction): p_hat is taken as
    p chi2(nu) / nu with Satterthwaite's nu(p) = 2 p^2 / sd(p)^2 at the *candidate* p, not at
    p_hat, so the ends solve p_hat = p_lo chi2_{1-q}(nu(p_lo)) / nu(p_lo) and
    p_hat = p_hi chi2_q(nu(p_hi)) / nu(p_hi), q = (1 - conf) / 2 (fixed-point iteration from
    the ends at nu(p_hat), ``steps`` steps). With nu from p_hat a chance high p_hat, whose
    relative sd the model at p_hat makes small, got a narrow interval above the truth (the
    quickstart's B, issue 15)."""
    q = (1.0 - conf) / 2.0

    def nu(p: float) -> float:
        sd = sd_at(p)
        return 2.0 * p * p / max(sd * sd, 1e-300)

    ends = []
    for quant in (1.0 - q, q):
        v = p_hat
        for _ in range(steps):
            r = _chi2_over_nu(quant, nu(v)) if v > 0 else 0.0
            if not r > 0:
                v = math.inf
                break
            v = p_hat / r
        ends.append(v)
    return math.sqrt(ends[0]), math.sqrt(ends[1])


def _bound_fit(a: np.ndarray, s2: np.ndarray, edf: np.ndarray, cols: list[int],
               cov_terms: dict | None, p: np.ndarray, iterations: int, chi2_red: float,
               model_err: float = 0.0, inflate: np.ndarray | None = None) -> tuple[float, float]:
    """Unconstrained GLS estimate of the last column's coefficient and the sd that puts
    the one-sided 95 % bound at p_u = max(p_hat, 0) + 1.645 sd(p_u): the sd is evaluated
    with the term *at the bound* in the covariance (its own variance grows with it), the
    Neyman construction for an estimate whose spread depends on the parameter."""

    done: dict[bytes, tuple[np.ndarray, float] | None] = {}

    def solve(model: np.ndarray) -> tuple[np.ndarray, float] | None:
        # a pure function of the model: the bound's fixed point, once reached, repeats it
        key = np.asarray(model, dtype=float).tobytes()
        if key not in done:
            done[key] = _solve(model)
        return done[key]

    def _solve(model: np.ndarray) -> tuple[np.ndarray, float] | None:
        cov = _model_cov(cov_terms, np.maximum(model, 0.0), cols, a, edf, model_err, inflate)
        if not np.all(np.diag(cov) > 0):
            # a model whose total is zero at some tau (its variance 2 sigma^4 / edf
            # underflows) has no covariance there and no whitener: None (seen on a channel of
            # period 3 samples, whose sigma^2 is ~1e-40 at every third tau: the unconstrained
            # estimate drove every term below zero, and the factor was singular)
            return None
        lw = _whiten(cov)
        aw = solve_triangular(lw, a, lower=True)
        bw = solve_triangular(lw, s2, lower=True)
        cj = _param_cov(aw)
        return cj @ aw.T @ bw, float(np.sqrt(max(cj[-1, -1], 0.0) * max(1.0, chi2_red)))

    sd = math.inf  # no usable model at all: nothing known of the term
    for _ in range(iterations):
        got = solve(p)
        if got is None:  # as _gls does: keep the last iterate
            break
        p, sd = got
    pj = float(p[-1])
    pu = max(pj, 0.0) + _Z95_ONE * sd
    for _ in range(2 * iterations):
        model = np.array(p, dtype=float)
        model[-1] = pu
        got = solve(model)
        if got is None:
            break
        pu = max(pj, 0.0) + _Z95_ONE * got[1]
    return pj, (pu - max(pj, 0.0)) / _Z95_ONE


#: one-sided level of the curve's upper band that holds B, K and R in the fit: the chance that
#: the true curve is above the band at *any* of the informative taus (family-wise)
LIMIT_ALPHA = 0.025


def _effective_taus(cov_terms: dict | None, a: np.ndarray, s2: np.ndarray, e: np.ndarray,
                    sel: np.ndarray) -> float:
    """Effective number of independent sigma^2 estimates among the taus ``sel`` (Galwey 2009:
    (sum sqrt(lambda))^2 / sum lambda over the eigenvalues of their correlation matrix), from
    the covariance of the estimates (allan_cov) under a first EDF-weighted NNLS fit of the
    curve. Overlapping estimates at taus 1.26x apart are correlated 0.8-0.97, at taus 2x apart
    0.6-0.7: the number is a property of the curve's span, not of how densely it is sampled
    (12 h consumer_mems ax: 14.7 from the 18 informative octave taus, 16.9 from 36 of the
    all-tau set). Without the covariance (no tau0/n_phase): the count, as if independent."""
    n = int(np.count_nonzero(sel))
    if cov_terms is None or n < 2:
        return float(max(n, 1))
    w = e / (2.0 * s2 ** 2)
    p = _nnls_cols(a * np.sqrt(w)[:, None], s2 * np.sqrt(w))
    cols = list(range(a.shape[1]))
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        cov = _stat_cov(cov_terms, p, cols, a, e)[np.ix_(sel, sel)]
        d = np.sqrt(np.diag(cov))
        corr = cov / np.outer(d, d)
    if not np.all(np.isfinite(corr)):
        return float(n)
    lam = np.clip(np.linalg.eigvalsh(0.5 * (corr + corr.T)), 0.0, None)
    if lam.sum() <= 0:
        return float(n)
    return float(min(n, max(1.0, np.sum(np.sqrt(lam)) ** 2 / lam.sum())))


def _family_band(s2: np.ndarray, e: np.ndarray, m_eff: float, alpha: float = LIMIT_ALPHA,
                 lower: bool = False) -> np.ndarray:
    """Upper end of the chi-square band of sigma that holds at every one of ``m_eff``
    independent taus with probability 1 - alpha (Sidak: each at 1 - (1 - alpha)^(1/m_eff)):
    sigma sqrt(nu / chi2_q(nu)), q = 1 - (1 - alpha)^(1 / m_eff); with ``lower`` its lower
    end, sigma sqrt(nu / chi2_{1-q}(nu))."""
    q = -math.expm1(math.log1p(-alpha) / max(m_eff, 1.0))
    return np.sqrt(s2) * np.sqrt(e / chi2.ppf(1.0 - q if lower else q, e))


#: design level of the test that decides whether B is in the data: the chance that a curve
#: of white noise + random walk (+ ramp, + a short low-pass) is reported with a B estimate
B_TEST_ALPHA = 0.025
#: the B test reads taus of at least this many samples: below, a sensor's low-pass filter is
#: not yet a 1/tau^2 term (a 3-tap filter is one exactly from m = 2 on, a real IMU's IIR
#: anti-aliasing filter within a few time constants)
B_TEST_M_MIN = 4
#: the terms the selection keeps only where their presence test (b_presence_test, at
#: B_TEST_ALPHA) finds them
PRESENCE_TESTED = ("B", "K")
#: the terms the null model of each presence test leaves out: B alone; for K, the rise at the
#: long taus, K and the ramp R together (in a short capture the two rise alike, and with R in
#: the null a rise 40x the quickstart's K over 5 minutes, seen in the curve, was not found)
PRESENCE_NULL = {"B": ("B",), "K": ("K", "R")}
#: the tests whose sigma^2 covariance is taken at the null's fit (the others: the alternative's)
PRESENCE_AT_NULL = ("K",)


def b_presence_test(tau: np.ndarray, s2: np.ndarray, e: np.ndarray,
                    tau0: float | None = None, n_phase: int | None = None,
                    cov_terms: dict | None = None, iterations: int = 4,
                    extra: np.ndarray | None = None, term: str = "B") -> dict:
    """Is B in the curve? A likelihood-ratio test of B = 0 against B > 0 with every other
    IEEE 952 shape present, on the taus where the model holds.

    The fit's own significance test (B's estimate 1.96 sd from 0) is done in whatever model
    the backward elimination has reached and with a diagonal model error, and both let B
    stand in for something else: on white noise + random walk whose K the data show only
    weakly, B and K are each insignificant in the joint fit, K (the weaker) is dropped and B
    alone then passes (5 of 60 plain 1-h captures); a low-pass before decimation bends the
    white-noise slope at short taus, N comes out low (0.73-0.79x) and B fills the bottom of
    the V (29 of 60 low-passed captures). Here:

    * the alternative and the null both hold N, K, R and a short-tau term c / tau^2 whose
      sign is free (3 Q^2 when positive; a filter when negative: a FIR low-pass of white
      noise gives sigma^2 = N^2 / tau - c / tau^2 exactly once m exceeds its length, e.g.
      c = 1.125 N^2 tau0 for taps (1/4, 1/2, 1/4)), fitted by non-negative generalized least
      squares with the full covariance of the sigma^2 estimates (allan_cov) at the
      alternative's fit, iterated, the same for both;
    * only taus of at least B_TEST_M_MIN samples take part (the filter's own region is not
      described by any 1/tau^2 term);
    * statistic: chi2_null - chi2_alt. Where the alternative leaves a residual scatter beyond
      the statistics (chi-square beyond its 99 % point: a real sensor's quantization or bump)
      a relative model error is added as in :func:`_model_error`, fitted for *this* model:
      on a low-passed capture the filter term takes what the diagonal model error of the
      main fit (0.2-0.33 there) otherwise spread over every tau;
    * B on the boundary of its range (B^2 >= 0): the statistic is a 50:50 mixture of 0 and
      chi-square(1) under the null (chi-bar-square), p = chi2.sf(stat, 1) / 2.

    ``extra``: a further non-negative column at every tau (the joint fit's Gauss-Markov term
    at its fitted Tc), present in both models.

    Returns {"p_value", "statistic", "n_taus", "overdispersion", "tested"}; "tested" False
    (p_value nan) when too few taus remain."""
    tau = np.asarray(tau, dtype=float)
    if tau0 is not None:
        ms = np.maximum(1, np.round(tau / tau0))
        sel = ms >= B_TEST_M_MIN
    else:
        sel = np.ones(tau.size, dtype=bool)
    out = {"p_value": math.nan, "statistic": math.nan, "n_taus": int(np.count_nonzero(sel)),
           "overdispersion": math.nan, "tested": False, "alpha": B_TEST_ALPHA,
           "m_min": B_TEST_M_MIN if tau0 is not None else 1}
    if np.count_nonzero(sel) < 7:
        return out
    t, y, ee = tau[sel], np.asarray(s2, dtype=float)[sel], np.asarray(e, dtype=float)[sel]
    ct = None
    if cov_terms is not None:
        ct = {k: v[np.ix_(sel, sel)] for k, v in cov_terms.items()}
    elif tau0 is not None and n_phase is not None:
        ct = C.term_covariances(tau0, np.maximum(1, np.round(t / tau0)).astype(np.int64),
                                int(n_phase))
    a = design_matrix(t)  # columns Q(signed here), N, B, K, R
    lower = np.array([-np.inf, 0.0, 0.0, 0.0, 0.0])
    if extra is not None:  # (GM_IDX): in the null and the alternative alike
        a = np.column_stack((a, np.asarray(extra, dtype=float)[sel]))
        lower = np.append(lower, 0.0)

    def solve(cols: list[int], lw: np.ndarray) -> tuple[np.ndarray, float]:
        aw = solve_triangular(lw, a[:, cols], lower=True)
        bw = solve_triangular(lw, y, lower=True)
        sc = np.linalg.norm(aw, axis=0)
        sc[sc == 0] = 1.0
        q = bvls(aw / sc, bw, lower[cols], np.full(len(cols), np.inf)) / sc
        r = bw - aw @ q
        return q, float(r @ r)

    # the Gauss-Markov column's own covariance (allan_cov's kernel at the fit's Tc, its pairs
    # with N, B, K) where the fit passed it in ``cov_terms``; else its correlations are the N,
    # B, K ones scaled to the total, as the filter term's and the ramp's
    gm_kernel = extra is not None and ct is not None and ("G", "G") in ct

    def data_whitener(eps: float) -> np.ndarray:
        # the data's own diagonal, 2 s2^2 / edf, plus the model error
        return _whiten_diag(2.0 * y ** 2 / ee + (eps * y) ** 2)

    def whiten_at(q: np.ndarray, eps: float = 0.0) -> np.ndarray:
        # the filter term and the ramp: the N, B, K (and GM) correlations, scaled
        total = a @ q
        if not np.all(total > 0):
            # a signed c / tau^2 term can take the total to 0 or below at the shortest taus
            # (a moving table's rise in tau^2): no covariance there, so the data's own diagonal,
            # as _whitened_residual does (a floor of 1e-300 made a singular factor)
            return data_whitener(eps)
        cols = [1, 2, 3, 5] if gm_kernel else [1, 2, 3]
        noisy = np.maximum(a[:, cols] @ np.maximum(q[cols], 0.0), 1e-300)
        return _model_whitener(ct, q[1:4], total, noisy, ee, eps,
                               q_gm=float(q[5]) if gm_kernel else None)

    gone = [TERMS.index(t) for t in PRESENCE_NULL[term]]
    alt = [0, 1, 2, 3, 4]
    null = [c for c in alt if c not in gone]
    if extra is not None:
        alt, null = alt + [5], null + [5]

    def fit_alt(eps: float) -> tuple[np.ndarray, float, np.ndarray]:
        lw = data_whitener(eps)
        for _ in range(iterations):
            q, _ = solve(alt, lw)
            lw = whiten_at(q, eps)
        q, c = solve(alt, lw)
        return q, c, lw

    q1, c1, lw = fit_alt(0.0)
    dof = max(1, t.size - int(np.count_nonzero(q1)))
    eps = 0.0
    if chi2.sf(c1, dof) < MODEL_ERROR_P:
        # the model (with the filter term) does not describe these taus to their statistical
        # precision (a real sensor: quantization, a bump): its relative error eps as in
        # _model_error, so that the alternative's reduced chi-square is 1
        eps = _unit_reduced_chi2_eps(lambda x: fit_alt(x)[1] / dof)
        q1, c1, lw = fit_alt(eps)
    # the scatter beyond the statistics: the alternative's, under its own covariance
    over = max(1.0, c1 / dof)
    if term in PRESENCE_AT_NULL:
        # the covariance the statistic's reference distribution assumes: that of the null
        # (iterated at the null's fit), the same for both models. At the alternative's fit a
        # K that runs 2x above the long taus inflates their variance 16x and so hides its
        # own misfit there (the quickstart's spurious K of issue 15)
        lw_alt = lw
        try:
            for _ in range(iterations):
                q0, _ = solve(null, lw)
                full0 = np.zeros(a.shape[1])
                full0[null] = q0
                lw = whiten_at(full0, eps)
            q1, c1 = solve(alt, lw)
        except np.linalg.LinAlgError:
            # the null's covariance is singular (its fit has no noise term left: a record of a
            # moving table, not a static capture, crashed `rigctl allan` here): the test is
            # read under the alternative's covariance, as B's is, and says so
            lw = lw_alt
            q1, c1 = solve(alt, lw)
            out["covariance_at"] = "alternative (the null's covariance is singular)"
    _, c0 = solve(null, lw)
    stat = max(c0 - c1, 0.0) / over
    # each term left out is on the boundary of its range: chi-bar-square, the weights of a
    # mixture of chi-square(k), k = 0 .. len(gone), binomial(len(gone), 1/2)
    ng = len(gone)
    p_val = sum(math.comb(ng, k) * float(chi2.sf(stat, k)) for k in range(1, ng + 1)) / 2 ** ng
    out.update({"p_value": float(p_val) if stat > 0 else 1.0, "null_without": list(PRESENCE_NULL[term]),
                "statistic": float(stat), "overdispersion": float(over), "model_error_rel": eps,
                "tested": True})
    return out


def _thin(n: int, max_taus: int) -> np.ndarray:
    if n <= max_taus:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, max_taus)).astype(int))


#: a rising front: the curve climbs from its shortest tau to more than this factor over its
#: lowest point so far, then falls to below 1 / this factor of its top (each step outside
#: both 95 % bands); sqrt(2): what white noise falls over one octave
FRONT_FACTOR = math.sqrt(2.0)


def rising_front(tau: np.ndarray, adev: np.ndarray, edf: np.ndarray) -> int:
    """How many of the shortest taus form a rising front that no IEEE 952 total can follow:
    the index of the front's top, 0 when there is none.

    Every IEEE 952 total is a sum of powers of tau with non-negative weights, so log sigma is
    convex in log tau: the curve can fall and then rise, never rise and then fall. A curve
    that climbs from its shortest taus to a top and then falls clearly (both by more than
    FRONT_FACTOR, outside the 95 % bands, on the informative taus) has, before its top, taus
    that describe the way the samples were made, not the sensor's IEEE 952 noise: a low-pass
    filter's correlation, or an output that dwells on its quantization levels (a raw output
    below one step of noise, smoothed by a decimation filter: the Galaxy S5 gyro in the tests,
    0.1-2.0 s, top at 2.3 s). Those taus sit below the white-noise line the later curve
    implies; a fit that includes them decides N by the density of the tau set (--taus octave
    puts 5 of 16 taus there, the default 16 of 84; issue 15: N < 0.26 deg/sqrt(h) against
    2.2 on the same data).
    A curve whose first clear move is down (the usual case, a bump later included), or that
    rises and never falls clearly (a rate random walk or ramp from the start, or a capture
    too short to see the fall), has no front. Decided on the curve's values, so every tau set
    that samples the top finds the same front up to its tau spacing."""
    tau = np.asarray(tau, dtype=float)
    dev = np.asarray(adev, dtype=float)
    e = np.asarray(edf, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        lo = dev * np.sqrt(e / chi2.ppf(0.975, e))
        hi = dev * np.sqrt(e / chi2.ppf(0.025, e))
    idx = np.flatnonzero(np.isfinite(dev) & (dev > 0) & np.isfinite(lo) & np.isfinite(hi)
                         & (hi <= INFORMATIVE_RATIO * lo))
    if idx.size < 3:
        return 0
    top = low = idx[0]
    rose = False
    for j in idx[1:]:
        if dev[j] > dev[top]:
            top = j
        if not rose:
            if dev[j] * FRONT_FACTOR < dev[top] and hi[j] < lo[top]:
                return 0  # the curve's first clear move is down
            if dev[j] < dev[low]:
                low = j
            rose = dev[j] > FRONT_FACTOR * dev[low] and lo[j] > hi[low]
        elif dev[j] * FRONT_FACTOR < dev[top] and hi[j] < lo[top]:
            return int(top)  # up, then clearly down: the taus before the top are the front
    return 0


def fit_terms(tau: np.ndarray, adev: np.ndarray, edf: np.ndarray, sensor: str = "gyro",
              terms: tuple[str, ...] = TERMS, tau0: float | None = None,
              n_phase: int | None = None, max_taus: int = 40, iterations: int = 4,
              select: bool = True, tones: list[dict] | None = None,
              stretch_samples: np.ndarray | None = None, gm: dict | None = None) -> dict:
    """Joint generalized least-squares fit (see :func:`_fit_terms`; BLAS single-threaded).

    ``gm``: a first-order Gauss-Markov term in the model beside the IEEE 952 terms (the
    candidate of :func:`rigctl.solvers.allan_gm.gm_candidate` found significant): a dict with
    ``tc_grid_s`` [lo, hi], the range of correlation times searched (the candidate's). Tc is
    the profile's best over that grid (GM_GRID_PER_OCTAVE per octave), refined around it; the
    result gains ``gm_term`` and ``coefficients.gm``.

    ``stretch_samples`` (with ``tau0``): the lengths (samples) of the gap-free stretches when
    the deviations pool the terms of several (gaps skipped, Stable32). The covariance across
    taus is then that of the pooled estimate
    (:func:`rigctl.solvers.allan_cov.gapped_term_covariances`), not that of one record of
    ``n_phase`` points; ``n_phase`` still gives the capture's length (Cramer-Rao figures).

    ``tones`` (needs ``tau0``): periodic components found before the fit (dicts with freq_hz
    and amp_si, :func:`rigctl.solvers.allan_tones.detect_tones`). Each adds the known term
    :func:`rigctl.solvers.allan_tones.tone_avar` to the model, its coefficient (a^2) fixed by
    the spectrum: the IEEE 952 terms are fitted to sigma^2(tau) minus the tones' sum (the
    self-check compares that too, i.e. the data with the total of the IEEE terms and the
    tones). The periodogram gives a^2 to a fraction of a per cent on a capture of an hour;
    a free a^2 column would be determined by the Allan curve far worse (its envelope is Q's
    1/tau^2). Taus where the tones take all of sigma^2 (difference <= 0) drop out. The result
    gains ``tones`` (the subtracted terms, with their largest share of sigma^2 and where)."""
    with blas_single_thread():
        if not tones:
            return _fit_terms(tau, adev, edf, sensor, terms, tau0, n_phase, max_taus,
                              iterations, select, stretch_samples, gm)
        if tau0 is None:
            raise ValueError("a tone term needs tau0")
        tau = np.asarray(tau, dtype=float)
        s2 = np.asarray(adev, dtype=float) ** 2
        m = np.maximum(1, np.round(tau / tau0))
        tone2 = TN.tones_avar(tau0, m, tones)
        rest = s2 - tone2
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.where(s2 > 0, tone2 / s2, 0.0)
        adev_rest = np.where(rest > 0, np.sqrt(np.maximum(rest, 0.0)), np.nan)
        out = _fit_terms(tau, adev_rest, edf, sensor, terms, tau0, n_phase, max_taus,
                         iterations, select, stretch_samples, gm)
        i = int(np.nanargmax(share)) if share.size else 0
        out["tones"] = {"terms": [dict(t) for t in tones], "tau0_s": float(tau0),
                        "max_share": float(share[i]) if share.size else 0.0,
                        "max_share_tau_s": float(tau[i]) if share.size else float("nan"),
                        "taus_dropped": int(np.count_nonzero(~(rest > 0)))}
        return out


def _fit_terms(tau: np.ndarray, adev: np.ndarray, edf: np.ndarray, sensor: str = "gyro",
               terms: tuple[str, ...] = TERMS, tau0: float | None = None,
               n_phase: int | None = None, max_taus: int = 40, iterations: int = 4,
               select: bool = True, stretch_samples: np.ndarray | None = None,
               gm: dict | None = None) -> dict:
    """Joint generalized least-squares fit of the IEEE 952 terms. See the module docstring.

    tau in s, adev in SI rate units, edf per tau (Greenhall, used for the first pass and
    when ``tau0``/``n_phase`` are not given). With ``tau0`` (s) and ``n_phase`` (phase
    points) the full covariance of the sigma^2 estimates under the fitted model is used
    (:mod:`rigctl.solvers.allan_cov`). Returns ``coefficients`` (NoiseCoefficients: each term's
    SI value with its 68 % / 95 % intervals, or a one-sided 95 % upper bound for a term the data
    do not support) and per term the fit's diagnostics (``terms``: name, the curve's limit,
    Cramer-Rao figures, whether it was pinned at the limit).
    """
    tau = np.asarray(tau, dtype=float)
    s2 = np.asarray(adev, dtype=float) ** 2
    e = np.asarray(edf, dtype=float)
    ok = np.isfinite(s2) & np.isfinite(e) & (e > 0) & (s2 > 0) & np.isfinite(tau) & (tau > 0)
    tau, s2, e = tau[ok], s2[ok], e[ok]
    if tau.size < 2:
        raise ValueError("need at least two finite Allan variance points to fit")
    # a rising front (a filter's or a dwelling quantizer's short taus, see rising_front) is
    # left out of the fit, so that every tau set fits the same part of the curve; the
    # self-check and the curve's limits on each term still see every tau
    front = rising_front(tau, np.sqrt(s2), e)
    # ... and so is a low-pass filter's region (filter_region: the leading taus below the
    # white-noise line by a deficit that fades per octave, found from the curve): the terms are
    # fitted from the taus past it, the self-check still judges it and names it
    filt = None if front else filter_region(tau, s2, e, tau0)
    is_front = bool(front)
    if filt is not None:
        front = filt["n_taus"]
    if tau.size - front < 2:
        front, filt, is_front = 0, None, False
    tau_front, s2_front, e_front = tau, s2, e
    tau, s2, e = tau[front:], s2[front:], e[front:]
    tau_all, s2_all, e_all = tau, s2, e
    keep = _thin(tau.size, max_taus)
    tau, s2, e = tau[keep], s2[keep], e[keep]
    cov_terms = None
    if tau0 is not None and stretch_samples is not None and len(stretch_samples) > 1:
        # gaps skipped: the pooled estimate of independent gap-free stretches
        ms = np.maximum(1, np.round(tau / tau0)).astype(np.int64)
        cov_terms = C.gapped_term_covariances(tau0, ms, np.asarray(stretch_samples))
    elif tau0 is not None and n_phase is not None:
        ms = np.maximum(1, np.round(tau / tau0)).astype(np.int64)
        cov_terms = C.term_covariances(tau0, ms, int(n_phase))

    def cov_at(tc: float) -> dict | None:
        """The covariance pairs with the Gauss-Markov kernel at correlation time ``tc``."""
        if cov_terms is None:
            return None
        ms_ = np.maximum(1, np.round(tau / tau0)).astype(np.int64)
        if stretch_samples is not None and len(stretch_samples) > 1:
            return C.gapped_term_covariances(tau0, ms_, np.asarray(stretch_samples), tc=tc)
        return C.term_covariances(tau0, ms_, int(n_phase), tc=tc)

    full_a = design_matrix(tau)
    active = [TERMS.index(t) for t in terms]
    # B, K and R no larger than the curve allows within its 95 % band (c_j^2 A_j <= hi95^2;
    # their limits come from the floor and the long taus). Q and N are left free: their
    # limits come from the shortest taus, where a sensor's anti-aliasing filter pulls the
    # curve below the white-noise line (0.7x at tau0 on an ADIS16405), not an IEEE 952 term
    # Only taus whose band is informative set this limit: the last few taus of a capture (a
    # handful of averages) scatter by 2-3x and would hold B below a floor that dozens of
    # well-determined taus show (seen on a 3 h mti_class capture: 5.5 deg/h floor from 30 to
    # 800 s, two points at 1.5 deg/h near 2000 s)
    hi95 = np.sqrt(s2_all) * np.sqrt(e_all / chi2.ppf(0.025, e_all))
    lo95 = np.sqrt(s2_all) * np.sqrt(e_all / chi2.ppf(0.975, e_all))
    inf95 = _informative_prefix(hi95 <= INFORMATIVE_RATIO * lo95)
    # ... and that band is simultaneous over the informative taus (see _family_band): the
    # limit is the minimum over many taus, and a pointwise 97.5 % upper end, whose minimum over
    # the 128 informative taus of --taus all falls below the truth far more often than over
    # the 18 of --taus octave, held a 12 h consumer_mems ax B at 0.128 mg [0.118, 0.138] where
    # octave gave 0.151 (truth 0.153): one chance dip of the curve to 0.6x at 2300-2500 s
    m_eff = _effective_taus(cov_terms, full_a, s2, e, inf95[keep])
    hi_fw = _family_band(s2_all, e_all, m_eff)
    # its lower end, where a term's absence is judged (back_down below)
    lo_fw = _family_band(s2_all, e_all, m_eff, lower=True)
    lim95 = (curve_limits(tau_all[inf95], hi_fw[inf95]) if np.any(inf95)
             else curve_limits(tau_all, hi_fw))
    upper_all = np.array([lim95[t] ** 2 if t in CONSTRAINED else np.inf for t in TERMS])
    # B is not held below this band's limit by min sigma / 0.664 itself: with the family-wise
    # band a chance dip of a floor (0.6x at 3000 s, test_a_chance_dip_of_the_floor_does_not_
    # hold_b_below_the_truth) would hold B at 0.6x the truth and drop it. So a B estimate can
    # sit above min sigma / 0.664 where the curve still falls (Astro Pi gyros; issue 15).
    inf_idx = np.flatnonzero(inf95)
    floor_seen = bool(inf_idx.size) and bool(
        tau_all[inf_idx[-1]] >= FLOOR_AFTER * tau_all[inf_idx[np.argmin(hi_fw[inf_idx])]])
    # a first-order Gauss-Markov term (the candidate found it: see fit_terms' ``gm``): Tc by
    # the profile of the fit's chi-square over its grid, refined; from here on it is a column
    # of the model like the others (GM_IDX), held within the curve's limits like B, K and R,
    # and never dropped by the selection (its presence was decided by its own test)
    tc_fit, gm_prof = None, None
    if gm is not None:
        tc_fit, gm_prof, model_err, chi2_stat = _gm_profile(
            gm, tau, s2, e, full_a, active, upper_all, cov_at, iterations, tau_all, s2_all,
            inf95, hi_fw)
        cov_terms = cov_at(tc_fit)
        full_a = full_design(tau, tc_fit)
        upper_all = np.append(upper_all, _gm_limit(tc_fit, tau_all, s2_all, inf95, hi_fw,
                                                   model_err))
        active = active + [GM_IDX]
    else:
        model_err, chi2_stat = _model_error(full_a[:, active], s2, e, active, cov_terms,
                                            iterations, upper_all[active])
    full_a_all = full_design(tau_all, tc_fit)
    # B and K are each resolved only where the data reject the model without them: the
    # likelihood-ratio test of b_presence_test with every other shape present (K as B: on a
    # 5-minute quickstart capture, N + B with K invisible, B failed its test, was dropped
    # first, and K alone with N then passed its Wald test by following a chance rise of the
    # curve at 10-40 s: 61 of 600 gyro fits reported a K above the truth, the total 2x above
    # the curve at 62-75 s; benchmarks/allan_quickstart_cov.py)
    presence = {t: (b_presence_test(tau, s2, e, tau0, n_phase, cov_terms, iterations,
                                    extra=None if tc_fit is None else full_a[:, GM_IDX],
                                    term=t)
                    if select and TERMS.index(t) in active else {"tested": False})
                for t in PRESENCE_TESTED}
    b_test = presence["B"]
    # ... but where the curve is not IEEE 952 (the model needs its own error, eps >=
    # MODEL_ERROR_HOLD), B is
    # held to the curve's own limit, min sigma / 0.664 over the well-determined taus, like
    # every bound (see _b_point_limit): the fit's B is then a compromise between terms that do
    # not describe the curve, not a reading of a floor. b_falling: that limit is set where
    # the curve still falls (its last well-determined tau): no floor at that level
    b_pt, b_falling = (_b_point_limit(tau_all, s2_all, inf95) if model_err >= MODEL_ERROR_HOLD
                       else (math.inf, False))
    upper_all[B_IDX] = min(upper_all[B_IDX], b_pt)
    # ... and so is every other term (the same principle, each at its own curve limit: N <=
    # min sigma sqrt(tau), K <= min sigma sqrt(3 / tau), R <= min sigma sqrt(2) / tau, Q <=
    # min sigma tau / sqrt(3); see _point_limits): a real Astro Pi gyro's N came out 2.3x its
    # limit, the total 2.3x above the curve at 10 s, once B was held and bounded
    held = (_point_limits(tau_all, s2_all, inf95, tau0) if model_err >= MODEL_ERROR_HOLD
            else np.full(len(TERMS), np.inf))
    if tc_fit is not None:  # GM's hold is in its limit already (_gm_limit)
        held = np.append(held, np.inf)
    upper_all = np.minimum(upper_all, held)
    inflate = None
    dropped: list[int] = []
    pinned_terms: set[int] = set()
    needed_terms: set[int] = set()
    held_needed: set[int] = set()
    while True:
        a = full_a[:, active]
        w = e / (2.0 * s2 ** 2)
        p0 = _nnls_cols(a * np.sqrt(w)[:, None], s2 * np.sqrt(w), upper_all[active])
        if model_err > 0:  # robust weights for this set of terms
            inflate = _robust_inflation(a, s2, e, active, cov_terms, iterations, model_err,
                                        upper_all[active])
        p, aw, rw = _gls(a, s2, e, active, cov_terms, p0, iterations, model_err,
                         upper_all[active], inflate)
        pos = p > 0
        dof = max(1, tau.size - int(np.count_nonzero(pos)))
        chi2_red = float(rw @ rw) / dof
        cov_p = np.zeros((len(active), len(active)))
        if np.any(pos):
            sub = _param_cov(aw[:, pos]) * max(1.0, chi2_red)
            cov_p[np.ix_(pos, pos)] = sub
        sd = np.sqrt(np.maximum(np.diag(cov_p), 0.0))
        z = np.where(sd > 0, p / np.where(sd > 0, sd, 1.0), 0.0)
        share = np.max(a * p / np.maximum(a @ p, 1e-300)[:, None], axis=0)
        score = np.minimum(z / _Z95, share / MIN_SHARE)
        # pressed against the curve's 95 % limit: the fit wants more of the term than the
        # curve allows, i.e. it fills a feature outside IEEE 952 (a bump): dropped first
        up = upper_all[active]
        at_limit = np.isfinite(up) & (p >= up * (1.0 - 1e-6)) & (p > 0)
        # (Q and N, held only where the model needs its own error, _point_limits: a white
        # noise pressed against the curve's shortest taus is the curve, not a bump)
        at_limit &= np.array([COLS[j] in CONSTRAINED for j in active])
        # ... except a B pressed against a floor: the curve's lowest informative point (which
        # sets B's limit) has informative taus after it, i.e. the curve flattened or came
        # back up rather than still falling at the end (the MTi-G's fall after its bump). A
        # floor whose deepest taus fell low by chance presses B against its limit too (seen
        # on a 30-minute emulated capture, 95 taus: B dropped, the total 4x below the curve
        # at 80 s)
        if floor_seen:
            at_limit &= np.array([COLS[j] != "B" for j in active])
        # a B, K or R whose line the curve ends up clearly below -- the fitted total above
        # the 95 % band, by more than 10 %, at the last well-determined tau where that term is
        # the largest part of the total -- is not in the data either (the MTi-G: a "floor" of
        # 11.7 deg/h fitted across a bump, while the curve goes on falling to 5-9 deg/h from
        # 300 s on): treated the same way. A dip in the middle (a periodic component, as on
        # the ADIS16405 accelerometers at 2-10 s) with the floor back after it is not.
        a_all = full_a_all[:, active]
        parts = a_all * p
        tot2 = np.maximum(parts.sum(axis=1), 1e-300)
        tot = np.sqrt(tot2)
        over = (tot > hi95) & (np.sqrt(s2_all) < (1.0 - DEPARTURE_REL) * tot)

        def back_down(i: int, k: int) -> bool:
            # the curve at tau k has come back down to what the other terms give: their total
            # without term i reaches the lower end of the band there. A curve still above the
            # others' total beyond its band shows the term at that tau -- only less of it than
            # the fit's line, or no more than the curve's limit -- so the term is kept (the
            # self-check names the taus its line misses). Seen with --taus all: a 12 h
            # consumer_mems gz (K 24.7 deg/h/sqrt(h) emulated) had K pressed at its limit and
            # dropped, bounded at 15.1; on the ADIS16405 ay, with the curve flat at 3.4e-3
            # m/s^2 over 250-600 s and the others' total at 2.1e-3 (lo95 2.5e-3), K dropped by
            # the tail rule below and bounded at 26.4, against octave's 53.6 [36.7, 99.2].
            # The band is the family-wise one (lo_fw, the same m_eff as the limits): k is
            # picked from the informative taus (the last one the term rules, or the one setting
            # its limit), and a pointwise 95 % edge there decided on a knife edge that the tau
            # set moves -- the MTi-G bag with 3 dropped messages, --taus all: N alone 6.867
            # deg/h at 327.7 s against lo95 6.883 (0.25 % short), so B stayed as 19.9 [15.0,
            # 29.7] deg/h, its whole interval above min sigma / 0.664 = 13.66, the total 14.9
            # where the curve is 9.08; octave bounded B at 13.66 (lo_fw there: 6.05)
            return math.sqrt(max(tot2[k] - parts[k, i], 0.0)) >= lo_fw[k]

        # a term pressed against its limit: judged at the tau that sets the limit (the tau
        # where the term's line meets hi95)
        lim_idx = inf_idx if inf_idx.size else np.arange(tau_all.size)
        for i in np.flatnonzero(at_limit):
            k = lim_idx[np.argmin(hi_fw[lim_idx] ** 2 / np.maximum(a_all[lim_idx, i], 1e-300))]
            at_limit[i] = back_down(i, int(k))
        for i, j in enumerate(active):
            if COLS[j] not in CONSTRAINED or p[i] <= 0:
                continue
            ruled = np.flatnonzero(inf95 & (parts[:, i] >= 0.5 * tot2))
            # and the curve keeps falling away from the line over the last octave of those
            # taus (data / total down by > 10 %), not a dip that one low tau makes (one
            # informative tau outside its 95 % band is a 1-in-20 event); for B only when no
            # floor is seen (floor_seen: a 30-minute emulated capture with a true floor, whose
            # last floor taus fell low by chance, had B dropped and the total 4x below the
            # curve at 80-160 s)
            # and the curve there has come back down to the other terms (back_down)
            if ruled.size and over[ruled[-1]] and not (floor_seen and COLS[j] == "B"):
                tail = ruled[tau_all[ruled] >= TAIL_SPAN * tau_all[ruled[-1]] * (1.0 - 1e-9)]
                ratio = np.sqrt(s2_all[tail]) / tot[tail]
                if ratio[-1] < (1.0 - DEPARTURE_REL) * ratio[0] and back_down(i, ruled[-1]):
                    at_limit[i] = True
        # a B held at the curve's own limit where the curve still falls there shows no floor
        # at that level: a bound (no more than the limit), whatever the other rules say
        if b_falling and B_IDX in active:
            ib = active.index(B_IDX)
            if p[ib] >= b_pt * (1.0 - 1e-6):
                at_limit[ib] = True
        score = np.where(at_limit, -1.0, score)
        # a B the curve needs is kept however weak its significance (see _floor_needs_b)
        if select and B_IDX in active:
            ib = active.index(B_IDX)
            # ... and a B the presence test does not find (b_presence_test: every other
            # shape present, the filter's 1/tau^2 term, taus past the filter) goes first
            if b_test["tested"] and not b_test["p_value"] < B_TEST_ALPHA:
                score[ib] = min(score[ib], 0.0)
        # ... and so do K and R where the presence test of a rise does not find one
        if select and presence["K"]["tested"] and not presence["K"]["p_value"] < B_TEST_ALPHA:
            for i, j in enumerate(active):
                if COLS[j] in PRESENCE_NULL["K"]:
                    score[i] = min(score[i], 0.0)
        if select and B_IDX in active:
            ib = active.index(B_IDX)
            if 0.0 <= score[ib] < 1.0 and p[ib] > 0 and _floor_needs_b(
                    full_a, s2, e, tau, active, p, cov_terms, iterations, model_err,
                    upper_all, inflate, s2_all, lo95, hi95, tau_all, e_all, full_a_all):
                score[ib] = 1.0
                needed_terms.add(B_IDX)
            else:
                needed_terms.discard(B_IDX)
            # (a significant B is not demoted when the curve shows no flat octave where B
            # dominates: on the emulator's declared_only profile, N + B + K, that dropped a
            # true B hidden in the bottom of the V and K took it: 1.50e-5 [1.28e-5, 1.79e-5]
            # rad/s/sqrt(s) for 1e-5; the MTi-G small-gap case it was made for holds without it)
        # a white noise (N) held at the curve's own limit is what the curve's shortest
        # well-determined taus show (sigma known there to < 1 %): kept as an estimate however
        # the misfit elsewhere inflates its sd (the Astro Pi gyros: N at its limit, B and K
        # bounds, every term dropped otherwise and the total 0). Not Q: each limit is that of
        # the term alone, and Q and N both at theirs put the total 1.41x over the same tau
        for i, j in enumerate(active):
            if COLS[j] == "N" and p[i] > 0 and p[i] >= held[j] * (1.0 - 1e-6):
                score[i] = max(score[i], 1.0)
                held_needed.add(j)
            else:
                held_needed.discard(j)
        # the Gauss-Markov term stays: its own likelihood-ratio test (allan_gm) decided it
        if GM_IDX in active:
            score[active.index(GM_IDX)] = max(score[active.index(GM_IDX)], 1.0)
            # ... and beside it a K whose significance it weakens (at tau << Tc the process
            # is a random walk too) is kept where the curve needs it, as B for a floor: the
            # model without K runs below the band (data above) over an octave of rising
            # curve (slope >= +FLAT_SLOPE) where the fit with K is inside it (simulated white +
            # GM + K, tests/test_allan_gm_fit.py seed 4: K dropped at z = 1.80, the total
            # 0.23-0.30x the curve past 1000 s)
            ik = active.index(K_IDX) if K_IDX in active else None
            if (select and ik is not None and 0.0 <= score[ik] < 1.0 and p[ik] > 0
                    and _floor_needs_b(full_a, s2, e, tau, active, p, cov_terms, iterations,
                                       model_err, upper_all, inflate, s2_all, lo95, hi95,
                                       tau_all, e_all, full_a_all, term=K_IDX)):
                score[ik] = 1.0
                needed_terms.add(K_IDX)
            else:
                needed_terms.discard(K_IDX)
        # no more resolved terms than the taus leave a degree of freedom for: with as many
        # positive terms as taus the covariance of the estimates is singular and its
        # pseudo-inverse gave every term a narrow interval -- a record whose gaps left
        # stretches of 4 samples (a clock's 3 + 1 reporting cycle read as gaps) had Q, N, B,
        # K and R all "resolved" from 2 taus, chi-square 0 on "1 dof". The weakest goes first
        if select and len(active) > 1 and int(np.count_nonzero(p > 0)) >= tau.size:
            i_min = min(range(len(active)), key=lambda i: score[i])
            score[i_min] = min(score[i_min], 0.0)
        weak = [i for i in range(len(active)) if score[i] < 1.0]
        if not select or not weak or len(active) == 1:
            break
        worst = min(weak, key=lambda i: score[i])
        if at_limit[worst]:
            pinned_terms.add(active[worst])
        dropped.append(active.pop(worst))
    values = dict(zip(active, p))
    sds = dict(zip(active, sd))
    for j in dropped:  # one-sided bound: the term refitted (unconstrained) with the others
        values[j], sds[j] = _bound_fit(full_a[:, active + [j]], s2, e, active + [j],
                                       cov_terms, np.append(p, 0.0), iterations, chi2_red,
                                       model_err, inflate)
    # the curve's hard limit on each term (no bound is reported above it): read off the
    # well-determined taus only -- those whose 95 % band is informative, hi95/lo95 =
    # sqrt(chi2_0.975(nu) / chi2_0.025(nu)) <= 2, i.e. EDF nu >= 16.95, where the true sigma
    # lies within 0.75 .. 1.50 x the measured one. A tau with a handful of averages (nu = 3:
    # 0.57 .. 3.6 x) says little about the true sigma there and must not cut a bound: a 12 h
    # consumer_mems gy had its K bound cut to 5.86 deg/h/sqrt(h) by the last octave tau
    # (10486 s, nu 3.1, sigma 5.8 deg/h where the emulated K alone gives 24), excluding the
    # truth 24.7 and disagreeing with --taus all (30.3 [21.3, 52.3]). Without an informative
    # tau (a capture of a few minutes) every tau counts
    # (every tau, a rising front included: no bound is reported above what the curve shows)
    inf95_front = (np.sqrt(s2_front) * np.sqrt(e_front / chi2.ppf(0.025, e_front))
                   <= INFORMATIVE_RATIO * np.sqrt(s2_front) * np.sqrt(e_front / chi2.ppf(0.975, e_front)))
    lim_sel = inf95_front if np.any(inf95_front) else np.ones(tau_front.size, dtype=bool)
    limits = curve_limits(tau_front[lim_sel], np.sqrt(s2_front[lim_sel]))
    lim_tau = curve_limit_taus(tau_front[lim_sel], np.sqrt(s2_front[lim_sel]))
    # ... but the measured curve is itself an estimate: a term's 95 % upper bound may be cut
    # only by what the curve permits at 95 %, the same read-off of the family-wise upper
    # band (hi_fw's construction on these taus: at most LIMIT_ALPHA that the true curve is
    # above it anywhere). Cut at the measured minimum, the bound excluded the truth whenever
    # the curve's lowest well-determined point fell below the true curve there: 5-minute
    # quickstart captures (configs/sim.yaml, B 5 deg/h, the curve 9 % above its floor at its
    # last well-determined tau) had B bounds below 5 deg/h in 52 of 600 gyro fits, B's
    # coverage 85 % (benchmarks/allan_quickstart_cov.py). Where the model needs its own error
    # (model_err >= MODEL_ERROR_HOLD) the estimates are held to the measured curve
    # (_point_limits) and so are the bounds, as before
    limits95 = curve_limits(tau_front[lim_sel],
                            _family_band(s2_front[lim_sel], e_front[lim_sel], m_eff))
    bound_cap, cap_source = ((limits, "curve") if model_err >= MODEL_ERROR_HOLD
                             else (limits95, "band"))
    out_terms: dict[str, dict] = {}
    coeff_sq: dict[str, float] = {}
    coefs: dict[str, NC.Coefficient] = {}
    for t in terms:
        j = TERMS.index(t)
        pj, sdj = float(values[j]), float(sds[j])
        unit_f, fac = FIELD_UNITS[sensor][t]
        unit_si = SI_UNITS[sensor][t]
        entry: dict = {"name": TERM_NAMES[sensor][t]}
        lim = limits[t]
        # dropped because the fit pressed it against the curve's limit (see above)
        entry["pinned_at_curve_limit"] = j in pinned_terms
        # kept because the curve needs it (a floor the other terms cannot reach): reported
        # as an estimate with its interval however wide
        entry["kept_for_floor"] = j in needed_terms and j in active and t == "B"
        if t == "K" and tc_fit is not None:  # kept beside the Gauss-Markov term for a rise
            entry["kept_for_rise"] = j in needed_terms and j in active
        # held at the curve's own limit (_point_limits, model error >= MODEL_ERROR_HOLD): the
        # fit wanted more of the term than the curve allows
        entry["held_at_curve_limit"] = bool(j in active and math.isfinite(held[j])
                                            and upper_all[j] <= held[j]
                                            and pj >= held[j] * (1.0 - 1e-6) and pj > 0)
        if math.isfinite(held[j]):
            # the limit the fit held the term to: curve_limit_* below, but for Q and N read
            # past a low-pass filter's taus (_filter_taus) and, like every hold, past a rising
            # front -- so an N above curve_limit_* (set inside the filter's taus) is not a
            # contradiction (ADIS16405: N 1.2x the curve at tau0, at the limit past m = 32)
            entry[f"held_limit_{unit_si}"] = math.sqrt(held[j])
            entry[f"held_limit_{unit_f}"] = math.sqrt(held[j]) * fac
        if t in presence and presence[t].get("tested"):
            entry["presence_test"] = dict(presence[t])  # b_presence_test: the p-value that decided
        nu = 2.0 * pj * pj / max(sdj * sdj, 1e-300)  # Satterthwaite dof of p_j
        kept = j in active and sdj > 0 and (pj - _Z95 * sdj > 0 or not select and pj > 0
                                            or (j in needed_terms or j in held_needed) and pj > 0)
        if kept and not nu >= MIN_ESTIMATE_EDF:
            # kept without its own significance (held at the curve's limit, kept for a floor,
            # select=False) but knowing less than one squared normal deviate: a bound at the
            # curve's limit (docs/allan.md, "An estimate needs one degree of freedom")
            entry["edf_below_estimate"] = nu
            kept = False
        if kept:
            coeff_sq[t] = pj
            # the interval: nu read at each candidate value, not at p_j (_neyman_chi2_ci)
            ij, a_act = active.index(j), full_a[:, active]
            # both intervals start at nu(p_j) and a fixed point repeats its value: each
            # candidate value's sd is computed once (a pure function of it)
            sd_memo: dict[float, float] = {}

            def sd_at(v: float, ij: int = ij, a_act: np.ndarray = a_act,
                      memo: dict[float, float] = sd_memo) -> float:
                if v not in memo:
                    memo[v] = _sd_at(a_act, s2, e, active, cov_terms, p, ij, v, chi2_red,
                                     model_err, inflate)
                return memo[v]

            coefs[t] = NC.Coefficient(math.sqrt(pj), _neyman_chi2_ci(pj, sd_at, 0.683),
                                      _neyman_chi2_ci(pj, sd_at, 0.95), edf=nu)
        else:
            coeff_sq[t] = 0.0
            ub = math.sqrt(max(pj, 0.0) + _Z95_ONE * sdj)
            source = "fit"
            if not ub <= bound_cap[t]:  # never above what the curve allows (also for nan)
                ub, source = bound_cap[t], cap_source
            est = min(math.sqrt(max(pj, 0.0)), ub)
            coefs[t] = NC.Coefficient(0.0 if math.isnan(est) else est, upper95=ub, bound_from=source)
        entry[f"curve_limit_{unit_si}"] = lim
        entry[f"curve_limit_{unit_f}"] = lim * fac
        entry["curve_limit_tau_s"] = lim_tau[t]  # the tau that sets it
        entry[f"curve_limit95_{unit_si}"] = limits95[t]  # ... and read off the 95 % band
        entry[f"curve_limit95_{unit_f}"] = limits95[t] * fac
        out_terms[t] = entry
    gm_coefs: tuple = ()
    gm_term = None
    gm_s2_front = None
    if tc_fit is not None:
        gm_term, gm_coef = _gm_result(
            gm_prof, tc_fit, values[GM_IDX], sds[GM_IDX], sensor, tau, s2, e, full_a, active,
            upper_all, cov_at, iterations, model_err, inflate, tau_front, s2_front,
            e_front, _gm_limit(tc_fit, tau_all, s2_all, inf95, None, model_err))
        gm_coefs = (gm_coef,)
        coeff_sq["GM"] = gm_coef.sigma.value ** 2 if gm_coef.sigma.resolved else 0.0
        gm_s2_front = gm_column(tau_front, tc_fit) * coeff_sq["GM"]
    if tau0 is not None and n_phase is not None:  # with the GM term's parameters when it is in
        gm_crb = _add_crb(out_terms, coefs, float(tau0), int(n_phase),
                          gm=((gm_coefs[0].sigma.value, gm_coefs[0].tau_c_s)
                              if gm_coefs and gm_coefs[0].sigma.resolved else None),
                          gm_bound=((gm_coefs[0].sigma.upper95, gm_coefs[0].tau_c_s)
                                    if gm_coefs and not gm_coefs[0].sigma.resolved else None))
        if gm_term is not None and gm_crb:  # the term's own figures
            gm_term["crb"] = gm_crb
    # the decision is taken on the model as reported (the supported terms, statistical
    # covariance) completed by the terms reported only as bounds, each within its bound
    # (_admissible_completion): a bounded term's part of the total is not known to be 0, only
    # to be at most its bound. Without it, the check judged the resolved terms alone and called
    # a B present but unresolved a misfit (5-minute quickstart captures, configs/sim.yaml: the
    # total below the curve at the last taus, 250 of 600 gyro checks failed). The statistic is
    # still never that of the fit with the term unconstrained, only within its reported bound
    # (seen: a B pinned at the curve's limit and dropped, the total 4x below the curve at 80 s,
    # while the fit with B had p = 0.83 and the departure was called chance)
    cols_rep = [TERMS.index(t) for t in terms]
    p_rep = np.array([coeff_sq[t] for t in terms])
    ub_rep = np.array([coefs[t].upper95 ** 2 if not coefs[t].resolved else 0.0 for t in terms])
    names_rep = list(terms)
    if tc_fit is not None:  # the Gauss-Markov term is part of the reported model
        cols_rep = cols_rep + [GM_IDX]
        p_rep = np.append(p_rep, coeff_sq["GM"])
        sig = gm_coefs[0].sigma
        ub_rep = np.append(ub_rep, sig.upper95 ** 2 if not sig.resolved else 0.0)
        names_rep.append("GM")
    ub_rep = np.where(np.isfinite(ub_rep) & (ub_rep > 0), ub_rep, 0.0)
    a_rep = full_a[:, cols_rep]
    p_adm = _admissible_completion(full_a, s2, e, cov_terms, cols_rep, p_rep, ub_rep)
    p_all = p_rep + p_adm
    # the completion's sigma^2 at every tau the check judges, and what it records per term
    a_front = full_design(tau_front, tc_fit)[:, cols_rep]
    adm_terms = {n: {"value_si": math.sqrt(p_adm[k]), "upper95_si": math.sqrt(ub_rep[k]),
                     "fraction_of_bound": math.sqrt(p_adm[k] / ub_rep[k])}
                 for k, n in enumerate(names_rep) if ub_rep[k] > 0}
    check = self_check(tau_front, np.sqrt(s2_front), e_front,
                       {t: v for t, v in coeff_sq.items() if t in TERMS}, m_eff,
                       extra_avar=gm_s2_front,
                       bounded_avar=a_front[:, ub_rep > 0] * p_adm[ub_rep > 0],
                       bounded_names=[n for k, n in enumerate(names_rep) if ub_rep[k] > 0])
    check["bounded_terms"] = adm_terms
    # the rising front left out of the fit (rising_front): its taus, which the check names
    check["front_excluded"] = ({"n_taus": int(front), "tau_from_s": float(tau_front[0]),
                                "tau_to_s": float(tau_front[front - 1]),
                                "top_tau_s": float(tau_front[front])} if is_front else None)
    # the low-pass filter's region left out of the fit (filter_region): its taus, which the
    # check names ("data below the fit": the filter)
    check["filter_excluded"] = filt
    # the statistic of the model as reported (the resolved terms), as before ...
    r_rep = _whitened_residual(full_a, s2, e, cov_terms, cols_rep, p_rep)[0]
    dof_rep = max(1, tau.size - int(np.count_nonzero(p_rep > 0)))
    chi_rep = float(r_rep @ r_rep)
    p_value = float(chi2.sf(chi_rep, dof_rep))
    # ... and of the completed total, which decides (``completed``)
    r_c = _whitened_residual(full_a, s2, e, cov_terms, cols_rep, p_all)[0]
    dof_c = max(1, tau.size - int(np.count_nonzero(p_all > 0)))
    p_c = float(chi2.sf(float(r_c @ r_c), dof_c))
    check["completed"].update({"chi2": float(r_c @ r_c), "dof": dof_c, "p_value": p_c})
    check.update({"chi2": chi_rep, "dof": dof_rep, "p_value": p_value,
                  "chi2_before_selection": list(chi2_stat), "model_error_rel": model_err})
    # the fit passes when no informative tau is off, or when the reported model describes the
    # curve as a whole (statistical chi-square within its 99 % point: a few of ~70 taus
    # outside a 95 % band are then chance, and are still listed)
    # outside: against the family-wise band (self_check), so that a pure-noise curve fails
    # at the design rate CHECK_ALPHA (at most) whether its taus are octave-spaced or dense
    # ... and a chi-square beyond its 99 % point is a finding, never a pass, even when every
    # informative tau is inside its family-wise band (the OCXO record's quiet half, tests/data:
    # every tau inside, chi-square 179.6 on 37 dof): ``ok`` is false, ``chi2_beyond_99`` says why and
    # ``chi2_carried_by`` names the run of taus that carries the chi-square
    # ... all of it on the completed total (the resolved terms and the bounded ones within
    # their bounds, _admissible_completion); ``passes_on_bounds``: the resolved terms alone
    # would have failed it
    beyond = bool(p_c < MODEL_ERROR_P)
    check["ok"] = bool((check["completed"]["n_outside_familywise"] == 0 or p_c >= MODEL_ERROR_P)
                       and not beyond)
    check["chi2_beyond_99"] = beyond
    # the run that carries it, named on the total reported and plotted (the resolved terms':
    # where a reader sees the curve leave it)
    check["chi2_carried_by"] = (chi2_carrier(tau, s2, a_rep @ p_rep, r_rep) if beyond else None)
    check["passes_on_bounds"] = bool(check["ok"] and (p_value < MODEL_ERROR_P))
    model = "IEEE 952 model" + (" + a first-order Gauss-Markov term" if tc_fit is not None else "")
    out = {"method": f"joint generalized least squares ({model}, covariance of the "
                     "sigma^2 estimates across taus)" if cov_terms is not None else
                     f"joint EDF-weighted least squares ({model}, diagonal)",
           "sensor": sensor, "terms": out_terms,
           # the IEEE 952 coefficients (SI) with their intervals or upper bounds, and the
           # Gauss-Markov term when fitted (gm); the model the fit reports (and checks) is
           # fitted_avar(): the bounded terms at 0
           "coefficients": NC.NoiseCoefficients(**coefs, gm=gm_coefs, sensor=sensor,
                                                source="rigctl allan (IEEE 952 joint fit"
                                                + (" + Gauss-Markov)" if gm_coefs else ")")),
           "reduced_chi2": chi2_red, "n_taus": int(tau.size), "check": check}
    if gm_term is not None:
        out["gm_term"] = gm_term
    return out


#: the Gauss-Markov term's Tc: this many grid points per octave over the candidate's range,
#: then FINE_POINTS between the points two steps either side of the best
GM_GRID_PER_OCTAVE = 4
GM_FINE_POINTS = 33
#: ... and, where the profile's 95 % set still reaches the range's lower end, continued below
#: it down to the fit's first tau / this (a Tc below the first tau is identified only by the
#: curve's slope there: sigma^2(tau) / (N^2 / tau) = 1 - 3 Tc / (2 tau) + ... for tau >> Tc)
GM_BELOW_FIRST_TAU = 4.0


def _gm_limit(tc: float, tau_all: np.ndarray, s2_all: np.ndarray, inf95: np.ndarray,
              hi_fw: np.ndarray | None, model_err: float) -> float:
    """sigma_GM^2's limit at correlation time ``tc``: the curve's family-wise upper band
    ``hi_fw`` over the well-determined taus (as B, K and R: every term adds a non-negative
    part, sigma_GM^2 g(tau) <= hi^2), and, where the model needs its own error (model_err >=
    MODEL_ERROR_HOLD), the curve's own limit min sigma^2 / g(tau) (as every term, _point_limits).
    ``hi_fw`` None: the latter alone (inf where it does not apply)."""
    g = np.maximum(gm_column(tau_all, tc), 1e-300)
    sel = inf95 if np.any(inf95) else np.ones(tau_all.size, dtype=bool)
    lim = math.inf if hi_fw is None else float(np.min(hi_fw[sel] ** 2 / g[sel]))
    if model_err >= MODEL_ERROR_HOLD and np.any(inf95):
        lim = min(lim, float(np.min(s2_all[inf95] / g[inf95])))
    return lim


def tc_profile_interval(tcs: np.ndarray, crit: np.ndarray, chi: np.ndarray, dof: int
                        ) -> tuple[tuple[float, float], list[bool], np.ndarray, float]:
    """Tc's 95 % profile interval from a profile evaluated at the increasing ``tcs`` (s):
    ``crit`` the criterion minimised (-2 ln L or a chi-square), ``chi`` the chi-square there
    (its value at the best over ``dof`` is the overdispersion, at least 1). The set is the Tc
    whose criterion is within over x chi2_0.95(1) of the least, bracketed by the next evaluated
    Tc either side (the crossing lies between); an end of the set at the first or last Tc
    evaluated is the range's, not the data's: open. Returns ((lo, hi), [lower open, upper
    open], the indices of the bracketed set, over). One rule for the candidate test's profile
    (allan_gm) and the joint fit's (:func:`_gm_profile`, :func:`_gm_result`)."""
    crit = np.asarray(crit, dtype=float)
    best = int(np.argmin(crit))
    over = max(1.0, float(chi[best]) / max(int(dof), 1))
    thr = float(crit[best]) + over * float(chi2.ppf(0.95, 1))
    inside = np.flatnonzero(crit <= thr)
    inside = np.arange(max(inside.min() - 1, 0), min(inside.max() + 1, tcs.size - 1) + 1)
    return ((float(tcs[inside].min()), float(tcs[inside].max())),
            [bool(crit[0] <= thr), bool(crit[-1] <= thr)], inside, over)


def extend_tc_profile_below(tcs: np.ndarray, c: np.ndarray,
                            at: Callable[[float], tuple[float, float]], floor: float, dof: int,
                            per_octave: int = GM_GRID_PER_OCTAVE, step: float | None = None
                            ) -> tuple[np.ndarray, np.ndarray]:
    """A Tc profile continued below its lowest Tc an octave at a time (``per_octave`` points,
    the grid's step where it has one), down to ``floor`` (s), while its 95 % set
    (:func:`tc_profile_interval`) still reaches the lowest Tc evaluated: an interval cut by the
    range searched would be reported as the data's. ``step``: ln of the ratio between the new
    points (default: the first two Tc's). ``c``: rows (chi-square, criterion) at
    ``tcs``; ``at(tc)`` gives that row at a new Tc. A Tc below the first tau is identified
    only weakly, by the curve's slope there (for tau >> Tc, g = 2 Tc/tau (1 - 3 Tc/(2 tau) +
    ...)), hence the floor (the fit's: its first tau / GM_BELOW_FIRST_TAU). Returns the
    extended (tcs, c)."""
    if step is None:
        step = math.log(tcs[1] / tcs[0]) if tcs.size > 1 else math.log(2.0) / per_octave
    while tcs[0] > floor * (1.0 + 1e-9):
        if not tc_profile_interval(tcs, c[:, 1], c[:, 0], dof)[1][0]:
            break
        new = tcs[0] * np.exp(-step * np.arange(per_octave, 0, -1))
        if new[0] <= floor * (1.0 + 1e-9):  # the last octave: ends at the floor
            new = np.append(floor, new[new > floor * (1.0 + 1e-9)])
        tcs = np.concatenate((new, tcs))
        c = np.concatenate((np.array([at(float(tc)) for tc in new]).reshape(-1, 2), c))
    return tcs, c


def _gm_profile(gm: dict, tau: np.ndarray, s2: np.ndarray, e: np.ndarray, full_a: np.ndarray,
                active: list[int], upper_all: np.ndarray, cov_at: Callable[[float], dict | None],
                iterations: int, tau_all: np.ndarray, s2_all: np.ndarray, inf95: np.ndarray,
                hi_fw: np.ndarray) -> tuple[float, dict, float, tuple]:
    """Tc of the fit's Gauss-Markov term: the profile of the joint fit's chi-square (every
    IEEE 952 term of ``active`` and sigma_GM^2, non-negative, within their limits; the
    covariance of the estimates at the fit) over GM_GRID_PER_OCTAVE points per octave of the
    candidate's range ``gm["tc_grid_s"]``, first with the statistical covariance alone, then,
    where that leaves the model's own error (the fit's _model_error at the best Tc), with it;
    refined with GM_FINE_POINTS between the grid points two steps either side of the best.
    Tc is the least -2 ln L = chi-square + ln det C over the Tc tried (``at``). Returns (Tc,
    the profile {"tc_s", "chi2", "neg2lnl", "dof", "model_error_rel"}, the model error at Tc,
    the statistical goodness of fit at Tc (chi2, dof, p))."""
    lo, hi = (float(v) for v in gm["tc_grid_s"])
    n = max(2, int(math.ceil(math.log2(hi / lo) * GM_GRID_PER_OCTAVE)) + 1)
    grid = np.exp(np.linspace(math.log(lo), math.log(hi), n))
    w = e / (2.0 * s2 ** 2)

    def at(tc: float, eps: float) -> tuple[float, float]:
        """(chi-square, chi-square + ln det C) of the fit at ``tc``: C, the covariance of the
        estimates, depends on Tc (the Gauss-Markov kernel) and on the fitted terms, so Tc is
        chosen by the Gaussian likelihood's -2 ln L, not by the chi-square alone, which
        favours the Tc whose C is larger. On 100 simulated captures of the MTi-G's fitted
        model (1.39 h, benchmarks/allan_gm_crb.py) Tc's scatter (sd of estimate/truth) went
        0.181 +- 0.013, mean +6 %, -> 0.145 +- 0.010, mean -3 %: the Cramer-Rao bound's 0.141."""
        a = np.column_stack((full_a[:, active], gm_column(tau, tc)))
        cols = active + [GM_IDX]
        up = np.append(upper_all[active], _gm_limit(tc, tau_all, s2_all, inf95, hi_fw, eps))
        p0 = _nnls_cols(a * np.sqrt(w)[:, None], s2 * np.sqrt(w), up)
        cov = cov_at(tc)
        p, _, rw = _gls(a, s2, e, cols, cov, p0, iterations, eps, up)
        lw = _whiten(_model_cov(cov, p, cols, a, e, eps, None))
        chi = float(rw @ rw)
        return chi, chi + 2.0 * float(np.sum(np.log(np.abs(np.diag(lw)))))

    def err_at(tc: float) -> tuple[float, tuple]:
        a = np.column_stack((full_a[:, active], gm_column(tau, tc)))
        up = np.append(upper_all[active], _gm_limit(tc, tau_all, s2_all, inf95, hi_fw, 0.0))
        return _model_error(a, s2, e, active + [GM_IDX], cov_at(tc), iterations, up)

    floor = min(lo, float(tau[0]) / GM_BELOW_FIRST_TAU)
    dof = max(1, tau.size - len(active) - 1)

    c = np.array([at(tc, 0.0) for tc in grid])  # columns: chi-square, -2 ln L
    grid, c = extend_tc_profile_below(grid, c, lambda tc: at(tc, 0.0), floor, dof)
    eps, stat = err_at(float(grid[int(np.argmin(c[:, 1]))]))
    if eps > 0:  # the profile with the model's own error (its weights decide the fit)
        c = np.array([at(tc, eps) for tc in grid])
        grid, c = extend_tc_profile_below(grid, c, lambda tc: at(tc, eps), floor, dof)
    i = int(np.argmin(c[:, 1]))
    fine = np.exp(np.linspace(math.log(grid[max(i - 2, 0)]),
                              math.log(grid[min(i + 2, grid.size - 1)]), GM_FINE_POINTS))
    fine = fine[~np.any(np.isclose(fine[:, None], grid[None, :], rtol=1e-9), axis=1)]
    tcs = np.concatenate((grid, fine))
    c = np.concatenate((c, np.array([at(tc, eps) for tc in fine]).reshape(-1, 2)))
    o = np.argsort(tcs)
    tcs, c = tcs[o], c[o]
    tc = float(tcs[int(np.argmin(c[:, 1]))])
    if eps > 0:  # the model error at the refined Tc (the one the fit then uses)
        eps, stat = err_at(tc)
    return tc, {"tc_s": tcs, "chi2": c[:, 0], "neg2lnl": c[:, 1], "dof": dof,
                "model_error_rel": eps, "kernel": cov_at(tc) is not None}, eps, stat


def _gm_result(prof: dict, tc: float, p_gm: float, sd_gm: float, sensor: str,
               tau: np.ndarray, s2: np.ndarray, e: np.ndarray, full_a: np.ndarray,
               active: list[int], upper_all: np.ndarray,
               cov_at: Callable[[float], dict | None],
               iterations: int, model_err: float, inflate: np.ndarray | None,
               tau_front: np.ndarray, s2_front: np.ndarray, e_front: np.ndarray,
               point_limit: float) -> tuple[dict, "NC.GaussMarkov"]:
    """The fitted Gauss-Markov term: Tc's 95 % interval from the profile (the Tc whose -2 ln L
    is within chi2_0.95(1) of the least, scaled by the overdispersion -- the chi-square at the
    best Tc over its dof, at least 1 -- bracketed by the next evaluated Tc either side); sigma_GM's intervals Satterthwaite's with the marginal
    sd of p = sigma_GM^2 (Tc estimated too, not known)::

        sd(p)^2 = sd(p | Tc)^2 + (dp/d ln Tc)^2 sd(ln Tc)^2

    sd(p | Tc) the GLS sd at the fitted Tc, dp/d ln Tc the slope of p refitted at each Tc of
    that set (the final terms, as the selection fits them; least squares over the set), sd(ln
    Tc) = ln(hi / lo) / (2 x 1.96) from Tc's interval (the linear-Gaussian marginal: p's
    estimate given Tc moves along that slope). It was the union of each Tc's conditional
    interval, which adds the two parts linearly instead of in quadrature: on simulated
    captures of the MTi-G's fitted model (benchmarks/allan_gm_crb.py) 1.40x wider than the
    scatter of sigma_GM, which is the Cramer-Rao bound's. Also the curve's limit and whether
    the fit was held at it."""
    tcs, c = prof["tc_s"], prof.get("neg2lnl", prof["chi2"])
    tc_ci, tc_open, inside, over = tc_profile_interval(tcs, c, prof["chi2"], prof["dof"])
    ig = active.index(GM_IDX)

    def interval(pj: float, sdj: float, conf: float) -> tuple[float, float] | None:
        if not (pj > 0 and sdj > 0):
            return None
        return _chi2_ci(pj, 2.0 * pj * pj / (sdj * sdj), conf)

    along = [(math.log(tc), p_gm)]  # (ln Tc, p refitted there) over Tc's interval
    for k in inside:
        if math.isclose(float(tcs[k]), tc, rel_tol=1e-12):
            continue
        a = full_a.copy()
        a[:, GM_IDX] = gm_column(tau, float(tcs[k]))
        a = a[:, active]
        w = e / (2.0 * s2 ** 2)
        up = upper_all[active]
        p0 = _nnls_cols(a * np.sqrt(w)[:, None], s2 * np.sqrt(w), up)
        try:
            p, _, _ = _gls(a, s2, e, active, cov_at(float(tcs[k])), p0, iterations,
                             model_err, up, inflate)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if p[ig] > 0:
            along.append((math.log(float(tcs[k])), float(p[ig])))
    sd_marg = sd_gm
    x = np.array([a for a, _ in along])
    if x.size >= 2 and np.ptp(x) > 0 and math.isfinite(sd_gm):
        slope = float(np.polyfit(x, np.array([b for _, b in along]), 1)[0])
        sd_ln_tc = math.log(tc_ci[1] / tc_ci[0]) / (2.0 * 1.959964)
        sd_marg = math.sqrt(sd_gm * sd_gm + (slope * sd_ln_tc) ** 2)
    ci95 = interval(p_gm, sd_marg, 0.95)
    ci68 = interval(p_gm, sd_marg, 0.683)
    g_front = np.maximum(gm_column(tau_front, tc), 1e-300)
    inf_front = (np.sqrt(e_front / chi2.ppf(0.025, e_front))
                 <= INFORMATIVE_RATIO * np.sqrt(e_front / chi2.ppf(0.975, e_front)))
    sel = inf_front if np.any(inf_front) else np.ones(tau_front.size, dtype=bool)
    lim = math.sqrt(float(np.min(s2_front[sel] / g_front[sel])))
    held = bool(math.isfinite(point_limit) and p_gm >= point_limit * (1.0 - 1e-6) and p_gm > 0)
    if ci95:
        sig = NC.Coefficient(math.sqrt(p_gm), ci68, ci95,
                             edf=2.0 * p_gm * p_gm / (sd_marg * sd_marg))
    else:  # the joint fit put no Gauss-Markov term where the candidate saw one: a bound
        ub = min(math.sqrt(max(p_gm, 0.0) + _Z95_ONE * max(sd_gm, 0.0)), lim)
        sig = NC.Coefficient(min(math.sqrt(max(p_gm, 0.0)), ub), upper95=ub,
                             bound_from="curve" if ub >= lim else "fit")
    coef = NC.GaussMarkov(sig, tc, tau_c_ci95=tc_ci, tau_c_ci95_open=(tc_open[0], tc_open[1]))
    term = {"name": "first-order Gauss-Markov process", "tc_s": tc, "tc_ci95_s": list(tc_ci),
            "tc_ci95_open": tc_open,
            "tc_profile_s": [float(tcs[0]), float(tcs[-1])], "tc_points": int(tcs.size),
            "sigma_si": sig.value, "sigma_ci95_si": list(sig.interval95),
            "resolved": sig.resolved, "curve_limit_si": lim, "held_at_curve_limit": held,
            "overdispersion": over, "profile_model_error_rel": prof["model_error_rel"],
            "covariance": ("the Gauss-Markov kernel of allan_cov at each Tc"
                           if prof.get("kernel") else "none (EDF-weighted, diagonal)")}
    if math.isfinite(point_limit):
        term["held_limit_si"] = math.sqrt(point_limit)
    return term, coef


#: an estimate needs at least this Satterthwaite EDF (nu = 2 p^2 / sd(p)^2): below it sd(p) >
#: sqrt(2) p, less than one squared normal deviate tells about its variance, and the chi-square
#: interval degenerates (nu = 0.01: [1.18, inf) x the value; below ~1e-3 [0, inf)). A term kept
#: without its own significance (held at the curve's limit, kept for a floor) with fewer is a
#: bound at the curve's limit -- the one thing the data say about it. A significant term has
#: nu > 2 x 1.96^2 = 7.7 and is never affected.
MIN_ESTIMATE_EDF = 1.0

#: a B, K or R is dropped as a bump when the curve is clearly below the total at the last
#: informative tau it dominates and falls away from it from TAIL_SPAN x that tau on
TAIL_SPAN = 0.5
#: a floor is seen when the informative taus go on to FLOOR_AFTER x the tau of the lowest
#: informative upper band point (then a B pressed against its limit is the floor, not a bump)
FLOOR_AFTER = 1.4
#: terms held within the curve's 95 % limit in the fit (see _fit_terms)
CONSTRAINED = ("B", "K", "R")
B_IDX = TERMS.index("B")
K_IDX = TERMS.index("K")
#: a floor needs B when the fit without it leaves the curve's 95 % band (data above) over at
#: least this ratio of taus (an octave), where the fit with B is within it
FLOOR_SPAN = 2.0


def _informative_prefix(inf: np.ndarray) -> np.ndarray:
    """The well-determined taus: informative (EDF >= ~17) up to the first tau that is not.
    A deviation's EDF falls as tau grows for one noise type; a tau past an uninformative one
    is "informative" again only because its noise ID changed on a handful of averages (B1 on
    8-9 averages calling a chance fall of the curve flicker PM: EDF 12.5 at 737 s, then 212
    at 819 s on a 2 h mti_class gyro with --taus all, seed 20002). Those taus set B's hold
    at the curve's last point and the model error to 0.20, and a clear B (octave: 0.90x
    the truth) was pinned there and dropped, the total 4.6-5x below the curve from 11 to
    1638 s (tests/test_allan_false_alarms.py)."""
    inf = np.asarray(inf, dtype=bool)
    if inf.size == 0 or not inf[0]:
        return inf
    return np.logical_and.accumulate(inf)


#: the model error (relative, of sigma^2) from which B (and K) are held to the curve's own
#: limits (see _b_point_limit): real curves the model does not describe need 0.077-0.38
#: (phone 0.08-0.14, Astro Pi gyros 0.15-0.38); 12 h emulated full-profile captures, whose
#: filter edges and quantizer add 0.1-0.2 %, 0.0015-0.0022 -- held there, a chance low at
#: the last well-determined tau made B a bound at 0.7x the truth (mti_class ax octave
#: < 0.0107 mg, all 0.0146) and split octave from all
MODEL_ERROR_HOLD = 0.05


def _b_point_limit(tau: np.ndarray, s2: np.ndarray, inf: np.ndarray) -> tuple[float, bool]:
    """B^2's hold where the IEEE 952 model needs its own error (model_err >=
    MODEL_ERROR_HOLD): the curve's
    own limit, min sigma^2 / 0.664^2 over the well-determined taus ``inf`` (the limit every
    bound is held to; issue 15: no B above min(sigma) / 0.664), and whether the tau that sets
    it is the last well-determined one (the curve still falls there: no floor at that level).

    Why only then: on a curve the model describes (eps ~ 0) the lowest well-determined point
    can be a chance dip of a true floor, and the family-wise band is the right limit (a 12 h
    emulated floor dipping to 0.6x at 2600 s held at this limit gave B 0.6x the truth:
    test_a_chance_dip_of_the_floor_does_not_hold_b_below_the_truth). Where the model needs
    its own error the fit's B is a compromise between terms that do not describe the curve:
    a real Astro Pi gyro (its bias tracked by RTIMULib) falls with slope -0.1 .. -0.4 from 10
    to 1360 s, and N + B put the total 1.4x above the curve at both ends, B 25.8 [23.6,
    28.5] deg/h where the curve's lowest well-determined point allows 18.3. No
    well-determined tau: no hold (a capture of minutes)."""
    if not np.any(inf):
        return math.inf, False
    idx = np.flatnonzero(inf)
    k = idx[int(np.argmin(s2[idx]))]
    return float(s2[k]) / _B_FACTOR, bool(k == idx[-1])


#: a low-pass filter's region: S = sigma^2 tau rises by less each octave, each rise below this
#: fraction of the one before (a filter's deficit c / tau halves per octave: 0.5)
FILTER_DECAY = 0.75


def _filter_taus(tau: np.ndarray, s2: np.ndarray, inf: np.ndarray,
                 tau0: float | None) -> np.ndarray:
    """The leading well-determined taus that a low-pass filter may pull below the white-noise
    line, where N's and Q's curve limits do not hold (a filter subtracts c / tau^2 from
    sigma^2: not an IEEE 952 term, whose parts are all non-negative).

    By default those of fewer than B_TEST_M_MIN samples: the fit's own convention for the
    filter's region (b_presence_test). Read off S = sigma^2 tau (N^2 on a white-noise line)
    at m = 1, 2, 4, ... samples (interpolated in log tau), two cases differ:

    * S rises by less each octave from the second octave on, each rise below FILTER_DECAY of
      the one before: a filter's deficit c / tau fading (it halves per octave). The region
      then runs to the octave where the rises stop shrinking (ADIS16405 gx: rises 0.30, 0.16,
      0.07, 0.04, 0.02 of S(tau0) from m = 1 to 32, then B's rise: m < 32; a 3-tap (1/4, 1/2,
      1/4) filter: 0.30, 0.28, 0.14, 0.07, ... of N^2, m up to where K's rise takes over).
    * S rises by more each octave (the second rise over 1 / FILTER_DECAY of the first): a
      correlated process above the white noise from the first tau on (B, a bump), no filter:
      no tau is left out (the Astro Pi gyros, RTIMULib's output point-sampled every 10 s:
      rises 0.51, 1.10, 2.02; N came out 2.3x the curve at 10 s).

    Without tau0, or a curve that does not start at tau0: none."""
    out = np.zeros(tau.size, dtype=bool)
    idx = np.flatnonzero(inf)
    if tau0 is None or idx.size < 3:
        return out
    lm = np.log2(tau[idx] / tau0)
    if lm[0] > 0.5:
        return out
    ks = np.arange(0, int(np.floor(lm[-1])) + 1)
    m_to = float(B_TEST_M_MIN)
    if ks.size >= 3:
        d = np.diff(np.interp(ks, lm, s2[idx] * tau[idx]))
        if d[0] > 0 and d[1] > d[0] / FILTER_DECAY:
            return out
        # from the second octave on (tau0 itself is special for any filter longer than one
        # sample: a 3-tap (1/4, 1/2, 1/4) gives rises 0.30, 0.28, 0.14, 0.07 of N^2)
        k = 2
        while k < d.size and d[0] > 0 and 0.0 < d[k] < FILTER_DECAY * d[k - 1]:
            k += 1
        if k > 2:
            m_to = max(m_to, 2.0 ** ks[k])
    out[idx[tau[idx] < tau0 * m_to * (1.0 - 1e-9)]] = True
    return out


#: a filter's deficit is left in the fit from the octave where it is at most this many
#: standard deviations of that tau's sigma^2 estimate (filter_region)
FILTER_DEFICIT_SD = 1.0


def filter_region(tau: np.ndarray, s2: np.ndarray, edf: np.ndarray,
                  tau0: float | None) -> dict | None:
    """The leading taus a sensor's low-pass (anti-aliasing) filter pulls below the white-noise
    line, detected from the curve, or None: the taus the fit leaves out (docs/allan.md, "The
    sensor's anti-aliasing filter: its taus left out of the fit").

    A filter whose correlation is short against tau makes the rate's Allan variance
    sigma^2(tau) = N^2 / tau - c / tau^2 + ... (c > 0: the filter's correlation at its lags),
    i.e. S = sigma^2 tau = N^2 - c / tau rises towards N^2 by a deficit that halves per
    octave -- the curve falls faster than tau^-1/2 there -- not an IEEE 952 term, whose parts
    are all non-negative (Q's 3 Q^2 / tau^2 has the other sign). Read at m = 1, 2, 4, ...
    samples (S interpolated in log tau over the well-determined taus, which must start at
    tau0), a filter is found when

    * S rises from m = 1 to 2 and the rise from 2 to 4 is at most FILTER_DECAY of it (a
      fading deficit; B's rise doubles per octave, K's quadruples: the Astro Pi gyros' 0.51,
      1.10, 2.02 are no filter), and
    * the rise is beyond the estimates' noise: S's 95 % upper end at tau0 is below its 95 %
      lower end at m = 4 (each tau's own chi-square band from its EDF; none found on the 20
      unfiltered records of benchmarks/allan_aafilter.py).

    The region then runs to the first octave m = 2^k (k >= 1) where the deficit c / m left,
    c = 4 x (the rise from 2 to 4), is at most FILTER_DEFICIT_SD standard deviations of that
    tau's sigma^2 estimate (S sqrt(2 / EDF)): past it the filter biases no tau by more than
    its own noise -- or, before that, where the rise from one octave to the next grows past
    the one before / FILTER_DECAY by more than twice its noise (another process takes over:
    B, K, a bump; the ADIS16405 az's curve: rises 0.26, 0.17, 0.03, then 0.13 of S(tau0)
    from m = 8 on: m < 8). A longer capture resolves a smaller deficit, so its region reaches
    further (a 5-minute record at 100 Hz through a 2nd-order Butterworth at 0.8 Nyquist: m < 8
    or 16; the 2.8 h ADIS16405 gyros: m < 64). Returns {n_taus, tau_from_s, tau_to_s, m_to (the first m fitted), the
    octave S values relative to S at m_to's octave, c}; None without tau0, a curve that does
    not start at tau0, fewer than four octaves, or no filter found."""
    tau, s2, e = (np.asarray(v, dtype=float) for v in (tau, s2, edf))
    if tau0 is None or tau.size < 3:
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        lo = np.sqrt(s2 * e / chi2.ppf(0.975, e))
        hi = np.sqrt(s2 * e / chi2.ppf(0.025, e))
    idx = np.flatnonzero(_informative_prefix(hi <= INFORMATIVE_RATIO * lo))
    if idx.size < 3:
        return None
    lm = np.log2(tau[idx] / tau0)
    if abs(lm[0]) > 1e-6:
        return None
    ks = np.arange(0, int(np.floor(lm[-1] + 1e-9)) + 1)
    if ks.size < 4:
        return None
    big_s = np.interp(ks, lm, s2[idx] * tau[idx])
    d = np.diff(big_s)
    if not (d[0] > 0 and d[1] <= FILTER_DECAY * d[0]):
        return None
    s_hi0 = float(hi[idx[0]] ** 2 * tau[idx[0]])
    s_lo4 = float(np.interp(2.0, lm, lo[idx] ** 2 * tau[idx]))
    if not s_hi0 < s_lo4:
        return None
    c = 4.0 * max(float(d[1]), 0.0)  # S = N^2 - c / m from m = 2 on: rise 2 -> 4 is c / 4
    sd = big_s * np.sqrt(2.0 / np.interp(ks, lm, e[idx]))

    def grows(k: int) -> bool:
        """The rise from 2^k to 2^(k+1) outgrows the fading deficit beyond the noise: another
        process (B, K, a bump, a tone) takes over from this octave on."""
        return bool(d[k] > max(float(d[k - 1]), 0.0) / FILTER_DECAY
                    + 2.0 * math.hypot(sd[k], sd[k + 1]))

    k = 1
    while k < ks.size - 1 and c / 2.0 ** ks[k] > FILTER_DEFICIT_SD * sd[k] and not grows(k):
        k += 1
    m_to = float(2.0 ** ks[k])
    sel = tau < tau0 * m_to * (1.0 - 1e-9)
    n = int(np.count_nonzero(sel))
    if n == 0:
        return None
    return {"n_taus": n, "tau_from_s": float(tau[0]), "tau_to_s": float(tau[n - 1]),
            "m_to": m_to, "tau_to_fit_s": float(tau0 * m_to),
            "s_over_s_fit": [float(v) for v in big_s[:k + 1] / big_s[k]], "c_rel": c / big_s[k]}


def _point_limits(tau: np.ndarray, s2: np.ndarray, inf: np.ndarray,
                  tau0: float | None) -> np.ndarray:
    """Each term's hold (c_j^2, order TERMS) where the IEEE 952 model needs its own error
    (model_err >= MODEL_ERROR_HOLD): the curve's own limit, min sigma^2 / A_j(tau) over the
    well-determined taus ``inf`` -- the principle of _b_point_limit for every term: where
    the model does not describe the curve, no term is fitted above what the curve allows
    (issue 15). For Q and N the taus of a low-pass filter's region are left out
    (:func:`_filter_taus`); the taus of a rising front are not passed in (rising_front).
    No well-determined tau: no hold."""
    tau, s2, inf = np.asarray(tau, float), np.asarray(s2, float), np.asarray(inf, bool)
    if not np.any(inf):
        return np.full(len(TERMS), np.inf)
    a = design_matrix(tau)
    lim = np.min(s2[inf][:, None] / a[inf], axis=0)
    past = inf & ~_filter_taus(tau, s2, inf, tau0)
    if np.any(past):
        short = np.min(s2[past][:, None] / a[past], axis=0)
        for t in ("Q", "N"):
            lim[TERMS.index(t)] = short[TERMS.index(t)]
    return lim


def _floor_needs_b(full_a: np.ndarray, s2: np.ndarray, e: np.ndarray, tau: np.ndarray,
                   active: list[int], p: np.ndarray, cov_terms: dict | None, iterations: int,
                   model_err: float, upper_all: np.ndarray, inflate: np.ndarray | None,
                   s2_all: np.ndarray, lo95: np.ndarray, hi95: np.ndarray,
                   tau_all: np.ndarray, e_all: np.ndarray,
                   a_all_full: np.ndarray | None = None, term: int = B_IDX) -> bool:
    """Does the curve need B, whatever its significance in the joint fit? Yes when the
    model refitted without B (same weights, model error and robust inflation) runs below the
    curve's 95 % band -- the data above it -- over a run of consecutive taus spanning at
    least an octave (FLOOR_SPAN), at taus where the fit with B is inside the band, and the curve
    is flat over an octave of that run (log-log slope within +-FLAT_SLOPE; the falling side of
    a bump is not a floor): a flat region whose level the other terms cannot reach, which B
    explains. This is the
    self-check's own test (the band) applied to the model without B: dropping B would make
    the reported total leave the band there.

    Why: the significance test (p_B > 1.96 sd_B) with the model error that real curves need
    (16-20 %) drops B at a floor the curve plainly shows (a 2.8 h ADIS16405 gz with --taus
    octave: flat at 29-31 deg/h over 41-328 s, B reported as < 38 deg/h; with the exact
    deviations, 26.6 [17.9, 51.8]). The band is each tau's own 95 % chi-square interval
    (its EDF), so a tau with few averages, whose band is wide, is outside it only when far
    off: no hard cut on the EDF. On white noise + random walk (no B) the model without B
    follows the curve's V-shaped minimum within the band: the false-B rate is measured in
    tests/test_allan_fit.py."""
    keep = [j for j in active if j != term]
    if not keep:
        return True
    ib = active.index(term)
    a = full_a[:, keep]
    p0 = np.delete(p, ib)
    try:
        q, _, _ = _gls(a, s2, e, keep, cov_terms, p0, iterations, model_err, upper_all[keep],
                       inflate)
    except (ValueError, np.linalg.LinAlgError):
        return False
    a_all = design_matrix(tau_all) if a_all_full is None else a_all_full
    without = np.sqrt(np.maximum(a_all[:, keep] @ q, 0.0))
    with_b = np.sqrt(np.maximum(a_all[:, active] @ p, 0.0))
    hit = (without < lo95) & (with_b >= lo95) & (with_b <= hi95) & (e_all > 2.0)
    lt, ld = np.log(tau_all), 0.5 * np.log(np.maximum(s2_all, 1e-300))
    i, n = 0, tau_all.size
    while i < n:
        if hit[i]:
            j = i
            while j + 1 < n and hit[j + 1]:
                j += 1
            if _flat_octave(lt[i:j + 1], ld[i:j + 1], rising=term != B_IDX):
                return True
            i = j + 1
        else:
            i += 1
    return False


#: a floor is flat: the curve's log-log slope over the octave within +-FLAT_SLOPE (white noise
#: gives -1/2, random walk +1/2; the falling side of a bump, as on the MTi-G at 80-330 s, -0.52)
FLAT_SLOPE = 0.25


def _flat_octave(lt: np.ndarray, ld: np.ndarray, rising: bool = False) -> bool:
    """Is there a stretch of these (log tau, log sigma) points spanning at least FLOOR_SPAN
    in tau over which the least-squares log-log slope is within +-FLAT_SLOPE? (``rising``:
    at least +FLAT_SLOPE, a rise such as a random walk's +1/2)"""
    span = math.log(FLOOR_SPAN) * (1.0 - 1e-9)
    for a in range(lt.size):
        for b in range(a + 1, lt.size):
            if lt[b] - lt[a] >= span:
                slope = float(np.polyfit(lt[a:b + 1], ld[a:b + 1], 1)[0])
                if (slope >= FLAT_SLOPE) if rising else abs(slope) < FLAT_SLOPE:
                    return True
                break  # longer stretches from a: tried from the next start
    return False


#: p-value below which the statistical covariance alone does not explain the residuals
MODEL_ERROR_P = 0.01

#: a data/fit deviation ratio this large is a curve over a fitted total of 0 (every term a
#: bound; the check floors the total at 1e-300): said in words, not as a 300-digit factor
NO_TOTAL_RATIO = 1e12


def chi2_carrier(tau: np.ndarray, s2: np.ndarray, total: np.ndarray,
                 r_white: np.ndarray) -> dict | None:
    """The run of consecutive taus that carries a fit's chi-square: the taus split into runs
    where the curve stays on one side of the fitted total (sigma^2 above or below it); each
    run scored by the sum of its whitened residuals squared (``r_white``, one per tau: with
    the lower Cholesky factor the i-th is tau i's innovation given the shorter taus); the
    largest returned with its span, its share of the chi-square and the curve's deviation
    over the fitted total's (min, max) there. None when there is nothing to name."""
    tau, s2, total, r = (np.asarray(x, dtype=float) for x in (tau, s2, total, r_white))
    chi = float(r @ r)
    if not tau.size or not chi > 0 or not np.all(np.isfinite(r)):
        return None
    above = s2 > total
    best, start = None, 0
    for i in range(1, tau.size + 1):
        if i == tau.size or above[i] != above[start]:
            score = float(r[start:i] @ r[start:i])
            if best is None or score > best[0]:
                best = (score, start, i)
            start = i
    score, a, b = best
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.sqrt(s2[a:b] / np.maximum(total[a:b], 1e-300))
    return {"tau_from_s": float(tau[a]), "tau_to_s": float(tau[b - 1]), "n_taus": int(b - a),
            "chi2": score, "chi2_share": score / chi,
            "side": "data above" if above[a] else "data below",
            "data_over_fit_min": float(np.min(ratio)), "data_over_fit_max": float(np.max(ratio))}


def _model_error(a: np.ndarray, s2: np.ndarray, e: np.ndarray, cols: list[int],
                 cov_terms: dict | None, iterations: int, upper: np.ndarray | None = None
                 ) -> tuple[float, tuple]:
    """Relative idealisation error of the IEEE 952 model for this curve, and the goodness of
    fit (chi2, dof, p) of the fit with the statistical covariance alone.

    On real sensors the short taus hold 1e5..1e7 terms and their sigma^2 are known to 0.1 %,
    far better than the five-term model describes them (anti-aliasing filters, quantization,
    a bump of a correlated process): the statistical weights then let a few short taus decide
    the fit and the floor and the long-tau rise are ignored (seen on a 2.8 h ADIS16405
    capture: the fitted total ran 10x below the curve's 25 deg/h floor). When the
    statistical chi-square is beyond its 99 % point, a relative model error eps is added to
    every sigma^2 (variance (eps sigma^2)^2) and eps is chosen so that the reduced chi-square
    is 1: the usual "intrinsic scatter" of a misspecified model. eps = 0 for a curve the
    model describes (every synthetic IEEE 952 capture)."""
    w = e / (2.0 * s2 ** 2)
    p0 = _nnls_cols(a * np.sqrt(w)[:, None], s2 * np.sqrt(w), upper)

    def red(eps: float) -> tuple[float, int]:
        p, _, rw = _gls(a, s2, e, cols, cov_terms, p0, iterations, eps, upper)
        dof = max(1, s2.size - int(np.count_nonzero(p > 0)))
        return float(rw @ rw), dof

    chi, dof = red(0.0)
    stat = (chi, dof, float(chi2.sf(chi, dof)))
    if stat[2] >= MODEL_ERROR_P:
        return 0.0, stat
    top = math.exp(math.log(10.0))  # the bisection's upper end, as it computes it
    if red(top)[0] / dof > 1.0:
        return top, stat
    return _unit_reduced_chi2_eps(lambda x: (lambda c, d: c / d)(*red(x))), stat


#: Huber constant of the robust weights (standardized residual of sigma^2)
HUBER_C = 1.0


def _robust_inflation(a: np.ndarray, s2: np.ndarray, e: np.ndarray, cols: list[int],
                      cov_terms: dict | None, iterations: int, model_err: float,
                      upper: np.ndarray | None) -> np.ndarray:
    """Per-tau variance inflation (Huber, iterated): a tau whose sigma^2 misses the fit by
    more than HUBER_C standard deviations (statistical + model error) is weighted down by
    |r| / HUBER_C. A feature outside IEEE 952 (the bump of a correlated process, a periodic
    dip) then no longer drags the terms it is not made of: on a real MTi-G gyro whose curve has
    a bump at 5-250 s, N follows the slope -1/2 region instead of splitting the difference."""
    w = e / (2.0 * s2 ** 2)
    p = _nnls_cols(a * np.sqrt(w)[:, None], s2 * np.sqrt(w), upper)
    f = np.ones(s2.size)
    for _ in range(6):
        p, _, _ = _gls(a, s2, e, cols, cov_terms, p, iterations, model_err, upper, f)
        var = np.diag(_model_cov(cov_terms, p, cols, a, e, model_err))
        r = np.abs(s2 - a @ p) / np.sqrt(np.maximum(var, 1e-300))
        f_new = np.maximum(1.0, r / HUBER_C)
        if np.allclose(f_new, f, rtol=1e-3):
            break
        f = f_new
    return f


def curve_limits(tau: np.ndarray, adev: np.ndarray) -> dict[str, float]:
    """The largest value of each term the curve itself allows (SI): every IEEE 952 term adds
    a non-negative part to sigma^2, so c_j^2 * A_j(tau) <= sigma^2(tau) at every tau, e.g.
    B <= min sigma / 0.664, N <= min sigma sqrt(tau), K <= min sigma sqrt(3 / tau)."""
    tau = np.asarray(tau, dtype=float)
    s2 = np.asarray(adev, dtype=float) ** 2
    ok = np.isfinite(tau) & np.isfinite(s2) & (tau > 0) & (s2 > 0)
    if not np.any(ok):
        return {t: math.inf for t in TERMS}
    a = design_matrix(tau[ok])
    lim = np.min(s2[ok][:, None] / a, axis=0)
    return {t: float(math.sqrt(v)) for t, v in zip(TERMS, lim)}


def curve_limit_taus(tau: np.ndarray, adev: np.ndarray) -> dict[str, float]:
    """The tau at which each term's :func:`curve_limits` is set (nan without a usable tau)."""
    tau = np.asarray(tau, dtype=float)
    s2 = np.asarray(adev, dtype=float) ** 2
    ok = np.isfinite(tau) & np.isfinite(s2) & (tau > 0) & (s2 > 0)
    if not np.any(ok):
        return {t: math.nan for t in TERMS}
    k = np.argmin(s2[ok][:, None] / design_matrix(tau[ok]), axis=0)
    return {t: float(tau[ok][i]) for t, i in zip(TERMS, k)}


#: a tau's 95 % band is informative when hi/lo is at most this: sqrt(chi2_0.975(nu) /
#: chi2_0.025(nu)) <= 2 for EDF nu >= 16.95 (the band is then 0.75 .. 1.50 x sigma). Only such
#: taus set the curve's limits and are held to the band by the self-check
INFORMATIVE_RATIO = 2.0
#: a departure is reported when the fit leaves the band *and* misses the deviation by more
#: than this fraction: at short taus the band is +-0.1 %, far narrower than any model of a
#: real sensor (a 2 % ripple of its filter would otherwise be listed tau by tau)
DEPARTURE_REL = 0.10


#: design false-alarm rate of the self-check on a curve the model describes: the chance that
#: the fitted total leaves the band (by more than DEPARTURE_REL) at *any* informative tau
CHECK_ALPHA = 0.05


def _whitened_residual(full_a: np.ndarray, s2: np.ndarray, e: np.ndarray,
                       cov_terms: dict | None, cols: list[int], p: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(whitened residual, lower Cholesky factor L) of sigma^2 against the model p on
    columns ``cols``: r = L^-1 (s2 - A p), L L^T the statistical covariance of the sigma^2
    estimates under that model (no model error). Where the model gives no usable covariance
    (its total 0 at some tau, a singular factor) the data's own diagonal, 2 s2^2 / edf."""
    a = full_a[:, cols]
    try:
        if not np.all(a @ p > 0):
            raise ValueError("the total is zero at some taus")
        with np.errstate(invalid="ignore", divide="ignore"):
            lw = _whiten(_model_cov(cov_terms, p, cols, a, e, 0.0, None))
        r = solve_triangular(lw, s2 - a @ p, lower=True)
        if not np.all(np.isfinite(r)):
            raise ValueError("not finite")
        return r, lw
    except (ValueError, np.linalg.LinAlgError):
        sd = np.sqrt(2.0 * s2 ** 2 / e)
        return (s2 - a @ p) / sd, np.diag(sd)


def _admissible_completion(full_a: np.ndarray, s2: np.ndarray, e: np.ndarray,
                           cov_terms: dict | None, cols: list[int], p_rep: np.ndarray,
                           ub: np.ndarray, iterations: int = 3) -> np.ndarray:
    """The part of the terms reported only as bounds that the self-check adds to the resolved
    total: the point of their admissible set that follows the curve best.

    A term reported as a bound (one-sided 95 % upper bound u_j on its coefficient c_j) is not
    known to be absent, only to be at most u_j; its share of sigma^2 is p_j A_j(tau) with
    p_j = c_j^2 >= 0 (every IEEE 952 term and the Gauss-Markov term add a non-negative part:
    a variance). The admissible set is the box

        P = { p_u : 0 <= p_j <= u_j^2 for each bounded term j },

    lower ends 0 (a variance is never negative; the unconstrained estimate of a bounded term is
    often below 0, which no sensor has), upper ends the reported bounds: the set a reader of
    the result can check, term by term. It is wider than a joint 95 % region (each u_j is
    marginal), which is why one point of it is taken, not each tau's most favourable one: the
    completed total is ONE model, sigma^2_c(tau) = A_r(tau) p_r + A_u(tau) p_u*, with

        p_u* = argmin_{p_u in P} || L^-1 (s2 - A_r p_r - A_u p_u) ||^2,

    the resolved terms p_r held, L L^T the covariance of the sigma^2 estimates under the
    completed model (iterated ``iterations`` times from p_u = 0). A feature outside the model
    (a bump, a dip, an excursion) is then still a misfit: no single admissible p_u follows it
    without leaving the band elsewhere. Returns p_u* on the columns ``cols`` (0 where the
    term is resolved, ``ub`` 0)."""
    p_u = np.zeros_like(p_rep)
    free = ub > 0
    if not np.any(free):
        return p_u
    base = s2 - full_a[:, cols] @ p_rep
    a_u = full_a[:, cols][:, free]
    for _ in range(iterations):
        _, lw = _whitened_residual(full_a, s2, e, cov_terms, cols, p_rep + p_u)
        aw = solve_triangular(lw, a_u, lower=True)
        bw = solve_triangular(lw, base, lower=True)
        new = np.zeros_like(p_u)
        new[free] = _nnls_cols(aw, bw, ub[free])  # within [0, ub] (clipped there)
        done = np.allclose(new, p_u, rtol=1e-6, atol=0.0)
        p_u = new
        if done:
            break
    return p_u


def self_check(tau: np.ndarray, adev: np.ndarray, edf: np.ndarray, coeff_sq: dict,
               m_eff: float | None = None, extra_avar: np.ndarray | None = None,
               bounded_avar: np.ndarray | None = None,
               bounded_names: list[str] | None = None) -> dict:
    """Does the fitted total follow the curve? At every well-determined tau (its 95 %
    chi-square band informative, hi/lo <= INFORMATIVE_RATIO, as are all the taus before it:
    :func:`_informative_prefix`), the fitted sigma must lie in the band.
    Returns {"ok", "n_informative", "n_outside", "outside": runs of consecutive taus outside
    the band with the side ("data above"/"data below" the fit), the largest ratio data/fit,
    and the likely reason (a feature outside IEEE 952)}. A tau counts as outside when the fit
    leaves its band and misses the deviation by more than DEPARTURE_REL; ``n_outside_band``
    counts every informative tau outside the band.

    Those runs are read against each tau's own (pointwise) 95 % band, so their number grows
    with the density of the taus: on pure noise some informative tau of ``--taus all`` is
    outside it far more often than one of ``--taus octave``. Whether the check *fails* is
    therefore decided on the family-wise band: two-sided, simultaneous over the informative
    taus at CHECK_ALPHA (Sidak over ``m_eff`` independent estimates, the effective number of
    the informative taus from the correlation of their estimates, :func:`_effective_taus`;
    without it, the number of informative taus, as if independent). ``n_outside_familywise``
    counts the informative taus outside that band by more than DEPARTURE_REL (and
    ``n_outside_familywise_band`` every one outside it): on a curve the model describes the
    latter is 0 in 1 - CHECK_ALPHA of captures, at any tau density. ``extra_avar``: a further
    part of the fitted total at each tau (the fit's Gauss-Markov term), added to the IEEE 952
    terms' sigma^2.

    ``bounded_avar`` (taus x k, sigma^2): the part of the terms reported only as bounds
    (``bounded_names``, k of them) that completes the total -- each within [0, its bound], one
    point for all taus (:func:`_admissible_completion`):

        sigma^2_fit(tau) = sum_resolved p_j A_j(tau) [+ GM] + sum_bounded p_j* A_j(tau)

    The runs and counts above stay those of the resolved total (the total reported, plotted
    and exported, whose bumps and dips the pipeline reads: Gauss-Markov candidate,
    stationarity, quiet stretch); ``completed`` holds the counts of the completed total, which
    decide (:func:`_fit_terms`: a tau is outside only where the admissible completion does not
    bring the total into the band). A run of the resolved total that the completed total
    follows names the bounded term that carries most of the completion at its worst tau
    (``followed_by_bound``, else None); ``needs_bounds`` lists the runs of informative taus
    where the resolved total leaves the band (by more than DEPARTURE_REL, or the family-wise
    band) and the completed total does not, each with that term (``term``) and the data over
    the resolved total at its worst tau."""
    tau = np.asarray(tau, dtype=float)
    dev = np.asarray(adev, dtype=float)
    e = np.asarray(edf, dtype=float)
    q = chi2.ppf([0.975, 0.025], e[:, None]).T
    lo, hi = dev * np.sqrt(e / q[0]), dev * np.sqrt(e / q[1])
    fit2_res = model_avar(tau, {t: math.sqrt(v) for t, v in coeff_sq.items()})
    if extra_avar is not None:
        fit2_res = fit2_res + np.asarray(extra_avar, dtype=float)
    parts = (np.zeros((tau.size, 0)) if bounded_avar is None
             else np.asarray(bounded_avar, dtype=float).reshape(tau.size, -1))
    fit_res = np.sqrt(np.maximum(fit2_res, 0.0))
    fit = np.sqrt(np.maximum(fit2_res + parts.sum(axis=1), 0.0))
    # the well-determined taus (_informative_prefix): a tau past an uninformative one whose EDF
    # rose again only because the noise ID changed on a handful of averages is not judged (seed
    # 20002, --taus all: flicker PM from B1 on 4-8 averages, EDF 100-212 at 819-1638 s where
    # flicker FM gives 3.4-8.5, named "a dip ... 0.49x" at 901-1638 s, a chance low there)
    informative = _informative_prefix(hi <= INFORMATIVE_RATIO * lo)
    n = tau.size
    n_inf = int(np.count_nonzero(informative))
    m = float(m_eff) if m_eff is not None and m_eff >= 1 else float(max(n_inf, 1))
    q_fw = -math.expm1(math.log1p(-CHECK_ALPHA) / m)  # per tau, both tails together
    qf = chi2.ppf([1.0 - q_fw / 2.0, q_fw / 2.0], e[:, None]).T
    lo_fw, hi_fw = dev * np.sqrt(e / qf[0]), dev * np.sqrt(e / qf[1])

    def misses(f: np.ndarray) -> dict:
        """The taus where the total ``f`` (sigma) leaves the band, pointwise and family-wise."""
        s_above, s_below = informative & (f < lo), informative & (f > hi)
        fw_band = informative & ((f < lo_fw) | (f > hi_fw))
        return {"strict_above": s_above, "strict_below": s_below,
                "above": s_above & (dev > (1.0 + DEPARTURE_REL) * f),  # data above the total
                "below": s_below & (dev < (1.0 - DEPARTURE_REL) * f),
                "fw_band": fw_band,
                "fw": fw_band & (((f < lo_fw) & (dev > (1.0 + DEPARTURE_REL) * f))
                                 | ((f > hi_fw) & (dev < (1.0 - DEPARTURE_REL) * f)))}

    mc = misses(fit)
    # the runs, counts and sentences are those of the resolved total (the one reported, plotted
    # and exported, and the one the pipeline reads the bumps and dips of); the decision's counts
    # are the completed total's (``completed``), and a run the completion brings into the band
    # says which bounded term follows it (``followed_by_bound``)
    mr = misses(fit_res) if parts.shape[1] else mc
    above, below = mr["above"], mr["below"]
    strict_above, strict_below = mr["strict_above"], mr["strict_below"]
    inside_c = ~(mc["above"] | mc["below"] | mc["fw"])
    names = list(bounded_names or [])

    def carrier(k: int) -> str | None:
        return names[int(np.argmax(parts[k]))] if names and parts.shape[1] else None

    runs = []
    i = 0
    while i < n:
        if above[i] or below[i]:
            side = above[i]
            j = i
            while j + 1 < n and (above[j + 1] if side else below[j + 1]):
                j += 1
            ratio = dev[i:j + 1] / np.maximum(fit_res[i:j + 1], 1e-300)
            k = i + int(np.argmax(np.abs(np.log(ratio))))
            runs.append({"tau_from_s": float(tau[i]), "tau_to_s": float(tau[j]),
                         "side": "data above the fit" if side else "data below the fit",
                         "worst_tau_s": float(tau[k]), "data_over_fit": float(ratio[k - i]),
                         "likely": _likely_reason(tau, dev, i, j, bool(side)),
                         "followed_by_bound": (carrier(k) if parts.shape[1]
                                               and np.all(inside_c[i:j + 1]) else None)})
            i = j + 1
        else:
            i += 1
    # the taus outside the band by less than DEPARTURE_REL: named too (as runs, in one
    # sentence), so that every informative tau where the total leaves the band is named
    small = (strict_above | strict_below) & ~(above | below)
    small_runs = _mask_runs(small, tau, dev, fit_res)
    # past the well-determined taus: a band informative again (its EDF from a noise ID that
    # changed on a handful of averages) is not judged, but a tau whose fitted total leaves it
    # is named (consumer_mems 12 h ax, --taus all: EDF 15.9 at 2621 s, 17.5 at 2949 s, the
    # total x1.75 above the curve there, in the tail of a chance dip the check names)
    past = (hi <= INFORMATIVE_RATIO * lo) & ~informative & ((fit_res < lo) | (fit_res > hi))
    past_runs = _mask_runs(past, tau, dev, fit_res)
    first_uninf = np.flatnonzero(~informative)
    n_out = int(np.count_nonzero(above | below))
    needs = []
    for o in _mask_runs((mr["above"] | mr["fw"]) & inside_c, tau, dev, fit_res):
        o["term"] = carrier(int(np.flatnonzero(tau == o["worst_tau_s"])[0]))
        needs.append(o)
    return {"ok": n_out == 0, "n_informative": n_inf,
            "n_outside_familywise": int(np.count_nonzero(mr["fw"])),
            "n_outside_familywise_band": int(np.count_nonzero(mr["fw_band"])),
            "familywise_alpha": CHECK_ALPHA,
            "m_eff": m,
            "n_outside": n_out, "outside": runs, "outside_small": small_runs,
            "outside_past_prefix": past_runs,
            "prefix_end_s": float(tau[first_uninf[0]]) if first_uninf.size else None,
            "band": "95 % chi-square (EDF)",
            "n_outside_band": int(np.count_nonzero(strict_above | strict_below)),
            "informative_ratio": INFORMATIVE_RATIO, "departure_rel": DEPARTURE_REL,
            "completed": {"n_outside": int(np.count_nonzero(mc["above"] | mc["below"])),
                          "n_outside_familywise": int(np.count_nonzero(mc["fw"])),
                          "n_outside_familywise_band": int(np.count_nonzero(mc["fw_band"]))},
            "needs_bounds": needs}


def _mask_runs(mask: np.ndarray, tau: np.ndarray, dev: np.ndarray, fit: np.ndarray) -> list:
    """Runs of consecutive taus where ``mask`` holds: their span (s), the worst tau and its
    ratio data / fitted total (the largest |log| in the run)."""
    runs = []
    i, n = 0, tau.size
    while i < n:
        if mask[i]:
            j = i
            while j + 1 < n and mask[j + 1]:
                j += 1
            ratio = dev[i:j + 1] / np.maximum(fit[i:j + 1], 1e-300)
            k = i + int(np.argmax(np.abs(np.log(ratio))))
            runs.append({"tau_from_s": float(tau[i]), "tau_to_s": float(tau[j]),
                         "worst_tau_s": float(tau[k]), "data_over_fit": float(ratio[k - i])})
            i = j + 1
        else:
            i += 1
    return runs


def _likely_reason(tau: np.ndarray, dev: np.ndarray, i: int, j: int, above: bool) -> str:
    """A plain reading of why the curve leaves the IEEE 952 model between taus i..j."""
    n = tau.size
    lt = np.log(tau)
    ld = np.log(np.maximum(dev, 1e-300))
    a, b = max(0, i - 1), min(n - 1, j + 1)
    slope = float((ld[b] - ld[a]) / (lt[b] - lt[a])) if b > a else 0.0
    first, last = i == 0 or i <= 1, j >= n - 2
    if first and not above:
        return ("the sensor's low-pass filter, or an output dwelling on its quantization "
                "levels: samples correlated at the shortest taus (below the white-noise line; "
                "not an IEEE 952 term)")
    if first and above and slope < -0.5:
        return (f"quantization or white phase noise at the shortest taus (local slope "
                f"{slope:+.2f}, steeper than -1/2)")
    # a hump whose top is on the curve: from the first taus it rises by more than
    # DEPARTURE_REL, then falls as much again within the run -- a correlated (Gauss-Markov)
    # process whose rise lies below the first tau (a servo-locked Sr optical clock at tau0 =
    # 2.5 s: up 18 % to 12.5 s, then down 2x by 190 s), read as the bump it is (its
    # stationarity and a Gauss-Markov term are then tested), not as a monotone fall
    top = int(np.argmax(dev[:j + 1]))
    if (first and above and 0 < top < j and dev[top] > (1.0 + DEPARTURE_REL) * dev[0]
            and dev[j] < dev[top] / (1.0 + DEPARTURE_REL)):
        return ("a bump: a correlated (Gauss-Markov) process or a periodic disturbance "
                "between these taus (not an IEEE 952 term)")
    if first and above:  # shallower than white noise from the start (the Astro Pi gyros)
        return (f"a correlated process above the white noise from the shortest taus on (local "
                f"slope {slope:+.2f}, shallower than -1/2: e.g. a flicker floor or a "
                f"Gauss-Markov process, which no IEEE 952 term within the curve's limits follows)")
    # a drift or trend rises (a ramp +1, a random walk +1/2); a run at the longest taus that
    # still falls is the tail of a bump (the MTi-G gyro with --taus octave: slope -0.44 at
    # 2.6-328 s, named a drift, so its stationarity was never tested)
    if last and above and slope >= 0:
        return (f"a drift or temperature trend at the longest taus (local slope {slope:+.2f})")
    if above:
        return ("a bump: a correlated (Gauss-Markov) process or a periodic disturbance "
                "between these taus (not an IEEE 952 term)")
    return ("a dip: a periodic component (e.g. a temperature-control or vibration cycle) "
            "that averages out near these taus (not an IEEE 952 term)")


def _add_crb(out_terms: dict, coefs: dict, tau0: float, n_phase: int,
             gm: tuple[float, float] | None = None,
             gm_bound: tuple[float, float] | None = None) -> dict[str, dict]:
    """Add ``crb_rel_sd`` to each Q/N/B/K entry: the best relative standard deviation any
    estimator could reach for that coefficient from this capture (Cramer-Rao, Whittle; see
    :mod:`rigctl.solvers.allan_crb`), at the fitted model (the supported terms, and the
    Gauss-Markov term ``gm`` = (sigma_GM, Tc) when the fit has one: its two parameters are then
    nuisance parameters of every bound); for a bounded term, with that term added at its 95 %
    upper bound. A bounded term with
    crb_rel_sd >~ 0.5 is not identifiable from a capture of this length even if it were as
    large as its bound: only a longer capture can resolve it. Where the bound is wider than
    ``TARGET_REL_SD`` (95 % of estimates within +-25 %), ``capture_h_for_25pct`` is the capture
    length (h) at which it would not be (:func:`rigctl.solvers.allan_crb.duration_for`; for a
    bounded term at its upper bound, so a lower limit: a smaller term needs longer). For a
    bounded term that lower limit can come out at or below this capture's own length
    (``capture_h``): the term is then smaller than its bound, and the honest statement is
    only "longer than this capture" (see :func:`rigctl.display_units.need_text`).

    Returns the Gauss-Markov term's own figures, {"sigma": entry, "tc": entry} with entries
    like the terms' (``crb_rel_sd``: sd(sigma_GM)/sigma_GM and sd(Tc)/Tc; ``capture_h``; and
    ``capture_h_for_25pct`` where the bound is wider than the target), at the fitted model with
    ``gm``; for a bounded sigma_GM (``gm_bound`` = (its 95 % upper bound, Tc)) with the term at
    its bound, so lower limits as for a bounded IEEE term (``bounded``: True). {} without a
    Gauss-Markov term."""
    gm_out: dict[str, dict] = {}
    if n_phase < 3:
        return gm_out
    base, bounded = {}, {}
    for t in R.TERMS4:
        c = coefs.get(t)
        if c is None:
            continue
        if c.resolved:
            base[t] = c.value
        elif c.upper95 > 0 and math.isfinite(c.upper95):
            bounded[t] = c.upper95
    length = (n_phase - 1) * tau0
    # (coefficients, the IEEE terms read off it, the GM model, the GM entries read off it)
    models = [(base, tuple(base), gm, gm is not None)]
    models += [({**base, t: v}, (t,), gm, False) for t, v in bounded.items()]
    if gm_bound is not None and base:
        models.append((base, (), gm_bound, True))
    gm_keys = {"sigma": "GM_sigma", "tc": "GM_tc"}
    for coeffs, report, g, with_gm in models:
        try:
            best = R.crb_rel_sd(coeffs, length, 1.0 / tau0, gm=g)
        except (ValueError, np.linalg.LinAlgError):
            continue
        entries = [(out_terms[t], t) for t in report]
        memo: dict[float, dict[str, float]] = {}  # this model's bounds per duration
        if with_gm and gm_keys["tc"] in best:
            for k, key in gm_keys.items():
                gm_out[k] = {"bounded": g is gm_bound}
                entries.append((gm_out[k], key))
        for entry, key in entries:
            entry["crb_rel_sd"] = best[key]
            entry["capture_h"] = length / 3600.0
            if key != "Q" and best[key] > TARGET_REL_SD:  # how long a capture would resolve it
                try:
                    need = R.duration_for(coeffs, key, TARGET_REL_SD, 1.0 / tau0,
                                          t_min_s=min(600.0, 0.5 * length), gm=g,
                                          memo=memo)
                except (ValueError, np.linalg.LinAlgError):
                    continue
                entry["capture_h_for_25pct"] = need / 3600.0
    return gm_out


def term_value_si(fit: dict, term: str) -> float:
    """Value (SI) of a term in the model the fit reports: its estimate if resolved, else 0."""
    return NC.resolved_values(fit["coefficients"]).get(term, 0.0)


def piecewise_readoffs(tau: np.ndarray, adev: np.ndarray, sensor: str = "gyro") -> dict:
    """The paper's hand-ranged read-offs (SI and field units; None where no points)."""
    tau = np.asarray(tau, dtype=float)
    sig = np.asarray(adev, dtype=float)

    def gmean(v: np.ndarray) -> float | None:
        v = v[np.isfinite(v) & (v > 0)]
        return float(np.exp(np.mean(np.log(v)))) if v.size else None

    sel_q = tau < 0.5
    sel_n = (tau >= 0.5) & (tau <= 2.0)
    vals: dict[str, float | None] = {
        "Q": gmean(sig[sel_q] * tau[sel_q] / math.sqrt(3.0)),
        "N": gmean(sig[sel_n] * np.sqrt(tau[sel_n])),
        "B": None, "K": None, "R": None}
    flat = tau >= 20.0
    if np.any(flat):
        i = int(np.argmin(np.where(flat, sig, np.inf)))
        vals["B"] = float(sig[i] / 0.664)
        sel_k = tau >= 4.0 * tau[i]
        vals["K"] = gmean(sig[sel_k] * np.sqrt(3.0 / tau[sel_k]))
    out = {}
    for t, v in vals.items():
        unit_f, fac = FIELD_UNITS[sensor][t]
        out[t] = {f"value_{SI_UNITS[sensor][t]}": v,
                  f"value_{unit_f}": None if v is None else v * fac}
    return {"method": "piecewise read-offs (slope -1 < 0.5 s, -1/2 in 0.5-2 s, "
                      "min/0.664 above 20 s, +1/2 above 4x the minimum)",
            "terms": out, "si": vals}
