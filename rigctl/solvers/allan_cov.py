"""Covariance of overlapping Allan-variance estimates at many taus, for a mixture of noises.

The estimate at factor m (tau = m tau0, M = N - 2m terms) is
``s2(m) = sum_i D_m[i]^2 / (2 tau^2 M)``, D_m[i] = x[i+2m] - 2x[i+m] + x[i]. For Gaussian
noise with stationary second differences (Isserlis: Cov(X^2, Y^2) = 2 Cov(X, Y)^2)::

    Cov(s2(a), s2(b)) = 2 sum_{i,i'} R_ab(i' - i)^2 / (4 tau_a^2 tau_b^2 M_a M_b)
                      = 2 sum_k R_ab(k)^2 w_ab(k) / (...),
    R_ab(k) = Cov(D_a[i], D_b[i+k]) = sum_{j,l} c_j c_l s((j m_a - l m_b - k) tau0),

c = (1, -2, 1), w_ab(k) = number of index pairs at lag k, and s the generalized
autocovariance of the phase (defined up to a cubic, which the second differences cancel),
one kernel per IEEE 952 term (coefficients in SI rate units)::

    Q  white PM:   Q^2 [t = 0]              (AVAR 3 Q^2 / tau^2)
    N  white FM:  -N^2 |t| / 2              (AVAR N^2 / tau)
    B  flicker FM: B^2 t^2 ln|t| / (2 pi)   (AVAR (2 ln2 / pi) B^2)
    K  RW FM:      K^2 |t|^3 / 12           (AVAR K^2 tau / 3)

(the rate ramp R is deterministic and adds no variance here). This is the calculation behind
Greenhall's EDF, done for a mixture and for pairs of taus: the diagonal is 2 s2^2 / edf.
Small factors are summed exactly over integer lags; otherwise the lag sum is integrated with
8-point Gauss-Legendre between the kinks of R and w (exact for the polynomial kernels; the
flicker tail ~1/k^4 is followed to 16 (m_a + m_b)). Strided (fast-mode) estimates are treated
as fully overlapping ones, whose degrees of freedom they keep.

:func:`term_covariances` returns one matrix per pair of terms, so the covariance for any
coefficients is a cheap weighted sum (:func:`combine`).
"""
from __future__ import annotations

import functools
import math

import numpy as np

TERMS4 = ("Q", "N", "B", "K")
PAIRS = [(t, u) for i, t in enumerate(TERMS4) for u in TERMS4[i:]]
_C = np.array([1.0, -2.0, 1.0])
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)
DISCRETE_MAX = 64  # m_a + m_b up to this: exact sum over integer lags


def _kernel(term: str, t: np.ndarray, tc: float | None = None) -> np.ndarray:
    """Generalized autocovariance of the phase for unit coefficient, t in s (``tc``: the
    Gauss-Markov term's correlation time, s; see :func:`gm_term_covariances`)."""
    a = np.abs(t)
    if term == "G":
        return tc * tc * _gm_phi(a / tc)
    if term == "N":
        return -0.5 * a
    if term == "K":
        return a ** 3 / 12.0
    if term == "B":
        with np.errstate(divide="ignore", invalid="ignore"):
            v = t * t * np.log(a) / (2.0 * math.pi)
        return np.where(a > 0, v, 0.0)
    if term == "Q":
        return np.where(a < 1e-9 * (1.0 + a.max(initial=0.0)), 1.0, 0.0)
    raise ValueError(term)


def _r_lags(term: str, ma: np.ndarray, mb: np.ndarray, k: np.ndarray, tau0: float,
            tc: float | None = None) -> np.ndarray:
    """R_ab(k) for unit coefficient; ma, mb, k broadcast together (sample units)."""
    out = np.zeros(np.broadcast(ma, mb, k).shape)
    for j in range(3):
        for l in range(3):
            if term == "Q":
                lag = j * ma - l * mb - k
                out += _C[j] * _C[l] * (np.abs(lag) < 0.5)
            else:
                out += _C[j] * _C[l] * _kernel(term, (j * ma - l * mb - k) * tau0, tc)
    return out


