"""Spectral factorisation: white (N) + flicker cascade (B) + random walk (K) as ONE filtered white sequence.

Per output sample, with u = |1 - e^{-jw}|^2 = 4 sin^2(w/2) and, for a real pole or zero r = e^{-a},
|1 - r e^{-jw}|^2 = r (gamma(a) + u) with gamma(a) = 4 sinh^2(a/2), the (pseudo-)spectrum of the sum of
independent white noise of variance sn2, the flicker cascade H = prod (1 - e^{-b_k} z^-1)/(1 - e^{-a_k} z^-1)
driven by white noise of variance sb2, and a random walk with increments of variance sk2 is::

    S(u) = sn2 + sb2 |H|^2 + sk2 / u,    |H|^2 = prod_k e^{-b_k} (gamma(b_k) + u) / prod_k e^{-a_k} (gamma(a_k) + u)

As a function of u, S is a Stieltjes function (the cascade's poles and zeros interlace, pole first, so every
partial-fraction residue is positive; sk2/u adds a pole at u = 0): it increases strictly with c = -u between
consecutive poles c = gamma(a_k) (and c = 0 when sk2 > 0), from -inf to +inf, so it has exactly one root c_j in
each such interval, plus one above the last pole when sn2 > 0 (where S -> sn2 > 0). Each root gives the zero
zeta_j = e^{-b_j}, gamma(b_j) = c_j, i.e. b_j = 2 asinh(sqrt(c_j)/2), of the minimum-phase factor::

    S = g^2 |prod_j (1 - zeta_j e^{-jw})|^2 / (|prod_k (1 - e^{-a_k} e^{-jw})|^2 |1 - e^{-jw}|^{2 [sk2 > 0]})

A sum of independent Gaussian processes is Gaussian, and a Gaussian process is determined by its second-order
statistics, so ``g G(z)`` applied to ONE unit white Gaussian sequence has exactly the law of the sum (for
sk2 > 0: of its increments, which is all an Allan variance sees). Roots are found by bisection in s = ln c to
machine precision, with every factor evaluated in the (a, gamma) form: poles at e^{-1e-7} cause no cancellation.

:class:`rigctl.sim.noise.NoiseGenerator` uses it with sk2 = 0 (N + B). With sk2 > 0 the increments are exact,
but no start of the filter gives the power-on level of "stationary N + B plus a walk from 0": the best one
leaves an extra constant offset of variance of the order of sk2 / a_min (the walk over the slowest flicker
time).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


def log_gamma(a: np.ndarray) -> np.ndarray:
    """ln gamma(a) = ln 4 sinh^2(a/2) = ln((1 - e^-a)^2 / e^-a), accurate for tiny a; +inf for a = inf."""
    a = np.asarray(a, dtype=np.float64)
    with np.errstate(over="ignore"):
        return 2.0 * np.log(2.0 * np.sinh(a / 2.0))


@dataclass(frozen=True)
class CombinedFilter:
    """g * prod_j (1 - e^{-b_j} z^-1) / (prod_k (1 - e^{-a_k} z^-1) * (1 - z^-1)^[integrator]).

    ``b_stable`` (same length as ``a_stable``, padded with +inf = zero at the origin) go with the stable poles;
    ``b_integrator`` (inf if none) is the zero paired with the random walk's pole at z = 1.
    """

    a_stable: np.ndarray
    b_stable: np.ndarray
    integrator: bool
    b_integrator: float
    gain: float


def _spectrum(s: np.ndarray, sn2: float, sb2: float, sk2: float, lg_p: np.ndarray, a_p: np.ndarray,
              lg_z: np.ndarray, b_z: np.ndarray) -> np.ndarray:
    """S(u) at u = -e^s (vector s); lg_* = ln gamma of the cascade's poles and finite zeros."""
    s = np.asarray(s, dtype=np.float64)[:, None]
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        total = sn2 - sk2 * np.exp(-s[:, 0])
        if sb2 > 0:
            num = -np.expm1(s - lg_z)  # (gamma_z - c) / gamma_z
            den = -np.expm1(s - lg_p)
            logmag = (np.sum(lg_z - b_z + np.log(np.abs(num)), axis=1)
                      - np.sum(lg_p - a_p + np.log(np.abs(den)), axis=1))
            sign = np.prod(np.sign(num), axis=1) * np.prod(np.sign(den), axis=1)
            total = total + sb2 * sign * np.exp(logmag)
    return total


