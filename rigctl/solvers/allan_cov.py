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


def _kernel(term: str, t: np.ndarray) -> np.ndarray:
    """Generalized autocovariance of the phase for unit coefficient, t in s."""
    a = np.abs(t)
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


def _r_lags(term: str, ma: np.ndarray, mb: np.ndarray, k: np.ndarray, tau0: float
            ) -> np.ndarray:
    """R_ab(k) for unit coefficient; ma, mb, k broadcast together (sample units)."""
    out = np.zeros(np.broadcast(ma, mb, k).shape)
    for j in range(3):
        for l in range(3):
            if term == "Q":
                lag = j * ma - l * mb - k
                out += _C[j] * _C[l] * (np.abs(lag) < 0.5)
            else:
                out += _C[j] * _C[l] * _kernel(term, (j * ma - l * mb - k) * tau0)
    return out


def _weight(ma_n: np.ndarray, mb_n: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Number of (i, i') with i' - i = k, 0 <= i < M_a, 0 <= i' < M_b (real k: its length)."""
    return np.maximum(0.0, np.minimum(ma_n, mb_n - k) - np.maximum(0.0, -k))


def term_covariances(tau0: float, ms: np.ndarray, n_phase: int) -> dict:
    """{(t, u): matrix} with Cov(s2(a), s2(b)) = sum_{t<=u} f_tu p_t p_u C_tu[a, b],
    p = coefficient^2, f_tu = 1 if t == u else 2 (use :func:`combine`). A function of
    (tau0, ms, n_phase) only: the six axes of a recording share it, so the last few are kept
    (the matrices are read-only)."""
    return _cached(float(tau0), np.asarray(ms, dtype=float).tobytes(), int(n_phase))


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
        span = 16 * (ma + mb)
        k0 = -2 * mb - span
        length = int(np.max(2 * ma + span - k0)) + 1
        k = k0 + np.arange(length)[None, :]
        w = _weight(big_m[da][:, None], big_m[db][:, None], k)
        w = np.where(k <= 2 * ma + span, w, 0.0)
        r = {t: _r_lags(t, ma, mb, k, tau0) for t in TERMS4}
        for t, u in PAIRS:
            out[(t, u)][da, db] = np.sum(r[t] * r[u] * w, axis=1)
    # Gauss-Legendre between kinks for the rest (Q negligible there)
    ca, cb = ia[~disc], ib[~disc]
    if ca.size:
        ma, mb = ms[ca][:, None], ms[cb][:, None]
        taps = np.concatenate([j * ma - l * mb for j in range(3) for l in range(3)], axis=1)
        s = ma + mb
        lo, hi = taps.min(1, keepdims=True), taps.max(1, keepdims=True)
        geo = np.array([1.0, 2.0, 4.0, 8.0, 16.0])[None, :]
        wk = np.concatenate([-big_m[ca][:, None], np.zeros_like(ma),
                             (big_m[cb] - big_m[ca])[:, None], big_m[cb][:, None]], axis=1)
        k_lo = np.maximum(lo - 16 * s, -big_m[ca][:, None])
        k_hi = np.minimum(hi + 16 * s, big_m[cb][:, None])
        bp = np.concatenate([taps, lo - s * geo, hi + s * geo, wk], axis=1)
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
    norm = 2.0 / (4.0 * np.outer(tau ** 2 * big_m, tau ** 2 * big_m))
    for p in PAIRS:
        c = out[p]
        c = c + np.triu(c, 1).T
        out[p] = c * norm
    return out


def combine(cov_terms: dict, coeff_sq: dict) -> np.ndarray:
    """Covariance matrix of the AVAR estimates for coefficients^2 {Q, N, B, K} (SI)."""
    total = None
    for t, u in PAIRS:
        f = (1.0 if t == u else 2.0) * coeff_sq.get(t, 0.0) * coeff_sq.get(u, 0.0)
        part = f * cov_terms[(t, u)]
        total = part if total is None else total + part
    return total


# --- gaps skipped (Stable32): the pooled estimator of independent gap-free stretches --------
#: pairs of factors whose lag range holds at most this many integer lags are summed exactly
#: (gapped records: the range is bounded by the longest stretch, so short stretches are exact)
GAPPED_DISCRETE_LAGS = 4096


def gapped_term_covariances(tau0: float, ms: np.ndarray, stretch_samples: np.ndarray) -> dict:
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
    :func:`term_covariances` (it is called)."""
    st = np.asarray(stretch_samples, dtype=np.int64)
    st = st[st > 0]
    lengths, counts = np.unique(st, return_counts=True)
    if lengths.size == 1 and counts[0] == 1:
        return term_covariances(tau0, ms, int(lengths[0]) + 1)
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


def _gapped(tau0: float, ms: np.ndarray, lengths: np.ndarray, counts: np.ndarray) -> dict:
    ms = np.asarray(ms, dtype=float)
    n = ms.size
    phase = lengths.astype(float) + 1.0
    n_s = np.maximum(0.0, phase[None, :] - 2.0 * ms[:, None])  # terms per stretch, per factor
    big_n = n_s @ counts.astype(float)
    tau = ms * tau0
    out = {p: np.zeros((n, n)) for p in PAIRS}
    for a in range(n):
        for b in range(a, n):
            if big_n[a] <= 0 or big_n[b] <= 0:
                continue
            kn, val = _w_knots(n_s[a], n_s[b], counts)
            ma, mb = ms[a], ms[b]
            s = ma + mb
            lo, hi = -2.0 * mb, 2.0 * ma  # the taps' range: R's support (+ flicker's tail)
            k_lo, k_hi = max(lo - 16.0 * s, kn[0]), min(hi + 16.0 * s, kn[-1])
            if k_hi <= k_lo:
                continue
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
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = 2.0 / (4.0 * np.outer(tau ** 2 * big_n, tau ** 2 * big_n))
    norm[~np.isfinite(norm)] = 0.0
    for p in PAIRS:
        c = out[p]
        c = c + np.triu(c, 1).T
        out[p] = c * norm
    return out
