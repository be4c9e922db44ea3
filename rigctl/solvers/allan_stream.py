"""Streaming overlapping-Allan sums for long records: a polyphase-Gram pyramid (fast mode).

For increments w (rate samples; the phase is their running sum) the overlapping Allan term at
lag k is a filter of w::

    D_k[i] = x[i+2k] - 2 x[i+k] + x[i] = sum_{j=0}^{2k-1} h_k[j] w[i+j],
    h_k = (-1, ..., -1, +1, ..., +1)   (k times each)

Group the increments in rows of 16, U[r, a] = w[16 r + a], and let V_r = (U[r], U[r+1], U[r+2])
(48 values). For k <= 16 every D_k[16 r + a] (a = 0..15) is a row of M_k V_r with
M_k[a, a + j] = h_k[j], so for all k at once::

    sum_i D_k[i]^2 = sum_r |M_k V_r|^2 = sum_ab (M_k^T M_k)[a, b] G[a, b],
    G = sum_r V_r V_r^T   (48 x 48, block Toeplitz up to edge rows)

G is accumulated with three 16-wide matrix products per block (B_d = U[0:n]^T U[d:d+n],
d = 0, 1, 2), i.e. one read of memory per block serves every lag k <= 16 -- this is still the
fully overlapping sum (stride 1), only computed in a different order. Each block is centred
by its own mean first (h_k sums to zero, so D_k is unchanged) to keep rounding small; blocks
are 4096 rows (512 kB, in L2), and the loop runs under :func:`blas_single_thread`.

Long taus use a pyramid of pair sums, w_{j+1}[i] = w_j[2i] + w_j[2i+1] (the increments of the
phase decimated by 2^(j+1)); level j serves m = k 2^j with 8 <= k < 16 (stride 2^j, i.e. m/16
< stride <= m/8) with the same Gram. Terms not anchored by a full block (the last few dozen)
are summed directly at the end. Memory: a few kilobytes per level.
"""
from __future__ import annotations

import contextlib
import ctypes
import glob
import os
from typing import Iterator

import numpy as np

from . import allan_kernels as K

ROW = 16
_NR = 3  # rows spanned by one term for k <= 16 (a + 2k - 1 <= 46 < 48)
BLOCK_ROWS = 4096  # rows per block: 512 kB of float64, stays in L2
KMAX = 16


_OPENBLAS: list = []


def _openblas_local() -> list:
    """openblas_set_num_threads_local of the OpenBLAS copies bundled with numpy and scipy
    (thread-local setting, OpenBLAS >= 0.3.27); empty when they use another BLAS."""
    if not _OPENBLAS:
        fns = []
        site = os.path.dirname(os.path.dirname(np.__file__))
        for libdir in ("numpy.libs", "scipy.libs"):
            for path in sorted(glob.glob(os.path.join(site, libdir, "*openblas*"))):
                try:
                    fn = ctypes.CDLL(path).openblas_set_num_threads_local
                except (OSError, AttributeError):
                    continue
                fn.restype, fn.argtypes = ctypes.c_int, [ctypes.c_int]
                fns.append(fn)
        _OPENBLAS.append(fns)
    return _OPENBLAS[0]


@contextlib.contextmanager
def blas_single_thread() -> Iterator[None]:
    """Run the block with the bundled OpenBLAS limited to one thread in this thread
    (restored afterwards). Small products in a hot loop gain nothing from threads, and on a
    shared machine the spinning helper threads can make a job 10-30x slower."""
    fns = _openblas_local()
    prev = [fn(1) for fn in fns]
    try:
        yield
    finally:
        for fn, p in zip(fns, prev):
            fn(max(1, p))


def quad_weights(k: int) -> np.ndarray:
    """M_k^T M_k (48 x 48) for lag k <= 16 (see the module docstring)."""
    if not 1 <= k <= KMAX:
        raise ValueError(f"lag {k} outside 1..{KMAX}")
    h = np.concatenate((-np.ones(k), np.ones(k)))
    m = np.zeros((ROW, ROW * _NR))
    for a in range(ROW):
        m[a, a: a + 2 * k] = h
    return m.T @ m


