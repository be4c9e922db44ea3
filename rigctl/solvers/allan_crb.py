"""How well can a capture determine the IEEE 952 noise terms? Cramer-Rao bounds (Whittle).

The rate signal's one-sided PSD for the IEEE 952 terms (coefficients in SI rate units u;
conversions from the Allan variance relations h_0 = 2 N^2, h_-1 = B^2 / pi, h_-2 =
K^2 / (2 pi^2), white phase of variance Q^2 per sample)::

    S(f) = 8 pi^2 Q^2 tau0 f^2 + 2 N^2 + B^2 / (pi f) + K^2 / (2 pi^2 f^2)     (u^2 / Hz)

(the rate ramp R is deterministic and carries no spectral information here). When the fit
has a first-order Gauss-Markov (GM) term -- a rate with autocovariance sigma_GM^2 e^(-|t|/Tc),
whose Allan variance is :func:`rigctl.solvers.allan_fit.gm_avar` -- its spectrum adds::

    S_GM(f) = 4 sigma_GM^2 Tc / (1 + (2 pi f Tc)^2)                            (u^2 / Hz)

(white with N^2 = 2 sigma_GM^2 Tc below f = 1 / (2 pi Tc), a random walk with K^2 =
2 sigma_GM^2 / Tc above). For a capture of duration T sampled at fs, the Fourier frequencies
f_k = k / T, k = 1 .. T fs / 2, are asymptotically independent with periodogram ~ S(f_k) x
Exp(1) (Whittle), so the Fisher information of theta = (Q^2, N^2, B^2, K^2[, sigma_GM^2, Tc])
is::

    I_ij = sum_k (d ln S / d theta_i)(d ln S / d theta_j)(f_k)

and no unbiased estimator from those T seconds beats sd(theta_i) = sqrt((I^-1)_ii); for a
coefficient c = sqrt(theta), sd(c)/c = sd(theta)/(2 theta). With a GM term its two parameters
are nuisance parameters: the IEEE terms' bounds are those of the full inverse, so they include
what the data cannot tell apart (a GM hump and B's flat floor, a GM hump's flanks and N or K)
and are never below the bounds without the term (S only grows, and a nuisance parameter only
adds to a marginal variance). Without one, theta and the sums are the four IEEE terms' alone. Random-walk terms are not
stationary, but the differenced series is and has the same d ln S (the differencing gain
cancels). The sum is exact over the first ``EXACT_BINS`` frequencies (where the long-term
terms live) and a trapezoid integral over log-spaced f above.

The overlapping Allan-variance fit with the full inter-tau covariance
(:mod:`rigctl.solvers.allan_fit`) reaches these bounds to within a few per cent (benchmark:
benchmarks/allan.py), so when a bound is wide no other estimator (longer taus, total or
Hadamard deviations, log-domain fits) can do better from the same capture: only a longer
capture can.
"""
from __future__ import annotations

import math
from typing import Mapping

import numpy as np
from .distributions import norm

TERMS4 = ("Q", "N", "B", "K")
#: the GM term's parameters in :func:`fisher`'s names: sigma_GM (theta = sigma_GM^2, u^2) and Tc
#: (theta = Tc, s)
GM_PARAMS = ("GM_sigma", "GM_tc")
EXACT_BINS = 20000
_QUAD_POINTS = 4000


def _columns(f: np.ndarray, tau0: float) -> dict[str, np.ndarray]:
    """dS/d theta for each term (theta = coefficient^2), u^2/Hz per u^2."""
    return {"Q": 8.0 * math.pi ** 2 * tau0 * f * f, "N": np.full(f.shape, 2.0),
            "B": 1.0 / (math.pi * f), "K": 1.0 / (2.0 * math.pi ** 2 * f * f)}


def psd(f: np.ndarray, coeffs: Mapping[str, float], tau0: float,
        gm: tuple[float, float] | None = None) -> np.ndarray:
    """One-sided PSD S(f) of the rate (u^2/Hz) for SI coefficients {Q, N, B, K}, plus the
    Gauss-Markov term's S_GM(f) when ``gm`` = (sigma_GM (u), Tc (s)) is given."""
    f = np.asarray(f, dtype=float)
    s = _psd_of(_columns(f, tau0), coeffs)
    gm = _usable_gm(gm)
    return s if gm is None else s + _gm_columns(f, gm)[0]


