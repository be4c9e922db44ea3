"""Fits written for the real-data Allan tests with numpy/scipy only, independent of rigctl's
solvers (one definition for every test that reads a real curve this way).

* ``white_gm_fit``: white noise + a first-order Gauss-Markov (GM) term on the Allan variance
  sigma^2(tau) = N^2/tau + sigma_GM^2 (Tc/tau)^2 (2 tau/Tc - 3 + 4 e^(-tau/Tc) - e^(-2 tau/Tc)),
  by weighted least squares (scipy.optimize.least_squares in log parameters,
  var(sigma^2) = 2 sigma^4 / EDF with the model's sigma^2, iterated); 95 % intervals from the
  Jacobian, the correlation across taus neglected (narrower intervals: a stricter comparison).
* ``white_gm_profile``: the same model's profile chi-square over a grid of Tc (N^2 and
  sigma_GM^2 linear at each Tc) and Tc's 95 % profile-likelihood interval.
* ``floor_fit``: B and K above a given white-noise offset, sigma^2 - off = (0.664 B)^2 + K^2 tau/3,
  by non-negative weighted least squares with the same iterated weights; B's 95 % interval from
  that fit's covariance, the correlation across taus neglected.
* ``agree``: two values within their combined 95 % intervals, in log: |ln(a/b)| <=
  sqrt(h_a^2 + h_b^2), h the log half-width of each interval on the side facing the other value.
* ``bound_ceiling``: the curve each term's reported bound is held under, read from the
  deviations and their EDF with scipy's chi-square (curve_ceiling below).
* ``assert_gm_agrees``: rigctl's Tc and sigma_GM against ``white_gm_fit``'s by ``agree``, and the
  same comparison rejecting either value 2x off (either way), so that it can fail.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares, nnls
from scipy.stats import chi2

#: flicker FM's Allan deviation per unit B: sqrt(2 ln 2 / pi) = 0.664
B_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)
Z95 = 1.959964
#: rad/s to deg/h (the messages only)
RAD_S_TO_DEG_H = 180.0 / math.pi * 3600.0


def bound_ceiling(dev: np.ndarray, edf: np.ndarray, model_error_rel: float,
                  hold: float, alpha: float = 0.025) -> np.ndarray:
    """The curve a bound may not exceed, at each tau (its read-off per term: c^2 A(tau) <=
    ceiling^2 at every tau). Where the fit needs a model error of at least ``hold`` (its
    MODEL_ERROR_HOLD; the curve is not IEEE 952 and the fit holds its terms to the measured
    curve) the measured deviations themselves. Else the curve is an estimate and a 95 % bound
    can only be held to what it permits at 95 %: the upper end of each deviation's chi-square
    band, sigma sqrt(nu / chi2_q(nu)), simultaneous over the n taus given (Sidak, q = 1 - (1 -
    alpha)^(1/n), the most the fit's own family-wise band can reach: it counts the effective
    number of independent taus, at most n)."""
    dev, edf = np.asarray(dev, float), np.asarray(edf, float)
    if model_error_rel >= hold:
        return dev
    q = -math.expm1(math.log1p(-alpha) / max(dev.size, 1))
    return dev * np.sqrt(edf / chi2.ppf(q, edf))


def gm_avar(tau: np.ndarray, var_gm: float, tc: float) -> np.ndarray:
    """Allan variance of a first-order Gauss-Markov process of variance ``var_gm`` and
    correlation time ``tc`` (s) at ``tau`` (s)."""
    r = tau / tc
    return var_gm * (2.0 * r - 3.0 + 4.0 * np.exp(-r) - np.exp(-2.0 * r)) / r ** 2


def white_gm_fit(tau: np.ndarray, s2: np.ndarray, edf: np.ndarray) -> dict:
    """White + GM on the Allan variances ``s2`` at ``tau`` with their EDFs (module docstring):
    {"tc", "tc_ci95", "sigma", "sigma_ci95", "chi2", "dof", "tau", "s2", "edf"}, SI."""
    def model(p: np.ndarray) -> np.ndarray:
        return math.exp(p[0]) / tau + gm_avar(tau, math.exp(p[1]), math.exp(p[2]))

    p = np.log([3e-7, 1e-7, 3.0])  # N^2, sigma_GM^2, Tc: starting values, not the answer
    sd_s2 = s2 * np.sqrt(2.0 / edf)
    for _ in range(10):
        p = least_squares(lambda q: (model(q) - s2) / sd_s2, p).x
        sd_s2 = model(p) * np.sqrt(2.0 / edf)
    fit = least_squares(lambda q: (model(q) - s2) / sd_s2, p)
    sd = np.sqrt(np.diag(np.linalg.inv(fit.jac.T @ fit.jac)))
    tc, var = math.exp(fit.x[2]), math.exp(fit.x[1])
    return {"tc": tc, "tc_ci95": (tc * math.exp(-Z95 * sd[2]), tc * math.exp(Z95 * sd[2])),
            "sigma": math.sqrt(var),
            "sigma_ci95": (math.sqrt(var) * math.exp(-Z95 * sd[1] / 2), math.sqrt(var) * math.exp(Z95 * sd[1] / 2)),
            "chi2": float(np.sum(((model(fit.x) - s2) / sd_s2) ** 2)), "dof": int(tau.size - 3),
            "tau": tau, "s2": s2, "edf": edf}


def _nnls_iterated(a: np.ndarray, s2: np.ndarray, edf: np.ndarray,
                   off: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Non-negative c with a c + off ~ s2, weighted by 1 / sd(s2), sd(s2) = model sqrt(2 / EDF)
    with the model a c + off (iterated from the data): (c, the final weights)."""
    mod = s2.copy()
    for _ in range(100):
        w = np.sqrt(edf / 2.0) / mod
        c, _ = nnls(a * w[:, None], (s2 - off) * w)
        new = np.maximum(a @ c + off, 1e-300)
        if np.allclose(new, mod, rtol=1e-12):
            break
        mod = new
    return c, w


