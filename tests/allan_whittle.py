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

For the Monte Carlo checks of what those bounds promise: white + Gauss-Markov series with the
GM rate sampled exactly (:func:`white_gm_series`), and the Whittle maximum-likelihood estimate
of (N, sg, tc) from their periodogram, one series (:func:`whittle_fit_white_gm`, scipy's
L-BFGS-B) or many at once (:func:`whittle_fit_white_gm_batch`, Fisher scoring in numpy).
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


def white_gm_series(n: int, tau0: float, n_white: float, sg: float, tc: float,
                    rng: np.random.Generator) -> np.ndarray:
    """``n`` samples (every tau0 s) of a white rate of density ``n_white`` (u sqrt(s): sd
    n_white / sqrt(tau0) per sample) plus a Gauss-Markov rate of sd ``sg`` (u) and correlation
    time ``tc`` (s), the latter sampled exactly: an AR(1) with phi = e^(-tau0/tc) started in
    its stationary distribution, so that its autocovariance is sg^2 e^(-|t|/tc) at every lag."""
    from scipy.signal import lfilter

    phi = math.exp(-tau0 / tc)
    x0 = rng.standard_normal() * sg  # x_(-1), stationary
    gm = lfilter([sg * math.sqrt(1.0 - phi * phi)], [1.0, -phi], rng.standard_normal(n),
                 zi=[phi * x0])[0]
    return n_white / math.sqrt(tau0) * rng.standard_normal(n) + gm