def _bisect(f, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Vectorised bisection of increasing f with f(lo) < 0 < f(hi), to ~1e-16 in s (relative in c = e^s)."""
    lo, hi = lo.astype(np.float64).copy(), hi.astype(np.float64).copy()
    for _ in range(2100):
        mid = 0.5 * (lo + hi)
        done = (mid <= lo) | (mid >= hi) | (hi - lo <= 2.3e-16 * np.maximum(1.0, np.abs(mid)))
        if np.all(done):
            break
        neg = f(mid) < 0
        lo = np.where(neg & ~done, mid, lo)
        hi = np.where(~neg & ~done, mid, hi)
    return 0.5 * (lo + hi)


@lru_cache(maxsize=256)
def _factor_cached(sn2: float, sb2: float, sk2: float, a_pole: tuple, a_zero: tuple) -> CombinedFilter:
    a_p = np.array(a_pole, dtype=np.float64) if sb2 > 0 else np.zeros(0)
    b_all = np.array(a_zero, dtype=np.float64) if sb2 > 0 else np.zeros(0)
    b_z = b_all[np.isfinite(b_all)]
    lg_p, lg_z = log_gamma(a_p), log_gamma(b_z)

    def f(s: np.ndarray) -> np.ndarray:
        return _spectrum(s, sn2, sb2, sk2, lg_p, a_p, lg_z, b_z)

    poles = np.sort(lg_p)
    if sk2 > 0:
        poles = np.concatenate([[-np.inf], poles])
    lo, hi = list(poles[:-1]), list(poles[1:])
    if sn2 > 0 and len(poles):
        lo.append(poles[-1])
        hi.append(np.inf)
    lo, hi = np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64)
    for i in range(len(lo)):  # finite brackets for the unbounded ends
        if not np.isfinite(lo[i]):
            start = hi[i] if np.isfinite(hi[i]) else np.log(sk2 / sn2)
            lo[i] = start - 1.0
            while f(np.array([lo[i]]))[0] >= 0:
                lo[i] -= 10.0
        if not np.isfinite(hi[i]):
            hi[i] = lo[i] + 1.0
            while f(np.array([hi[i]]))[0] <= 0:
                hi[i] += 10.0
    s_root = _bisect(f, lo, hi) if len(lo) else np.zeros(0)
    b_root = 2.0 * np.arcsinh(np.exp(s_root / 2.0) / 2.0)  # ascending, like the brackets
    if sk2 > 0:  # the largest zero goes with the random walk's pole at z = 1
        b_int, b_root = (b_root[-1], b_root[:-1]) if len(b_root) else (np.inf, b_root)
    else:
        b_int = np.inf
    b_stable = np.full(len(a_p), np.inf)
    b_stable[: len(b_root)] = b_root
    # gain from S at u* = 1 (w = pi/3), every factor in the e^{-a} (gamma(a) + u) form
    u = 1.0
    s_val = sn2 + sk2 / u
    if sb2 > 0:
        s_val += sb2 * np.exp(np.sum(-b_z + np.log(np.exp(lg_z) + u)) - np.sum(-a_p + np.log(np.exp(lg_p) + u)))
    b_fin = np.concatenate([b_stable[np.isfinite(b_stable)], [b_int] if np.isfinite(b_int) else []])
    log_fac = (np.sum(-b_fin + np.log(np.exp(log_gamma(b_fin)) + u)) - np.sum(-a_p + np.log(np.exp(lg_p) + u))
               - (np.log(u) if sk2 > 0 else 0.0))
    gain = float(np.sqrt(s_val / np.exp(log_fac))) if s_val > 0 else 0.0
    return CombinedFilter(a_p, b_stable, sk2 > 0, float(b_int), gain)


def factor(sn2: float, sb2: float, sk2: float, a_pole: np.ndarray, a_zero: np.ndarray) -> CombinedFilter:
    """Minimum-phase G with g^2 |G|^2 = sn2 + sb2 |H|^2 + sk2/|1 - e^{-jw}|^2 (variances per sample).

    ``a_pole``, ``a_zero``: the flicker cascade H (``a_zero`` may hold +inf, a zero at the origin); ignored
    when sb2 == 0. Cached: generators with the same coefficients share one factorisation.
    """
    if min(sn2, sb2, sk2) < 0:
        raise ValueError("variances must be >= 0")
    return _factor_cached(float(sn2), float(sb2), float(sk2),
                          tuple(np.asarray(a_pole, float)), tuple(np.asarray(a_zero, float)))


def residues(a_pole: np.ndarray, b_zero: np.ndarray) -> np.ndarray:
    """Partial fractions of prod_j (1 - e^{-b_j} z^-1) / prod_k (1 - e^{-a_k} z^-1) (distinct poles, no more
    zeros than poles): H = (1 - sum r) + sum_k r_k / (1 - e^{-a_k} z^-1), with
    r_k = prod_j (1 - e^{a_k - b_j}) / prod_{j != k} (1 - e^{a_k - a_j}), every factor an expm1 (no cancellation)."""
    a = np.asarray(a_pole, dtype=np.float64)
    b = np.asarray(b_zero, dtype=np.float64)
    with np.errstate(over="ignore"):
        num = np.prod(-np.expm1(a[:, None] - b[None, :]), axis=1)
        d = -np.expm1(a[:, None] - a[None, :])
    np.fill_diagonal(d, 1.0)
    return num / np.prod(d, axis=1)


def pseudo_spectrum(w: np.ndarray, sn2: float, sb2: float, sk2: float, a_pole: np.ndarray,
                    a_zero: np.ndarray) -> np.ndarray:
    """S at angular frequencies w (rad/sample) of the sum (reference for tests), in the (a, gamma) form."""
    u = 4.0 * np.sin(np.asarray(w, dtype=np.float64) / 2.0) ** 2
    out = sn2 + sk2 / u
    if sb2 > 0:
        ap, bz = np.asarray(a_pole, float), np.asarray(a_zero, float)
        bz = bz[np.isfinite(bz)]
        out = out + sb2 * np.exp(np.sum(-bz[:, None] + np.log(np.exp(log_gamma(bz))[:, None] + u), axis=0)
                                 - np.sum(-ap[:, None] + np.log(np.exp(log_gamma(ap))[:, None] + u), axis=0))
    return out