def _weight(ma_n: np.ndarray, mb_n: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Number of (i, i') with i' - i = k, 0 <= i < M_a, 0 <= i' < M_b (real k: its length)."""
    return np.maximum(0.0, np.minimum(ma_n, mb_n - k) - np.maximum(0.0, -k))


def _integer_lags(ma: np.ndarray, mb: np.ndarray, big_a: np.ndarray, big_b: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The integer lags k of an exact lag sum for pairs (m_a, m_b) (columns), padded to a common
    length, from -2 m_b - span to 2 m_a + span (span = 16 (m_a + m_b)), and their pair counts w
    (0 past a pair's own end). Returns (k0, span, k, w)."""
    span = 16 * (ma + mb)
    k0 = -2 * mb - span
    length = int(np.max(2 * ma + span - k0)) + 1
    k = k0 + np.arange(length)[None, :]
    w = _weight(big_a, big_b, k)
    return k0, span, k, np.where(k <= 2 * ma + span, w, 0.0)


def _kinks(ma: np.ndarray, mb: np.ndarray, big_a: np.ndarray, big_b: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where R_ab and w have kinks, for the Gauss-Legendre lag integral of pairs (m_a, m_b):
    the nine taps j m_a - l m_b, points 1-16 (m_a + m_b) outside the outer taps, and w's four
    corners; the integral runs from k_lo to k_hi (16 (m_a + m_b) past the taps, within the
    record). Returns (taps, m_a + m_b, k_lo, k_hi, kinks)."""
    taps = np.concatenate([j * ma - l * mb for j in range(3) for l in range(3)], axis=1)
    s = ma + mb
    lo, hi = taps.min(1, keepdims=True), taps.max(1, keepdims=True)
    geo = np.array([1.0, 2.0, 4.0, 8.0, 16.0])[None, :]
    wk = np.concatenate([-big_a, np.zeros_like(ma), big_b - big_a, big_b], axis=1)
    k_lo = np.maximum(lo - 16 * s, -big_a)
    k_hi = np.minimum(hi + 16 * s, big_b)
    return taps, s, k_lo, k_hi, np.concatenate([taps, lo - s * geo, hi + s * geo, wk], axis=1)


def _q_tap_sums(ma: np.ndarray, mb: np.ndarray, big_a: np.ndarray, big_b: np.ndarray,
                tau0: float) -> dict:
    """sum_k R_Q(k) R_u(k) w(k) for u in Q, N, B, K over pairs (m_a, m_b) (columns): white PM's
    R_ab(k) is nonzero only at the taps k = j m_a - l m_b, so the lag sum is exact over those
    (each distinct tap once). Left out past DISCRETE_MAX, white PM made the covariance of a
    white-PM-dominated curve (an OCXO's, Q up to tau ~100 s) indefinite: the diagonal without
    Q's share, its cross terms with N, B, K cut at m_a + m_b = 64 (correlation eigenvalues down
    to -0.064 on the OCXO's quiet half, chi-square 2.8e5 on 37 dof from the clipped
    directions)."""
    taps = np.concatenate([j * ma - l * mb for j in range(3) for l in range(3)], axis=1)
    eq = taps[:, :, None] == taps[:, None, :]
    first = ~np.any(np.tril(eq, -1), axis=2)  # a tap equal to an earlier one is not summed again
    w = _weight(big_a, big_b, taps) * first
    rq = _r_lags("Q", ma, mb, taps, tau0)
    return {u: np.sum(rq * _r_lags(u, ma, mb, taps, tau0) * w, axis=1) for u in TERMS4}


def term_covariances(tau0: float, ms: np.ndarray, n_phase: int, tc: float | None = None
                     ) -> dict:
    """{(t, u): matrix} with Cov(s2(a), s2(b)) = sum_{t<=u} f_tu p_t p_u C_tu[a, b],
    p = coefficient^2, f_tu = 1 if t == u else 2 (use :func:`combine`). A function of
    (tau0, ms, n_phase) only: the six axes of a recording share it, so the last few are kept
    (the matrices are read-only). With ``tc`` (s), also the Gauss-Markov pairs GPAIRS for
    p_G = sigma_GM^2 at that correlation time (:func:`gm_term_covariances`)."""
    base = _cached(float(tau0), np.asarray(ms, dtype=float).tobytes(), int(n_phase))
    if tc is None:
        return base
    return {**base, **_gm_cached(float(tau0), np.asarray(ms, dtype=float).tobytes(),
                                 int(n_phase), float(tc))}


@functools.lru_cache(maxsize=8)
def _cached(tau0: float, ms_key: bytes, n_phase: int) -> dict:
    out = _term_covariances(tau0, np.frombuffer(ms_key, dtype=float), n_phase)
    for c in out.values():
        c.setflags(write=False)
    return out


def _term_covariances(tau0: float, ms: np.ndarray, n_phase: int) -> dict:
    ms = np.asarray(ms, dtype=float)
    n = ms.size
    big_m = n_phase - 2.0 * ms
    tau = ms * tau0
    out = {p: np.zeros((n, n)) for p in PAIRS}
    ia, ib = np.triu_indices(n)
    disc = (ms[ia] + ms[ib]) <= DISCRETE_MAX
    # exact sums over integer lags (all such pairs at once, padded to a common length)
    da, db = ia[disc], ib[disc]
    if da.size:
        ma, mb = ms[da][:, None], ms[db][:, None]
        k0, span, k, w = _integer_lags(ma, mb, big_m[da][:, None], big_m[db][:, None])
        r = {t: _r_lags(t, ma, mb, k, tau0) for t in TERMS4}
        for t, u in PAIRS:
            out[(t, u)][da, db] = np.sum(r[t] * r[u] * w, axis=1)
    # Gauss-Legendre between kinks for the rest; the white-PM (Q) pairs exactly at its taps
    ca, cb = ia[~disc], ib[~disc]
    if ca.size:
        ma, mb = ms[ca][:, None], ms[cb][:, None]
        taps, s, k_lo, k_hi, kinks = _kinks(ma, mb, big_m[ca][:, None], big_m[cb][:, None])
        bp = kinks
        bp = np.sort(np.clip(bp, k_lo, k_hi), axis=1)
        bp = np.concatenate([k_lo, bp, k_hi], axis=1)
        half = 0.5 * (bp[:, 1:] - bp[:, :-1])
        mid = 0.5 * (bp[:, 1:] + bp[:, :-1])
        k = mid[:, :, None] + half[:, :, None] * _GL_X[None, None, :]
        wq = (half[:, :, None] * _GL_W[None, None, :]) * _weight(
            big_m[ca][:, None, None], big_m[cb][:, None, None], k)
        mab, mbb = ma[:, :, None], mb[:, :, None]
        r = {t: _r_lags(t, mab, mbb, k, tau0) for t in ("N", "B", "K")}
        for t, u in PAIRS:
            if t == "Q" or u == "Q":
                continue
            out[(t, u)][ca, cb] = np.sum(r[t] * r[u] * wq, axis=(1, 2))
        # white PM's R_ab is zero except at the nine taps: its pairs are exact sums over them
        for u, v in _q_tap_sums(ma, mb, big_m[ca][:, None], big_m[cb][:, None], tau0).items():
            out[("Q", u)][ca, cb] = v
    norm = 2.0 / (4.0 * np.outer(tau ** 2 * big_m, tau ** 2 * big_m))
    for p in PAIRS:
        c = out[p]
        c = c + np.triu(c, 1).T
        out[p] = c * norm
    return out


def combine(cov_terms: dict, coeff_sq: dict) -> np.ndarray:
    """Covariance matrix of the AVAR estimates for coefficients^2 {Q, N, B, K} (SI), and
    {"G": sigma_GM^2} where ``cov_terms`` holds the Gauss-Markov pairs (``tc`` given to
    :func:`term_covariances` / :func:`gapped_term_covariances`)."""
    total = None
    pairs = PAIRS + [p for p in GPAIRS if p in cov_terms and coeff_sq.get("G", 0.0)]
    for t, u in pairs:
        f = (1.0 if t == u else 2.0) * coeff_sq.get(t, 0.0) * coeff_sq.get(u, 0.0)
        part = f * cov_terms[(t, u)]
        total = part if total is None else total + part
    return total


# --- gaps skipped (Stable32): the pooled estimator of independent gap-free stretches --------
#: pairs of factors whose lag range holds at most this many integer lags are summed exactly
#: (gapped records: the range is bounded by the longest stretch, so short stretches are exact)
GAPPED_DISCRETE_LAGS = 4096


def gapped_term_covariances(tau0: float, ms: np.ndarray, stretch_samples: np.ndarray,
                            tc: float | None = None) -> dict:
    """:func:`term_covariances` for the estimate that skips gaps: the terms of every gap-free
    stretch (L_s samples, P_s = L_s + 1 phase points, n_s(m) = max(0, P_s - 2m) terms) pooled,
    s2(m) = sum_s sum_i D_{s,m}[i]^2 / (2 tau^2 N(m)), N(m) = sum_s n_s(m). With the stretches
    independent (exact for Q, N, K, whose second differences over disjoint spans are; flicker's
    correlation across a gap is neglected, as in the EDF)::

        Cov(s2(a), s2(b)) = 2 sum_k R_ab(k)^2 W_ab(k) / (4 tau_a^2 tau_b^2 N(a) N(b)),
        W_ab(k) = sum_s w(n_s(a), n_s(b), k)

    R_ab is the same as for one record (it does not depend on the length), so the stretches
    enter through the summed pair-count W only: exactly sum_s n_s(a) n_s(b) Cov_s(a, b) / (N(a)
    N(b)) with Cov_s that of stretch s alone, at the cost of one record of the longest stretch's
    lag range. W is piecewise linear with 4 kinks per distinct length, evaluated exactly
    (np.interp on its values at the kinks). A pair is summed over integer lags where
    m_a + m_b <= DISCRETE_MAX or its lag range holds at most GAPPED_DISCRETE_LAGS lags, else
    integrated with Gauss-Legendre between the kinks of R and W. One stretch: identical to
    :func:`term_covariances` (it is called). ``tc``: as there (the Gauss-Markov pairs; a GM
    rate is correlated across a gap as e^(-gap / Tc), which is neglected like flicker's)."""
    st = np.asarray(stretch_samples, dtype=np.int64)
    st = st[st > 0]
    lengths, counts = np.unique(st, return_counts=True)
    if lengths.size == 1 and counts[0] == 1:
        return term_covariances(tau0, ms, int(lengths[0]) + 1, tc)
    if tc is not None:
        return {**gapped_term_covariances(tau0, ms, stretch_samples),
                **_gm_gapped_cached(float(tau0), np.asarray(ms, dtype=float).tobytes(),
                                    lengths.tobytes(), counts.tobytes(), float(tc))}
    # the axes of a sensor share this matrix (kept in the cache). No lock here: solvers import
    # no threading (the layers contract); axes fitted on threads at once may each compute it
    # (Astro Pi, 6 axes, --taus all: 2 computations, 0.67 s thread CPU instead of 0.30 s).
    return _gapped_cached(float(tau0), np.asarray(ms, dtype=float).tobytes(),
                          lengths.tobytes(), counts.tobytes())


@functools.lru_cache(maxsize=8)
def _gapped_cached(tau0: float, ms_key: bytes, len_key: bytes, cnt_key: bytes) -> dict:
    out = _gapped(tau0, np.frombuffer(ms_key, dtype=float),
                  np.frombuffer(len_key, dtype=np.int64), np.frombuffer(cnt_key, dtype=np.int64))
    for c in out.values():
        c.setflags(write=False)
    return out


def _w_knots(na: np.ndarray, nb: np.ndarray, cnt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """W(k) = sum_s cnt_s w(na_s, nb_s, k) (stretches with terms at both factors) as its
    kinks and its values there; zero outside."""
    use = (na > 0) & (nb > 0)
    na, nb, c = na[use], nb[use], cnt[use].astype(float)
    if na.size == 0:
        return np.zeros(2), np.zeros(2)
    d = nb - na
    # w = relu(k + na) - relu(k - min(0, d)) - relu(k - max(0, d)) + relu(k - nb)
    kn = np.concatenate([-na, np.minimum(0.0, d), np.maximum(0.0, d), nb])
    sl = np.concatenate([c, -c, -c, c])
    o = np.argsort(kn, kind="stable")
    kn, sl = kn[o], sl[o]
    slope = np.cumsum(sl)  # slope right of each kink
    val = np.zeros(kn.size)
    val[1:] = np.cumsum(slope[:-1] * np.diff(kn))
    return kn, val


def _stretch_terms(ms: np.ndarray, lengths: np.ndarray, counts: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Terms per stretch at each factor (rows: factors, columns: stretch lengths) and their
    total over the record (``counts`` stretches of each length)."""
    n_s = np.maximum(0.0, (lengths.astype(float) + 1.0)[None, :] - 2.0 * ms[:, None])
    return n_s, n_s @ counts.astype(float)


def _gapped_pairs(ms: np.ndarray, lengths: np.ndarray, counts: np.ndarray):
    """Each pair of factors a <= b with terms at both and a lag range to sum over: (a, b, the
    knots and values of W(k) (_w_knots), m_a, m_b, m_a + m_b, the taps' range (R's support,
    + flicker's tail) lo, hi, and the lag range k_lo..k_hi, 16 (m_a + m_b) past the taps within
    W's support)."""
    n_s, big_n = _stretch_terms(ms, lengths, counts)
    for a in range(ms.size):
        for b in range(a, ms.size):
            if big_n[a] <= 0 or big_n[b] <= 0:
                continue
            kn, val = _w_knots(n_s[a], n_s[b], counts)
            ma, mb = ms[a], ms[b]
            s = ma + mb
            lo, hi = -2.0 * mb, 2.0 * ma
            k_lo, k_hi = max(lo - 16.0 * s, kn[0]), min(hi + 16.0 * s, kn[-1])
            if k_hi > k_lo:
                yield a, b, kn, val, ma, mb, s, lo, hi, k_lo, k_hi


def _gapped(tau0: float, ms: np.ndarray, lengths: np.ndarray, counts: np.ndarray) -> dict:
    ms = np.asarray(ms, dtype=float)
    n = ms.size
    big_n = _stretch_terms(ms, lengths, counts)[1]
    tau = ms * tau0
    out = {p: np.zeros((n, n)) for p in PAIRS}
    for a, b, kn, val, ma, mb, s, lo, hi, k_lo, k_hi in _gapped_pairs(ms, lengths, counts):
        if s <= DISCRETE_MAX or k_hi - k_lo <= GAPPED_DISCRETE_LAGS:
            k = np.arange(math.ceil(k_lo), math.floor(k_hi) + 1, dtype=float)
            w = np.interp(k, kn, val)
            r = {t: _r_lags(t, ma, mb, k, tau0) for t in TERMS4}
            for t, u in PAIRS:
                out[(t, u)][a, b] = np.sum(r[t] * r[u] * w)
            continue
        taps = np.array([j * ma - l * mb for j in range(3) for l in range(3)])
        geo = np.array([1.0, 2.0, 4.0, 8.0, 16.0])
        bp = np.concatenate([[k_lo, k_hi], taps, lo - s * geo, hi + s * geo, kn])
        bp = np.unique(bp[(bp >= k_lo) & (bp <= k_hi)])
        half = 0.5 * np.diff(bp)
        mid = 0.5 * (bp[1:] + bp[:-1])
        k = (mid[:, None] + half[:, None] * _GL_X[None, :]).ravel()
        wq = (half[:, None] * _GL_W[None, :]).ravel() * np.interp(k, kn, val)
        r = {t: _r_lags(t, ma, mb, k, tau0) for t in ("N", "B", "K")}
        for t, u in PAIRS:
            if t == "Q" or u == "Q":
                continue
            out[(t, u)][a, b] = np.sum(r[t] * r[u] * wq)
        # white PM exactly at its taps (as in _term_covariances: each distinct tap once)
        kt = np.unique(taps)
        wt = np.where((kt >= kn[0]) & (kt <= kn[-1]), np.interp(kt, kn, val), 0.0)
        rq = _r_lags("Q", ma, mb, kt, tau0)
        for u in TERMS4:
            out[("Q", u)][a, b] = np.sum(rq * _r_lags(u, ma, mb, kt, tau0) * wt)
    return _symmetric_normed(out, tau, big_n)


# --- a first-order Gauss-Markov rate ------------------------------------------------------
#: the Gauss-Markov term's pairs with every term (f_tu = 2 except ("G", "G"))
GPAIRS = [(t, "G") for t in TERMS4 + ("G",)]
#: breakpoints either side of every tap at these multiples of h = Tc / tau0 (where h < s / 4):
#: the exponential part of the kernel varies on the scale h there, not s
_GM_NEAR = np.array([1.0, 4.0, 16.0])
#: the (G, G) tail past the lag range of the other terms, at these multiples of h
#: (beyond 64 h: e^-128)
_GM_TAIL = np.array([0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])
_PHI_SERIES = [(-1.0) ** (n + 1) / math.factorial(n) for n in range(3, 18)]


def _gm_phi(u: np.ndarray) -> np.ndarray:
    """phi(u) = 1 - u + u^2 / 2 - e^-u (u >= 0) without cancellation: its series
    u^3/6 - u^4/24 + ... (to u^17) below u = 0.5, else -expm1(-u) - u + u^2/2."""
    u = np.asarray(u, dtype=float)
    out = -np.expm1(-u)
    out -= u
    out += 0.5 * u * u
    small = u < 0.5
    if np.any(small):
        us = u[small]
        acc = np.full_like(us, _PHI_SERIES[-1])
        for a in reversed(_PHI_SERIES[:-1]):
            acc = acc * us + a
        out[small] = acc * us ** 3
    return out


def gm_term_covariances(tau0: float, ms: np.ndarray, n_phase: int, tc: float) -> dict:
    """The Gauss-Markov pairs alone: {(t, "G"): matrix} for t in Q, N, B, K, G, in the form of
    :func:`term_covariances` (which adds them to the IEEE 952 pairs when given ``tc``).

    The rate y(t) (rad/s, or m/s^2, ...) with autocovariance sigma_GM^2 e^(-|t| / Tc)
    integrates to a phase x (rad, m/s) whose generalized autocovariance is minus the even
    function whose second derivative is the rate's autocovariance::

        s(t) = -sigma_GM^2 Tc^2 (|t| / Tc + e^(-|t| / Tc))       [SI phase^2]

    (a C^2 function, its third derivative jumps at t = 0), up to a quadratic in t, which the
    second differences cancel. The kernel used is the cancellation-free member
    sigma_GM^2 Tc^2 phi(|t| / Tc), phi(u) = 1 - u + u^2 / 2 - e^-u = u^3 / 6 - u^4 / 24 + ...
    (a rate random walk, K^2 = 2 sigma_GM^2 / Tc, for |t| << Tc; a white FM, N^2 =
    2 sigma_GM^2 Tc, for |t| >> Tc). Its Allan variance, Var(D) / (2 tau^2) with Var(D) =
    6 s(0) - 8 s(tau) + 2 s(2 tau)::

        sigma^2(tau) = sigma_GM^2 (Tc / tau)^2 (2 tau / Tc - 3 + 4 e^(-tau/Tc) - e^(-2 tau/Tc))

    (rigctl.solvers.allan_gm.gm_avar). Per Tc (h = Tc / tau0 samples) the pairs are summed like
    the others: exactly over integer lags where m_a + m_b <= DISCRETE_MAX; otherwise
    integrated over the lags, on a mesh that does not depend on Tc (the kinks of R and w, and
    breakpoints graded by 4 toward every tap down to one sample, so that e^(-|k - tap| / h) is
    followed for any h >= 1) with 4-point Gauss-Legendre, R_G = 2 Tc R_N + R_E, R_E =
    -Tc^2 sum_taps c e^(-|t - tap| / Tc) (the kernel directly where h > 1e3 (m_a + m_b));
    R_G R_G is followed past the other terms' lag range (16 (m_a + m_b)) to 64 h by its
    exponential tail (R_G times flicker's R there is neglected: both are small). The gapped
    path does the same per pair with 8-point Gauss-Legendre and breakpoints at h, 4 h, 16 h
    either side of the taps where h < (m_a + m_b) / 4. The kernel is not a polynomial, so the
    quadrature is not exact: against the exact integer-lag sums (4e5 phase points, m from 5
    to 3000, h from 1 to 1e4 samples) the diagonal was within 1.3e-4 and the largest entries
    within 7.9e-3, both from the white-FM-like part's sum-vs-integral difference, which N's
    own kernel has too (2.6e-4 and 2e-2 there); against a brute force from the exact phase
    covariance see tests/test_allan_gmcov.py. (Q, G) is summed exactly at white PM's taps
    past DISCRETE_MAX, as Q's other pairs (:func:`_q_tap_sums`). The Gauss-Legendre sums run compiled
    where numba is there (allan_cov_kernels.gm_gl_sums, the same numbers as :func:`_gm_gl_numpy`).
    Cost: ~0.05 s per Tc for 40 taus of a 1.4 h, 100 Hz record (~0.1 s with numpy), 1.5 s for the first
    (the mesh, kept per (tau0, ms, n_phase)); the matrices are kept per Tc too (the fits try
    one Tc after another and come back to them)."""
    return _gm_cached(float(tau0), np.asarray(ms, dtype=float).tobytes(), int(n_phase),
                      float(tc))


#: Gauss-Markov matrices kept (one dict of 5 matrices per (tau0, taus, record length, Tc), 64 KB
#: at 40 taus): the candidate's lattice Tc (~80) stay in while the fit's profile grid (~70 Tc of
#: its own taus per axis) passes through; at 128 one axis' candidate + fit (~150) cycled the
#: lattice out before the next axis of the same sampling came back to it
GM_CACHE_SIZE = 256


@functools.lru_cache(maxsize=GM_CACHE_SIZE)
def _gm_cached(tau0: float, ms_key: bytes, n_phase: int, tc: float) -> dict:
    out = _gm_contiguous(tau0, np.frombuffer(ms_key, dtype=float), n_phase, tc)
    for c in out.values():
        c.setflags(write=False)
    return out


#: the gapped ones alike: at 64 the candidate's grid passes (its second pass with the model
#: error, the refinement) found their Tc cycled out: IEEE 952 noise with one gap
#: (test_allan_gm_gaps, nbk), 349 computations of 148 distinct (taus, Tc), 0.1-0.2 s each
@functools.lru_cache(maxsize=GM_CACHE_SIZE)
def _gm_gapped_cached(tau0: float, ms_key: bytes, len_key: bytes, cnt_key: bytes,
                      tc: float) -> dict:
    out = _gm_gapped(tau0, np.frombuffer(ms_key, dtype=float),
                     np.frombuffer(len_key, dtype=np.int64),
                     np.frombuffer(cnt_key, dtype=np.int64), tc)
    for c in out.values():
        c.setflags(write=False)
    return out


def _gm_tail(start: np.ndarray, end: np.ndarray, sign: float, amp: np.ndarray, h: float,
             kinks: np.ndarray, weight) -> np.ndarray:
    """Integral of amp^2 e^(-2 |k - start| / h) weight(k) from ``start`` towards ``end``
    (sign +1: right, -1: left); per pair (rows), the weight piecewise linear with ``kinks``.
    Past all taps R_G is amp e^(-|k - start| / h) exactly."""
    length = np.maximum((end - start) * sign, 0.0)[:, None]
    d = np.concatenate([np.zeros_like(length), np.broadcast_to(h * _GM_TAIL, (length.shape[0],
                        _GM_TAIL.size)), (kinks - start[:, None]) * sign, length], axis=1)
    d = np.sort(np.clip(d, 0.0, length), axis=1)
    half = 0.5 * np.diff(d, axis=1)
    mid = 0.5 * (d[:, 1:] + d[:, :-1])
    x = mid[:, :, None] + half[:, :, None] * _GL_X[None, None, :]
    k = start[:, None, None] + sign * x
    f = np.exp(-2.0 * x / h) * weight(k) * (half[:, :, None] * _GL_W[None, None, :])
    return amp ** 2 * np.sum(f, axis=(1, 2))


#: the GL pairs' fixed mesh: breakpoints at (m_a + m_b) 4^-j either side of every tap, j = 1..,
#: down to one sample, so that e^(-|k - tap| / h) is followed for any h >= 1 sample
_GM_GRADE = 4.0
#: Gauss-Legendre order on the graded mesh (its intervals are short next to the scale of
#: the exponentials; measured against the exact sums: see gm_term_covariances)
_GM_GL_X, _GM_GL_W = np.polynomial.legendre.leggauss(4)
#: past this h / (m_a + m_b) the split R_G = 2 Tc R_N + R_E loses digits: the kernel directly
_GM_SPLIT_MAX = 1e3


@functools.lru_cache(maxsize=8)
def _gm_nodes(tau0: float, ms_key: bytes, n_phase: int) -> dict:
    """What does not depend on Tc: the lags, weights and the other terms' R at them (the
    integer lags of the small pairs; the Gauss-Legendre nodes of a fixed graded mesh for the
    rest), and each node's interval with the taps left and right of it."""
    ms = np.frombuffer(ms_key, dtype=float)
    big_m = n_phase - 2.0 * ms
    ia, ib = np.triu_indices(ms.size)
    disc = (ms[ia] + ms[ib]) <= DISCRETE_MAX
    out: dict = {"ia": ia, "ib": ib}
    da, db = ia[disc], ib[disc]
    if da.size:
        ma, mb = ms[da][:, None], ms[db][:, None]
        k0, span, k, w = _integer_lags(ma, mb, big_m[da][:, None], big_m[db][:, None])
        # |j m_a - l m_b - k| of each tap (integers): R_G from a table of the kernel at the
        # integer lags (its values there, so R_G is the same number for number as _r_lags')
        # (integer factors, as the callers' round(tau / tau0); others: _r_lags itself)
        lags = [np.abs(j * ma - l * mb - k) for j in range(3) for l in range(3)]
        if all(np.array_equal(v, np.round(v)) for v in lags):
            lags = [v.astype(np.intp) for v in lags]
        else:
            lags = None
        out["disc"] = {"a": da, "b": db, "ma": ma, "mb": mb, "k": k, "w": w,
                       "r": {t: _r_lags(t, ma, mb, k, tau0) for t in TERMS4}, "lags": lags,
                       "lag_max": None if lags is None else max(int(v.max()) for v in lags),
                       "left": (k0 - 0.5)[:, 0], "right": (2 * ma + span + 0.5)[:, 0]}
    ca, cb = ia[~disc], ib[~disc]
    if ca.size:
        ma, mb = ms[ca][:, None], ms[cb][:, None]
        taps, s, k_lo, k_hi, kinks = _kinks(ma, mb, big_m[ca][:, None], big_m[cb][:, None])
        coef = np.array([_C[j] * _C[l] for j in range(3) for l in range(3)])
        levels = _GM_GRADE ** -np.arange(1, int(math.ceil(math.log(float(s.max()), _GM_GRADE))) + 1)
        off = s[:, :, None] * levels[None, None, :]
        bp = np.concatenate([kinks,
                             (taps[:, :, None] + off).reshape(taps.shape[0], -1),
                             (taps[:, :, None] - off).reshape(taps.shape[0], -1)], axis=1)
        bp = np.sort(np.clip(bp, k_lo, k_hi), axis=1)
        bp = np.concatenate([k_lo, bp, k_hi], axis=1)
        a_i, b_i = bp[:, :-1], bp[:, 1:]
        half = 0.5 * (b_i - a_i)
        k = 0.5 * (a_i + b_i)[:, :, None] + half[:, :, None] * _GM_GL_X[None, None, :]
        wq = (half[:, :, None] * _GM_GL_W[None, None, :]) * _weight(
            big_m[ca][:, None, None], big_m[cb][:, None, None], k)
        mab, mbb = ma[:, :, None], mb[:, :, None]
        left = taps[:, None, :] <= a_i[:, :, None]
        d_left = np.maximum(a_i[:, :, None] - taps[:, None, :], 0.0)
        d_right = np.maximum(taps[:, None, :] - b_i[:, :, None], 0.0)
        # no tap inside an interval (they are breakpoints): one of the two distances is 0, so
        # their sum is the other one exactly and one exponential per tap serves both sides
        assert not np.any(np.minimum(d_left, d_right) > 0)
        # kept per (tau0, taus, record length) and several at once (a gapped record's long
        # stretches, GM_LONG_LENGTHS): the node-sized arrays (pairs x intervals x 4, or x 9
        # taps) only where a call cannot make them as cheaply; the intervals' ends (a_i, b_i)
        # instead of the distances from them, and which taps lie left (bool) instead of two
        # float copies of the taps' coefficients (88 -> 51 MB for 40 taus of a 12 h x 2 kHz
        # record; the same numbers)
        out["gl"] = {"a": ca, "b": cb, "ma": ma[:, 0], "mb": mb[:, 0], "s": s[:, 0], "k": k,
                     "wq": wq, "r": {t: _r_lags(t, mab, mbb, k, tau0) for t in ("N", "B", "K")},
                     "a_i": a_i, "b_i": b_i, "left": left, "coef": coef,
                     "d_tap": d_left + d_right,
                     "k_lo": k_lo[:, 0], "k_hi": k_hi[:, 0]}
        # white PM's pairs with G exactly at the taps (each distinct tap once): R_Q there and
        # the pair counts do not depend on Tc
        gma, gmb = ma, mb
        eq = taps[:, :, None] == taps[:, None, :]
        out["gl"]["q_taps"] = taps
        out["gl"]["q_rq"] = _r_lags("Q", gma, gmb, taps, tau0)
        out["gl"]["q_wt"] = _weight(big_m[ca][:, None], big_m[cb][:, None], taps) * ~np.any(
            np.tril(eq, -1), axis=2)
    return out


def _gm_gl_numpy(g: dict, rows: np.ndarray, direct: np.ndarray, tau0: float, tc: float,
                 h: float) -> dict:
    """The Gauss-Legendre pairs ``rows`` of :func:`_gm_contiguous` with numpy: their lag sums
    {(t, "G"): values} for t = N, B, K, G (``direct``: those rows' R_G from the kernel
    directly). Row by row the numbers that allan_cov_kernels.gm_gl_sums computes."""
    def gr(name: str) -> np.ndarray:
        return g[name][rows]

    # R_G = 2 Tc R_N + R_E, R_E = -Tc^2 sum_taps c e^(-|k - tap| / h): on a mesh interval
    # [a_i, b_i] (no tap inside) the taps left of it give A_i e^(-(k - a_i) / h), those
    # right of it B_i e^(-(b_i - k) / h)
    # (each tap's c e^(-d / h) on the side it lies, +0.0 on the other: the products of
    # the coefficient-or-zero arrays this was written with, number for number)
    left = gr("left")
    ce = np.exp(-gr("d_tap") / h)
    ce *= g["coef"]
    a_l = np.sum(np.where(left, ce, 0.0), axis=2)[:, :, None]
    b_r = np.sum(np.where(left, 0.0, ce), axis=2)[:, :, None]
    del ce
    k = gr("k")
    x = k - gr("a_i")[:, :, None]  # from the interval's ends
    y = gr("b_i")[:, :, None] - k
    r = {t: g["r"][t][rows] for t in ("N", "B", "K")}
    rg = 2.0 * tc * r["N"] - tc * tc * (a_l * np.exp(-x / h) + b_r * np.exp(-y / h))
    if np.any(direct):
        rg[direct] = _r_lags("G", gr("ma")[direct][:, None, None],
                             gr("mb")[direct][:, None, None], k[direct], tau0, tc)
    r["G"] = rg
    wq = gr("wq")
    return {(t, u): np.sum(r[t] * r[u] * wq, axis=(1, 2)) for t, u in GPAIRS[1:]}


def _gm_contiguous(tau0: float, ms: np.ndarray, n_phase: int, tc: float) -> dict:
    ms = np.asarray(ms, dtype=float)
    n = ms.size
    big_m = n_phase - 2.0 * ms
    tau = ms * tau0
    h = tc / tau0
    nodes = _gm_nodes(float(tau0), ms.tobytes(), int(n_phase))
    out = {p: np.zeros((n, n)) for p in GPAIRS}

    def tails(a_idx, b_idx, k_left, k_right):
        """(G, G) past [k_left, k_right] to the ends of w (-M_a, M_b)."""
        ma, mb = ms[a_idx], ms[b_idx]
        na, nb = big_m[a_idx], big_m[b_idx]
        kinks = np.column_stack((-na, np.zeros_like(na), nb - na, nb))

        def weight(k):
            return _weight(na[:, None, None], nb[:, None, None], k)
        amp_r = _r_lags("G", ma, mb, k_right, tau0, tc)
        amp_l = _r_lags("G", ma, mb, k_left, tau0, tc)
        return (_gm_tail(k_right, nb, 1.0, amp_r, h, kinks, weight)
                + _gm_tail(k_left, -na, -1.0, amp_l, h, kinks, weight))

    d = nodes.get("disc")
    if d is not None:
        r = dict(d["r"])
        if d["lags"] is None:
            r["G"] = _r_lags("G", d["ma"], d["mb"], d["k"], tau0, tc)
        else:
            table = _kernel("G", np.arange(d["lag_max"] + 1, dtype=float) * tau0, tc)
            rg = np.zeros(d["k"].shape)
            for (j, l), lag in zip(((j, l) for j in range(3) for l in range(3)), d["lags"]):
                rg += _C[j] * _C[l] * table[lag]
            r["G"] = rg
        for t, u in GPAIRS:
            out[(t, u)][d["a"], d["b"]] = np.sum(r[t] * r[u] * d["w"], axis=1)
        # the integer lags past them: the midpoint rule's integral from half a lag out
        out[("G", "G")][d["a"], d["b"]] += tails(d["a"], d["b"], d["left"], d["right"])
    g = nodes.get("gl")
    if g is not None:
        # (see _gm_gl_numpy: R_G from R_N and the taps' exponentials, per mesh interval)
        direct = h > _GM_SPLIT_MAX * g["s"]
        if _kc().HAVE_NUMBA:  # compiled: the same numbers (allan_cov_kernels.gm_gl_sums)
            sums = _kc().gm_gl_sums(tc, h, g["d_tap"], g["left"], g["coef"], g["k"], g["a_i"],
                                    g["b_i"], g["r"]["N"], g["r"]["B"], g["r"]["K"], g["wq"],
                                    direct)
            for i, pair in enumerate(GPAIRS[1:]):
                out[pair][g["a"], g["b"]] = sums[:, i]
            rows = np.flatnonzero(direct)  # the kernel directly: numpy, below
        else:
            rows = np.arange(direct.size)
        if rows.size:
            for pair, v in _gm_gl_numpy(g, rows, direct[rows], tau0, tc, h).items():
                out[pair][g["a"][rows], g["b"][rows]] = v
        gma, gmb = g["ma"][:, None], g["mb"][:, None]
        out[("Q", "G")][g["a"], g["b"]] = np.sum(
            g["q_rq"] * _r_lags("G", gma, gmb, g["q_taps"], tau0, tc) * g["q_wt"], axis=1)
        out[("G", "G")][g["a"], g["b"]] += tails(g["a"], g["b"], g["k_lo"], g["k_hi"])
    norm = 2.0 / (4.0 * np.outer(tau ** 2 * big_m, tau ** 2 * big_m))
    for p in GPAIRS:
        c = out[p]
        c = c + np.triu(c, 1).T
        out[p] = c * norm
    return out


#: without the compiled pair loop (no numba, or factors that are not integers), stretches of
#: at least this many samples (at most GM_LONG_LENGTHS distinct lengths of them, the longest)
#: enter the gapped Gauss-Markov pairs through the contiguous kernel of their own length (one
#: vectorized call per length, its mesh cached), weighted n_s(a) n_s(b): the same sum the numpy
#: pair loop computes, 10-20x faster than it where lag ranges are long (two stretches of 2e5
#: and 3e5 samples, 40 factors: 0.7-1.1 s per Tc in the loop, 0.05-0.1 s so). With the
#: compiled loop every stretch goes through it: faster (one axis of a 4 h x 2 kHz record, 13
#: stretches, 76 Tc: 6.9 s instead of 16.2 s thread CPU) and closer to the exact integer-lag
#: sums on long stretches (its 8-point mesh with breakpoints at h, 4 h, 16 h from the taps
#: against the contiguous kernel's fixed 4-point mesh; one stretch of 2e6 samples at 2 kHz,
#: Tc 0.01-100 s: (G, G) within 2e-9 instead of up to 5.2e-6, (K, G) within 1.1e-9 instead of
#: 1.2e-6; (B, G) the other way, up to 1.3e-4 against 5e-6: see docs/allan.md).
GM_LONG_MIN = 20000
GM_LONG_LENGTHS = 4


def _kc():
    """:mod:`rigctl.solvers.allan_cov_kernels`, imported where a Gauss-Markov kernel is asked for
    (it imports numba, ~0.25 s of CPU, which a process without a Gauss-Markov term need not pay)."""
    from . import allan_cov_kernels

    return allan_cov_kernels


def _loop_compiled(ms: np.ndarray) -> bool:
    """Whether :func:`_gm_gapped_loop` runs compiled for these factors."""
    return bool(_kc().HAVE_NUMBA) and np.array_equal(ms, np.round(ms))


def _gm_gapped(tau0: float, ms: np.ndarray, lengths: np.ndarray, counts: np.ndarray,
               tc: float) -> dict:
    """The gapped Gauss-Markov pairs: sum_s n_s(a) n_s(b) Cov_s(a, b) / (N(a) N(b)) over the
    stretches (see gapped_term_covariances): all from the pair loop where it runs compiled,
    else the long ones (GM_LONG_MIN, GM_LONG_LENGTHS) from the contiguous kernel of their
    length and the others from the numpy pair loop."""
    ms = np.asarray(ms, dtype=float)
    n = ms.size
    n_s, big_n = _stretch_terms(ms, lengths, counts)
    long_ = np.zeros(lengths.size, dtype=bool)
    cand = np.flatnonzero((lengths >= GM_LONG_MIN) & (not _loop_compiled(ms)))
    long_[cand[np.argsort(lengths[cand])[::-1][:GM_LONG_LENGTHS]]] = True
    sums = {p: np.zeros((n, n)) for p in GPAIRS}
    for j in np.flatnonzero(long_):
        have = np.flatnonzero(n_s[:, j] > 0)
        if have.size == 0:
            continue
        cs = gm_term_covariances(tau0, ms[have], int(lengths[j]) + 1, tc)
        # Cov_s = norm_s * sums_s with norm_s = 2 / (4 tau_a^2 tau_b^2 n_s(a) n_s(b)): back to
        # the sums (times the stretches of this length), normalized below by N(a) N(b)
        w = counts[j] * np.outer(n_s[have, j], n_s[have, j])
        for p in GPAIRS:
            sums[p][np.ix_(have, have)] += cs[p] * w
    if np.any(~long_):
        rest = _gm_gapped_loop(tau0, ms, lengths[~long_], counts[~long_], tc)
        n_rest = _stretch_terms(ms, lengths[~long_], counts[~long_])[1]
        scale = np.outer(n_rest, n_rest)
        for p in GPAIRS:
            sums[p] += rest[p] * scale
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.outer(big_n, big_n)
    inv[~np.isfinite(inv)] = 0.0
    return {p: sums[p] * inv for p in GPAIRS}


def _gm_gapped_loop(tau0: float, ms: np.ndarray, lengths: np.ndarray, counts: np.ndarray,
                    tc: float) -> dict:
    """The gapped Gauss-Markov pairs of the stretches ``lengths`` (``counts`` of each) from
    their lag sums pair by pair (normalized by their own N(a) N(b)): compiled
    (:mod:`rigctl.solvers.allan_cov_kernels`) where numba is there and the factors are
    integers, else :func:`_gm_gapped_loop_numpy` (the same sums; ~1 s per Tc for 40 factors
    of two stretches of 1.3e4 and 1.6e4 samples, compiled 0.06-0.09 s)."""
    ms = np.asarray(ms, dtype=float)
    if not _loop_compiled(ms):
        return _gm_gapped_loop_numpy(tau0, ms, lengths, counts, tc)
    pr = _gm_gapped_pairs(float(tau0), ms.tobytes(), np.asarray(lengths, np.int64).tobytes(),
                          np.asarray(counts, np.int64).tobytes())
    # R_G at the integer lags, where the tails start and at the taps with numpy, as the
    # numpy loop has them (R_G there is a small difference of large terms)
    tab_g = _kernel("G", pr["t_int"], tc)
    ma, mb = pr["ma"][:, None], pr["mb"][:, None]
    r_g = (_r_lags("G", pr["ma"], pr["mb"], pr["right"], tau0, tc),
           _r_lags("G", pr["ma"], pr["mb"], pr["left"], tau0, tc),
           _r_lags("G", ma, mb, np.concatenate([j * ma - l * mb for j in range(3)
                                                 for l in range(3)], axis=1), tau0, tc))
    sums = _kc().gm_pair_sums(tau0, tc, pr["ma"], pr["mb"], pr["k_lo"], pr["k_hi"], pr["disc"],
                           pr["kn"], pr["val"], pr["kn_off"], (*pr["tables"], tab_g), r_g,
                           _GM_CONSTS)
    out = {p: np.zeros((ms.size, ms.size)) for p in GPAIRS}
    for i, p in enumerate(GPAIRS):
        out[p][pr["a"], pr["b"]] = sums[:, i]
    return _symmetric_normed(out, ms * tau0, pr["big_n"])


#: the constants the compiled pair loop reads, as the numpy loop has them
_GM_CONSTS = (_C, np.array(_PHI_SERIES), _GL_X, _GL_W, np.array([1.0, 2.0, 4.0, 8.0, 16.0]),
              _GM_NEAR, _GM_TAIL)


@functools.lru_cache(maxsize=8)
def _gm_gapped_pairs(tau0: float, ms_key: bytes, len_key: bytes, cnt_key: bytes) -> dict:
    """What the compiled pair loop needs that does not depend on Tc (_gapped_pairs as flat
    arrays: each pair's factors, lag range, whether it is summed over integer lags, W's knots
    and values one pair after another with their offsets) and the N, B, K kernels at the
    integer lags those pairs reach (t_int = lag tau0, s)."""
    ms = np.frombuffer(ms_key, dtype=float)
    lengths = np.frombuffer(len_key, dtype=np.int64)
    counts = np.frombuffer(cnt_key, dtype=np.int64)
    rows = list(_gapped_pairs(ms, lengths, counts))
    col = {name: np.array([r[i] for r in rows], dtype=dt) for name, i, dt in (
        ("a", 0, np.intp), ("b", 1, np.intp), ("ma", 4, float), ("mb", 5, float),
        ("s", 6, float), ("k_lo", 9, float), ("k_hi", 10, float))}
    col["disc"] = (col["s"] <= DISCRETE_MAX) | (col["k_hi"] - col["k_lo"] <= GAPPED_DISCRETE_LAGS)
    col["kn"] = np.concatenate([r[2] for r in rows]) if rows else np.zeros(0)
    col["val"] = np.concatenate([r[3] for r in rows]) if rows else np.zeros(0)
    col["kn_off"] = np.concatenate([[0], np.cumsum([r[2].size for r in rows])]).astype(np.int64)
    d = col["disc"]
    # where the (G, G) tails start: half a lag past the integer lags, or the lag range's ends
    col["right"] = np.where(d, np.floor(col["k_hi"]) + 0.5, col["k_hi"])
    col["left"] = np.where(d, np.ceil(col["k_lo"]) - 0.5, col["k_lo"])
    # the integer lags j m_a - l m_b - k of the exactly summed pairs: -2 m_b - k .. 2 m_a - k
    lag_max = int(max(np.max(2.0 * col["ma"][d] - np.ceil(col["k_lo"][d]), initial=0.0),
                      np.max(np.floor(col["k_hi"][d]) + 2.0 * col["mb"][d], initial=0.0)))
    col["t_int"] = np.arange(lag_max + 1, dtype=float) * tau0
    col["tables"] = tuple(_kernel(t, col["t_int"]) for t in ("N", "B", "K"))
    col["big_n"] = _stretch_terms(ms, lengths, counts)[1]
    return col


def _symmetric_normed(out: dict, tau: np.ndarray, big_n: np.ndarray) -> dict:
    """The upper triangles of lag sums made symmetric and normalized,
    2 / (4 tau_a^2 tau_b^2 N(a) N(b)) (0 where a factor has no terms)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = 2.0 / (4.0 * np.outer(tau ** 2 * big_n, tau ** 2 * big_n))
    norm[~np.isfinite(norm)] = 0.0
    for p in out:
        c = out[p]
        c = c + np.triu(c, 1).T
        out[p] = c * norm
    return out


def _gm_gapped_loop_numpy(tau0: float, ms: np.ndarray, lengths: np.ndarray,
                          counts: np.ndarray, tc: float) -> dict:
    ms = np.asarray(ms, dtype=float)
    n = ms.size
    big_n = _stretch_terms(ms, lengths, counts)[1]
    tau = ms * tau0
    h = tc / tau0
    out = {p: np.zeros((n, n)) for p in GPAIRS}
    for a, b, kn, val, ma, mb, s, lo, hi, k_lo, k_hi in _gapped_pairs(ms, lengths, counts):

        def weight(k, kn=kn, val=val):
            return np.interp(k, kn, val)
        if s <= DISCRETE_MAX or k_hi - k_lo <= GAPPED_DISCRETE_LAGS:
            k = np.arange(math.ceil(k_lo), math.floor(k_hi) + 1, dtype=float)
            w = np.interp(k, kn, val)
            r = {t: _r_lags(t, ma, mb, k, tau0, tc) for t in TERMS4 + ("G",)}
            for t, u in GPAIRS:
                out[(t, u)][a, b] = np.sum(r[t] * r[u] * w)
            left, right = k[0] - 0.5, k[-1] + 0.5
        else:
            taps = np.array([j * ma - l * mb for j in range(3) for l in range(3)])
            geo = np.array([1.0, 2.0, 4.0, 8.0, 16.0])
            parts = [[k_lo, k_hi], taps, lo - s * geo, hi + s * geo, kn]
            if h < s / 4.0:
                off = h * _GM_NEAR
                parts += [(taps[:, None] + off[None, :]).ravel(),
                          (taps[:, None] - off[None, :]).ravel()]
            bp = np.concatenate(parts)
            bp = np.unique(bp[(bp >= k_lo) & (bp <= k_hi)])
            half = 0.5 * np.diff(bp)
            mid = 0.5 * (bp[1:] + bp[:-1])
            k = (mid[:, None] + half[:, None] * _GL_X[None, :]).ravel()
            wq = (half[:, None] * _GL_W[None, :]).ravel() * np.interp(k, kn, val)
            r = {t: _r_lags(t, ma, mb, k, tau0, tc) for t in ("N", "B", "K", "G")}
            for t, u in GPAIRS:
                if t == "Q":
                    continue
                out[(t, u)][a, b] = np.sum(r[t] * r[u] * wq)
            kt = np.unique(taps)  # white PM exactly at its taps (each distinct tap once)
            wt = np.where((kt >= kn[0]) & (kt <= kn[-1]), np.interp(kt, kn, val), 0.0)
            out[("Q", "G")][a, b] = np.sum(_r_lags("Q", ma, mb, kt, tau0)
                                           * _r_lags("G", ma, mb, kt, tau0, tc) * wt)
            left, right = k_lo, k_hi
        kinks = kn[None, :]
        for start, end, sign in ((right, kn[-1], 1.0), (left, kn[0], -1.0)):
            amp = _r_lags("G", ma, mb, np.array([start]), tau0, tc)
            out[("G", "G")][a, b] += float(_gm_tail(np.array([start]), np.array([end]),
                                                    sign, amp, h, kinks, weight)[0])
    return _symmetric_normed(out, tau, big_n)
