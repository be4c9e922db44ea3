"""Noise model of the segment means: from IEEE 952 coefficients, or estimated from the session.

The calibration fits need the covariance of the segment means per channel
(:mod:`rigctl.solvers.segment_cov`). Two sources:

1. **IEEE 952 coefficients** (``rigctl allan``'s /results/allan, or a datasheet):
   :meth:`rigctl.solvers.noise_coefficients.NoiseCoefficients.cov`,
   C = N^2 C_white + Q^2 C_quant + B^2 C_flicker + K^2 C_rw(t0).
2. **The session itself** (:func:`estimate_channel_noise`), when no characterisation exists.
   Per channel the unknowns are theta = (N_g^2 for each segment kind g -- static and rate
   windows may differ in white noise --, B^2, K^2); Sigma(theta) = sum_j theta_j C_j is linear in
   them. Three Gaussian restricted likelihoods (REML: the likelihood of error contrasts, free of
   the fixed effects) are added (a composite likelihood; their weak mutual dependence under slow
   noise is ignored):

   * **within windows**: each window is cut into 8 equal batches; the batch means z_i (8,) have
     covariance S_i(theta) from the same kernels on the batch windows. Only contrasts u_i =
     N_i^T z_i that no calibration effect can reach are used: on a static window the reference
     is constant, so every contrast of the 8 batch means (N_i: orthonormal complement of 1, 7
     columns); on a rate window holding exactly R >= 2 whole revolutions every effect of the
     attitude (gravity and Earth rate turning through the axes, quadratic, asymmetric,
     g-sensitive terms, servo ripple per revolution ...) is periodic with period T/R, so its batch
     means hold only batch frequencies that are multiples of R: N_i is the complement of the
     cosines/sines at those frequencies (R = 2: 4 contrasts immune to any such effect). Other
     windows contribute nothing here. -2 l_w = sum_i log|N_i^T S_i N_i| + u_i^T (N_i^T S_i N_i)^-1 u_i.
     This is what separates white noise, flicker and random walk: a random walk makes the batch
     means of a window trend, white noise does not.
   * **between windows**: the segment means y = X beta + e, e ~ N(0, Sigma(theta)):

         -2 l_b = log|Sigma| + log|X^T Sigma^-1 X| + y^T P y,
         P = Sigma^-1 - Sigma^-1 X (X^T Sigma^-1 X)^-1 X^T Sigma^-1.

   * **the warm-up** (``SegmentTable.rest``: 30-s batch means of the static record before the
     positions), the same REML with design [1, temperature] -- no time column: a trend is the
     random walk's signature, and a warm-up transient is thermal. It is the session's best view
     of slow noise.

   theta_hat minimises -l_w - l_b - l_rest by Fisher scoring (gradient tr(P C_j) - y^T P C_j P y,
   expected information tr(P C_j P C_k), and the same for each window), projected onto
   theta >= 0. The REML likelihood does not depend on the constant part of Sigma (X holds the
   bias column), so the random walk's origin and the flicker's stationary variance enter only
   the biases' intervals, through the model.

**Confounding with real slow effects.** A warm-up drift, a bias following temperature, a lever
arm acting only in the rate windows at the end of the run: all of these make the means wander
between windows, as random walk and flicker do. Two guards keep the variance components from
absorbing them (and the closed loop, testing against an inflated covariance, from losing the
power to find them): (1) the within-window contrasts above, which no calibration effect reaches,
pin the white level and the flicker, and bound the random walk from above (its trend inside
each window); (2) X in the between part is the *protected* design: the declared model plus the
library's slow regressors -- time, temperature, temperature x input -- untied per channel, and an
offset per segment kind beyond the first (anything acting only in the rate windows shifts that
block). REML uses only contrasts orthogonal to X, so those cannot inflate theta_hat; each costs
one residual degree of freedom.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from . import distributions as _dist
from . import segment_cov as sc
from .noise_coefficients import Coefficient, NoiseCoefficients, coefficient_json, power_on_k2
from .segment_stats import N_BATCHES


def channel_covs(models: Sequence[NoiseCoefficients], a: ArrayLike, b: ArrayLike, groups: Sequence[str],
                 t0: float = 0.0, flicker: NDArray[np.float64] | None = None,
                 rw: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """(len(models), K, K): :meth:`NoiseCoefficients.cov` of each channel on the same windows,
    the unit flicker and random-walk components computed once (or given: ``flicker`` for B = 1
    on the models' band, ``rw`` for K = 1 from ``t0``) when the models share a flicker band."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if not models:
        return np.zeros((0, a.size, a.size))
    m0 = models[0]
    if any((m.flicker_tau_min_s, m.flicker_tau_max_s) != (m0.flicker_tau_min_s, m0.flicker_tau_max_s)
           for m in models):
        return np.stack([m.cov(a, b, groups, t0) for m in models])
    if flicker is None and any(m.B.value for m in models):
        flicker = sc.cov_flicker(a, b, sc.flicker_bank(m0.flicker_tau_min_s, m0.flicker_tau_max_s))
    if rw is None and any(m.K.value for m in models):
        rw = sc.cov_random_walk(a, b, t0)
    return np.stack([m.cov(a, b, groups, t0, flicker, rw) for m in models])


def _full_rank(X: NDArray[np.float64], rtol: float = 1e-9) -> NDArray[np.float64]:
    """Columns of X spanning its column space (pivoted QR on unit-norm columns). X may have more
    columns than rows (a session with fewer segments than the protected design has columns): R
    then has min(rows, columns) diagonal entries, one for each of the first pivots."""
    nrm = np.linalg.norm(X, axis=0)
    X = X[:, nrm > 0]
    if X.shape[1] == 0:
        return X
    Xs = X / np.linalg.norm(X, axis=0)
    _, r, piv = scipy.linalg.qr(Xs, mode="economic", pivoting=True)
    d = np.abs(np.diag(r))
    return X[:, np.sort(piv[:d.size][d > rtol * d[0]])]


def within_basis(n_batches: int, revolutions: float | None, trend: bool = False) -> NDArray[np.float64]:
    """(n_batches, m) orthonormal contrasts of a window's batch means that no effect of the
    attitude reaches (module docstring).

    revolutions: 0 for a static window (complement of the constant: m = n_batches - 1); an
    integer R >= 2 for a rate window holding R whole revolutions (complement of the cosines and
    sines at batch frequencies that are multiples of R); None or anything else: no contrast (m = 0).
    trend: also the complement of a straight line in batch index (one contrast fewer): a window
    taken while the temperature ramps drifts along its thermal coefficients, and equal batches
    of a linear drift have linear means, so no such contrast sees it.
    """
    B = n_batches
    k = np.arange(B)
    lin = [k - (B - 1) / 2.0] if trend else []
    if revolutions == 0:
        D = np.stack([np.ones(B), *lin], axis=1)
    elif revolutions is not None and revolutions >= 2 and float(revolutions).is_integer():
        cols = [np.ones(B), *lin]
        R = int(revolutions)
        for f in range(R, B // 2 + 1, R):
            cols += [np.cos(2 * np.pi * f * k / B), np.sin(2 * np.pi * f * k / B)]
        D = np.stack(cols, axis=1)
    else:
        return np.zeros((B, 0))
    u, sv, _ = np.linalg.svd(D, full_matrices=True)
    rank = int(np.sum(sv > 1e-9 * sv[0]))
    return u[:, rank:]


def window_revolutions(kind: str, table_rate: ArrayLike | None, duration_s: float, tol: float = 0.02
                       ) -> float | None:
    """0 for a static window, R for a window turning R >= 2 whole revolutions, else None."""
    if table_rate is None:
        return 0.0 if kind == "orientation" else None
    r = float(np.max(np.abs(np.asarray(table_rate, dtype=np.float64))))
    if r == 0.0:
        return 0.0
    R = r * duration_s / (2.0 * np.pi)
    return float(round(R)) if round(R) >= 2 and abs(R - round(R)) < tol else None


@dataclass
class WindowTerms:
    """Unit covariance components of a set of windows, shared by every channel.

    comps: [C_white(g) for each group label, C_flicker (B = 1), C_rw (K = 1, origin t0)] of the
    window means (n_comp, K, K); within: the same components for each window's contrasts
    N_i^T C N_i, zero-padded to (n_comp, K, B-1, B-1), with ``mask`` (K, B-1) marking the
    contrasts that exist and ``basis`` (K, B, B-1) the N_i (padded with zero columns).

    A segment kind whose windows give fewer than ``min_contrasts`` within-window contrasts (rate
    windows not holding whole revolutions, ramps) has no white level of its own -- the means
    alone cannot separate it from the other terms -- and shares that of the kind with the most
    contrasts: ``group_of`` maps each kind to the label whose white level it uses.

    ``trend`` (build): the within-window contrasts are also free of a straight line in time
    (:func:`within_basis`), for windows taken while the temperature ramps (the thermal fit).
    """

    a: NDArray[np.float64]
    b: NDArray[np.float64]
    groups: NDArray[np.str_]
    labels: list[str]
    group_of: dict[str, str]
    comps: NDArray[np.float64]
    within: NDArray[np.float64]
    mask: NDArray[np.bool_]
    basis: NDArray[np.float64]
    t0: float
    bank: sc.FlickerBank
    rest_comps: NDArray[np.float64] | None = None
    rest_X: NDArray[np.float64] | None = None

    @classmethod
    def build(cls, a: ArrayLike, b: ArrayLike, groups: Sequence[str], revolutions: Sequence[float | None],
              t0: float = 0.0, tau_min_s: float = 1.0, tau_max_s: float = 1.0e4,
              n_batches: int = N_BATCHES, min_contrasts: int = 8,
              rest: dict[str, Any] | None = None, trend: bool = False) -> "WindowTerms":
        a = np.asarray(a, dtype=np.float64)
        b = np.asarray(b, dtype=np.float64)
        kinds = np.asarray(groups).astype(str)
        T = b - a
        K, B = a.size, n_batches
        basis = np.zeros((K, B, B - 1))
        mask = np.zeros((K, B - 1), dtype=bool)
        for i, R in enumerate(revolutions):
            Ni = within_basis(B, R, trend)
            basis[i, :, : Ni.shape[1]] = Ni
            mask[i, : Ni.shape[1]] = True
        n_con = {k: int(mask[kinds == k].sum()) for k in sorted(set(kinds.tolist()))}
        best = max(n_con, key=lambda k: n_con[k])
        group_of = {k: (k if n >= min_contrasts else best) for k, n in n_con.items()}
        g = np.array([group_of[k] for k in kinds])
        labels = sorted(set(group_of.values()))
        bank = sc.flicker_bank(tau_min_s, tau_max_s)
        comps = [np.diag(np.where(g == lab, 1.0 / T, 0.0)) for lab in labels]
        comps += [sc.cov_flicker(a, b, bank), sc.cov_random_walk(a, b, t0)]
        ba, bb = sc.batch_windows(a, b, B)  # (K, B)
        wc = [np.where(g == lab, B / T, 0.0)[:, None, None] * np.eye(B) for lab in labels]
        wc += [sc.cov_flicker(ba, bb, bank), sc.cov_random_walk(ba, bb, t0)]
        within = np.stack([np.swapaxes(basis, 1, 2) @ c @ basis for c in wc])
        rest_comps = rest_X = None
        if rest is not None:  # static record: white level of the static windows' group
            ra, rb = np.asarray(rest["t_start"], dtype=np.float64), np.asarray(rest["t_end"], dtype=np.float64)
            lab = group_of.get("orientation", best)
            rc = [np.diag((1.0 / (rb - ra)) * (lab == lb)) for lb in labels]
            rest_comps = np.array(rc + [sc.cov_flicker(ra, rb, bank), sc.cov_random_walk(ra, rb, t0)])
            cols = [np.ones(ra.size)]  # no time column: a trend is the random walk's signature
            temp = rest.get("temperature")
            if temp is not None and np.ptp(temp) > 0:
                cols.append(np.asarray(temp, dtype=np.float64) - np.mean(temp))
            rest_X = _full_rank(np.stack(cols, axis=1))
        return cls(a, b, g, labels, group_of, np.array(comps), within, mask, basis, float(t0), bank,
                   rest_comps, rest_X)

    def subset(self, idx: NDArray[np.int64]) -> "WindowTerms":
        """Terms of the windows idx (group labels kept as they are)."""
        return WindowTerms(self.a[idx], self.b[idx], self.groups[idx], self.labels, self.group_of,
                           self.comps[:, idx][:, :, idx], self.within[:, idx], self.mask[idx],
                           self.basis[idx], self.t0, self.bank, self.rest_comps, self.rest_X)


def _reml_factor(theta: NDArray[np.float64], y: NDArray[np.float64], X: NDArray[np.float64],
                 comps: NDArray[np.float64]) -> tuple[float, NDArray[np.float64], NDArray[np.float64]] | None:
    """-l_R of y = X beta + e, Cov e = sum_j theta_j comps_j, with what its derivatives need
    (P and P y); None when the covariance is not positive definite."""
    S = np.tensordot(theta, comps, axes=1)
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None
    Li = scipy.linalg.solve_triangular(L, np.eye(len(y)), lower=True, check_finite=False)
    q, rr = np.linalg.qr(Li @ X)
    A = Li - q @ (q.T @ Li)  # (I - q q^T) L^-1
    P = A.T @ A
    Py = P @ y
    f = float(np.sum(np.log(np.diag(L))) + np.sum(np.log(np.abs(np.diag(rr)))) + 0.5 * y @ Py)
    return f, P, Py


def _reml_derivs(P: NDArray[np.float64], Py: NDArray[np.float64], comps: NDArray[np.float64]
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Gradient and expected information of -l_R from :func:`_reml_factor`'s P and P y."""
    PC = np.einsum("ij,cjk->cik", P, comps)
    grad = 0.5 * (np.einsum("cii->c", PC) - np.einsum("i,cij,j->c", Py, comps, Py))
    return grad, 0.5 * np.einsum("aij,bji->ab", PC, PC)


@dataclass
class _Factored:
    """:func:`_objective_value` at one theta: f and what the derivatives need (the within
    part's G^-1 and G^-1 u, each block's P and P y), so that the derivatives at an accepted
    step reuse the factorisations the step search made (the same values as computing them
    again)."""

    f: float
    Gi: NDArray[np.float64]
    Giu: NDArray[np.float64]
    blocks: list[tuple[NDArray[np.float64], NDArray[np.float64]]]


def _objective_value(theta: NDArray[np.float64], u: NDArray[np.float64], terms: WindowTerms,
                     blocks: list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]
                     ) -> _Factored | None:
    """f = -l_w - sum over blocks of l_R (module docstring) with its factorisations; None when a
    covariance is not positive definite (f = inf)."""
    pad = (~terms.mask)[:, :, None] & np.eye(terms.mask.shape[1], dtype=bool)[None]
    G = np.tensordot(theta, terms.within, axes=1) + pad  # (K, m, m); padding -> identity
    try:
        Lw = np.linalg.cholesky(G)
    except np.linalg.LinAlgError:
        return None
    Gi = np.linalg.inv(G)
    Giu = np.einsum("kij,kj->ki", Gi, u)
    f = float(np.sum(np.log(np.diagonal(Lw, axis1=1, axis2=2))) + 0.5 * np.sum(u * Giu))
    facs = []
    for y, X, comps in blocks:
        fac = _reml_factor(theta, y, X, comps)
        if fac is None:
            return None
        f += fac[0]
        facs.append((fac[1], fac[2]))
    return _Factored(f, Gi, Giu, facs)


def _objective_derivs(fac: _Factored, terms: WindowTerms,
                      blocks: list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Gradient and expected information of f at the theta of ``fac``."""
    GC = np.einsum("kij,ckjl->ckil", fac.Gi, terms.within)  # (n_c, K, m, m)
    grad = 0.5 * (np.einsum("ckii->c", GC) - np.einsum("ki,ckij,kj->c", fac.Giu, terms.within, fac.Giu))
    hess = 0.5 * np.einsum("akij,bkji->ab", GC, GC)
    for (_, _, comps), (P, Py) in zip(blocks, fac.blocks):
        gb, hb = _reml_derivs(P, Py, comps)
        grad, hess = grad + gb, hess + hb
    return grad, hess


def _objective(theta: NDArray[np.float64], u: NDArray[np.float64], terms: WindowTerms,
               blocks: list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
               derivs: bool) -> tuple[float, NDArray[np.float64] | None, NDArray[np.float64] | None]:
    """f = -l_w - sum over blocks of l_R (module docstring); gradient and expected information."""
    fac = _objective_value(theta, u, terms, blocks)
    if fac is None:
        return np.inf, None, None
    if not derivs:
        return fac.f, None, None
    return (fac.f, *_objective_derivs(fac, terms, blocks))


def estimate_channel_noise(y: ArrayLike, X: ArrayLike, terms: WindowTerms, z: ArrayLike,
                           rest: ArrayLike | None = None, min_dof: int = 8, max_iter: int = 60
                           ) -> NoiseCoefficients:
    """REML estimate of (N_g^2, B^2, K^2) for one channel (module docstring).

    Args:
        y: (K,) segment means; X: (K, p) protected design (:func:`protected_design`).
        terms: the windows' unit covariance components (:class:`WindowTerms`).
        z: (K, B) the batch means of each window.
        rest: (M,) batch means of the static record (``terms.rest_comps``), or None.
        min_dof: below this many residual dof the between-window part is not used and the terms
            come from the windows alone (said in ``info``).

    Minimised by Fisher scoring with step halving, projected onto N_g^2 > 0, B^2, K^2 >= 0.
    """
    y = np.asarray(y, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    ok = np.flatnonzero(np.isfinite(y) & np.all(np.isfinite(z), axis=1))
    terms = terms.subset(ok) if ok.size < y.size else terms
    y, z = y[ok], z[ok]
    u = np.einsum("kbm,kb->km", terms.basis, z)
    Xr = _full_rank(np.asarray(X, dtype=np.float64)[ok])
    T = terms.b - terms.a
    nl = len(terms.labels)
    dof = y.size - Xr.shape[1]
    between = dof >= min_dof
    blocks = [(y, Xr, terms.comps)] if between else []
    if rest is not None and terms.rest_comps is not None and np.all(np.isfinite(rest)):
        blocks.append((np.asarray(rest, dtype=np.float64), terms.rest_X, terms.rest_comps))
    # start: white level per group from the within contrasts (batch means of a T/B batch)
    B = terms.basis.shape[1]
    n2 = []
    for lab in terms.labels:
        sel = terms.groups == lab
        m = terms.mask[sel]
        n2.append(float(np.sum((u[sel] ** 2 * (T[sel] / B)[:, None])[m]) / max(1, m.sum()))
                  if m.any() else float(np.var(y[sel]) * np.median(T[sel])) if sel.sum() > 1 else 1e-30)
    n2 = np.maximum(np.array(n2), 1e-300)
    w_ref = float(np.median(n2) / np.median(T))
    span = float(np.ptp(np.concatenate([terms.a, terms.b]))) or 1.0
    scale = np.concatenate([n2, [w_ref / sc._PLATEAU, w_ref / span]])
    lb = np.concatenate([1e-6 * n2, [0.0, 0.0]])
    th = scale * np.concatenate([np.ones(nl), [0.1, 0.1]])
    f, g, H = _objective(th, u, terms, blocks, True)
    it, converged = 0, False
    for it in range(1, max_iter + 1):
        free = ~((th <= lb) & (g > 0))
        d = np.zeros_like(th)
        Hs = H[np.ix_(free, free)] * np.outer(scale[free], scale[free])
        d[free] = -scale[free] * np.linalg.lstsq(Hs, g[free] * scale[free], rcond=1e-12)[0]
        step, accepted = 1.0, False
        while step > 1e-8:
            tn = np.maximum(th + step * d, lb)
            fac = _objective_value(tn, u, terms, blocks)
            fn = np.inf if fac is None else fac.f
            if fn <= f:
                accepted = True
                break
            step /= 2.0
        if not accepted:
            converged = True
            break
        df = f - fn
        th = tn
        # f, gradient and information at the accepted step, from its factorisations
        f, (g, H) = fac.f, _objective_derivs(fac, terms, blocks)  # type: ignore[union-attr]
        if df < 1e-9 * max(1.0, abs(f)) and np.max(np.abs(step * d) / scale) < 1e-6:
            converged = True
            break
    info = {"method": "REML: batch-mean contrasts within windows + segment means (protected design)",
            "residual_dof": int(dof), "within_contrasts": int(terms.mask.sum()), "n_segments": int(y.size),
            "rest_batches": 0 if len(blocks) < 1 + between else int(terms.rest_comps.shape[1]),
            "iterations": it, "converged": converged}
    if not between:
        info["note"] = (f"only {dof} residual dof after the protected design: terms from the windows "
                        "alone")
    theta_cov = np.linalg.pinv(H) if H is not None and np.all(np.isfinite(H)) else None
    var_th = (np.full(th.size, np.nan) if theta_cov is None else np.diag(theta_cov))
    coefs = [component_coefficient(t, v) for t, v in zip(th, var_th)]
    wv = {lab: float(w) for lab, w in zip(terms.labels, th[:nl])}
    info["white_level_shared"] = {k: v for k, v in terms.group_of.items() if k != v}
    # each group's N (u sqrt(s)) with its interval, as /results stores a Coefficient
    info["N_by_group"] = {k: coefficient_json(coefs[terms.labels.index(v)]) for k, v in terms.group_of.items()}
    by_group = {k: float(np.sqrt(wv[v])) for k, v in terms.group_of.items()}
    top = terms.labels.index(terms.group_of[max(by_group, key=lambda k: by_group[k])])
    return NoiseCoefficients(N=coefs[top], B=coefs[nl], K=coefs[nl + 1],
                             flicker_tau_min_s=terms.bank.tau_min_s, flicker_tau_max_s=terms.bank.tau_max_s,
                             source="session (REML)", white_by_group=by_group, theta_cov=theta_cov,
                             details=info)


def component_coefficient(theta: float, var_theta: float) -> Coefficient:
    """A noise coefficient c = sqrt(theta) from a REML variance component theta = c^2 (SI^2) and
    the variance of its estimate (``var_theta``: the inverse expected information, SI^4).

    With s = sqrt(var_theta): the term is resolved when the two-sided Wald interval of theta
    excludes zero (theta > 1.96 s); its intervals are then the Satterthwaite chi-square ones,
    nu = 2 theta^2 / s^2, theta nu / chi2_{nu}(1 -+ p/2) (always positive), square-rooted.
    Otherwise only the one-sided 95 % upper bound c < sqrt(theta + 1.645 s) is supported
    (``upper95``; ``value`` stays the estimate sqrt(theta), which the covariance uses:
    docs/calibration.md section 10). Without a finite variance: a bare value (no interval).
    """
    theta = max(float(theta), 0.0)
    v = float(var_theta)
    if not (np.isfinite(v) and v > 0.0):
        return Coefficient(float(np.sqrt(theta)))
    s = float(np.sqrt(v))
    if theta > 1.959963984540054 * s:
        nu = 2.0 * theta**2 / v

        def ci(p: float) -> tuple[float, float]:
            return (float(np.sqrt(theta * nu / _dist.chi2.ppf(1.0 - p / 2.0, nu))),
                    float(np.sqrt(theta * nu / _dist.chi2.ppf(p / 2.0, nu))))
        return Coefficient(float(np.sqrt(theta)), ci(0.3173105078629141), ci(0.05), edf=float(nu))
    return Coefficient(float(np.sqrt(theta)), upper95=float(np.sqrt(theta + 1.6448536269514722 * s)),
                       bound_from="fit")


# ------------------------------------------------------------------------------ session level
def protected_design(seg: Any, c: int, quadratic: bool = True) -> NDArray[np.float64]:
    """(K, p) design of channel c for the variance components (module docstring).

    The declared A2 columns of that channel plus, untied per channel (each channel its own
    coefficients), every candidate of the effect library this session can identify, and an
    offset per segment kind beyond the first. Dependent columns are dropped later
    (:func:`_full_rank`).
    """
    from .accel24 import accel_columns
    from .effect_library import LIBRARY
    from .gyro_rate import gyro_columns

    Xs, _ = accel_columns(seg, quadratic) if c < 3 else gyro_columns(seg)
    cols = [Xs[:, c % 3, j] for j in range(Xs.shape[2]) if np.any(Xs[:, c % 3, j])]
    for eff in LIBRARY:
        if quadratic and eff.name == "accel_quadratic":
            continue
        built = eff.build(seg)
        if isinstance(built, str):
            continue
        Xe = built[0]
        cols += [Xe[:, c, j] for j in range(Xe.shape[2]) if np.any(Xe[:, c, j])]
    kinds, counts = np.unique(seg.kind, return_counts=True)
    for k in kinds[np.argsort(-counts, kind="stable")][1:]:
        cols.append((seg.kind == k).astype(np.float64))
    return np.stack(cols, axis=1)


def apply_session_noise(seg: Any, acc_model: Sequence[NoiseCoefficients] | None = None,
                        gyro_model: Sequence[NoiseCoefficients] | None = None, t0: float = 0.0,
                        quadratic: bool = True) -> list[NoiseCoefficients]:
    """Set ``seg.cov`` (6, K, K) from the noise model of each channel; returns the six models.

    With IEEE 952 coefficients (``acc_model``/``gyro_model``: three axes' NoiseCoefficients,
    t0 the random walk's origin) the covariance comes
    from them; otherwise (None) each channel's model is estimated from the session
    (:func:`estimate_channel_noise` on :func:`protected_design`). Needs ``seg.t_start``,
    ``seg.t_end`` (and ``seg.batch_means`` for the estimate); without them nothing is changed and
    [] is returned (the means stay independent).
    """
    if seg.t_start is None or seg.t_end is None:
        return []
    a, b = np.asarray(seg.t_start, dtype=np.float64), np.asarray(seg.t_end, dtype=np.float64)
    models: list[NoiseCoefficients] = []
    terms = None
    y = seg.y()
    for c, model in enumerate((acc_model,) * 3 + (gyro_model,) * 3):
        if model is not None:
            models.append(model[c % 3])
            continue
        if seg.batch_means is None:
            return []
        if terms is None:
            rate = seg.table_rate if seg.table_rate is not None else [None] * len(seg)
            revs = [window_revolutions(k, r, bb - aa) for k, r, aa, bb in zip(seg.kind, rate, a, b)]
            terms = WindowTerms.build(a, b, seg.kind, revs, t0, n_batches=seg.batch_means.shape[2],
                                      rest=seg.rest)
        models.append(estimate_channel_noise(y[:, c], protected_design(seg, c, quadratic), terms,
                                             seg.batch_means[:, c],
                                             None if seg.rest is None else seg.rest["mean"][:, c]))
    seg.set_cov(np.stack([m.cov(a, b, seg.kind, t0) for m in models]))
    # a random walk at its boundary 0: the biases carry its bound to power-on (closed_loop)
    seg.extra["power_on_k2"] = {"k2": [power_on_k2(m) for m in models], "t0": float(t0)}
    if terms is not None and all(m.theta_cov is not None for m in models):
        # for the Satterthwaite degrees of freedom of the calibration's intervals
        seg.extra["noise_components"] = {"comps": terms.comps, "theta_cov": [m.theta_cov for m in models]}
    else:
        seg.extra.pop("noise_components", None)
    return models
