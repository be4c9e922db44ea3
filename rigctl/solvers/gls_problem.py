"""The whitened observation problem of the closed loop: GLS fits, identifiability, cross-validation.

All segments and channels are flattened into rows (segment-major, k * 6 + c, finite rows only)
with covariance Sigma, block diagonal over the channels (each block the covariance of a
channel's segment means, :mod:`rigctl.solvers.segment_cov`). Sigma = L L^T is factored once
(:class:`~rigctl.solvers.segment_cov.Whitener`) and every statistic of the loop is computed on
the whitened rows L^-1 y, L^-1 X (see :mod:`rigctl.solvers.closed_loop`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from .calibration_result import CalibrationResult, fit_linear
from .segment_cov import Whitener
from .segments import SegmentTable


@dataclass
class _Problem:
    """Flattened observation rows (finite ones only) and the whitening of their covariance."""

    y: NDArray[np.float64]
    s: NDArray[np.float64]
    group: NDArray[np.int64]
    channel: NDArray[np.int64]
    keep: NDArray[np.bool_]
    W: Whitener
    _inv: NDArray[np.float64] | None = None

    @classmethod
    def from_table(cls, seg: SegmentTable) -> "_Problem":
        y = seg.y().ravel()
        s = seg.sigma().ravel()
        keep = np.isfinite(y) & np.isfinite(s)
        K = len(seg)
        group = np.repeat(np.arange(K), 6)[keep]
        channel = np.tile(np.arange(6), K)[keep]
        if seg.cov is None:
            W = Whitener(sigma=s[keep])
        else:  # rows are segment-major (k * 6 + c); channels independent
            C = np.zeros((6 * K, 6 * K))
            for c in range(6):
                idx = np.arange(K) * 6 + c
                C[np.ix_(idx, idx)] = seg.cov[c]
            W = Whitener(cov=C[np.ix_(keep, keep)])
        return cls(y[keep], s[keep], group, channel, keep, W)

    def rows(self, X3: NDArray[np.float64]) -> NDArray[np.float64]:
        return X3.reshape(-1, X3.shape[-1])[self.keep]

    def white(self, A: NDArray[np.float64]) -> NDArray[np.float64]:
        """L^-1 A (whitened rows)."""
        return self.W.apply(A)

    def inv_factor(self) -> NDArray[np.float64]:
        """L^-1 (n, n), cached."""
        if self._inv is None:
            self._inv = self.W.inverse_factor()
        return self._inv

    def qr(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        """Orthonormal basis of the whitened design's columns."""
        return np.linalg.qr(self.white(X))[0]


def _fit(prob: _Problem, X: NDArray[np.float64], names: list[str], method: str) -> CalibrationResult:
    return fit_linear(X, prob.y, prob.s, names, method=method, rescale_if_poor=False, cov=prob.W)


def _identifiable(prob: _Problem, q: NDArray[np.float64], Xc: NDArray[np.float64],
                  rtol: float = 1e-6) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """Columns of Xc that add something the whitened span (orthonormal basis q) lacks.

    Returns the mask and the whitened columns projected off that span (B - q q^T B).
    """
    B = prob.white(Xc)
    Bp = B - q @ (q.T @ B)
    norms = np.linalg.norm(B, axis=0)
    keep = np.zeros(B.shape[1], dtype=bool)
    if not np.any(norms > 0):
        return keep, Bp
    _, r, piv = scipy.linalg.qr(Bp / np.where(norms > 0, norms, 1.0), mode="economic", pivoting=True)
    d = np.abs(np.diag(r))
    keep[piv[d > rtol]] = True
    return keep & (norms > 0), Bp


def _chi2_drop(Bp: NDArray[np.float64], e: NDArray[np.float64]) -> float:
    """Drop of chi2 when columns with projected part Bp join a fit with whitened residual e:

        d chi2 = e^T Bp (Bp^T Bp)^-1 Bp^T e
    """
    z = Bp.T @ e
    return float(z @ np.linalg.lstsq(Bp.T @ Bp, z, rcond=None)[0])


