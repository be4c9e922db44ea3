"""Result of any calibration fit, with its uncertainty, plus the weighted linear least-squares fit.

Every solver in :mod:`rigctl.solvers` returns a :class:`CalibrationResult`: parameter names
(units in the names, e.g. ``accel_bias_x_m_s2``), values, the full covariance matrix, 1-sigma,
95 % intervals, the correlation matrix, degrees of freedom, chi-square against the noise model
and the residuals.

Generalised least squares (:func:`fit_linear`), observations y with covariance Sigma (diagonal
diag(s^2) when the errors are independent; full when segment means share time-correlated noise,
:mod:`rigctl.solvers.segment_cov`). With the Cholesky factor Sigma = L L^T the problem is
whitened, X_w = L^-1 X, y_w = L^-1 y, and solved as ordinary least squares:

    minimise  chi2(beta) = (y - X beta)^T Sigma^-1 (y - X beta) = |y_w - X_w beta|^2
    beta_hat = (X^T Sigma^-1 X)^-1 X^T Sigma^-1 y
    Cov(beta_hat) = (X^T Sigma^-1 X)^-1                 (noise model trusted)
    dof = n - rank(X),   E[chi2] = dof when the model and the noise model are right.

(Diagonal Sigma: W = diag(1/s^2), the weighted least squares of A3.) The normalised residuals
are the whitened ones, L^-1 (y - X beta_hat): independent unit-variance when all is right.

Intervals: with the noise model trusted the estimates are normal, so the 95 % interval is
beta +- 1.959964 sigma. When the covariance is rescaled by the observed chi2/dof (Birge ratio,
done only when the fit is clearly worse than the noise model), the scale is itself estimated
from dof residuals and the interval uses Student's t with dof degrees of freedom.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from . import distributions as _dist
from ..jsonable import jsonable
from .segment_cov import Whitener

#: Result status values.
STATUS_OK = "ok"
STATUS_POOR_FIT = "poor_fit"
STATUS_INSUFFICIENT = "insufficient_poses"
STATUS_UNDERDETERMINED = "underdetermined"


@dataclass
class CalibrationResult:
    """A fitted parameter vector with its uncertainty.

    Attributes:
        method: short name of the solver ("accel24", "gyro_rate", "multipos_accel", ...).
        names: parameter names, each with its unit, e.g. ``gyro_bias_x_rad_s``.
        values: (p,) estimates in the units of the names.
        covariance: (p, p) covariance of the estimates.
        dof: degrees of freedom of the residuals (n_obs - n_params).
        chi2: sum of squared normalised residuals against the noise model.
        residuals: (n,) residuals y - model (in the observations' units; NaN allowed).
        normalized_residuals: (n,) residuals / their standard uncertainty.
        interval: "normal" (covariance from the noise model) or "t" (scaled by chi2/dof).
        status: "ok", "poor_fit", "insufficient_poses" or "underdetermined".
        warnings: human-readable caveats; never empty when status is not "ok".
        extra: solver-specific JSON-able details (matrices, per-rate residuals, ...).
        param_dof: optional (p,) degrees of freedom behind each parameter's t interval (when
            independent sub-fits were combined, e.g. the three accelerometer axes).
    """

    method: str
    names: list[str]
    values: NDArray[np.float64]
    covariance: NDArray[np.float64]
    dof: int
    chi2: float
    residuals: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    normalized_residuals: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    interval: str = "normal"
    status: str = STATUS_OK
    warnings: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    param_dof: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        self.values = np.asarray(self.values, dtype=np.float64)
        self.covariance = np.asarray(self.covariance, dtype=np.float64)
        if len(self.names) != self.values.shape[0]:
            raise ValueError("names and values differ in length")
        if self.covariance.shape != (len(self.names), len(self.names)):
            raise ValueError("covariance must be (p, p)")

    # ------------------------------------------------------------------ derived quantities
    @property
    def sigma(self) -> NDArray[np.float64]:
        """1-sigma standard uncertainties, sqrt(diag(Cov))."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def coverage_factor(self) -> float:
        """Factor k of the 95 % interval beta +- k sigma (normal or Student t with dof)."""
        if self.interval == "t" and self.dof > 0:
            return float(_dist.t.ppf(0.975, self.dof))
        return float(_dist.norm.ppf(0.975))

    @property
    def coverage_factors(self) -> NDArray[np.float64]:
        """(p,) factors of the 95 % intervals (per-parameter dof when given)."""
        if self.interval == "t" and self.param_dof is not None:
            d = np.asarray(self.param_dof, dtype=np.float64)
            return np.where(d > 0, _dist.t.ppf(0.975, np.maximum(d, 1)), np.inf)
        return np.full(len(self.names), self.coverage_factor)

    @property
    def interval_dof(self) -> NDArray[np.float64]:
        """(p,) degrees of freedom behind each parameter's interval (inf: normal interval)."""
        if self.interval != "t":
            return np.full(len(self.names), np.inf)
        if self.param_dof is not None:
            return np.where(np.asarray(self.param_dof, dtype=np.float64) > 0,
                            np.maximum(np.asarray(self.param_dof, dtype=np.float64), 1.0), np.nan)
        return np.full(len(self.names), float(self.dof) if self.dof > 0 else np.nan)

    @property
    def ci95(self) -> NDArray[np.float64]:
        """(p, 2) 95 % intervals [low, high]."""
        k = self.coverage_factors
        return np.stack([self.values - k * self.sigma, self.values + k * self.sigma], axis=1)

    @property
    def correlation(self) -> NDArray[np.float64]:
        """(p, p) correlation matrix Cov_ij / (sigma_i sigma_j)."""
        s = self.sigma
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.covariance / np.outer(s, s)
        return np.where(np.isfinite(c), c, 0.0)

    @property
    def chi2_per_dof(self) -> float:
        """chi2 / dof (NaN when dof <= 0)."""
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

    @property
    def chi2_p_value(self) -> float:
        """Probability of a chi2 at least this large if model and noise model are right."""
        return float(_dist.chi2.sf(self.chi2, self.dof)) if self.dof > 0 else float("nan")

    def value(self, name: str) -> float:
        """Value of one parameter by name."""
        return float(self.values[self.names.index(name)])

    def sigma_of(self, name: str) -> float:
        """1-sigma of one parameter by name."""
        return float(self.sigma[self.names.index(name)])

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (NaN and inf become None)."""
        ci = self.ci95
        params = [
            {"name": n, "value": _num(v), "sigma": _num(s), "ci95_low": _num(lo), "ci95_high": _num(hi),
             "dof": _num(d)}
            for n, v, s, (lo, hi), d in zip(self.names, self.values, self.sigma, ci, self.interval_dof)
        ]
        return {
            "method": self.method,
            "status": self.status,
            "warnings": list(self.warnings),
            "parameters": params,
            "covariance": jsonable(self.covariance),
            "correlation": jsonable(self.correlation),
            "dof": int(self.dof),
            "chi2": _num(self.chi2),
            "chi2_per_dof": _num(self.chi2_per_dof),
            "chi2_p_value": _num(self.chi2_p_value),
            "interval": self.interval,
            "coverage_factors": jsonable(self.coverage_factors),
            "residuals": jsonable(self.residuals),
            "normalized_residuals": jsonable(self.normalized_residuals),
            "extra": jsonable(self.extra),
        }


def _num(x: Any) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def format_table(result: CalibrationResult, scale: dict[str, tuple[float, str]] | None = None) -> str:
    """Human table of a result: name, value, 1-sigma, 95 % interval; status and chi2 line.

    Args:
        result: the fit.
        scale: optional {name: (factor, display_name)} to show a parameter in field units
            (e.g. {"gyro_bias_x_rad_s": (206264.806*..., "gyro_bias_x_deg_h")}).
    """
    scale = scale or {}
    lines = [f"{result.method}: status={result.status}  dof={result.dof}  "
             f"chi2={result.chi2:.4g}  chi2/dof={result.chi2_per_dof:.3g}  "
             f"p={result.chi2_p_value:.3g}  interval={result.interval}"]
    for w in result.warnings:
        lines.append(f"  WARNING: {w}")
    trusted = result.status in (STATUS_OK, STATUS_POOR_FIT)
    head = f"  {'parameter':<34} {'value':>14} {'1-sigma':>12} {'95% low':>14} {'95% high':>14}"
    lines.append(head if trusted else head + "   (NOT TRUSTWORTHY)")
    for n, v, s, (lo, hi) in zip(result.names, result.values, result.sigma, result.ci95):
        f, disp = scale.get(n, (1.0, n))
        lines.append(f"  {disp:<34} {v * f:>14.6g} {s * abs(f):>12.3g} {min(lo, hi) * f:>14.6g} "
                     f"{max(lo, hi) * f:>14.6g}")
    return "\n".join(lines)


def fit_linear(
    X: NDArray[np.float64],
    y: NDArray[np.float64],
    s: NDArray[np.float64],
    names: list[str],
    method: str = "linear",
    rescale_if_poor: bool = True,
    poor_fit_p: float = 1e-3,
    cov: NDArray[np.float64] | Whitener | None = None,
) -> CalibrationResult:
    """Generalised (weighted) linear least squares with the full covariance of the estimates.

    Args:
        X: (n, p) design matrix.
        y: (n,) observations.
        s: (n,) standard uncertainties of the observations (same units as y); used when ``cov``
            is None (independent errors).
        cov: (n, n) covariance of the observations, or a :class:`~rigctl.solvers.segment_cov.
            Whitener` already factored (the closed loop factors once for all its fits).
        names: p parameter names with units.
        method: label stored in the result.
        rescale_if_poor: when chi2 is improbable (p < ``poor_fit_p``), inflate the covariance by
            chi2/dof (Birge ratio), switch to t intervals and set status "poor_fit".
        poor_fit_p: threshold of the chi2 tail probability for "poor_fit".

    Returns:
        CalibrationResult; parameters that the design cannot determine (rank deficiency) get
        NaN values and the status "underdetermined".
    """
    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    n, p = X.shape
    if cov is None:
        wh = Whitener(sigma=np.asarray(s, dtype=np.float64))
    else:
        wh = cov if isinstance(cov, Whitener) else Whitener(cov=cov)
    if wh.n != n:
        raise ValueError(f"noise covariance is for {wh.n} observations, the design has {n}")
    beta, cb, rank = _wls_core(wh.apply(X), wh.apply(y))
    resid = y - X @ np.nan_to_num(beta)
    nres = wh.apply(resid)
    chi2 = float(nres @ nres)
    dof = n - rank
    cov = cb
    res = CalibrationResult(method=method, names=list(names), values=beta, covariance=cov,
                            dof=int(dof), chi2=chi2, residuals=resid, normalized_residuals=nres)
    if rank < p:
        res.status = STATUS_UNDERDETERMINED
        res.warnings.append(f"design matrix has rank {rank} < {p} parameters: "
                            "some parameters are not determined by these segments")
    elif dof <= 0:
        res.status = STATUS_UNDERDETERMINED
        res.warnings.append(f"{n} observations for {p} parameters: no degrees of freedom left")
    elif rescale_if_poor and res.chi2_p_value < poor_fit_p:
        birge = chi2 / dof
        res.covariance = cov * birge
        res.interval = "t"
        res.status = STATUS_POOR_FIT
        res.warnings.append(
            f"chi2/dof = {birge:.3g} (p = {res.chi2_p_value:.2g}): residuals exceed the noise model; "
            "covariance inflated by chi2/dof and t intervals used; the model may lack an effect")
    return res


def _wls_core(Xw: NDArray[np.float64], yw: NDArray[np.float64]
              ) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """Solve the whitened problem by pivoted QR; NaN for parameters outside the column space."""
    n, p = Xw.shape
    if n == 0:
        return np.full(p, np.nan), np.full((p, p), np.nan), 0
    col_norm = np.linalg.norm(Xw, axis=0)
    col_norm[col_norm == 0] = 1.0
    Xs = Xw / col_norm
    q, r, piv = scipy.linalg.qr(Xs, mode="economic", pivoting=True)
    d = np.abs(np.diag(r))
    tol = max(n, p) * np.finfo(float).eps * 1e3 * (d[0] if d.size else 0.0)
    rank = int(np.sum(d > tol))
    beta = np.full(p, np.nan)
    cov = np.full((p, p), np.nan)
    if rank == 0:
        return beta, cov, 0
    r1 = r[:rank, :rank]
    z = scipy.linalg.solve_triangular(r1, q[:, :rank].T @ yw)
    rinv = scipy.linalg.solve_triangular(r1, np.eye(rank))
    idx = piv[:rank]
    beta[idx] = z / col_norm[idx]
    c = rinv @ rinv.T
    cov[np.ix_(idx, idx)] = c / np.outer(col_norm[idx], col_norm[idx])
    return beta, cov, rank
