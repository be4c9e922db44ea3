"""Compiled kernels for the Gauss-Markov covariance pairs (numba, optional): the gapped pair
loop (:func:`gm_pair_sums`) and the contiguous kernel's Gauss-Legendre sums (:func:`gm_gl_sums`).

:func:`gm_pair_sums` is the pair loop of :func:`rigctl.solvers.allan_cov._gm_gapped_loop_numpy`
compiled: the same lags, mesh and quadrature, the kernels in the same order of operations
(libm's log and exp where numpy has its own vectorized code: see _phi, _cube).
For every pair of factors (m_a, m_b) and one correlation time Tc (h = Tc / tau0 samples) it
returns the lag sums::

    S_t(a, b) = sum_k R_t(k) R_G(k) W(k)     t = Q, N, B, K, G

(for t = G plus R_G^2 W followed past the lag range by its exponential tail,
e^(-2 |k - k_end| / h), to the end of W), over the integer lags where the pair is summed
exactly, else by 8-point Gauss-Legendre between the kinks of R and W (and at h, 4 h, 16 h
either side of the nine taps where h < (m_a + m_b) / 4); Q exactly at its taps there. At
integer lags R_t is read from tables of the kernels at the integer lags that the caller
makes with numpy (the same numbers as evaluating the kernels there); elsewhere the kernels
are evaluated here. The lag sums are Neumaier-compensated: they differ from numpy's
pairwise sums by numpy's own rounding only.

Without numba (``HAVE_NUMBA`` False) the caller keeps the numpy loop.
"""
from __future__ import annotations

import math

import numpy as np

from .allan_kernels import HAVE_NUMBA

#: the sums per pair, in this order (allan_cov.GPAIRS: (Q, G), (N, G), (B, G), (K, G), (G, G))
N_SUMS = 5