def white_gm_profile(tau: np.ndarray, s2: np.ndarray, edf: np.ndarray,
                     tcs: np.ndarray) -> dict:
    """White + GM's profile over the correlation times ``tcs`` (s): at each Tc, N^2 and
    sigma_GM^2 by non-negative weighted least squares (var(sigma^2) = 2 model^2 / EDF,
    iterated), its chi-square; Tc's 95 % profile-likelihood interval the Tc whose chi-square is
    within chi2_0.95(1) of the least (scaled by chi2/dof where that exceeds 1). Returns {"tc",
    "tc_ci95", "chi2", "dof", "open" (the set reaches the first or last Tc given)}, SI."""
    def chi2_at(tc: float) -> float:
        a = np.column_stack([1.0 / tau, gm_avar(tau, 1.0, tc)])
        c, w = _nnls_iterated(a, s2, edf)
        return float(np.sum(((a @ c - s2) * w) ** 2))

    c = np.array([chi2_at(float(t)) for t in tcs])
    i, dof = int(np.argmin(c)), int(tau.size - 3)
    inside = np.flatnonzero(c <= c[i] + max(1.0, c[i] / dof) * chi2.ppf(0.95, 1))
    return {"tc": float(tcs[i]), "tc_ci95": (float(tcs[inside[0]]), float(tcs[inside[-1]])),
            "chi2": float(c[i]), "dof": dof, "open": (inside[0] == 0, inside[-1] == tcs.size - 1)}


def floor_fit(tau: np.ndarray, dev: np.ndarray, nu: np.ndarray, off: np.ndarray) -> tuple[float, float, float]:
    """B and its 95 % interval (lower, upper) from the deviations ``dev`` at ``tau`` with EDFs
    ``nu``, above the white terms' variance ``off`` at the same taus (module docstring)."""
    a = np.column_stack([np.full(tau.size, B_FACTOR ** 2), tau / 3])
    c, w = _nnls_iterated(a, dev ** 2, nu, off)
    sd = math.sqrt(np.linalg.inv((a * w[:, None]).T @ (a * w[:, None]))[0, 0])
    return math.sqrt(c[0]), math.sqrt(max(c[0] - 1.96 * sd, 0.0)), math.sqrt(c[0] + 1.96 * sd)


def agree(a: float, a_ci: tuple[float, float], b: float, b_ci: tuple[float, float]) -> bool:
    """a and b within their combined 95 % intervals, in log (module docstring)."""
    ha = math.log(a_ci[1] / a) if b > a else math.log(a / a_ci[0])
    hb = math.log(b / b_ci[0]) if b > a else math.log(b_ci[1] / b)
    return abs(math.log(a / b)) <= math.hypot(ha, hb)


def assert_gm_agrees(gm: dict, ind: dict) -> None:
    """rigctl's GM values ``gm`` ({"tc", "tc_ci95", "sigma", "sigma_ci95"}, SI) inside their own
    intervals and agreeing with ``ind`` (:func:`white_gm_fit`'s) by :func:`agree`; the same
    comparison rejects a Tc or a sigma_GM 2x off either way (so it has teeth)."""
    assert gm["tc_ci95"][0] <= gm["tc"] <= gm["tc_ci95"][1]
    msg = (f"rigctl Tc {gm['tc']:.3f} s {gm['tc_ci95']}, sigma_GM {gm['sigma'] * RAD_S_TO_DEG_H:.2f} "
           f"deg/h; here Tc {ind['tc']:.3f} s {ind['tc_ci95']}, sigma_GM "
           f"{ind['sigma'] * RAD_S_TO_DEG_H:.2f} deg/h")
    assert agree(gm["tc"], gm["tc_ci95"], ind["tc"], ind["tc_ci95"]), msg
    assert agree(gm["sigma"], gm["sigma_ci95"], ind["sigma"], ind["sigma_ci95"]), msg
    for f in (2.0, 0.5):
        tc_ci = tuple(v * f for v in gm["tc_ci95"])
        assert not agree(gm["tc"] * f, tc_ci, ind["tc"], ind["tc_ci95"]), (f, msg)
        s_ci = tuple(v * f for v in gm["sigma_ci95"])
        assert not agree(gm["sigma"] * f, s_ci, ind["sigma"], ind["sigma_ci95"]), (f, msg)
