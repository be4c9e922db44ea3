"""A Whittle Fisher information written for the tests with numpy only, independent of
rigctl.solvers.allan_crb (one definition for the tests that check its Cramer-Rao figures).

The rate's one-sided PSD (u^2/Hz) of the IEEE 952 terms and a first-order Gauss-Markov (GM)
process of variance sg^2 and correlation time tc (autocovariance sg^2 e^(-|t|/tc), whose
cosine transform 4 int_0^inf sg^2 e^(-t/tc) cos(2 pi f t) dt is the Lorentzian below)::

    S(f) = 8 pi^2 Q^2 tau0 f^2 + 2 N^2 + B^2 / (pi f) + K^2 / (2 pi^2 f^2)
           + 4 sg^2 tc / (1 + (2 pi f tc)^2)

Whittle: over the Fourier frequencies f_k = k / T, k = 1 .. floor(T fs / 2) -- every one of
them, summed in chunks (no quadrature) -- I_ij = sum_k (d ln S / d phi_i)(d ln S / d phi_j) with
phi the logarithms of the parameters (Q^2, N^2, B^2, K^2, sg^2 and tc), the derivatives by
central differences of ln S (step 1e-5 in phi). sd(phi_i) = sqrt((I^-1)_ii) is the relative sd of
the parameter; a coefficient c (c^2 the parameter) has half of it.
"""
from __future__ import annotations

import math

import numpy as np

#: parameter names: IEEE 952 coefficients, then the GM term's sigma and correlation time
NAMES = ("Q", "N", "B", "K", "sg", "tc")
_STEP = 1e-5
_CHUNK = 500_000


def psd(f: np.ndarray, p: dict[str, float], tau0: float) -> np.ndarray:
    """S(f), u^2/Hz, for the coefficients ``p`` (SI; missing ones 0; the GM term when "sg" and
    "tc" are given)."""
    s = (8.0 * math.pi ** 2 * p.get("Q", 0.0) ** 2 * tau0 * f * f + 2.0 * p.get("N", 0.0) ** 2
         + p.get("B", 0.0) ** 2 / (math.pi * f) + p.get("K", 0.0) ** 2 / (2.0 * math.pi ** 2 * f * f))
    if p.get("sg", 0.0) > 0:
        s = s + 4.0 * p["sg"] ** 2 * p["tc"] / (1.0 + (2.0 * math.pi * f * p["tc"]) ** 2)
    return s


def rel_sd(p: dict[str, float], duration_s: float, rate_hz: float) -> dict[str, float]:
    """Cramer-Rao relative sd of each nonzero parameter of ``p`` (module docstring): sd(c)/c
    for Q, N, B, K and sg, sd(tc)/tc for tc."""
    names = [k for k in NAMES if p.get(k, 0.0) > 0]
    n_bins = int(duration_s * rate_hz / 2.0)
    info = np.zeros((len(names), len(names)))
    for first in range(1, n_bins + 1, _CHUNK):
        f = np.arange(first, min(first + _CHUNK, n_bins + 1)) / duration_s
        rows = []
        for k in names:
            # phi = ln(c^2) for a coefficient (c scales by e^(phi/2)), ln(tc) for tc
            e = _STEP if k == "tc" else _STEP / 2.0
            up, dn = dict(p), dict(p)
            up[k], dn[k] = p[k] * math.exp(e), p[k] * math.exp(-e)
            rows.append((np.log(psd(f, up, 1.0 / rate_hz)) - np.log(psd(f, dn, 1.0 / rate_hz)))
                        / (2.0 * _STEP))
        g = np.array(rows)
        info += g @ g.T
    cov = np.linalg.inv(info)
    return {k: math.sqrt(cov[i, i]) * (1.0 if k == "tc" else 0.5) for i, k in enumerate(names)}
