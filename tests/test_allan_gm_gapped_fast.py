"""The gapped Gauss-Markov covariance pairs from the compiled pair loop
(rigctl.solvers.allan_cov._gm_gapped_loop with numba, rigctl.solvers.allan_cov_kernels) equal
the same lag sums evaluated directly with numpy here, and the numpy loop kept as the fallback.

The expected values are written out below from the definitions (allan_cov's docstrings), not
taken from the code under test: for each pair of factors a <= b,

    S_t(a, b) = sum_k R_t(k) R_G(k) W(k),   R_t(k) = sum_{j,l} c_j c_l s_t((j m_a - l m_b - k) tau0)

over the integer lags k within 16 (m_a + m_b) of the taps and inside W's support, with W(k) the
number of pairs of terms at lag k summed over the stretches (counted here term by term), and
for (G, G) the exponential tail of R_G^2 W past both ends (R_G there = R_G(end) e^-|k - end|/h)
integrated with 8-point Gauss-Legendre between 0, h/4 ... 64 h and W's kinks, as the kernel's
documented rule; normalized 2 / (4 tau_a^2 tau_b^2 N(a) N(b)). The small cases are all summed
over integer lags (the kernel tables them; the sums are compensated), so they agree to
~1e-15; the Gauss-Legendre pairs evaluate the kernels with libm where numpy uses its own
(vectorized) log/expm1, so entries that are differences of large terms carry numpy's own
rounding: the numpy loop itself moves by up to 1.3e-8 relative in such entries between
numpy's AVX-512 and baseline builds on the same machine (measured, see the commit), so those
are compared against the size an entry can have (Cauchy-Schwarz: |S_t| <= sqrt(S_tt S_GG)).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.solvers import allan_cov as C
from rigctl.solvers import allan_cov_kernels as KC

pytestmark = pytest.mark.skipif(not KC.HAVE_NUMBA, reason="the compiled loop needs numba")

TAU0 = 0.01
CW = np.array([1.0, -2.0, 1.0])
GL_X, GL_W = np.polynomial.legendre.leggauss(8)
TAIL = np.array([0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])


def s_kernel(term: str, t: np.ndarray, tc: float) -> np.ndarray:
    """Generalized autocovariance of the phase, unit coefficient (t in s)."""
    a = np.abs(t)
    if term == "Q":
        return (a < 0.5 * TAU0).astype(float)
    if term == "N":
        return -0.5 * a
    if term == "K":
        return a ** 3 / 12.0
    if term == "B":
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(a > 0, t * t * np.log(a) / (2.0 * math.pi), 0.0)
    # G: Tc^2 phi(u), phi = 1 - u + u^2/2 - e^-u, its series u^3/6 - u^4/24 ... below 0.5
    # (Horner, highest order first: some entries are fourth differences of phi at a step of
    # 1/h and carry its rounding amplified ~h^2, so it is evaluated in the kernel's order)
    u = a / tc
    acc = np.full_like(u, 1.0 / math.factorial(17))
    for n in range(16, 2, -1):
        acc = acc * u + (-1.0) ** (n + 1) / math.factorial(n)
    return tc * tc * np.where(u < 0.5, acc * u ** 3, -np.expm1(-u) - u + 0.5 * u * u)


def r_lags(term: str, ma: float, mb: float, k: np.ndarray, tc: float) -> np.ndarray:
    out = np.zeros(np.shape(k))
    for j in range(3):
        for l in range(3):
            out += CW[j] * CW[l] * s_kernel(term, (j * ma - l * mb - k) * TAU0, tc)
    return out


def pair_count(lengths: list[int], ma: float, mb: float, k: np.ndarray) -> np.ndarray:
    """W(k): pairs (i, i') of terms at factors a, b with i' - i = k, over every stretch."""
    out = np.zeros(np.shape(k))
    for n in lengths:
        na, nb = n + 1 - 2 * ma, n + 1 - 2 * mb
        if na > 0 and nb > 0:
            out += np.maximum(0.0, np.minimum(na, nb - k) - np.maximum(0.0, -k))
    return out


def tail(lengths: list[int], ma: float, mb: float, start: float, end: float, sign: float,
         amp: float, h: float) -> float:
    """Integral of amp^2 e^(-2 x / h) W(start + sign x), x from 0 to |end - start|."""
    length = max((end - start) * sign, 0.0)
    kinks = []
    for n in lengths:
        na, nb = n + 1 - 2 * ma, n + 1 - 2 * mb
        if na > 0 and nb > 0:
            kinks += [-na, min(0.0, nb - na), max(0.0, nb - na), nb]
    d = np.sort(np.clip(np.concatenate([[0.0], h * TAIL, (np.array(kinks) - start) * sign,
                                        [length]]), 0.0, length))
    half, mid = 0.5 * np.diff(d), 0.5 * (d[1:] + d[:-1])
    x = mid[:, None] + half[:, None] * GL_X[None, :]
    w = pair_count(lengths, ma, mb, start + sign * x)
    return amp ** 2 * float(np.sum(np.exp(-2.0 * x / h) * w * (half[:, None] * GL_W)))


def direct(ms: np.ndarray, lengths: list[int], tc: float) -> dict:
    """The Gauss-Markov pairs of stretches ``lengths`` summed over every integer lag."""
    h = tc / TAU0
    n = ms.size
    big_n = np.array([sum(max(0, L + 1 - 2 * m) for L in lengths) for m in ms], dtype=float)
    out = {(t, "G"): np.zeros((n, n)) for t in "QNBKG"}
    for a in range(n):
        for b in range(a, n):
            ma, mb = float(ms[a]), float(ms[b])
            na = [L + 1 - 2 * ma for L in lengths if L + 1 - 2 * ma > 0 and L + 1 - 2 * mb > 0]
            nb = [L + 1 - 2 * mb for L in lengths if L + 1 - 2 * ma > 0 and L + 1 - 2 * mb > 0]
            if not na:
                continue
            s = ma + mb
            k_lo, k_hi = max(-2 * mb - 16 * s, -max(na)), min(2 * ma + 16 * s, max(nb))
            assert k_hi - k_lo <= C.GAPPED_DISCRETE_LAGS  # the case is summed over lags
            k = np.arange(math.ceil(k_lo), math.floor(k_hi) + 1, dtype=float)
            w = pair_count(lengths, ma, mb, k)
            rg = r_lags("G", ma, mb, k, tc)
            for t in "QNBKG":
                out[(t, "G")][a, b] = np.sum(r_lags(t, ma, mb, k, tc) * rg * w)
            for start, end, sign in ((k[-1] + 0.5, max(nb), 1.0), (k[0] - 0.5, -max(na), -1.0)):
                amp = float(r_lags("G", ma, mb, np.array([start]), tc)[0])
                out[("G", "G")][a, b] += tail(lengths, ma, mb, start, end, sign, amp, h)
    tau = ms * TAU0
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = 2.0 / (4.0 * np.outer(tau ** 2 * big_n, tau ** 2 * big_n))
    norm[~np.isfinite(norm)] = 0.0
    return {p: (c + np.triu(c, 1).T) * norm for p, c in out.items()}


def compiled(ms: np.ndarray, lengths: list[int], tc: float) -> dict:
    ln, cnt = np.unique(np.asarray(lengths, dtype=np.int64), return_counts=True)
    return C._gm_gapped_loop(TAU0, ms.astype(float), ln, cnt.astype(np.int64), tc)


MS = np.array([1, 2, 3, 5, 8, 13, 21, 30])


@pytest.mark.parametrize("tc", [0.004, 0.03, 0.3, 3.0])
@pytest.mark.parametrize("lengths", [[97, 233, 150, 97], [400]],
                         ids=["pieces of three lengths", "one piece"])
def test_compiled_loop_equals_the_direct_sums(lengths: list[int], tc: float) -> None:
    got = compiled(MS, lengths, tc)
    ref = direct(MS, lengths, tc)
    for p in ref:
        assert np.any(ref[p] != 0)
        np.testing.assert_allclose(got[p], ref[p], rtol=1e-12, atol=0, err_msg=str(p))


def test_one_piece_equals_the_ungapped_covariance() -> None:
    """One stretch through the gapped pair loop is the one-record covariance (pairs with
    m_a + m_b <= 64: both sum them over every integer lag)."""
    for tc in (0.03, 3.0):
        got = compiled(MS, [400], tc)
        ref = C.gm_term_covariances(TAU0, MS, 401, tc)
        for p in ref:
            np.testing.assert_allclose(got[p], ref[p], rtol=1e-12, atol=0, err_msg=str(p))


@pytest.mark.parametrize("tc", [0.02, 2.0])
def test_gauss_legendre_pairs_equal_the_numpy_loop(tc: float) -> None:
    """Pairs integrated by Gauss-Legendre (lag ranges past GAPPED_DISCRETE_LAGS; near
    breakpoints at Tc = 0.02 s, h = 2 < (m_a + m_b) / 4): the compiled loop against the numpy
    loop it replaces, which the fallback keeps."""
    ms = np.array([1.0, 7.0, 60.0, 150.0, 400.0, 1100.0])
    ln, cnt = np.array([4100, 6500], dtype=np.int64), np.array([2, 1], dtype=np.int64)
    got = C._gm_gapped_loop(TAU0, ms, ln, cnt, tc)
    ref = C._gm_gapped_loop_numpy(TAU0, ms, ln, cnt, tc)
    ieee = C._gapped(TAU0, ms, ln, cnt)
    pairs = list(C._gapped_pairs(ms, ln, cnt))
    assert any(s > C.DISCRETE_MAX and k_hi - k_lo > C.GAPPED_DISCRETE_LAGS
               for *_, s, lo, hi, k_lo, k_hi in pairs)
    for t, u in ref:
        bound = np.sqrt(np.abs((ref[("G", "G")] if t == "G" else ieee[(t, t)]) * ref[("G", "G")]))
        assert np.max(np.abs(got[(t, u)] - ref[(t, u)]) / bound) < 1e-9, (t, u)
        big = np.abs(ref[(t, u)]) > 1e-3 * bound  # not a difference of much larger terms
        np.testing.assert_allclose(got[(t, u)][big], ref[(t, u)][big], rtol=1e-10, atol=0)


def test_without_numba_the_numpy_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    ln, cnt = np.array([97, 150], dtype=np.int64), np.array([1, 1], dtype=np.int64)
    monkeypatch.setattr(KC, "HAVE_NUMBA", False)
    got = C._gm_gapped_loop(TAU0, MS.astype(float), ln, cnt, 0.3)
    ref = direct(MS, [97, 150], 0.3)
    for p in ref:
        np.testing.assert_allclose(got[p], ref[p], rtol=1e-12, atol=0, err_msg=str(p))


LD = np.longdouble


def _phi_ld(u: np.ndarray) -> np.ndarray:
    """phi(u) = 1 - u + u^2 / 2 - e^-u in long double (its series below u = 0.5)."""
    out = LD(1) - u + u * u / 2 - np.exp(-u)
    small = u < 0.5
    us = u[small]
    acc = np.zeros_like(us)
    for n in range(30, 2, -1):
        acc = acc * us + LD((-1) ** (n + 1)) / LD(math.factorial(n))
    out[small] = acc * us ** 3
    return out


def exact_gg_kg(tau0: float, ma: int, mb: int, length: int, tc: float) -> tuple[LD, LD]:
    """sum_k R_G(k)^2 w(k) and sum_k R_K(k) R_G(k) w(k) over every integer lag of one stretch
    of ``length`` samples (the exact lag sums of the estimator's covariance), in long double:
    R over the taps and 16 (m_a + m_b) past them from the kernels, beyond that R_K = 0 and
    R_G = -Tc^2 e^(-|k - k_0| / h) times (e^(m_a/h) - 1)^2 (e^(-m_b/h) - 1)^2 (right; mirrored
    left), c = (1, -2, 1) summed in closed form (no cancellation)."""
    t0, tcl = LD(tau0), LD(tc)
    h = tcl / t0
    big_a, big_b = length + 1 - 2 * ma, length + 1 - 2 * mb
    s = ma + mb
    k_lo, k_hi = max(-2 * mb - 16 * s, -big_a + 1), min(2 * ma + 16 * s, big_b - 1)

    def w(k):
        return np.maximum(LD(0), np.minimum(LD(big_a), LD(big_b) - k) - np.maximum(LD(0), -k))
    k = np.arange(k_lo, k_hi + 1).astype(LD)
    rg = np.zeros(k.size, dtype=LD)
    rk = np.zeros(k.size, dtype=LD)
    for j in range(3):
        for l in range(3):
            a = np.abs((j * ma - l * mb) - k) * t0
            rg += LD(CW[j] * CW[l]) * tcl * tcl * _phi_ld(a / tcl)
            rk += LD(CW[j] * CW[l]) * a ** 3 / 12
    gg, kg = np.sum(rg * rg * w(k)), np.sum(rk * rg * w(k))
    kr = np.arange(k_hi + 1, big_b).astype(LD)
    rg = -tcl * tcl * np.exp(-kr / h) * np.expm1(LD(ma) / h) ** 2 * np.expm1(-LD(mb) / h) ** 2
    gg += np.sum(rg * rg * w(kr))
    kl = np.arange(-big_a + 1, k_lo).astype(LD)
    rg = -tcl * tcl * np.exp(kl / h) * np.expm1(-LD(ma) / h) ** 2 * np.expm1(LD(mb) / h) ** 2
    gg += np.sum(rg * rg * w(kl))
    return gg, kg


@pytest.mark.parametrize("tc", [0.01, 1.0])
def test_long_stretches_match_the_exact_lag_sums(tc: float) -> None:
    """Stretches past GM_LONG_MIN (30000 and 45000 samples at 2 kHz) go through the compiled
    pair loop, whose (G, G) and (K, G) entries are within 1e-7 of the exact integer-lag sums
    (long double, above; measured at most 5.2e-8, the small diagonal pair's sum-vs-integral
    difference, which both methods share). The contiguous kernel these stretches went through
    before was off by up to 2.7e-6 (G, G) and 3.2e-7 (K, G) here (its fixed 4-point mesh;
    h = Tc / tau0 = 20 and 2000 samples)."""
    tau0, ms, lengths = 5e-4, [150, 1000, 6000], [30000, 45000]
    assert min(lengths) >= C.GM_LONG_MIN
    C._gm_gapped_cached.cache_clear()
    got = C.gapped_term_covariances(tau0, np.array(ms, float), np.array(lengths), tc)
    n_terms = [sum(L + 1 - 2 * m for L in lengths) for m in ms]
    for a in range(len(ms)):
        for b in range(a, len(ms)):
            sums = [exact_gg_kg(tau0, ms[a], ms[b], L, tc) for L in lengths]
            norm = 2.0 / (4.0 * (ms[a] * tau0) ** 2 * (ms[b] * tau0) ** 2
                          * n_terms[a] * n_terms[b])
            gg = float(sum(x[0] for x in sums)) * norm
            kg = float(sum(x[1] for x in sums)) * norm
            assert abs(got[("G", "G")][a, b] / gg - 1.0) < 1e-7, (a, b, got[("G", "G")][a, b], gg)
            assert abs(got[("K", "G")][a, b] / kg - 1.0) < 1e-7, (a, b, got[("K", "G")][a, b], kg)
