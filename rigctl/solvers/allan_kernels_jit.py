"""The numba-compiled kernels of :mod:`rigctl.solvers.allan_kernels` (see its docstring for
what they compute and how).

Kept apart so that importing :mod:`rigctl.solvers.allan_kernels` does not import numba (~0.25 s
of CPU per process): a process that never runs a compiled kernel (``rigctl calibrate`` on a
recording, ``rigctl batch``, ``rigctl history``) does not pay for it. allan_kernels imports this
module at the first use of a kernel or of ``HAVE_NUMBA``; importing it without numba raises
ImportError (numba is the ``fast`` extra).
"""
from __future__ import annotations

import gc

import numba
import numpy as np
from numba import prange
from numba.core import event as _event

from rigctl.jit import njit  # (absolute: tests/test_allan_kernels_cache.py imports a copy of this module)


def _probe() -> None:  # pragma: no cover - never compiled: decorated to find a cache place
    pass


def _cache_place() -> bool:
    """Whether numba can keep this module's compiled kernels on disk (``cache=True``: the
    first run on a machine compiles them, ~14 s of CPU, later runs load them). numba keeps
    them beside the source (``__pycache__``) where that is writable, else in the user's cache
    directory (~/.cache/numba); where neither is (a read-only install run by a user without
    a writable home: a service account, a read-only container), decorating a function with
    ``cache=True`` raises RuntimeError ("no locator available") and the import failed. Then
    this user's own directory under the system's temporary directory is used
    (``rigctl-numba-<uid>``, made 0700 and used only if it is this user's and no one else
    can write it: numba's index files are pickles), and failing that, no cache (compiled
    in every process)."""
    try:
        njit(cache=True)(_probe)  # finds numba's cache place, or raises; compiles nothing
        return True
    except RuntimeError:
        pass
    import os
    import stat
    import tempfile

    try:
        path = os.path.join(tempfile.gettempdir(), f"rigctl-numba-{os.getuid()}")
        os.makedirs(path, mode=0o700, exist_ok=True)
        st = os.lstat(path)
        if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o022:
            return False
        numba.config.CACHE_DIR = path  # (numba's NUMBA_CACHE_DIR, set for this process)
        njit(cache=True)(_probe)
        return True
    except (OSError, RuntimeError, AttributeError):
        return False


_CACHE = _cache_place()


class _CollectAfterCompile(_event.Listener):
    """numba's compiler makes cyclic garbage (its IR, typing and LLVM objects: ~413,000
    objects for the kernels of one ``rigctl allan``), which waits for the cyclic collector;
    while it is paused (``rigctl allan``: :func:`rigctl.analysis.allan.collector_paused_for_command`)
    it waited for the exit, beside the stream. So at the end of each outermost compilation
    (a kernel not in numba's on-disk cache: the first run after an install or a
    change of the source; none when the kernels are loaded from the cache) the youngest
    generation is collected while the collector is paused (where it runs, it collects as
    usual). On the 12 h x 2 kHz x 6-axis file with an empty cache: peak RSS 766 -> 700 MB,
    0.33 s of CPU for 8 collections beside ~14 s of compilation (docs/allan.md)."""

    def __init__(self) -> None:
        # numba triggers its compile events under its global compiler lock (one compilation at a
        # time in the process, nested ones on the same thread), so one counter is exact
        self._depth = 0

    def on_start(self, event: _event.Event) -> None:
        self._depth += 1

    def on_end(self, event: _event.Event) -> None:
        # (never below 0: a compilation already under way when this module was imported -- on
        # another thread -- ends without the start this listener saw, and would otherwise leave
        # the count at -1 for good, so that no later compilation was collected)
        self._depth = max(self._depth - 1, 0)
        if self._depth == 0 and not gc.isenabled():
            gc.collect(0)  # (with the collector paused every object made since is young)


_event.register("numba:compile", _CollectAfterCompile())


@njit(fastmath=True, cache=_CACHE, nogil=True)
def _d2_block(p, q, r, n):  # pragma: no cover - compiled
    s = 0.0
    for j in range(n):
        d = p[j] - 2.0 * q[j] + r[j]
        s += d * d
    return s


@njit(fastmath=True, cache=_CACHE, nogil=True)
def _d3_block(p, q, r, t, n):  # pragma: no cover - compiled
    s = 0.0
    for j in range(n):
        d = p[j] - 3.0 * q[j] + 3.0 * r[j] - t[j]
        s += d * d
    return s


