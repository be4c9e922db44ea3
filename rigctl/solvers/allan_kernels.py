"""Compiled kernels for the exact (fully overlapping) Allan-family sums (numba, optional).

The exact overlapping Allan sum for factor m over phase points x[0..N-1] is::

    S(m) = sum_{i=0}^{N-2m-1} (x[i+2m] - 2 x[i+m] + x[i])^2

Every term of every factor is evaluated (stride 1, no approximation). Cost model (docs/allan.md):
``sum_m (N - 2m)`` terms of three loads and three flops each. The loop runs over blocks of
``BLOCK`` consecutive i outside and over the factors inside, so x[a:a+BLOCK] is read from memory
once for all factors and stays in L2; a factor m > BLOCK brings two further streams
(x[a+m..], x[a+2m..]) of BLOCK contiguous values each, long enough for the hardware
prefetcher. The inner loop is a SIMD reduction (numba with ``fastmath``: several vector
accumulators, i.e. pairwise-like summation inside a block); block sums are added with
Neumaier compensation, so the summation adds no error beyond ~1e-16 relative. The precision
limit is the phase itself: x is a float64 running sum, so each term carries a rounding error of
about eps |x| (random, averaging down over the terms); offsets are removed before the running
sum (see :func:`phase`) so |x| stays small.

``threads`` > 1 splits the blocks into contiguous parts run on numba's thread pool (each part
its own compensated sums; the parts are added at the end, so results do not depend on the
thread count beyond the last bits).

Without numba (``HAVE_NUMBA`` False) the callers fall back to numpy. The compiled code is in
:mod:`rigctl.solvers.allan_kernels_jit`, imported (with numba) at the first use of a kernel or of
``HAVE_NUMBA``, not with this module.
"""
from __future__ import annotations

import numpy as np

#: phase points per block (512 kB: x[a:a+BLOCK] stays in the 1 MB L2 while the factors run)
BLOCK = 1 << 16


def _jit():
    """The compiled kernels (:mod:`rigctl.solvers.allan_kernels_jit`), imported at the first call,
    or None without numba. Importing numba costs ~0.25 s of CPU, which a process that never runs
    a kernel (e.g. ``rigctl calibrate``, ``rigctl batch``) no longer pays; the first call also
    sets the module's ``HAVE_NUMBA``."""
    global _JIT
    if _JIT is _UNSET:
        try:  # numba is the ``fast`` extra
            from . import allan_kernels_jit as jit
        except ImportError:  # pragma: no cover - exercised only without the extra
            jit = None
        _JIT = jit
        globals()["HAVE_NUMBA"] = jit is not None
    return _JIT


_UNSET = object()
_JIT = _UNSET