class GramLevel:
    """Exact sums sum_i D_k[i]^2 (i = 0 .. n - 2k, n increments) for lags ``ks`` <= 16,
    streamed from increment chunks."""

    def __init__(self, ks: list[int]):
        self.ks = sorted(int(k) for k in ks)
        self.wq = np.stack([quad_weights(k) for k in self.ks]) if self.ks else None
        self.s = np.zeros((_NR, ROW, ROW))  # sum over blocks of B_d
        self.edges: list[np.ndarray] = []  # per block rows (0, 1, n, n+1), centred
        self.pend = np.empty(0)  # increments not yet anchored
        self.n = 0  # increments seen
        self.anchored = 0  # increments anchored (multiple of 16)
        self._buf = np.empty(ROW * (BLOCK_ROWS + _NR - 1))

    def _process(self, arr: np.ndarray) -> int:
        """Anchor all complete rows of ``arr`` that have two further rows; return samples used."""
        anchors = arr.size // ROW - (_NR - 1)
        r0 = 0
        s0, s1, s2 = self.s
        tmp = np.empty((ROW, ROW))
        buf = self._buf
        while r0 < anchors:
            nr = min(BLOCK_ROWS, anchors - r0)
            blk = arr[ROW * r0: ROW * (r0 + nr + _NR - 1)]
            w = np.subtract(blk, np.add.reduce(blk[: 4 * ROW]) / (4 * ROW),
                            out=buf[: blk.size]).reshape(nr + _NR - 1, ROW)
            a = w[:nr].T
            s0 += np.matmul(a, w[:nr], out=tmp)
            s1 += np.matmul(a, w[1: nr + 1], out=tmp)
            s2 += np.matmul(a, w[2: nr + 2], out=tmp)
            self.edges.append(w[[0, 1, nr, nr + 1]])  # for the shifted-block corrections
            r0 += nr
        return ROW * max(anchors, 0)

    def feed(self, w: np.ndarray) -> None:
        """Append increments (float64, 1-D)."""
        if w.size == 0:
            return
        self.n += w.size
        pos = 0
        if self.pend.size:  # bridge the pending tail (< 64 increments) and the new chunk
            take = min(w.size, ROW * BLOCK_ROWS)
            bridge = np.concatenate((self.pend, w[:take]))
            used = self._process(bridge)
            self.anchored += used
            if take == w.size:
                self.pend = bridge[used:].copy()
                return
            pos = used - self.pend.size  # >= 0: the bridge holds >= 3 rows beyond pend
        used = self._process(w[pos:])
        self.anchored += used
        self.pend = w[pos + used:].copy()

    def gram(self) -> np.ndarray:
        """G = sum_r V_r V_r^T over all anchored rows (48 x 48)."""
        s0, s1, s2 = self.s
        g = np.zeros((ROW * _NR, ROW * _NR))
        x00 = x11 = x01 = np.zeros((ROW, ROW))
        if self.edges:
            e = np.stack(self.edges)  # (blocks, 4, 16): rows 0, 1, n, n+1
            x00 = e[:, 2].T @ e[:, 2] - e[:, 0].T @ e[:, 0]
            x11 = e[:, 3].T @ e[:, 3] - e[:, 1].T @ e[:, 1]
            x01 = e[:, 2].T @ e[:, 3] - e[:, 0].T @ e[:, 1]
        blocks = {(0, 0): s0, (0, 1): s1, (0, 2): s2, (1, 1): s0 + x00, (1, 2): s1 + x01,
                  (2, 2): s0 + x00 + x11}
        for (p, q), b in blocks.items():
            g[ROW * p: ROW * (p + 1), ROW * q: ROW * (q + 1)] = b
            if p != q:
                g[ROW * q: ROW * (q + 1), ROW * p: ROW * (p + 1)] = b.T
        return g

    def sums(self) -> tuple[np.ndarray, np.ndarray]:
        """(sum of D_k^2, number of terms) per lag in ``ks`` over everything fed."""
        if not self.ks:
            return np.zeros(0), np.zeros(0, dtype=np.int64)
        tot = np.einsum("kab,ab->k", self.wq, self.gram())
        # terms from the first unanchored increment on: direct
        tail = self.pend - (self.pend.mean() if self.pend.size else 0.0)
        x = np.concatenate(([0.0], np.cumsum(tail)))
        counts = []
        for i, k in enumerate(self.ks):
            if x.size > 2 * k:
                d = x[2 * k:] - 2.0 * x[k: x.size - k] + x[: x.size - 2 * k]
                tot[i] += float(np.sum(d * d))
            counts.append(max(0, self.n + 1 - 2 * k))
        return tot, np.array(counts, dtype=np.int64)