@njit(cache=_CACHE, nogil=True)
def _part_sums(x, ms, order, lo, hi, block, tot, comp):  # pragma: no cover - compiled
    """Sums of the blocks [lo, hi) of i for every factor (ms ascending); order 2 = Allan
    second differences, 3 = Hadamard third differences. Neumaier-compensated."""
    n = x.size
    k_n = ms.size
    for a in range(lo, hi, block):
        for k in range(k_n):
            m = ms[k]
            end = min(a + block, n - order * m)
            if end <= a:
                break
            ln = end - a
            if order == 2:
                v = _d2_block(x[a + 2 * m: end + 2 * m], x[a + m: end + m], x[a:end], ln)
            else:
                v = _d3_block(x[a + 3 * m: end + 3 * m], x[a + 2 * m: end + 2 * m],
                              x[a + m: end + m], x[a:end], ln)
            t = tot[k] + v
            if abs(tot[k]) >= abs(v):
                comp[k] += (tot[k] - t) + v
            else:
                comp[k] += (v - t) + tot[k]
            tot[k] = t


@njit(fastmath=True, cache=_CACHE, nogil=True)
def _d2_block2(r, p0, q0, p1, q1, n):  # pragma: no cover - compiled
    s0 = 0.0
    s1 = 0.0
    for j in range(n):
        v = r[j]
        d0 = p0[j] - 2.0 * q0[j] + v
        d1 = p1[j] - 2.0 * q1[j] + v
        s0 += d0 * d0
        s1 += d1 * d1
    return s0, s1


@njit(fastmath=True, cache=_CACHE, nogil=True)
def _d2_block4(r, p0, q0, p1, q1, p2, q2, p3, q3, n):  # pragma: no cover - compiled
    """Four lags' sums over the same terms i: x[i] is loaded once for the four, and the
    four reductions are independent chains (0.126 ns per term against 0.176 one lag at a
    time, measured on this machine's cores)."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    for j in range(n):
        v = r[j]
        d0 = p0[j] - 2.0 * q0[j] + v
        d1 = p1[j] - 2.0 * q1[j] + v
        d2 = p2[j] - 2.0 * q2[j] + v
        d3 = p3[j] - 2.0 * q3[j] + v
        s0 += d0 * d0
        s1 += d1 * d1
        s2 += d2 * d2
        s3 += d3 * d3
    return s0, s1, s2, s3


@njit(cache=_CACHE, nogil=True)
def _add_comp(out, k, v):  # pragma: no cover - compiled
    t = out[k, 0] + v
    if abs(out[k, 0]) >= abs(v):
        out[k, 1] += (out[k, 0] - t) + v
    else:
        out[k, 1] += (v - t) + out[k, 0]
    out[k, 0] = t


@njit(cache=_CACHE, nogil=True)
def _range_sums(x, ks, los, his, block, out):  # pragma: no cover - compiled
    """out[k] += sum_{i=los[k]}^{his[k]-1} (x[i+2ks[k]] - 2x[i+ks[k]] + x[i])^2, blocks of
    i outside (x[a:a+block] read once for all lags), compensated; out is (K, 2). Within a
    block the lags go four (then two, then one) at a time over the terms they share, each
    lag's own first and last few terms alone."""
    a0 = los.min()
    a1 = his.max()
    nk = ks.size
    for a in range(a0, a1, block):
        g = 0
        while g < nk:
            w = 4 if nk - g >= 4 else (2 if nk - g >= 2 else 1)
            clo = a
            chi = a + block
            for k in range(g, g + w):
                clo = max(clo, los[k])
                chi = min(chi, his[k])
            if w > 1 and chi > clo:
                c = chi - clo
                if w == 4:
                    m0 = ks[g]
                    m1 = ks[g + 1]
                    m2 = ks[g + 2]
                    m3 = ks[g + 3]
                    v0, v1, v2, v3 = _d2_block4(
                        x[clo:chi], x[clo + 2 * m0: chi + 2 * m0], x[clo + m0: chi + m0],
                        x[clo + 2 * m1: chi + 2 * m1], x[clo + m1: chi + m1],
                        x[clo + 2 * m2: chi + 2 * m2], x[clo + m2: chi + m2],
                        x[clo + 2 * m3: chi + 2 * m3], x[clo + m3: chi + m3], c)
                    _add_comp(out, g, v0)
                    _add_comp(out, g + 1, v1)
                    _add_comp(out, g + 2, v2)
                    _add_comp(out, g + 3, v3)
                else:
                    m0 = ks[g]
                    m1 = ks[g + 1]
                    v0, v1 = _d2_block2(
                        x[clo:chi], x[clo + 2 * m0: chi + 2 * m0], x[clo + m0: chi + m0],
                        x[clo + 2 * m1: chi + 2 * m1], x[clo + m1: chi + m1], c)
                    _add_comp(out, g, v0)
                    _add_comp(out, g + 1, v1)
            else:
                clo = a
                chi = a  # nothing shared: every lag alone below
            for k in range(g, g + w):  # each lag's terms outside the shared range
                m = ks[k]
                lo = max(a, los[k])
                hi = min(a + block, his[k])
                if hi <= lo:
                    continue
                for e0, e1 in ((lo, min(hi, clo)), (max(lo, chi), hi)):
                    if e1 > e0:
                        _add_comp(out, k, _d2_block(x[e0 + 2 * m: e1 + 2 * m],
                                                    x[e0 + m: e1 + m], x[e0:e1], e1 - e0))
            g += w