def whittle_fit_white_gm(y: np.ndarray, tau0: float, start: dict[str, float]) -> dict[str, float]:
    """Whittle maximum-likelihood estimate of (N, sg, tc) of white + Gauss-Markov from the
    rates ``y`` (u, every tau0 s): the periodogram I_k = 2 tau0 |sum_j y_j e^(-2 pi i j k/n)|^2
    / n at f_k = k / (n tau0), k = 1 .. n/2, and the minimum over the log parameters of
    sum_k ln S(f_k) + I_k / S(f_k), S = 2 N^2 + 4 sg^2 tc / (1 + (2 pi f tc)^2) (the module's
    PSD), by L-BFGS-B with the analytic gradient, started at ``start`` ({"N", "sg", "tc"}). The
    sum is taken relative to its value at the start (L-BFGS-B's stopping rule is relative to
    |sum|, which is ~1e7 for 1e6 frequencies: it would stop where Tc has not moved yet)."""
    from scipy.optimize import minimize

    n = y.size
    f = np.arange(1, n // 2 + 1) / (n * tau0)
    per = 2.0 * tau0 * np.abs(np.fft.rfft(y - y.mean())[1:n // 2 + 1]) ** 2 / n
    w2 = (2.0 * math.pi * f) ** 2

    def nll(phi: np.ndarray, s_ref: np.ndarray) -> tuple[float, np.ndarray]:
        n2, s2, tc = np.exp(phi)
        x = w2 * tc * tc
        s_gm = 4.0 * s2 * tc / (1.0 + x)
        s = 2.0 * n2 + s_gm
        r = 1.0 - per / s
        grad = np.array([np.sum(r * 2.0 * n2 / s), np.sum(r * s_gm / s),
                         np.sum(r * s_gm * (1.0 - x) / (1.0 + x) / s)])
        return float(np.sum(np.log(s / s_ref) + per / s - per / s_ref)), grad

    x0 = np.log([start["N"] ** 2, start["sg"] ** 2, start["tc"]])
    s0 = 2.0 * start["N"] ** 2 + 4.0 * start["sg"] ** 2 * start["tc"] / (1.0 + w2 * start["tc"] ** 2)
    res = minimize(nll, x0, args=(s0,), jac=True, method="L-BFGS-B",
                   options={"ftol": 1e-13, "gtol": 1e-7, "maxiter": 500})
    n2, s2, tc = np.exp(res.x)
    return {"N": math.sqrt(n2), "sg": math.sqrt(s2), "tc": float(tc), "converged": bool(res.success)}


def whittle_fit_white_gm_batch(ys: np.ndarray, tau0: float, start: dict[str, float],
                               iterations: int = 40, tol: float = 1e-6) -> dict[str, np.ndarray]:
    """:func:`whittle_fit_white_gm` for many series at once (rows of ``ys``) by Fisher scoring
    in the log parameters phi = ln(N^2, sg^2, tc): phi += I^-1 U with the score U = sum_k (I_k /
    S_k - 1) d ln S_k / d phi and the information I = sum_k (d ln S / d phi)(d ln S / d phi)^T,
    each step at most 0.5 in every phi and halved (up to 30 times) until the likelihood does
    not fall; until every step is below ``tol`` (at most ``iterations`` steps: a series still
    moving then is not converged). A series whose Tc leaves [start / 1000, start x 1000] is
    stopped there and not converged. Returns {"N", "sg", "tc": arrays, "converged": bool
    array}. Agrees with :func:`whittle_fit_white_gm` to ~1e-7."""
    ys = np.atleast_2d(np.asarray(ys, dtype=float))
    n = ys.shape[1]
    f = np.arange(1, n // 2 + 1) / (n * tau0)
    per = 2.0 * tau0 * np.abs(np.fft.rfft(ys - ys.mean(axis=1, keepdims=True),
                                          axis=1)[:, 1:n // 2 + 1]) ** 2 / n
    w2 = (2.0 * math.pi * f) ** 2

    def parts(phi: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
        """S, the columns d ln S / d phi and the negative log-likelihood, per series."""
        n2, s2, tc = (np.exp(phi[:, i])[:, None] for i in range(3))
        x = w2 * tc * tc
        s_gm = 4.0 * s2 * tc / (1.0 + x)
        s = 2.0 * n2 + s_gm
        b = s_gm / s
        return s, [2.0 * n2 / s, b, b * (1.0 - x) / (1.0 + x)], np.sum(np.log(s) + per / s, axis=1)

    phi = np.tile(np.log([start["N"] ** 2, start["sg"] ** 2, start["tc"]]), (ys.shape[0], 1))
    done = np.zeros(ys.shape[0], dtype=bool)
    stuck = np.zeros(ys.shape[0], dtype=bool)
    s, g, nll = parts(phi)
    for _ in range(iterations):
        r = per / s - 1.0
        u = np.stack([np.sum(r * gi, axis=1) for gi in g], axis=1)
        info = np.empty((ys.shape[0], 3, 3))
        for i in range(3):
            for j in range(i + 1):
                info[:, i, j] = info[:, j, i] = np.sum(g[i] * g[j], axis=1)
        # a series whose estimate runs off to where the GM term is a white noise or a random
        # walk (tc -> 0 or inf: its columns collinear) is stopped there, not converged
        info += 1e-12 * np.trace(info, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        step = np.linalg.solve(info, u[:, :, None])[:, :, 0]
        lost = ~np.all(np.isfinite(step), axis=1) | (np.abs(phi[:, 2] - math.log(start["tc"]))
                                                       > math.log(1e3))
        stuck |= lost & ~done
        done |= lost
        step[done] = 0.0
        step *= np.minimum(1.0, 0.5 / np.maximum(np.max(np.abs(step), axis=1), 1e-300))[:, None]
        for _ in range(30):
            s_new, g_new, nll_new = parts(phi + step)
            worse = nll_new > nll + 1e-12 * np.abs(nll)
            if not np.any(worse):
                break
            step[worse] *= 0.5
        phi = phi + step
        s, g, nll = s_new, g_new, nll_new
        done |= np.max(np.abs(step), axis=1) < tol
        if np.all(done):
            break
    n2, s2, tc = np.exp(phi).T
    return {"N": np.sqrt(n2), "sg": np.sqrt(s2), "tc": tc, "converged": done & ~stuck}