def conforming(m: int) -> tuple[int, int] | None:
    """(level j, lag k) if the pyramid serves factor m: m < 16 at level 0, else m = k 2^j
    with 8 <= k < 16 (stride 2^j, m/16 < stride <= m/8); None otherwise."""
    m = int(m)
    if m < 1:
        return None
    if m < KMAX:
        return 0, m
    j = 0
    while m % 2 == 0 and m // 2 >= 8 and m >= KMAX:
        m //= 2
        j += 1
    return (j, m) if 8 <= m < KMAX else None


class GramPyramid:
    """Overlapping-Allan sums for conforming factors (see :func:`conforming`) from a stream of
    increments (rate samples y, or phase differences). ``sums()`` returns per factor the sum of
    squared second differences in increment units (multiply by tau0^2 for rate input)."""

    def __init__(self, ms: np.ndarray):
        self.ms = np.asarray(ms, dtype=np.int64)
        plan: dict[int, list[int]] = {}
        for m in self.ms:
            jk = conforming(int(m))
            if jk is None:
                raise ValueError(f"factor {m} is not served by the pyramid")
            plan.setdefault(jk[0], []).append(jk[1])
        self.depth = max(plan) + 1 if plan else 0
        self.levels = [GramLevel(sorted(set(plan.get(j, [])))) for j in range(self.depth)]
        self.odd: list[np.ndarray] = [np.empty(0) for _ in range(self.depth)]

    def feed(self, w: np.ndarray, offset: float = 0.0) -> None:
        """Append increments (any real dtype, converted to float64). ``offset`` (the mean
        increment, e.g. gravity on an accelerometer axis) is removed from the pair sums so
        that deeper levels stay small; level 0 is centred per block anyway."""
        w = np.asarray(w, dtype=np.float64).ravel()
        with blas_single_thread():
            self._feed(w, offset)

    def _feed(self, w: np.ndarray, offset: float) -> None:
        for j, lev in enumerate(self.levels):
            if w.size == 0:
                return
            if lev.ks:
                lev.feed(w)
            if j + 1 == self.depth:
                return
            if self.odd[j].size:  # carry the unpaired increment of the previous chunk
                w = np.concatenate((self.odd[j], w))
            h = w.size // 2
            self.odd[j] = w[2 * h:].copy()
            w = np.add(w[0: 2 * h: 2], w[1: 2 * h: 2])
            if j == 0 and offset:
                w -= 2.0 * offset

    def sums(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sum of D^2 per factor, terms summed per factor, stride per factor)."""
        per_level = [lev.sums() for lev in self.levels]
        tot, cnt, stride = [], [], []
        for m in self.ms:
            j, k = conforming(int(m))
            i = self.levels[j].ks.index(k)
            tot.append(per_level[j][0][i])
            cnt.append(per_level[j][1][i])
            stride.append(1 << j)
        return np.array(tot), np.array(cnt, dtype=np.int64), np.array(stride, dtype=np.int64)


# --------------------------------------------------------------------------- strided (direct)
def sum_d2(x: np.ndarray, k: int, lo: int, hi: int, scratch: np.ndarray) -> float:
    """sum_{i=lo}^{hi-1} (x[i+2k] - 2 x[i+k] + x[i])^2, in blocks of ``scratch.size`` (call
    it under :func:`blas_single_thread`)."""
    total = 0.0
    step = scratch.size
    for a in range(lo, hi, step):
        b = min(hi, a + step)
        d = scratch[: b - a]
        np.add(x[a + 2 * k: b + 2 * k], x[a:b], out=d)
        d -= x[a + k: b + k]
        d -= x[a + k: b + k]
        total += float(np.dot(d, d))
    return total


def sums_d2_x2(x: np.ndarray, x2: np.ndarray, ks: np.ndarray, block: int = 1 << 18
               ) -> np.ndarray:
    """For every lag k in ``ks``: sum_{i=0}^{N-2k-1} (x[i+2k] + x[i] - x2[i+k])^2 with
    x2 = 2x given. Blocks of i outside, lags inside: x[a:b] stays in cache for all lags
    (call under :func:`blas_single_thread`)."""
    ks = np.asarray(ks, dtype=np.int64)
    his = x.size - 2 * ks
    tot = np.zeros(ks.size)
    d = np.empty(block)
    for a in range(0, int(his.max(initial=0)), block):
        for j in np.flatnonzero(his > a):
            k, b = int(ks[j]), min(int(his[j]), a + block)
            dd = d[: b - a]
            np.add(x[a + 2 * k: b + 2 * k], x[a:b], out=dd)
            dd -= x2[a + k: b + k]
            tot[j] += float(np.dot(dd, dd))
    return tot


class StridedLevel:
    """Overlapping-Allan sums at lags ``ks`` on the phase decimated by ``s``, streamed from
    phase chunks (direct differences; used by exact mode and for non-pyramid factors)."""

    def __init__(self, s: int, ks: list[int]):
        self.s = s
        self.ks = sorted(ks)
        self.keep = 2 * self.ks[-1]
        self.tail = np.empty(0)
        self.b0 = 0  # decimated index of tail[0]
        self.next_start = {k: 0 for k in self.ks}
        self.sums = {k: 0.0 for k in self.ks}
        self.counts = {k: 0 for k in self.ks}

    def feed(self, x_chunk: np.ndarray, g0: int, scratch: np.ndarray, src_s: int = 1
             ) -> tuple[np.ndarray, int] | None:
        """Phase points x[g0 + i src_s] = x_chunk[i] (float64; ``src_s`` divides this level's
        stride). Returns this level's new points and the phase index of the first (a source
        for a level of a multiple stride: the decimation cascades, each level reads only the
        previous one's points), or None."""
        step = self.s // src_s
        start = ((-g0) % self.s) // src_s
        if start >= x_chunk.size:
            return None
        if K.HAVE_NUMBA:
            n_new = -(-(x_chunk.size - start) // step)
            buf = self._buffer(self.tail.size + n_new)
            K.gather_into(self.tail, x_chunk, start, step, buf)
        else:
            new = x_chunk[start:: step]
            buf = np.concatenate((self.tail, new)) if self.tail.size else np.ascontiguousarray(new)
        return self.feed_buffer(buf), g0 + start * src_s

    def _buffer(self, n: int) -> np.ndarray:
        """A scratch buffer of n points, kept between chunks (no fresh pages per chunk)."""
        if getattr(self, "_buf", None) is None or self._buf.size < n:
            self._buf = np.empty(max(n, 1024))
        return self._buf[:n]

    def feed_buffer(self, buf: np.ndarray) -> np.ndarray:
        """Sum the terms of ``buf`` = this level's tail followed by its new points (built by
        the caller, e.g. the phase written straight after the tail); returns the new points."""
        end = self.b0 + buf.size
        scratch = None
        if K.HAVE_NUMBA:  # every lag in one compiled pass over the chunk
            ks = np.array(self.ks, dtype=np.int64)
            los = np.array([self.next_start[k] - self.b0 for k in self.ks], dtype=np.int64)
            his = buf.size - 2 * ks
            ok = his > los
            if ok.any():
                v = K.range_sums(buf, ks[ok], los[ok], his[ok])
                for k, lo, hi, s in zip(ks[ok], los[ok], his[ok], v):
                    self.sums[int(k)] += float(s)
                    self.counts[int(k)] += int(hi - lo)
                    self.next_start[int(k)] = end - 2 * int(k)
        else:
            for k in self.ks:
                lo = self.next_start[k] - self.b0
                hi = buf.size - 2 * k
                if hi > lo:
                    if scratch is None:
                        scratch = np.empty(1 << 16)
                    self.sums[k] += sum_d2(buf, k, lo, hi, scratch)
                    self.counts[k] += hi - lo
                    self.next_start[k] = end - 2 * k
        n_old = self.tail.size
        cut = max(0, buf.size - self.keep)
        self.tail = buf[cut:].copy()
        self.b0 += cut
        return buf[n_old:]


class Cascade:
    """The strided levels of fast mode in one compiled pass per chunk (``K.HAVE_NUMBA``):
    levels of power-of-two strides s_0 = 1 < s_1 < ..., level j's points every s_j-th phase
    point, each level's lags summed by direct differences (every term at that stride, the same
    terms as :class:`StridedLevel`), each level's points taken from the one above.

    Level 0's points are summed where the caller wrote them (:meth:`target`, after the kept
    tail), in pieces of :data:`SUB` points that go down the cascade while they are in the
    core's caches (every second point on to level 1, ...); a deeper level runs once it has
    :data:`BATCH` points pending, so the deep levels, which get a point per thousands of
    samples, cost nothing per piece. Versus one :class:`StridedLevel` per stride fed chunk by
    chunk from Python: no Python per level (a dozen calls per chunk per axis), and no pass
    over the chunk per level to pick the next level's points from memory. Memory: the chunk,
    and ``levels x (2 max lag + 2 (SUB + BATCH))`` floats."""

    SUB = 1 << 14
    BATCH = 1 << 10

    def __init__(self, levels: dict[int, list[int]]):
        strides = sorted(levels)
        self.strides = np.array(strides, dtype=np.int64)
        nl = len(strides)
        kmax = max(len(v) for v in levels.values())
        self.ks = np.zeros((nl, kmax), dtype=np.int64)
        self.nks = np.zeros(nl, dtype=np.int64)
        for j, st in enumerate(strides):
            ks = sorted(int(k) for k in levels[st])
            self.ks[j, : len(ks)] = ks
            self.nks[j] = len(ks)
        self.keep = np.array([2 * int(self.ks[j, : self.nks[j]].max()) for j in range(nl)],
                             dtype=np.int64)
        cap = int(self.keep.max()) + 2 * (self.SUB + self.BATCH) + 2
        self.bufs = np.empty((nl, cap))  # levels >= 1; pages touched only where points go
        self.tlen = np.zeros(nl, dtype=np.int64)
        self.pend = np.zeros(nl, dtype=np.int64)
        self.b0 = np.zeros(nl, dtype=np.int64)
        self.nstart = np.zeros((nl, kmax), dtype=np.int64)
        self.sums = np.zeros((nl, kmax, 2))
        self.counts = np.zeros((nl, kmax), dtype=np.int64)
        self.k0 = int(self.keep[0])
        self.x0 = np.empty(self.k0 + 1024)  # level 0: kept tail, then the chunk's points
        self.n = 0  # phase points fed

    @staticmethod
    def usable(levels: dict[int, list[int]]) -> bool:
        """Power-of-two strides from 1, lags small enough for the per-level buffers."""
        st = sorted(levels)
        return (K.HAVE_NUMBA and bool(st) and st[0] == 1
                and all(s & (s - 1) == 0 for s in st)
                and max(max(v) for v in levels.values()) <= 1 << 12)

    def target(self, n: int) -> np.ndarray:
        """Where the next n phase points go (valid until :meth:`commit`)."""
        if self.x0.size < self.k0 + n:
            grown = np.empty(self.k0 + n)
            grown[: self.k0] = self.x0[: self.k0]
            self.x0 = grown
        return self.x0[self.k0: self.k0 + n]

    def commit(self, n: int, tap: np.ndarray | None = None, tap_step: int = 0) -> int:
        """Sum the n points written into :meth:`target`. With ``tap``: also copy the new
        points whose index is a multiple of ``tap_step`` into it (as many as fit) while they
        pass through the cache (a decimated copy of the phase, without a strided pass over
        the chunk in memory later); returns how many were copied."""
        if n <= 0:
            return 0
        if tap is None:
            tap, tap_step = np.empty(0), 0
        got = K._casc_chunk(self.x0, self.k0, n, self.strides, self.ks, self.nks, self.bufs,
                            self.tlen, self.pend, self.b0, self.nstart, self.sums, self.counts,
                            self.keep, self.SUB, self.BATCH, K.BLOCK, self.n, tap,
                            int(tap_step))
        self.n += n
        return int(got)

    def feed(self, x: np.ndarray, g0: int) -> None:
        """Phase points x[g0 + i] = x[i], the continuation of those fed before."""
        if g0 != self.n:
            raise ValueError(f"cascade fed at point {g0}, expected {self.n}")
        self.target(x.size)[:] = x
        self.commit(x.size)

    def flush(self) -> None:
        """Sum every level's pending points (before reading the sums; feeding may go on)."""
        if self.pend.any():
            K._casc_flush(self.strides, self.ks, self.nks, self.bufs, self.tlen, self.pend,
                          self.b0, self.nstart, self.sums, self.counts, self.keep, K.BLOCK)

    def level_sums(self, s: int) -> tuple[dict[int, float], dict[int, int]]:
        """(sum per lag, terms per lag) of the level of stride s, after :meth:`flush`."""
        j = int(np.searchsorted(self.strides, s))
        ks = self.ks[j, : self.nks[j]]
        tot = self.sums[j, : self.nks[j]].sum(axis=1)
        return ({int(k): float(v) for k, v in zip(ks, tot)},
                {int(k): int(c) for k, c in zip(ks, self.counts[j, : self.nks[j]])})