@njit(cache=_CACHE, nogil=True)
def _casc_pass(lv, arr, tl, strides, ks, nks, bufs, tlen, pend, b0, nstart, sums, counts,
               block):  # pragma: no cover - compiled
    """Level lv of a cascade, its points arr (arr[0] is its point b0[lv], arr[tl:] not
    summed yet): sum its lags over every term not summed before, and append the new
    points the next level takes (every step-th by index) to that level's pending ones."""
    size = arr.size
    nk = nks[lv]
    los = np.empty(nk, np.int64)
    his = np.empty(nk, np.int64)
    for k in range(nk):
        los[k] = nstart[lv, k] - b0[lv]
        his[k] = size - 2 * ks[lv, k]
    if nk:
        _range_sums(arr, ks[lv, :nk], los, his, block, sums[lv])
    for k in range(nk):
        if his[k] > los[k]:
            counts[lv, k] += his[k] - los[k]
            nstart[lv, k] = b0[lv] + size - 2 * ks[lv, k]
    if lv + 1 < strides.size:
        step = strides[lv + 1] // strides[lv]
        i0 = tl + (-(b0[lv] + tl)) % step
        if i0 < size:
            src = arr[i0:size:step]
            dst = tlen[lv + 1] + pend[lv + 1]
            bufs[lv + 1, dst: dst + src.size] = src
            pend[lv + 1] += src.size


@njit(cache=_CACHE, nogil=True)
def _casc_level(lv, strides, ks, nks, bufs, tlen, pend, b0, nstart, sums, counts, keep,
                block):  # pragma: no cover - compiled
    """A deeper level (lv >= 1, points in bufs[lv]): its pass, then only the last keep[lv]
    points are kept for the next terms."""
    size = tlen[lv] + pend[lv]
    _casc_pass(lv, bufs[lv, :size], tlen[lv], strides, ks, nks, bufs, tlen, pend, b0,
               nstart, sums, counts, block)
    cut = size - keep[lv]
    if cut > 0:
        for j in range(size - cut):
            bufs[lv, j] = bufs[lv, cut + j]
        b0[lv] += cut
    else:
        cut = 0
    tlen[lv] = size - cut
    pend[lv] = 0