if HAVE_NUMBA:
    from ..jit import njit

    from .allan_kernels import _CACHE

    _TWO_PI = 2.0 * math.pi

    @njit(cache=_CACHE, nogil=True)
    def _phi(u, series):  # pragma: no cover - compiled
        """allan_cov._gm_phi at one u >= 0: the series below u = 0.5 (Horner, the same
        coefficients), else -expm1(-u) - u + u^2 / 2 in the same steps, -expm1(-u) as
        1 - e^-u (within 1 ulp for u >= 0.5, where 1 - e^-u >= 0.39; libm's exp is twice as
        fast as its expm1, and numpy's expm1 is not libm's either) and as 1 past u = 40
        (where both round to 1)."""
        if u < 0.5:
            acc = series[series.size - 1]
            for i in range(series.size - 2, -1, -1):
                acc = acc * u + series[i]
            return acc * _cube(u)
        out = 1.0 if u > 40.0 else 1.0 - math.exp(-u)
        out -= u
        out += 0.5 * u * u
        return out

    @njit(cache=_CACHE, nogil=True)
    def _cube(a):  # pragma: no cover - compiled
        """a^3 to within ~0.5 ulp (as pow does, numpy's a ** 3; a * a * a rounds twice): the
        rounding errors of a * a and of (a * a) * a by Dekker's exact products added back."""
        p = a * a
        f = 134217729.0 * a  # 2^27 + 1: a = ah + al, halves of 26 bits
        ah = f - (f - a)
        al = a - ah
        e = ((ah * ah - p) + 2.0 * ah * al) + al * al  # a * a - p, exactly
        q = p * a
        f = 134217729.0 * p
        ph = f - (f - p)
        pl = p - ph
        e2 = ((ph * ah - q) + ph * al + pl * ah) + pl * al  # p * a - q, exactly
        return q + (e2 + e * a)

    @njit(cache=_CACHE, nogil=True)
    def _interp(x, xp, fp):  # pragma: no cover - compiled
        """np.interp(x, xp, fp) at one x (numpy's steps: fp[0] left of xp, fp[-1] right of
        it and at xp[-1], fp[j] at a knot, else the slope of [xp[j], xp[j+1]])."""
        n = xp.size
        if x > xp[n - 1] or x == xp[n - 1]:
            return fp[n - 1]
        if x < xp[0]:
            return fp[0]
        lo = 0
        hi = n - 1  # xp[lo] <= x < xp[hi]
        while hi - lo > 1:
            mid = (lo + hi) >> 1
            if xp[mid] <= x:
                lo = mid
            else:
                hi = mid
        if xp[lo] == x:
            return fp[lo]
        slope = (fp[lo + 1] - fp[lo]) / (xp[lo + 1] - xp[lo])
        return slope * (x - xp[lo]) + fp[lo]

    @njit(cache=_CACHE, nogil=True)
    def _interp_walk(x, xp, fp, j):  # pragma: no cover - compiled
        """_interp for x that move a little from one call to the next (the lags of a pair in
        order): the interval found by walking from the last one, ``j`` (0 <= j <= n - 2).
        Returns (value, j)."""
        n = xp.size
        if x > xp[n - 1] or x == xp[n - 1]:
            return fp[n - 1], j
        if x < xp[0]:
            return fp[0], j
        while xp[j + 1] <= x:  # to xp[j] <= x < xp[j + 1], as numpy's search finds it
            j += 1
        while xp[j] > x:
            j -= 1
        if xp[j] == x:
            return fp[j], j
        slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
        return slope * (x - xp[j]) + fp[j], j

    @njit(cache=_CACHE, nogil=True)
    def _kern_g(t, tc, series):  # pragma: no cover - compiled
        return tc * tc * _phi(abs(t) / tc, series)

    @njit(cache=_CACHE, nogil=True)
    def _add(s, c, i, v):  # pragma: no cover - compiled
        """Neumaier: s[i] + c[i] is the running sum."""
        t = s[i] + v
        if abs(s[i]) >= abs(v):
            c[i] += (s[i] - t) + v
        else:
            c[i] += (v - t) + s[i]
        s[i] = t

    @njit(cache=_CACHE, nogil=True)
    def _tail(start, end, sign, amp, h, kn, val, tail, glx, glw):  # pragma: no cover
        """allan_cov._gm_tail for one pair: amp^2 times the integral of e^(-2 x / h) W(k),
        k = start + sign x, x from 0 to |end - start|, on the breakpoints 0, h tail, W's
        kinks and the end (clipped, sorted; 8-point Gauss-Legendre)."""
        length = max((end - start) * sign, 0.0)
        nd = 2 + tail.size + kn.size
        d = np.empty(nd)
        d[0] = 0.0
        for i in range(tail.size):
            d[1 + i] = h * tail[i]
        for i in range(kn.size):
            d[1 + tail.size + i] = (kn[i] - start) * sign
        d[nd - 1] = length
        for i in range(nd):
            d[i] = min(max(d[i], 0.0), length)
        d.sort()
        s = np.zeros(1)
        c = np.zeros(1)
        jw = 0 if sign > 0 else kn.size - 2
        for i in range(nd - 1):
            if d[i] > 400.0 * h:  # e^(-2 x / h) underflows to 0 from here on: adds nothing
                break
            half = 0.5 * (d[i + 1] - d[i])
            if half == 0.0:  # (kinks clipped to an end) adds 0
                continue
            mid = 0.5 * (d[i + 1] + d[i])
            for g in range(glx.size):
                x = mid + half * glx[g]
                w, jw = _interp_walk(start + sign * x, kn, val, jw)
                _add(s, c, 0, math.exp(-2.0 * x / h) * w * (half * glw[g]))
        return amp * amp * (s[0] + c[0])

    @njit(cache=_CACHE, nogil=True)
    def _pair_sums(tau0, tc, ma_all, mb_all, klo_all, khi_all, disc_all, kn_all, val_all,
                   kn_off, tab_n, tab_b, tab_k, tab_g, amp_r, amp_l, rg_taps, c3, series, glx,
                   glw, geo, near, tail, out):  # pragma: no cover - compiled
        h = tc / tau0
        s = np.zeros(N_SUMS)
        c = np.zeros(N_SUMS)
        taps = np.empty(9)
        nb_max = 2 + 9 + 2 * geo.size + 2 * 9 * near.size + (kn_off[1:] - kn_off[:-1]).max()
        bp = np.empty(nb_max)
        cand = np.empty(2 + 9 + 2 * geo.size)
        for p in range(ma_all.size):
            ma, mb = ma_all[p], mb_all[p]
            k_lo, k_hi = klo_all[p], khi_all[p]
            kn = kn_all[kn_off[p]:kn_off[p + 1]]
            val = val_all[kn_off[p]:kn_off[p + 1]]
            s[:] = 0.0
            c[:] = 0.0
            for j in range(3):
                for l in range(3):
                    taps[3 * j + l] = j * ma - l * mb
            if disc_all[p]:
                k0 = math.ceil(k_lo)
                k1 = math.floor(k_hi)
                jw = 0
                for ki in range(k0, k1 + 1):
                    k = float(ki)
                    w, jw = _interp_walk(k, kn, val, jw)
                    rq = 0.0
                    rn = 0.0
                    rb = 0.0
                    rk = 0.0
                    rg = 0.0
                    for j in range(3):
                        for l in range(3):
                            cc = c3[j] * c3[l]
                            lag = j * ma - l * mb - k
                            i = int(abs(lag))
                            rq += cc * (1.0 if abs(lag) < 0.5 else 0.0)
                            rn += cc * tab_n[i]
                            rb += cc * tab_b[i]
                            rk += cc * tab_k[i]
                            rg += cc * tab_g[i]
                    _add(s, c, 0, rq * rg * w)
                    _add(s, c, 1, rn * rg * w)
                    _add(s, c, 2, rb * rg * w)
                    _add(s, c, 3, rk * rg * w)
                    _add(s, c, 4, rg * rg * w)
                left = k0 - 0.5
                right = k1 + 0.5
            else:
                sm = ma + mb
                lo, hi = -2.0 * mb, 2.0 * ma
                nb = 0
                cand[0] = k_lo
                cand[1] = k_hi
                for i in range(9):
                    cand[2 + i] = taps[i]
                for i in range(geo.size):
                    cand[11 + i] = lo - sm * geo[i]
                    cand[11 + geo.size + i] = hi + sm * geo[i]
                for i in range(11 + 2 * geo.size):
                    v = cand[i]
                    if v >= k_lo and v <= k_hi:
                        bp[nb] = v
                        nb += 1
                for i in range(kn.size):
                    v = kn[i]
                    if v >= k_lo and v <= k_hi:
                        bp[nb] = v
                        nb += 1
                if h < sm / 4.0:
                    for sg in (1.0, -1.0):
                        for i in range(9):
                            for q in range(near.size):
                                v = taps[i] + sg * (h * near[q])
                                if v >= k_lo and v <= k_hi:
                                    bp[nb] = v
                                    nb += 1
                u = np.sort(bp[:nb])
                m = 1
                for i in range(1, nb):
                    if u[i] != u[m - 1]:
                        u[m] = u[i]
                        m += 1
                jw = 0
                for i in range(m - 1):
                    half = 0.5 * (u[i + 1] - u[i])
                    mid = 0.5 * (u[i + 1] + u[i])
                    for g in range(glx.size):
                        k = mid + half * glx[g]
                        w, jw = _interp_walk(k, kn, val, jw)
                        wq = (half * glw[g]) * w
                        rn = 0.0
                        rb = 0.0
                        rk = 0.0
                        rg = 0.0
                        for j in range(3):
                            for l in range(3):
                                cc = c3[j] * c3[l]
                                t = (j * ma - l * mb - k) * tau0
                                a = abs(t)
                                rn += cc * (-0.5 * a)
                                rb += cc * (t * t * math.log(a) / _TWO_PI if a > 0 else 0.0)
                                rk += cc * (_cube(a) / 12.0)
                                rg += cc * _kern_g(t, tc, series)
                        _add(s, c, 1, rn * rg * wq)
                        _add(s, c, 2, rb * rg * wq)
                        _add(s, c, 3, rk * rg * wq)
                        _add(s, c, 4, rg * rg * wq)
                # white PM exactly at its taps, each distinct tap once (R_G there: rg_taps)
                order = np.argsort(taps)
                for i in range(9):
                    k = taps[order[i]]
                    if i > 0 and k == taps[order[i - 1]]:
                        continue
                    wt = _interp(k, kn, val) if (k >= kn[0] and k <= kn[kn.size - 1]) else 0.0
                    rq = 0.0
                    for j in range(3):
                        for l in range(3):
                            rq += c3[j] * c3[l] * (1.0 if abs(j * ma - l * mb - k) < 0.5
                                                   else 0.0)
                    _add(s, c, 0, rq * rg_taps[p, order[i]] * wt)
                left = k_lo
                right = k_hi
            for i in range(N_SUMS):
                out[p, i] = s[i] + c[i]
            out[p, 4] += _tail(right, kn[kn.size - 1], 1.0, amp_r[p], h, kn, val, tail, glx, glw)
            out[p, 4] += _tail(left, kn[0], -1.0, amp_l[p], h, kn, val, tail, glx, glw)


    @njit(cache=_CACHE, nogil=True)
    def _pairwise_block(buf, start, n):  # pragma: no cover - compiled
        """numpy's pairwise sum (npy_pairwise_sum) of buf[start:start + n], n <= 128: one
        running sum below 8 values, else eight accumulators added as a tree, then the rest."""
        if n < 8:
            res = 0.0
            for i in range(n):
                res += buf[start + i]
            return res
        r0 = buf[start]
        r1 = buf[start + 1]
        r2 = buf[start + 2]
        r3 = buf[start + 3]
        r4 = buf[start + 4]
        r5 = buf[start + 5]
        r6 = buf[start + 6]
        r7 = buf[start + 7]
        i = 8
        while i < n - (n % 8):
            r0 += buf[start + i]
            r1 += buf[start + i + 1]
            r2 += buf[start + i + 2]
            r3 += buf[start + i + 3]
            r4 += buf[start + i + 4]
            r5 += buf[start + i + 5]
            r6 += buf[start + i + 6]
            r7 += buf[start + i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += buf[start + i]
            i += 1
        return res

    @njit(cache=_CACHE, nogil=True)
    def _pairwise(buf, n):  # pragma: no cover - compiled
        """numpy's pairwise sum of buf[:n] (npy_pairwise_sum, the order np.sum adds a
        contiguous run in): blocks of at most 128 values (_pairwise_block), halves split at a
        multiple of 8, added pairwise up the tree. Without recursion (numba does not cache a
        recursive function): the blocks are the tree's leaves, found left to right, their
        sums combined on a stack as the recursion would add them."""
        # stack of (start, n, value, state): state 0 = to expand, 1 = left done
        st_start = np.empty(64, np.int64)
        st_n = np.empty(64, np.int64)
        st_val = np.empty(64)
        st_state = np.zeros(64, np.int64)
        top = 0
        st_start[0] = 0
        st_n[0] = n
        st_state[0] = 0
        result = 0.0
        have = False  # a finished subtree's value waiting in ``result``
        while top >= 0:
            if have:
                if top < 0:
                    break
                if st_state[top] == 0:
                    # the left half finished: keep it, expand the right half
                    st_val[top] = result
                    st_state[top] = 1
                    n2 = st_n[top] // 2
                    n2 -= n2 % 8
                    top += 1
                    st_start[top] = st_start[top - 1] + n2
                    st_n[top] = st_n[top - 1] - n2
                    st_state[top] = 0
                    have = False
                else:
                    result = st_val[top] + result
                    top -= 1
                continue
            m = st_n[top]
            if m <= 128:
                result = _pairwise_block(buf, st_start[top], m)
                top -= 1
                have = True
                continue
            # expand: the left half first (the node waits in state 0 for it)
            n2 = m // 2
            n2 -= n2 % 8
            top += 1
            st_start[top] = st_start[top - 1]
            st_n[top] = n2
            st_state[top] = 0
        return result

    @njit(cache=_CACHE, nogil=True)
    def _gl_sums(tc, h, d_tap, left, coef, k, a_i, b_i, r_n, r_b, r_k, wq, skip,
                 out):  # pragma: no cover - compiled
        n_p, n_i, n_q = k.shape
        n_t = coef.size
        c1 = 2.0 * tc
        c2 = tc * tc
        tv = np.empty(n_t)
        ce_t = np.empty(n_t)
        bufs = np.empty((4, n_i * n_q))
        for p in range(n_p):
            if skip[p]:
                continue
            for i in range(n_i):
                # the taps' c e^(-d / h), left of the interval and right of it, each side
                # summed as np.sum(np.where(left, ce, 0.0), axis=2) adds them. Past 746 h
                # e^(-d / h) is 0.0 (libm's exp underflows below -745.14): not computed, and
                # c times it is 0.0 c, the same signed zero
                for j in range(n_t):
                    u = -d_tap[p, i, j] / h
                    ce = math.exp(u) if u > -746.0 else 0.0
                    ce *= coef[j]
                    ce_t[j] = ce
                    tv[j] = ce if left[p, i, j] else 0.0
                a_l = 0.0 + _pairwise_block(tv, 0, n_t)
                for j in range(n_t):
                    tv[j] = 0.0 if left[p, i, j] else ce_t[j]
                b_r = 0.0 + _pairwise_block(tv, 0, n_t)
                for q in range(n_q):
                    kk = k[p, i, q]
                    x = kk - a_i[p, i]
                    y = b_i[p, i] - kk
                    # (a side whose sum is a zero: a_l e^(-x / h) is that zero, e^(-x / h) in
                    # [0, 1], not computed)
                    ea = a_l * math.exp(-x / h) if a_l != 0.0 else a_l
                    eb = b_r * math.exp(-y / h) if b_r != 0.0 else b_r
                    rg = c1 * r_n[p, i, q] - c2 * (ea + eb)
                    w = wq[p, i, q]
                    m = i * n_q + q
                    bufs[0, m] = r_n[p, i, q] * rg * w
                    bufs[1, m] = r_b[p, i, q] * rg * w
                    bufs[2, m] = r_k[p, i, q] * rg * w
                    bufs[3, m] = rg * rg * w
            for t in range(4):
                out[p, t] = 0.0 + _pairwise(bufs[t], n_i * n_q)


def gm_gl_sums(tc: float, h: float, d_tap: np.ndarray, left: np.ndarray, coef: np.ndarray,
               k: np.ndarray, a_i: np.ndarray, b_i: np.ndarray, r_n: np.ndarray,
               r_b: np.ndarray, r_k: np.ndarray, wq: np.ndarray, skip: np.ndarray
               ) -> np.ndarray:
    """The contiguous Gauss-Markov kernel's Gauss-Legendre lag sums
    (:func:`rigctl.solvers.allan_cov._gm_contiguous`, its mesh from ``_gm_nodes``): per pair
    (rows; those where ``skip`` left at 0) sum over the nodes of R_t R_G W for t = N, B, K, G,
    R_G = 2 Tc R_N - Tc^2 (A e^(-(k - a_i) / h) + B e^(-(b_i - k) / h)) with A, B the taps'
    c e^(-d / h) left and right of each interval. The same operations in the same order as
    that function's numpy expressions, its sums in numpy's pairwise order (_pairwise), with
    libm's exp, which is numpy's own where numpy has no vectorized exp of its own (no
    AVX-512): then the same numbers bit for bit; without numba the caller keeps numpy.
    Returns (pairs x 4): (N, G), (B, G), (K, G), (G, G)."""
    out = np.zeros((k.shape[0], 4))
    if k.shape[0]:
        _gl_sums(float(tc), float(h), d_tap, left, coef, k, a_i, b_i, r_n, r_b, r_k, wq,
                 skip, out)
    return out


def gm_pair_sums(tau0: float, tc: float, ma: np.ndarray, mb: np.ndarray, k_lo: np.ndarray,
                 k_hi: np.ndarray, disc: np.ndarray, kn: np.ndarray, val: np.ndarray,
                 kn_off: np.ndarray, tables: tuple, r_g: tuple, consts: tuple) -> np.ndarray:
    """The lag sums (pairs x N_SUMS) of pairs (ma, mb) (factors, samples) over [k_lo, k_hi]
    (integer lags where ``disc``, the kernels read from ``tables`` = (N, B, K, G) at the
    integer lags), W's knots and values kn[kn_off[p]:kn_off[p + 1]], val[...] per pair;
    ``r_g``: R_G where the tails start (right and left end of the lag sum, per pair) and at
    the nine taps j m_a - l m_b (pairs x 9, j major); ``consts``: (c, phi series, GL nodes,
    GL weights, kink multiples, near multiples of h, tail multiples of h) as allan_cov has
    them. tau0, tc in s."""
    out = np.zeros((ma.size, N_SUMS))
    if ma.size:
        _pair_sums(float(tau0), float(tc), ma, mb, k_lo, k_hi, disc, kn, val, kn_off,
                   *tables, *r_g, *consts, out)
    return out