def _gm_columns(f: np.ndarray, gm: tuple[float, float]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S_GM(f) (u^2/Hz) and its derivatives d S_GM / d sigma_GM^2 (1/Hz) and d S_GM / d Tc
    (u^2/Hz/s) for ``gm`` = (sigma_GM, Tc): S_GM = 4 sigma_GM^2 Tc / (1 + (2 pi f Tc)^2)."""
    sigma, tc = float(gm[0]), float(gm[1])
    x = (2.0 * math.pi * tc) ** 2 * f * f
    d_var = 4.0 * tc / (1.0 + x)
    d_tc = 4.0 * sigma * sigma * (1.0 - x) / (1.0 + x) ** 2
    return sigma * sigma * d_var, d_var, d_tc


def _usable_gm(gm: tuple[float, float] | None) -> tuple[float, float] | None:
    """``gm`` when both its sigma_GM and Tc are positive and finite, else None (no term)."""
    if gm is None:
        return None
    sigma, tc = float(gm[0]), float(gm[1])
    return (sigma, tc) if (0 < sigma < math.inf and 0 < tc < math.inf) else None


def _psd_of(cols: dict[str, np.ndarray], coeffs: Mapping[str, float]) -> np.ndarray:
    return sum(float(coeffs.get(t, 0.0)) ** 2 * cols[t] for t in TERMS4)


def fisher(coeffs: Mapping[str, float], duration_s: float, rate_hz: float,
           terms: tuple[str, ...] | None = None, gm: tuple[float, float] | None = None
           ) -> tuple[list[str], np.ndarray]:
    """Whittle Fisher information of theta = coefficient^2 for the nonzero ``terms`` and, when
    ``gm`` = (sigma_GM (u), Tc (s)) is given (both > 0), of the Gauss-Markov term's
    theta = (sigma_GM^2, Tc), named :data:`GM_PARAMS`, after them (module docstring)."""
    tau0 = 1.0 / rate_hz
    terms = tuple(t for t in (terms or TERMS4) if float(coeffs.get(t, 0.0)) > 0)
    gm = _usable_gm(gm)
    n_bins = int(duration_s * rate_hz / 2.0)
    if n_bins < 1 or not terms:
        raise ValueError("need a capture of at least 2 samples and one nonzero term")
    n_par = len(terms) + (len(GM_PARAMS) if gm is not None else 0)
    info = np.zeros((n_par, n_par))

    def add(f: np.ndarray, w: np.ndarray) -> None:
        cols = _columns(f, tau0)
        s = _psd_of(cols, coeffs)  # psd(f, coeffs, tau0), its columns computed once
        if gm is None:
            g = np.array([cols[t] / s for t in terms])
        else:  # the GM term: in S, and its two parameters as nuisance rows
            s_gm, d_var, d_tc = _gm_columns(f, gm)
            s = s + s_gm
            g = np.array([cols[t] / s for t in terms] + [d_var / s, d_tc / s])
        info[:, :] += (g * w) @ g.T

    k_ex = min(n_bins, EXACT_BINS)
    add(np.arange(1, k_ex + 1) / duration_s, np.ones(k_ex))
    if n_bins > k_ex:  # sum_k h(k/T) ~ T integral h(f) df over (k_ex + 1/2, n_bins + 1/2) / T
        f = np.geomspace((k_ex + 0.5) / duration_s, (n_bins + 0.5) / duration_s, _QUAD_POINTS)
        w = np.zeros(f.size)
        d = np.diff(f) * duration_s / 2.0
        w[:-1] += d
        w[1:] += d
        add(f, w)
    return list(terms) + (list(GM_PARAMS) if gm is not None else []), info


def crb_rel_sd(coeffs: Mapping[str, float], duration_s: float, rate_hz: float,
               terms: tuple[str, ...] | None = None, gm: tuple[float, float] | None = None
               ) -> dict[str, float]:
    """Best achievable relative standard deviation sd(c)/c of each nonzero coefficient c
    (Q, N, B, K) from ``duration_s`` of data at ``rate_hz`` (Cramer-Rao, Whittle). With
    ``gm`` = (sigma_GM (u), Tc (s)) the Gauss-Markov term is in the model and its parameters
    are nuisance parameters of the bound (module docstring); the result then also carries
    "GM_sigma" (sd(sigma_GM)/sigma_GM) and "GM_tc" (sd(Tc)/Tc)."""
    names, info = fisher(coeffs, duration_s, rate_hz, terms, gm)
    cov = np.linalg.inv(info)
    out = {t: 0.5 * math.sqrt(max(cov[i, i], 0.0)) / float(coeffs[t]) ** 2
           for i, t in enumerate(names) if t not in GM_PARAMS}
    usable = _usable_gm(gm)
    if usable is not None:  # the GM parameters, after the terms
        sigma, tc = usable
        i = len(out)
        out["GM_sigma"] = 0.5 * math.sqrt(max(cov[i, i], 0.0)) / sigma ** 2
        out["GM_tc"] = math.sqrt(max(cov[i + 1, i + 1], 0.0)) / tc
    return out


def prob_within(rel_sd: float, tolerance: float) -> float:
    """P(|c_hat / c - 1| <= tolerance) for an unbiased normal estimator with sd ``rel_sd``."""
    if rel_sd <= 0:
        return 1.0
    return float(2.0 * norm.cdf(tolerance / rel_sd) - 1.0)


#: longest capture :func:`duration_for` considers, s (10000 h; beyond it: inf)
MAX_CAPTURE_S = 3.6e7


def duration_for(coeffs: Mapping[str, float], term: str, rel_sd: float, rate_hz: float,
                 t_min_s: float = 600.0, t_max_s: float = MAX_CAPTURE_S,
                 gm: tuple[float, float] | None = None,
                 memo: dict[float, dict[str, float]] | None = None) -> float:
    """Shortest capture (s) whose bound for ``term`` is at most ``rel_sd`` (inf if even
    ``t_max_s`` does not reach it), with the Gauss-Markov term ``gm`` = (sigma_GM, Tc) in the
    model when given (:func:`crb_rel_sd`). Bisection on log T (the bound falls monotonically).
    ``memo``: {duration: crb_rel_sd's result} for these ``coeffs``, ``rate_hz`` and ``gm``,
    shared by the calls for the model's several terms (their searches start at the same
    durations): each duration's bounds are computed once."""
    cache: dict[float, dict[str, float]] = {} if memo is None else memo

    def sd(t: float) -> float:
        if t not in cache:
            cache[t] = crb_rel_sd(coeffs, t, rate_hz, gm=gm)
        return cache[t][term]

    if sd(t_max_s) > rel_sd:
        return math.inf
    lo, hi = math.log(t_min_s), math.log(t_max_s)
    if sd(t_min_s) <= rel_sd:
        return t_min_s
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if sd(math.exp(mid)) > rel_sd:
            lo = mid
        else:
            hi = mid
    return math.exp(hi)


def dominance(coeffs: Mapping[str, float], term: str, tau_min_s: float, tau_max_s: float
              ) -> tuple[float, float, float]:
    """Where ``term`` is the largest of the IEEE 952 Allan-variance terms within
    [tau_min_s, tau_max_s]: (fraction of the log-tau range, first tau, last tau); (0, nan,
    nan) if nowhere."""
    tau = np.geomspace(tau_min_s, tau_max_s, 4000)
    c = {t: float(coeffs.get(t, 0.0)) ** 2 for t in ("Q", "N", "B", "K", "R")}
    parts = {"Q": 3.0 * c["Q"] / tau ** 2, "N": c["N"] / tau,
             "B": np.full(tau.shape, 2.0 * math.log(2.0) / math.pi * c["B"]),
             "K": c["K"] * tau / 3.0, "R": c["R"] * tau ** 2 / 2.0}
    others = np.max([v for t, v in parts.items() if t != term], axis=0)
    top = parts[term] > others
    if not np.any(top):
        return 0.0, math.nan, math.nan
    return float(np.mean(top)), float(tau[top][0]), float(tau[top][-1])