@njit(cache=_CACHE, nogil=True)
def _casc_chunk(x0, k0, n, strides, ks, nks, bufs, tlen, pend, b0, nstart, sums, counts,
                keep, sub, batch, block, n_before, tap, tap_step):  # pragma: no cover
    """Level 0's new points are x0[k0:k0 + n], its kept points the tlen[0] before them:
    summed where they are, in pieces of ``sub`` points, each piece's every second (or
    step-th) point passed straight on while it is in the core's caches; a deeper level
    runs once it has ``batch`` points pending. Afterwards level 0's last keep[0] points
    are moved in front of x0[k0] for the next chunk. With ``tap_step`` > 0 the new points
    whose index (x0[k0] is point ``n_before``) is a multiple of tap_step are also copied
    into ``tap`` (as many as fit), piece by piece while they are in cache; returns how
    many."""
    nl = strides.size
    base = k0 - tlen[0]
    tpos = 0
    for a in range(0, n, sub):
        e = min(n, a + sub)
        _casc_pass(0, x0[base: k0 + e], k0 + a - base, strides, ks, nks, bufs, tlen,
                   pend, b0, nstart, sums, counts, block)
        if tap_step > 0:  # after the pass: the piece is in cache
            i = k0 + a + (-(n_before + a)) % tap_step
            while i < k0 + e and tpos < tap.size:
                tap[tpos] = x0[i]
                tpos += 1
                i += tap_step
        lv = 1
        while lv < nl and pend[lv] >= batch:
            _casc_level(lv, strides, ks, nks, bufs, tlen, pend, b0, nstart, sums, counts,
                        keep, block)
            lv += 1
    total = k0 + n - base
    kept = min(keep[0], total)
    for j in range(kept):  # forward: the source lies after the destination
        x0[k0 - kept + j] = x0[k0 + n - kept + j]
    b0[0] += total - kept
    tlen[0] = kept
    return tpos


@njit(cache=_CACHE, nogil=True)
def _casc_flush(strides, ks, nks, bufs, tlen, pend, b0, nstart, sums, counts, keep,
                block):  # pragma: no cover - compiled
    for lv in range(1, strides.size):
        if pend[lv] > 0:
            _casc_level(lv, strides, ks, nks, bufs, tlen, pend, b0, nstart, sums, counts,
                        keep, block)


@njit(cache=_CACHE, nogil=True)
def _jumps(c, lanes, starts, rows, out_i, out_d):  # pragma: no cover - compiled
    """Indices i >= 1 (and the step) where c[i] - c[i-1] > 1 (int64): a counter's gaps.
    The values are pieces of the 2-D ``c``: piece p is c[lanes[p], starts[p]: starts[p] +
    rows[p]], and i counts the pieces' values one after the other (one piece for one
    array)."""
    k = 0
    i = 0  # values before this piece
    for p in range(starts.size):
        m = rows[p]
        if m == 0:
            continue
        x = c[lanes[p], starts[p]: starts[p] + m]
        if i > 0:  # the step from the last value of the pieces before
            d = x[0] - c[lanes[p - 1], starts[p - 1] + rows[p - 1] - 1]
            if d > 1:
                out_i[k] = i
                out_d[k] = d
                k += 1
        for j in range(1, m):  # (a loop the compiler vectorizes on one contiguous lane)
            d = x[j] - x[j - 1]
            if d > 1:
                out_i[k] = i + j
                out_d[k] = d
                k += 1
        i += m
    return k


@njit(cache=_CACHE, nogil=True)
def _phase_chunk(y, c, tau0, x0, x):  # pragma: no cover - compiled
    acc = 0.0
    for i in range(y.size):
        acc += y[i] - c
        x[i] = acc * tau0 + x0


@njit(cache=_CACHE, nogil=True)
def _gather(tail, x, start, s, out):  # pragma: no cover - compiled
    nt = tail.size
    for i in range(nt):
        out[i] = tail[i]
    j = nt
    for i in range(start, x.size, s):
        out[j] = x[i]
        j += 1


@njit(cache=_CACHE, nogil=True)
def _far_from_range(y, w, thr, out):  # pragma: no cover - compiled
    """Indices i (into out; returns their count) where y[i] - min > thr or max - y[i] > thr
    over the window y[i - w//2 .. i + (w-1)//2], indices clipped to the ends: running
    min and max by van Herk / Gil-Werman, one block of w outputs at a time (the window of
    output b0 + k is the suffix k.. of block b0 and the prefix ..k-1 of the next one in
    the padded series), O(w) memory."""
    n = y.size
    lo = w // 2
    smin = np.empty(w)
    smax = np.empty(w)
    pmin = np.empty(w)
    pmax = np.empty(w)
    c = 0
    for b0 in range(0, n, w):
        a = y[min(max(b0 + w - 1 - lo, 0), n - 1)]
        z = a
        for k in range(w - 1, -1, -1):  # suffix extremes of padded [b0, b0 + w)
            v = y[min(max(b0 + k - lo, 0), n - 1)]
            a = v if v < a else a
            z = v if v > z else z
            smin[k] = a
            smax[k] = z
        a = y[min(max(b0 + w - lo, 0), n - 1)]
        z = a
        for k in range(w):  # prefix extremes of padded [b0 + w, b0 + 2w)
            v = y[min(max(b0 + w + k - lo, 0), n - 1)]
            a = v if v < a else a
            z = v if v > z else z
            pmin[k] = a
            pmax[k] = z
        for k in range(min(w, n - b0)):
            mn = smin[k]
            mx = smax[k]
            if k > 0:
                q = pmin[k - 1]
                mn = q if q < mn else mn
                q = pmax[k - 1]
                mx = q if q > mx else mx
            yi = y[b0 + k]
            if (yi - mn > thr) | (mx - yi > thr):
                out[c] = b0 + k
                c += 1
    return c