def _loo_blocks(prob: _Problem, q: NDArray[np.float64], idx: NDArray[np.int64]
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(P_gg, (Sigma^-1)_gg, A_g) for the rows idx (A = L^-1, P = A^T (I - q q^T) A)."""
    Ag = prob.inv_factor()[:, idx]
    Mg = Ag.T @ Ag
    QA = q.T @ Ag
    return Mg - QA.T @ QA, Mg, Ag


def loso_cv(prob: _Problem, X: NDArray[np.float64], segments: NDArray[np.int64] | None = None,
            q: NDArray[np.float64] | None = None) -> float:
    """Leave-one-segment-out prediction error (module docstring, step 3).

    Diagonal Sigma: sum_g |(I - H_gg)^-1 e_g|^2 with H = q q^T the whitened hat matrix.
    Full Sigma: sum_g e_g^T (Sigma^-1)_gg e_g, e_g = (P_gg)^-1 (P y)_g (the BLUP prediction error).
    """
    if q is None:
        q = prob.qr(X)
    yw = prob.white(prob.y)
    e = yw - q @ (q.T @ yw)
    total = 0.0
    groups = np.unique(prob.group) if segments is None else segments
    Py = None if prob.W.diagonal else prob.inv_factor().T @ e
    for g in groups:
        idx = np.flatnonzero(prob.group == g)
        try:
            if Py is None:
                qg = q[idx]
                eg = np.linalg.solve(np.eye(len(idx)) - qg @ qg.T, e[idx])
                total += float(eg @ eg)
            else:
                Pgg, Mg, _ = _loo_blocks(prob, q, idx)
                eg = np.linalg.solve(Pgg, Py[idx])
                total += float(eg @ Mg @ eg)
        except np.linalg.LinAlgError:
            continue
    return total


def _cv_groups(prob: _Problem, q: NDArray[np.float64]) -> NDArray[np.int64]:
    """Segments whose omission keeps the (larger) model estimable.

    Diagonal Sigma: leverage below 1 (|q_g|_2^2 < 1); full Sigma: P_gg non-singular relative to
    (Sigma^-1)_gg (smallest generalised eigenvalue > 1e-8; the same criterion).
    """
    ok = []
    for g in np.unique(prob.group):
        idx = np.flatnonzero(prob.group == g)
        if prob.W.diagonal:
            good = np.linalg.norm(q[idx], 2) ** 2 < 1.0 - 1e-8
        else:
            Pgg, Mg, _ = _loo_blocks(prob, q, idx)
            good = float(np.min(scipy.linalg.eigh(Pgg, Mg, eigvals_only=True))) > 1e-8
        if good:
            ok.append(g)
    return np.array(ok, dtype=np.int64)


def noise_floor(prob: _Problem, q: NDArray[np.float64]) -> NDArray[np.float64]:
    """(6,) RMS per channel that the noise alone leaves in the residuals of the model (basis q),
    per degree of freedom:

        floor_c^2 = E|r_c|^2 / (n_c - p_c),   E r r^T = M Sigma M^T = L (I - q q^T) L^T,

    M = I - X (X^T Sigma^-1 X)^-1 X^T Sigma^-1, p_c = sum over channel c's rows of |q_i|^2 (the
    parameters channel c carries; an integer when no parameter is shared between channels).
    With independent means of equal uncertainty s it is s; the constant part of time-correlated
    noise, absorbed by the biases, does not count.
    """
    hq = np.sum(q**2, axis=1)
    if prob.W.diagonal:
        num = prob.s**2 * (1.0 - hq)
    else:
        L = prob.W.L
        num = np.sum(L**2, axis=1) - np.sum((L @ q) ** 2, axis=1)
    out = np.full(6, np.nan)
    for c in range(6):
        m = prob.channel == c
        if np.any(m) and np.sum(1.0 - hq[m]) > 0:
            out[c] = np.sqrt(max(np.sum(num[m]), 0.0) / np.sum(1.0 - hq[m]))
    return out


def variance_gradient(prob: _Problem, X: NDArray[np.float64], cov_beta: NDArray[np.float64], c: int,
                      comps: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """(n_comp, p) diagonals of dV/d theta_k = V X^T Sigma^-1 C_k Sigma^-1 X V for unit
    components ``comps`` (n_comp, K, K) over the table's segments added to channel ``c``'s block
    of Sigma, V = ``cov_beta``: how much each parameter's variance grows per unit of theta_k
    (with the estimate beta itself unchanged: the sandwich of the GLS estimator under Sigma +
    theta_k C_k). None when channel c has no row."""
    rows = np.flatnonzero(prob.channel == c)
    if rows.size == 0:
        return None
    A = prob.inv_factor() if not prob.W.diagonal else np.diag(1.0 / prob.s)
    Wc = A[:, rows].T @ (A @ np.nan_to_num(X)) @ np.nan_to_num(cov_beta)  # (n_c, p)
    seg = prob.group[rows]
    return np.stack([np.einsum("ij,ik,kj->j", Wc, comps[k][np.ix_(seg, seg)], Wc)
                     for k in range(comps.shape[0])])


def satterthwaite_dof(prob: _Problem, X: NDArray[np.float64], cov_beta: NDArray[np.float64],
                      noise: dict | None) -> NDArray[np.float64] | None:
    """(p,) degrees of freedom of each parameter's variance when the noise model was estimated.

    With Sigma = sum_k theta_k C_k per channel and theta_hat estimated (covariance V_theta, the
    inverse information of its likelihood), V = Cov(beta) = (X^T Sigma^-1 X)^-1 is itself an
    estimate. Its derivatives

        dV/d theta_k = V X^T Sigma^-1 C_k Sigma^-1 X V

    give Var(V_jj) = g_j^T V_theta g_j (delta method, g_jk = (dV/d theta_k)_jj), and Satterthwaite's
    approximation V_jj ~ V_jj chi2_nu / nu with nu_j = 2 V_jj^2 / Var(V_jj) (Giesbrecht & Burns
    1985; the first part of Kenward & Roger 1997): the 95 % interval is beta_j +- t_{nu_j} sigma_j.

    ``noise``: {"comps": (n_c, K, K) unit components over the table's segments, "theta_cov":
    six (n_c, n_c)} (SegmentTable.extra["noise_components"]); None: returns None.
    """
    if noise is None:
        return None
    comps = np.asarray(noise["comps"])
    cb = np.nan_to_num(cov_beta)
    var_v = np.zeros(cb.shape[0])
    for c, tcov in enumerate(noise["theta_cov"]):
        g = variance_gradient(prob, X, cov_beta, c, comps)  # (n_comp, p)
        if g is not None:
            var_v += np.einsum("kj,kl,lj->j", g, np.asarray(tcov), g)
    vjj = np.diag(cb)
    with np.errstate(divide="ignore", invalid="ignore"):
        nu = np.where(var_v > 0, 2.0 * vjj**2 / var_v, np.inf)
    return np.clip(nu, 1.0, np.inf)