def __getattr__(name: str):
    """``HAVE_NUMBA`` (whether the compiled kernels are there: numba, the ``fast`` extra),
    ``numba`` and the compiled kernels themselves (``_CACHE``, ``_phase``, ...), imported at
    their first use (PEP 562): see :func:`_jit`."""
    if name == "HAVE_NUMBA":
        return _jit() is not None
    jit = _jit() if not name.startswith("__") else None
    if jit is not None and hasattr(jit, name):
        return getattr(jit, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def available() -> bool:
    return _jit() is not None


def phase(y: np.ndarray, tau0: float, offset: float | None = None) -> np.ndarray:
    """x[0] = 0, x[k] = tau0 * sum_{j<k} (y[j] - c), c = mean(y) unless given: one pass (two
    with the mean) instead of numpy's four. The running sum is sequential, like np.cumsum."""
    y = np.ascontiguousarray(y, dtype=np.float64)
    c = float(np.mean(y)) if offset is None else float(offset)
    x = np.empty(y.size + 1)
    _jit()._phase(y, c, float(tau0), x)
    return x


def _with_threads(n: int):
    numba = _jit().numba
    prev = numba.get_num_threads()
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    return prev


def diff_sums(x: np.ndarray, ms: np.ndarray, order: int = 2, threads: int = 1,
              block: int = BLOCK) -> np.ndarray:
    """Exact sums of squared order-2 (Allan) or order-3 (Hadamard) differences at lag m, every
    term, for each factor in ``ms`` (any order; factors with no term give 0)."""
    if order not in (2, 3):
        raise ValueError("order must be 2 or 3")
    x = np.ascontiguousarray(x, dtype=np.float64)
    ms = np.asarray(ms, dtype=np.int64)
    srt = np.argsort(ms)
    mss = np.ascontiguousarray(ms[srt])
    out = np.zeros(ms.size)
    if ms.size == 0:
        return out
    hi = max(0, x.size - order * int(mss[0]))
    parts = max(1, min(int(threads), hi // block))
    # contiguous parts of whole blocks; equal numbers of terms per part (the work)
    nb = -(-hi // block)
    bounds = np.minimum(np.linspace(0, nb, parts + 1).round().astype(np.int64) * block, hi)
    tot = np.zeros((parts, ms.size))
    comp = np.zeros((parts, ms.size))
    if parts == 1:
        _jit()._part_sums(x, mss, order, 0, hi, block, tot[0], comp[0])
    else:
        prev = _with_threads(parts)
        try:
            _jit()._par_sums(x, mss, order, bounds, block, tot, comp)
        finally:
            _jit().numba.set_num_threads(prev)
    s = (tot + comp).sum(axis=0)
    out[srt] = s
    return out


def range_sums(x: np.ndarray, ks: np.ndarray, los: np.ndarray, his: np.ndarray,
               block: int = BLOCK) -> np.ndarray:
    """Second-difference sums at lag ks[j] over i in [los[j], his[j]) (the caller keeps
    his[j] + 2 ks[j] <= x.size); one pass over x for all lags (a streamed level's chunk)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    ks = np.asarray(ks, dtype=np.int64)
    los = np.asarray(los, dtype=np.int64)
    his = np.asarray(his, dtype=np.int64)
    out = np.zeros((ks.size, 2))
    if ks.size and int(np.max(his - los)) > 0:
        _jit()._range_sums(x, ks, los, his, block, out)
    return out.sum(axis=1)


def phase_chunk(y: np.ndarray, offset: float, tau0: float, x0: float) -> np.ndarray:
    """x0 + tau0 * cumsum(y - offset) in one pass (a streamed chunk of the phase)."""
    y = np.ascontiguousarray(y, dtype=np.float64)
    x = np.empty(y.size)
    _jit()._phase_chunk(y, float(offset), float(tau0), float(x0), x)
    return x


def gather(tail: np.ndarray, x: np.ndarray, start: int, s: int) -> np.ndarray:
    """concatenate((tail, x[start::s])) in one pass."""
    n_new = max(0, -(-(x.size - start) // s))
    out = np.empty(tail.size + n_new)
    _jit()._gather(np.ascontiguousarray(tail, dtype=np.float64), x, int(start), int(s), out)
    return out


def gather_into(tail: np.ndarray, x: np.ndarray, start: int, s: int, out: np.ndarray) -> None:
    """out[:] = concatenate((tail, x[start::s])) (out sized by the caller)."""
    _jit()._gather(np.ascontiguousarray(tail, dtype=np.float64), x, int(start), int(s), out)


def phase_into(y: np.ndarray, offset: float, tau0: float, x0: float, out: np.ndarray) -> None:
    """out[:] = x0 + tau0 * cumsum(y - offset) (as :func:`phase_chunk`, into a given buffer)."""
    _jit()._phase_chunk(np.ascontiguousarray(y, dtype=np.float64), float(offset), float(tau0),
                        float(x0), out)


def extremes_block(w: int) -> int:
    """Rows per block of the spike prefilter's extremes for a window of w samples."""
    return max(32, int(w))


def any_block_examined(bmin: np.ndarray, bmax: np.ndarray, thr: float) -> bool:
    """Whether :func:`far_from_window_range` with these block extremes would look at any
    sample (a block whose neighbourhood spans more than ``thr``); False: it finds nothing."""
    return bool(_jit()._any_loud_block(bmin, bmax, float(thr))) if bmin.size else False


def far_from_window_range(y: np.ndarray, w: int, thr: float,
                          extremes: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Indices i where y[i] is more than ``thr`` above the minimum or below the maximum of its
    window of w samples (scipy.ndimage's alignment, "nearest" ends), ascending. ``extremes``:
    the minimum and maximum of each block of :func:`extremes_block` samples of y, when the
    caller has them already (:func:`phase_cols3`); y may then be a strided view."""
    bs = extremes_block(w)
    if extremes is None:
        y = np.ascontiguousarray(y, dtype=np.float64)
    out = np.empty(y.size, dtype=np.int64)
    if not y.size:
        return out[:0].copy()
    if extremes is None:
        c = _jit()._far_from_range_blocks(y, int(w), float(thr), bs, out)
    else:
        c = _jit()._far_from_range_pre(y, int(w), float(thr), bs, extremes[0], extremes[1], out)
    return out[:c].copy()


def _one_piece(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pieces (lanes, starts, rows) of one array of n rows."""
    return np.zeros(1, np.int64), np.zeros(1, np.int64), np.array([n], np.int64)


def _one_lane(base: np.ndarray, lanes: np.ndarray, starts: np.ndarray, rows: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pieces that all lie in one lane of ``base`` as pieces of that lane alone (a 1 x n
    array, contiguous: the compiled loops run on it as on an array)."""
    if base.shape[0] > 1 and lanes.size and bool(np.all(lanes == lanes[0])):
        ln = int(lanes[0])
        return base[ln: ln + 1], np.zeros_like(lanes), starts, rows
    return base, lanes, starts, rows


def phase_cols3(blk: np.ndarray, offsets: np.ndarray, tau0: float, x0: np.ndarray,
                outs: list[np.ndarray], bs: int,
                pieces: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """The running-sum phase of each column of ``blk`` (rows x 3, float64) into outs[c] (each
    of at least len(blk) points; see :func:`phase_into`), bit-identical to it, in one pass for
    the three columns; ``x0`` (3) is updated to each column's last phase point. Returns the
    minimum and maximum of every block of ``bs`` rows per column (3 x blocks).
    ``pieces`` = (lanes, starts, rows): the rows are pieces of ``blk`` (then 2-D float64:
    piece p is blk[lanes[p], starts[p]: starts[p] + 3 rows[p]], rows of 3), one after the
    other -- the same results as for their concatenation, without it (the rows of an HDF5
    dataset's chunks where they lie in a mapped file; a lane per byte offset modulo 8)."""
    if pieces is None:
        base, pieces = blk.reshape(1, -1), _one_piece(blk.shape[0])
    else:
        base = blk
    base, lanes, starts, rows = _one_lane(base, *pieces)
    nb = (int(np.sum(rows)) + bs - 1) // bs
    bmin = np.empty((3, nb))
    bmax = np.empty((3, nb))
    _jit()._phase_cols3(base, lanes, starts, rows, np.asarray(offsets, dtype=np.float64), float(tau0),
                        x0, outs[0], outs[1], outs[2], int(bs), bmin, bmax)
    return bmin, bmax


def counter_jumps(c: np.ndarray,
                  pieces: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(i, c[i] - c[i-1]) for every i where the int64 counter c steps by more than 1, in one
    pass without the difference array (a day's counter at 2 kHz is 0.7 GB). ``pieces`` =
    (lanes, starts, rows): the counter is the pieces c[lanes[p], starts[p]: starts[p] +
    rows[p]] of the 2-D c, one after the other (i counts their values), without their
    concatenation."""
    if pieces is None:
        c = np.ascontiguousarray(c, dtype=np.int64)
        c, pieces = c.reshape(1, -1), _one_piece(c.size)
    c, lanes, starts, rows = _one_lane(c, *pieces)
    n = int(np.sum(rows))
    out_i = np.empty(max(n - 1, 0), dtype=np.int64)
    out_d = np.empty_like(out_i)
    k = _jit()._jumps(c, lanes, starts, rows, out_i, out_d) if n > 1 else 0
    return out_i[:k].copy(), out_d[:k].copy()


def running_median(y: np.ndarray, w: int) -> np.ndarray | None:
    """The running median of ``w`` samples (odd w) with the ends' values repeated, as
    ``scipy.ndimage.median_filter(y, size=w, mode="nearest")`` gives it (the same order
    statistic of the same window, so the same values), compiled without the GIL (scipy's
    holds it for the whole filter: six axes' first chunks ran one at a time). None without
    numba, for an even or too-long window, or when y holds a non-finite value."""
    y = np.ascontiguousarray(y, dtype=np.float64)
    if _jit() is None or w % 2 == 0 or w < 1 or y.size == 0:
        return None
    out = np.empty_like(y)
    return out if _jit()._running_median(y, int(w), out) else None


def lag1_alpha(x: np.ndarray, m: int, dmax: int) -> int:
    """Compiled lag-1 noise identification of phase ``x`` decimated by m (see
    allan_noise_id.noise_id_lag1, which calls it for long series)."""
    return int(_jit()._lag1_alpha(np.ascontiguousarray(x, dtype=np.float64), int(m), int(dmax)))