@njit(cache=_CACHE, nogil=True)
def _block_extremes(y, bs, bmin, bmax):  # pragma: no cover - compiled
    n = y.size
    for b in range((n + bs - 1) // bs):
        a = y[b * bs]
        z = a
        for i in range(b * bs + 1, min(n, b * bs + bs)):
            v = y[i]
            a = v if v < a else a
            z = v if v > z else z
        bmin[b] = a
        bmax[b] = z


@njit(cache=_CACHE, nogil=True)
def _quiet_block(bmin, bmax, b, nb, thr):  # pragma: no cover - compiled
    """Blocks b - 1, b, b + 1 span at most thr: no sample of block b can be flagged."""
    mn = bmin[b]
    mx = bmax[b]
    if b > 0:
        mn = min(mn, bmin[b - 1])
        mx = max(mx, bmax[b - 1])
    if b + 1 < nb:
        mn = min(mn, bmin[b + 1])
        mx = max(mx, bmax[b + 1])
    return mx - mn <= thr


@njit(cache=_CACHE, nogil=True)
def _any_loud_block(bmin, bmax, thr):  # pragma: no cover - compiled
    nb = bmin.size
    for b in range(nb):
        if not _quiet_block(bmin, bmax, b, nb, thr):
            return True
    return False


@njit(cache=_CACHE, nogil=True)
def _far_from_range_pre(y, w, thr, bs, bmin, bmax, out):  # pragma: no cover - compiled
    """The second step of :func:`_far_from_range_blocks`, given the blocks' extremes."""
    n = y.size
    nb = (n + bs - 1) // bs
    lo = w // 2
    c = 0
    for b in range(nb):
        if _quiet_block(bmin, bmax, b, nb, thr):
            continue
        for i in range(b * bs, min(n, b * bs + bs)):
            a = y[min(max(i - lo, 0), n - 1)]
            z = a
            for k in range(i - lo + 1, i - lo + w):
                v = y[min(max(k, 0), n - 1)]
                a = v if v < a else a
                z = v if v > z else z
            yi = y[i]
            if (yi - a > thr) | (z - yi > thr):
                out[c] = i
                c += 1
    return c


@njit(cache=_CACHE, nogil=True)
def _far_from_range_blocks(y, w, thr, bs, out):  # pragma: no cover - compiled
    """As :func:`_far_from_range` (same indices), with a prefilter: the extremes of blocks
    of ``bs`` >= w samples (one SIMD-friendly pass); the window of every sample of block b
    lies inside blocks b-1, b, b+1 (clipped ends: the padding repeats y[0] or y[n-1],
    which are inside them), so when those three blocks span at most ``thr`` no sample of
    block b can be flagged. Only the other blocks are examined, sample by sample, with the
    window's own extremes."""
    nb = (y.size + bs - 1) // bs
    bmin = np.empty(nb)
    bmax = np.empty(nb)
    _block_extremes(y, bs, bmin, bmax)
    return _far_from_range_pre(y, w, thr, bs, bmin, bmax, out)


@njit(cache=_CACHE, nogil=True)  # no fastmath: the same roundings as _phase_chunk
def _phase_cols3(base, lanes, starts, rows, offs, tau0, x0, o0, o1, o2, bs, bmin,
                 bmax):  # pragma: no cover - compiled
    """For each column c of the rows (n x 3): o_c[i] = x0[c] + tau0 * sum_{j<=i} (row j's
    value c - offs[c]), the same operations in the same order as _phase_chunk
    (bit-identical), and the extremes of each block of ``bs`` rows per column (bmin/bmax,
    3 x blocks), in one pass over the rows: the three running sums are independent
    chains, so the pass costs about what one column's running sum alone costs (its add
    latency). x0 is set to the last phase point of each column. The rows are pieces of
    the 2-D ``base``: piece p holds rows[p] rows, row k of it at base[lanes[p],
    starts[p] + 3 k .. + 2]; row i counts the pieces' rows one after the other (one
    piece for one block of rows); the sums and the blocks run on across the pieces."""
    n = 0
    for p in range(starts.size):
        n += rows[p]
    c0 = offs[0]
    c1 = offs[1]
    c2 = offs[2]
    b0 = x0[0]
    b1 = x0[1]
    b2 = x0[2]
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    mn0 = mx0 = mn1 = mx1 = mn2 = mx2 = 0.0
    g = 0  # rows done (the output index of the next row)
    for p in range(starts.size):
        s = starts[p]
        m = rows[p]
        ln = lanes[p]
        i = 0
        while i < m:
            q = s + 3 * i
            if g % bs == 0:  # a block starts
                mn0 = base[ln, q]
                mx0 = mn0
                mn1 = base[ln, q + 1]
                mx1 = mn1
                mn2 = base[ln, q + 2]
                mx2 = mn2
            e = min(m, i + bs - g % bs)  # the block's end, or the piece's
            for k in range(e - i):
                v0 = base[ln, q]
                v1 = base[ln, q + 1]
                v2 = base[ln, q + 2]
                q += 3
                a0 += v0 - c0
                a1 += v1 - c1
                a2 += v2 - c2
                o0[g + k] = a0 * tau0 + b0
                o1[g + k] = a1 * tau0 + b1
                o2[g + k] = a2 * tau0 + b2
                mn0 = v0 if v0 < mn0 else mn0
                mx0 = v0 if v0 > mx0 else mx0
                mn1 = v1 if v1 < mn1 else mn1
                mx1 = v1 if v1 > mx1 else mx1
                mn2 = v2 if v2 < mn2 else mn2
                mx2 = v2 if v2 > mx2 else mx2
            g += e - i
            i = e
            if g % bs == 0 or g == n:  # the block is complete
                b = (g - 1) // bs
                bmin[0, b] = mn0
                bmax[0, b] = mx0
                bmin[1, b] = mn1
                bmax[1, b] = mx1
                bmin[2, b] = mn2
                bmax[2, b] = mx2
    if n:
        x0[0] = o0[n - 1]
        x0[1] = o1[n - 1]
        x0[2] = o2[n - 1]


@njit(cache=_CACHE, nogil=True)
def _running_median(y, w, out):  # pragma: no cover - compiled
    """out[i] = the median of y[i - w//2 .. i + w//2] (odd w; indices clipped to the
    ends: scipy.ndimage's mode "nearest"), from a sorted copy of the window: each step
    takes the value leaving out and puts the one entering in its place (their places
    are counts of smaller values, branch-free over the window; the values between
    move by one). Returns False at the first non-finite value (the sorted order would
    not hold; the caller falls back)."""
    n = y.size
    h = w // 2
    buf = np.empty(w)
    for j in range(w):
        v = y[min(max(j - h, 0), n - 1)]
        if not np.isfinite(v):
            return False
        buf[j] = v
    buf.sort()
    out[0] = buf[h]
    for i in range(1, n):
        old = y[min(max(i - 1 - h, 0), n - 1)]
        new = y[min(i + h, n - 1)]
        if not np.isfinite(new):
            return False
        if new != old:
            p = 0  # the first place holding old
            q = 0  # values below new (old among them when new > old)
            for j in range(w):
                p += buf[j] < old
                q += buf[j] < new
            if new > old:
                for j in range(p, q - 1):
                    buf[j] = buf[j + 1]
                buf[q - 1] = new
            else:
                for j in range(p, q, -1):
                    buf[j] = buf[j - 1]
                buf[q] = new
        out[i] = buf[h]
    return True


@njit(cache=_CACHE, nogil=True)
def _lag1_alpha(x, m, dmax):  # pragma: no cover - compiled
    """Riley & Greenhall's lag-1 noise identification on x[::m]: the same steps as
    allan_noise_id.noise_id_lag1 (mean removed, r1, delta = r1 / (1 + r1), differenced
    until delta < 0.25 or d = dmax), with two accumulators per sum (compensation not
    needed: the sums are ratios compared with 0.25). Each differencing order takes one
    pass: its differences are formed on the fly from the decimated series (the same
    subtractions as differencing it in place, order by order), and the pass that sums
    the products of order d also sums the differences of order d + 1 for their mean
    (each sum in index order, as a pass of its own would). The decimated series is
    copied (with its mean's sums) only for m > 1; for m = 1 x itself is read."""
    n0 = (x.size + m - 1) // m
    s0 = 0.0
    s1 = 0.0
    if m == 1:
        z = x
        i = 0
        while i + 1 < n0:
            s0 += z[i]
            s1 += z[i + 1]
            i += 2
        if i < n0:
            s0 += z[i]
    else:
        z = np.empty(n0)
        i = 0
        while i + 1 < n0:
            v0 = x[i * m]
            v1 = x[(i + 1) * m]
            z[i] = v0
            z[i + 1] = v1
            s0 += v0
            s1 += v1
            i += 2
        if i < n0:
            v0 = x[i * m]
            z[i] = v0
            s0 += v0
    cur = np.zeros(dmax + 1)  # the latest value of each order below d
    d = 0
    while True:
        n = n0 - d
        mean = (s0 + s1) / n
        # z_d[i] from z[i .. i + d]: push z[i + d] through the orders
        for t in range(d):
            v = z[t]
            for k in range(1, t + 1):
                nv = v - cur[k - 1]
                cur[k - 1] = v
                v = nv
            cur[t] = v
        den0 = 0.0
        den1 = 0.0
        num0 = 0.0
        num1 = 0.0
        s0 = 0.0  # the next order's sums (its differences, index order)
        s1 = 0.0
        if d == 0:  # (orders 0 and 1 written out, two terms a step: the same sums)
            last = z[0]
            prev = last - mean
            den0 += prev * prev
            i = 1
            while i + 1 < n:
                v = z[i]
                s0 += v - last
                w = v - mean
                den1 += w * w
                num1 += prev * w
                u = z[i + 1]
                s1 += u - v
                q = u - mean
                den0 += q * q
                num0 += w * q
                last = u
                prev = q
                i += 2
            if i < n:
                v = z[i]
                s0 += v - last
                w = v - mean
                den1 += w * w
                num1 += prev * w
        elif d == 1:
            b = z[1]
            last = b - z[0]
            prev = last - mean
            den0 += prev * prev
            i = 1
            while i + 1 < n:
                c = z[i + 1]
                v = c - b
                s0 += v - last
                w = v - mean
                den1 += w * w
                num1 += prev * w
                b = z[i + 2]
                u = b - c
                s1 += u - v
                q = u - mean
                den0 += q * q
                num0 += w * q
                last = u
                prev = q
                i += 2
            if i < n:
                c = z[i + 1]
                v = c - b
                s0 += v - last
                w = v - mean
                den1 += w * w
                num1 += prev * w
        else:
            v = z[d]
            for k in range(1, d + 1):
                nv = v - cur[k - 1]
                cur[k - 1] = v
                v = nv
            last = v
            prev = v - mean
            den0 += prev * prev
            for i in range(1, n):
                v = z[i + d]
                for k in range(1, d + 1):
                    nv = v - cur[k - 1]
                    cur[k - 1] = v
                    v = nv
                if i & 1:  # the next order's term i - 1 (even)
                    s0 += v - last
                else:
                    s1 += v - last
                last = v
                w = v - mean
                if i & 1:
                    den1 += w * w
                    num1 += prev * w
                else:
                    den0 += w * w
                    num0 += prev * w
                prev = w
        den = den0 + den1
        r1 = (num0 + num1) / den if den > 0 else 0.0
        delta = r1 / (1.0 + r1)
        if delta < 0.25 or d >= dmax or n < 3:
            return 2 - int(np.rint(2.0 * delta)) - 2 * d
        d += 1


@njit(parallel=True, cache=_CACHE)
def _par_sums(x, ms, order, bounds, block, tot, comp):  # pragma: no cover - compiled
    for p in prange(bounds.size - 1):
        _part_sums(x, ms, order, bounds[p], bounds[p + 1], block, tot[p], comp[p])


@njit(cache=_CACHE, nogil=True)  # no fastmath: (y - c) must be rounded before the sum
def _phase(y, c, tau0, x):  # pragma: no cover - compiled
    acc = 0.0
    x[0] = 0.0
    for i in range(y.size):
        acc += y[i] - c
        x[i + 1] = acc * tau0
