"""Allan-family deviations as pure functions of numpy arrays.

Conventions (IEEE Std 952-1997, NIST SP 1065 "Handbook of Frequency Stability Analysis"):

* ``rate`` input ``y`` (frequency-like: gyro rad/s, accelerometer m/s^2, fractional frequency)
  sampled every ``tau0`` seconds, or ``phase`` input ``x`` (integrated output: delta-angle
  running sum in rad, delta-velocity running sum in m/s, clock phase in s).
  ``x[k] = tau0 * sum_{j<k} y[j]`` (so ``N`` rate samples give ``N + 1`` phase points).
* Deviations come out in the units of ``y`` (rate units); ``tau = m * tau0`` in s.

Estimators, for phase points x[0..N-1] and averaging factor m (tau = m tau0):

* overlapping Allan (primary)::

      AVAR(tau) = sum_{i=0}^{N-2m-1} (x[i+2m] - 2 x[i+m] + x[i])^2 / (2 tau^2 (N - 2m))

* non-overlapping Allan: the same sum over i = 0, m, 2m, ... (floor((N-1)/m) - 1 terms)
* modified Allan::

      MVAR(tau) = sum_{j=0}^{N-3m} (sum_{i=j}^{j+m-1} x[i+2m] - 2x[i+m] + x[i])^2
                  / (2 m^2 tau^2 (N - 3m + 1))

  time deviation TDEV = tau * MDEV / sqrt(3)
* overlapping Hadamard::

      HVAR(tau) = sum_{i=0}^{N-3m-1} (x[i+3m] - 3x[i+2m] + 3x[i+m] - x[i])^2 / (6 tau^2 (N-3m))

  (non-overlapping Hadamard: every m-th term)
* total deviation (Howe): the overlapping Allan sum over the phase extended by uninverted
  even reflection at both ends, x*[1-j] = 2x[1] - x[1+j], x*[N+j] = 2x[N] - x[N-j]::

      TOTVAR(tau) = sum_{i=2}^{N-1} (x*[i-m] - 2x*[i] + x*[i+m])^2 / (2 tau^2 (N - 2))

Two ways to compute the overlapping Allan deviation: ``mode="exact"`` evaluates every term of
the fully overlapping sum in float64 (with numba: the compiled blocked kernel of
:mod:`rigctl.solvers.allan_kernels`, all factors, 2 threads; without: m <= 16 through the
polyphase Gram of :mod:`rigctl.solvers.allan_stream`, the same sum in another order, longer
taus by direct differences); ``mode="fast"`` (default) computes m < 16 with all terms too (one Gram pass for
all of them) and, for longer taus m = k 2^j (8 <= k < 16), every 2^j-th term, i.e. stride
m/16..m/8: the overlapping estimator on the phase decimated by 2^j (a pyramid of pair sums).
Consecutive terms at lags below m/8 are almost perfectly correlated, so the equivalent
degrees of freedom are kept (tested). :class:`OadevAccumulator` computes the same sums from
chunks with bounded memory; BLAS runs single-threaded in the hot loops.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Iterable, Sequence, Union

import numpy as np

from . import allan_kernels as K
from . import allan_stream as S

TauSpec = Union[str, int, Sequence[int]]

#: Stable32's "stop ratio" per estimator: its octave/decade runs end at the factor
#: (N - 1) // ratio, and its noise identification holds the previous tau's result once
#: fewer than 2 x ratio averages remain (see :mod:`rigctl.solvers.allan_noise_id`)
STOP_RATIO = {"adev": 5, "hdev": 5, "oadev": 4, "mdev": 4, "tdev": 4, "ohdev": 4,
              "totdev": 2}
_MAX_FRACTION = STOP_RATIO
_BLOCK = 1 << 16  # samples per block of the direct sums (512 kB, stays in L2)
#: below this many phase points mode="fast" computes the exact sums (they are cheap there)
FAST_MIN_POINTS = 1 << 20
#: threads of the compiled exact kernels (allan_kernels); both cores of a 2-core machine
THREADS = max(1, min(2, os.cpu_count() or 1))


@dataclass
class DevResult:
    """One deviation curve. ``dev`` in rate units; ``tau_s`` in s; ``n_terms`` summed terms;
    ``stride`` the spacing of the terms actually summed (1 = fully overlapping)."""

    kind: str
    tau0_s: float
    m: np.ndarray
    tau_s: np.ndarray
    dev: np.ndarray
    n_terms: np.ndarray
    n_phase: int
    stride: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def as_dict(self) -> dict:
        return {"kind": self.kind, "tau0_s": self.tau0_s, "n_phase": int(self.n_phase),
                "m": self.m.tolist(), "tau_s": self.tau_s.tolist(), "dev": self.dev.tolist(),
                "n_terms": self.n_terms.tolist(), "stride": self.stride.tolist()}


# --------------------------------------------------------------------------- input handling
def phase_from_rate(rate: np.ndarray, tau0: float, offset: float | None = None) -> np.ndarray:
    """Integrate a rate series to phase, float64: x[0] = 0, x[k] = tau0 * sum_{j<k}(y[j] - c).

    ``c`` (``offset``, default the mean of ``rate``) is removed first: a constant rate adds a
    linear phase term that every deviation here cancels exactly, and removing it keeps the
    running sum small (a float32 sum with gravity on the axis is wrong by orders of magnitude).
    """
    y = np.asarray(rate, dtype=np.float64)
    if y.ndim != 1:
        raise ValueError("rate must be one-dimensional")
    c = float(np.mean(y)) if offset is None else float(offset)
    if K.HAVE_NUMBA and y.size:
        return K.phase(y, tau0, c)  # the same operations in one pass
    x = np.empty(y.size + 1, dtype=np.float64)
    x[0] = 0.0
    np.subtract(y, c, out=x[1:])
    np.cumsum(x[1:], out=x[1:])
    x[1:] *= tau0
    return x


def _phase(data: np.ndarray, tau0: float, data_type: str) -> np.ndarray:
    if data_type == "phase":
        x = np.asarray(data, dtype=np.float64)
        if x.ndim != 1:
            raise ValueError("phase must be one-dimensional")
        return x
    if data_type in ("rate", "freq"):
        return phase_from_rate(data, tau0)
    raise ValueError(f"data_type must be 'rate' or 'phase', not {data_type!r}")


def max_factor(n_phase: int, kind: str) -> int:
    """Largest averaging factor Stable32 reports for ``kind`` with ``n_phase`` phase points."""
    return max(1, (n_phase - 1) // _MAX_FRACTION[kind])


def computable_factor(n_phase: int, kind: str) -> int:
    """Largest averaging factor giving at least one term of estimator ``kind``."""
    n = n_phase
    lim = {"adev": (n - 1) // 2, "oadev": (n - 1) // 2, "mdev": (n + 1) // 3,
           "tdev": (n + 1) // 3, "hdev": (n - 1) // 3, "ohdev": (n - 1) // 3,
           "totdev": n - 2}[kind]
    return max(1, lim)


def tau_factors(n_phase: int, taus: TauSpec = "octave", kind: str = "oadev") -> np.ndarray:
    """Averaging factors m for a tau set.

    ``"octave"``: 1, 2, 4, ...; ``"decade"``: 1, 2, 4, 10, 20, 40, ... (Stable32);
    ``"all"``: every integer; an int ``n``: n log-spaced factors (unique after rounding);
    a sequence: the given factors. Named and counted sets stop at Stable32's limit
    (:func:`max_factor`), explicit factors at the estimator's (:func:`computable_factor`).
    """
    mmax = max_factor(n_phase, kind)
    if not isinstance(taus, (str, int, np.integer)):
        mmax = computable_factor(n_phase, kind)
    if isinstance(taus, str):
        if taus == "octave":
            m = 2 ** np.arange(0, int(np.log2(mmax)) + 1)
        elif taus == "decade":
            dec = [k * 10 ** e for e in range(0, 19) for k in (1, 2, 4)]
            m = np.array([v for v in dec if v <= mmax])
        elif taus == "all":
            m = np.arange(1, mmax + 1)
        else:
            raise ValueError(f"unknown tau set {taus!r} (octave, decade, all or an integer)")
    elif isinstance(taus, (int, np.integer)):
        if taus < 1:
            raise ValueError("number of taus must be >= 1")
        m = np.unique(np.round(np.logspace(0, np.log10(mmax), int(taus))).astype(np.int64))
    else:
        m = np.unique(np.asarray(list(taus), dtype=np.int64))
    m = np.asarray(m, dtype=np.int64)
    return m[(m >= 1) & (m <= mmax)]


def fast_stride(m: int) -> int:
    """Stride of the fast estimator: the largest power of two s with s <= m/8 that divides m."""
    s = 1
    while (m % (2 * s) == 0) and (2 * s * 8 <= m):
        s *= 2
    return s


def snap_fast(m: np.ndarray) -> np.ndarray:
    """Round factors >= 16 to k * 2^j with 8 <= k < 16 (so the fast stride is m/16..m/8).
    j = floor(log2(m / 8)), k = m / 2^j rounded half to even (exact: a division by a power of
    two), k = 16 carried to j + 1, k = 8; all factors at once (a --taus all set is every
    integer up to N/4: ~9e4 of them for an hour at 100 Hz)."""
    v = np.asarray(m, dtype=np.int64).ravel()
    big = v >= 16
    vb = v[big]
    j = np.floor(np.log2(vb / 8.0)).astype(np.int64)
    p = np.ldexp(1.0, j)  # 2^j, exact
    k = np.rint(vb / p).astype(np.int64)
    carry = k >= 16
    j[carry] += 1
    k[carry] = 8
    out = v.copy()
    out[big] = k << j
    return np.unique(out)


# --------------------------------------------------------------------------- kernels
def _oadev_exact_sums(x: np.ndarray, ms: np.ndarray) -> np.ndarray:
    """sum_{i=0}^{N-2m-1} (x[i+2m] - 2x[i+m] + x[i])^2 for every m (all terms, stride 1).

    With numba (the ``fast`` extra): the compiled blocked kernel of
    :mod:`rigctl.solvers.allan_kernels` for every m (on ``THREADS`` threads). Without:
    m <= 16: the polyphase Gram of the increments (one pass for all of them, same sum in a
    different order); larger m: direct differences, on long series with 2x precomputed (one
    add, one subtract and one dot per block) and the loop over taus inside the loop over
    blocks (the block x[a:b] is read from memory once for all taus)."""
    if K.HAVE_NUMBA:
        return K.diff_sums(x, ms, 2, THREADS)
    out = np.empty(ms.size)
    small = ms <= S.KMAX
    with S.blas_single_thread():
        if np.any(small) and x.size > 4 * S.ROW * S.BLOCK_ROWS:
            lev = S.GramLevel([int(m) for m in ms[small]])
            step = 1 << 20
            for a in range(0, x.size - 1, step):
                lev.feed(np.diff(x[a: a + step + 1]))
            out[small] = lev.sums()[0]
        else:
            small[:] = False
        big = np.flatnonzero(~small)
        if big.size == 0:
            return out
        if x.size > FAST_MIN_POINTS:  # long series: 2x precomputed, blocks outside
            out[big] = S.sums_d2_x2(x, x + x, ms[big].astype(np.int64))
        else:
            scratch = np.empty(_BLOCK)
            for i in big:
                m = int(ms[i])
                out[i] = S.sum_d2(x, m, 0, x.size - 2 * m, scratch)
    return out


# --------------------------------------------------------------------------- streaming
#: strided levels from this stride on are fed in batches of DEFER_POINTS points
DEFER_STRIDE = 64
DEFER_POINTS = 1 << 16


class OadevAccumulator:
    """Streaming overlapping Allan deviation with bounded memory.

    Feed rate chunks (``add_rate``) or phase chunks (``add_phase``) of an arbitrarily long
    series; :meth:`result` gives the same sums as the one-shot estimator.

    * ``mode="fast"``: factors m < 16 and m = k 2^j (8 <= k < 16) go through the polyphase
      Gram pyramid of :mod:`rigctl.solvers.allan_stream` (m < 16 fully overlapping, longer
      ones at stride 2^j, m/16 < stride <= m/8; one pass over memory for all of them, no
      running sum needed). Other factors use direct differences of the phase decimated by
      :func:`fast_stride`.
    * ``mode="exact"``: direct differences of the full phase for every factor.

    The phase (when needed) is built with float64 cumulative sums after removing a constant
    offset (the first chunk's mean, or ``offset``), so gravity on an accelerometer axis costs
    no precision. Memory: kilobytes per pyramid level; 2 max(m / stride) phase points for
    the direct path (2 m_max in exact mode).
    """

    def __init__(self, tau0: float, ms: Iterable[int], mode: str = "fast",
                 offset: float | None = None):
        if mode not in ("fast", "exact"):
            raise ValueError("mode must be 'fast' or 'exact'")
        self.tau0 = float(tau0)
        self.ms = np.unique(np.asarray(list(ms), dtype=np.int64))
        if self.ms.size == 0 or self.ms[0] < 1:
            raise ValueError("need at least one averaging factor >= 1")
        self.mode = mode
        fast = mode == "fast"
        # with the compiled kernels every factor is summed by direct differences of the phase
        # (the same terms as the pyramid; 6.5-8.3 ns per sample against 14.7-15.5 for the
        # Gram pyramid, measured in one run); without them the pyramid takes what it can
        self._gram = np.array([fast and not K.HAVE_NUMBA and S.conforming(int(m)) is not None
                               for m in self.ms])
        self.pyramid = S.GramPyramid(self.ms[self._gram]) if self._gram.any() else None
        levels: dict[int, list[int]] = {}
        for m in self.ms[~self._gram]:
            s = fast_stride(int(m)) if fast else 1
            levels.setdefault(s, []).append(int(m) // s)
        #: fast mode with the compiled kernels: every strided level in one compiled cascade
        self.cascade = S.Cascade(levels) if fast and S.Cascade.usable(levels) else None
        self.levels = [] if self.cascade is not None else [
            S.StridedLevel(s, ks) for s, ks in sorted(levels.items())]
        self.offset = offset
        self.n_phase = 0
        self.phase_input: bool | None = None
        self._x_last = 0.0
        self._scratch = np.empty(_BLOCK)
        ss = [lv.s for lv in self.levels]
        self._defer_at = next((i for i, v in enumerate(ss) if v >= DEFER_STRIDE), -1)
        if self._defer_at > 0 and any(b % a for a, b in zip(ss, ss[1:])):
            self._defer_at = -1  # only a pure cascade (power-of-two strides) is deferred
        self._pending: list[tuple[np.ndarray, int, int]] = []
        self._pending_n = 0
        #: after add_rate: the phase points x[n_phase_before + i] of that chunk's samples
        #: (x[k] = tau0 sum_{j<k} (y[j] - offset)), a view valid until the next add_rate, or
        #: None when the path taken did not build them (the Gram pyramid alone)
        self.chunk_phase: np.ndarray | None = None

    def add_rate(self, y: np.ndarray) -> None:
        """Append rate samples (any float dtype); converted to float64 per chunk."""
        y = np.asarray(y, dtype=np.float64).ravel()
        self.chunk_phase = None
        if y.size == 0:
            return
        self._kind(False)
        if self.offset is None:
            self.offset = float(np.mean(y))
        if self.n_phase == 0:
            self.n_phase = 1  # x[0] = 0
            if self.levels:
                self._feed_levels(np.zeros(1), 0)
            elif self.cascade is not None:
                self.cascade.feed(np.zeros(1), 0)
        if self.pyramid is not None:
            self.pyramid.feed(y, self.offset)
        if self.cascade is not None:
            x = self.cascade.target(y.size)
            K.phase_into(y, self.offset, self.tau0, self._x_last, x)
            self._x_last = float(x[-1])
            self.cascade.commit(y.size)
            self.chunk_phase = x
        elif self.levels and K.HAVE_NUMBA and self.levels[0].s == 1:
            # the phase is written straight after the stride-1 level's tail (no copy), and
            # the other levels cascade from its points
            lev = self.levels[0]
            buf = lev._buffer(lev.tail.size + y.size)
            buf[: lev.tail.size] = lev.tail
            K.phase_into(y, self.offset, self.tau0, self._x_last, buf[lev.tail.size:])
            self._x_last = float(buf[-1])
            with S.blas_single_thread():
                x = lev.feed_buffer(buf)
            self.chunk_phase = x
            self._feed_levels(x, self.n_phase, first=1, src_s=1)
        elif self.levels:
            if K.HAVE_NUMBA:  # the same operations in one pass
                x = K.phase_chunk(y, self.offset, self.tau0, self._x_last)
            else:
                x = y - self.offset
                np.cumsum(x, out=x)
                x *= self.tau0
                x += self._x_last
            self._feed_levels(x, self.n_phase)
            self._x_last = float(x[-1])
            self.chunk_phase = x
        self.n_phase += y.size

    def can_take_phase(self) -> bool:
        """Whether :meth:`rate_target` / :meth:`commit_rate` can be used: rate samples added
        before (so the offset and x[0] are set), the compiled kernels, and the direct path
        starting at stride 1."""
        return (K.HAVE_NUMBA and self.n_phase > 0 and self.phase_input is False
                and self.pyramid is None and (self.cascade is not None or (
                    bool(self.levels) and self.levels[0].s == 1)))

    def rate_target(self, n: int) -> np.ndarray:
        """Where the phase points of the next ``n`` rate samples go when the caller computes
        them itself (``x[k] = x_last + tau0 * running sum of (y - offset)``, exactly as
        :func:`rigctl.solvers.allan_kernels.phase_into`; e.g. several axes in one pass,
        :func:`rigctl.solvers.allan_kernels.phase_cols3`), before :meth:`commit_rate`:
        a view of the stride-1 level's buffer, right after its tail (valid until the next
        call of this accumulator). Needs :meth:`can_take_phase`."""
        if self.cascade is not None:
            return self.cascade.target(n)
        lev = self.levels[0]
        buf = lev._buffer(lev.tail.size + n)
        return buf[lev.tail.size:]

    @property
    def x_last(self) -> float:
        """The last phase point so far (the running sum's start for the next chunk)."""
        return self._x_last

    def commit_rate(self, n: int, tap: np.ndarray | None = None, tap_step: int = 0) -> int:
        """Sum the ``n`` phase points written into :meth:`rate_target` (what :meth:`add_rate`
        does after building them; ``chunk_phase`` is set the same way). ``tap``: see
        :meth:`rigctl.solvers.allan_stream.Cascade.commit` (the phase points x[k], k a
        multiple of ``tap_step``, copied into it; only with the cascade, else nothing is
        copied); returns how many were copied."""
        self.chunk_phase = None
        if n == 0:
            return 0
        if self.cascade is not None:
            x = self.cascade.target(n)
            self._x_last = float(x[-1])
            got = self.cascade.commit(n, tap, tap_step)
            self.chunk_phase = x
            self.n_phase += n
            return got
        lev = self.levels[0]
        buf = lev._buffer(lev.tail.size + n)
        buf[: lev.tail.size] = lev.tail
        self._x_last = float(buf[-1])
        with S.blas_single_thread():
            x = lev.feed_buffer(buf)
        self.chunk_phase = x
        self._feed_levels(x, self.n_phase, first=1, src_s=1)
        self.n_phase += n
        return 0

    def add_phase(self, x: np.ndarray) -> None:
        """Append phase points (rate units x s). A constant offset is removed (float64)."""
        x = np.array(x, dtype=np.float64).ravel()
        if x.size == 0:
            return
        self._kind(True)
        if self.offset is None:
            self.offset = float(x[0])
        x -= self.offset
        if self.pyramid is not None:
            inc = np.diff(x, prepend=self._x_last) if self.n_phase else np.diff(x)
            self.pyramid.feed(inc)
        if self.levels:
            self._feed_levels(x, self.n_phase)
        elif self.cascade is not None:
            self.cascade.feed(x, self.n_phase)
        self._x_last = float(x[-1])
        self.n_phase += x.size

    def _kind(self, phase: bool) -> None:
        if self.phase_input is None:
            self.phase_input = phase
        elif self.phase_input != phase:
            raise ValueError("do not mix add_rate and add_phase on one accumulator")

    def _feed_levels(self, x: np.ndarray, g0: int, first: int = 0, src_s: int = 1) -> None:
        with S.blas_single_thread():
            self._cascade(x, g0, first, src_s, x, g0)

    def _cascade(self, src: np.ndarray, g: int, first: int, src_s: int, x: np.ndarray,
                 g0: int) -> None:
        """Feed levels[first:] (ascending strides) from ``src`` = phase points g, g + src_s,
        ...; each level passes its new points on when its stride divides the next one's. The
        levels from stride DEFER_STRIDE on get a few hundred points per chunk, so their points
        are collected (copied) until DEFER_POINTS are pending and then fed at once: the same
        points in the same order (the sums are grouped differently, ~1e-16), without a
        dozen Python calls per level per chunk."""
        for li in range(first, len(self.levels)):
            lev = self.levels[li]
            if lev.s % src_s:
                src, g, src_s = x, g0, 1
            if li and li == self._defer_at and src is not x:
                self._defer(src, g, src_s)
                return
            new = lev.feed(src, g, self._scratch, src_s)
            if new is not None:
                src, g = new
                src_s = lev.s

    def _defer(self, src: np.ndarray, g: int, src_s: int) -> None:
        p = self._pending
        if p and (p[-1][2] != src_s or p[-1][1] + p[-1][0].size * src_s != g):
            self._flush()  # not the continuation of the pending points
        self._pending.append((src.copy(), g, src_s))
        self._pending_n += src.size
        if self._pending_n >= DEFER_POINTS:
            self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        pend, self._pending, self._pending_n = self._pending, [], 0
        xs = pend[0][0] if len(pend) == 1 else np.concatenate([q[0] for q in pend])
        li = self._defer_at
        self._defer_at = -1  # feed through (no re-deferral of these points)
        try:
            with S.blas_single_thread():
                self._cascade(xs, pend[0][1], li, pend[0][2], xs, pend[0][1])
        finally:
            self._defer_at = li

    def result(self) -> DevResult:
        """Deviations for every factor with at least one complete term."""
        sums, counts, strides = self.raw_sums()
        return dev_from_sums(self.ms, self.tau0, sums, counts, strides,
                             np.where(strides == 1, counts, self.n_phase - 2 * self.ms),
                             self.n_phase)

    def raw_sums(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per factor (``ms``): the sum of the squared second differences summed so far (rate
        units^2 s^2), the number of terms in it and their stride. Sums of separate series
        (e.g. the gap-free stretches of a record, :func:`dev_from_sums`) add."""
        self._flush()
        sums = np.full(self.ms.size, np.nan)
        counts = np.zeros(self.ms.size, dtype=np.int64)
        strides = np.ones(self.ms.size, dtype=np.int64)
        if self.pyramid is not None:
            tot, cnt, st = self.pyramid.sums()
            scale = self.tau0 ** 2 if not self.phase_input else 1.0
            sums[self._gram], counts[self._gram], strides[self._gram] = tot * scale, cnt, st
        if self.cascade is not None:
            self.cascade.flush()
        got: dict[int, tuple[dict, dict]] = {}
        for i in np.flatnonzero(~self._gram):
            m = int(self.ms[i])
            s = fast_stride(m) if self.mode == "fast" else 1
            if self.cascade is not None:
                if s not in got:
                    got[s] = self.cascade.level_sums(s)
                lsums, lcounts = got[s]
            else:
                lev = next(lv for lv in self.levels if lv.s == s)
                lsums, lcounts = lev.sums, lev.counts
            sums[i], counts[i], strides[i] = lsums[m // s], lcounts[m // s], s
        return sums, counts, strides


def dev_from_sums(ms: np.ndarray, tau0: float, sums: np.ndarray, counts: np.ndarray,
                  strides: np.ndarray, n_terms: np.ndarray, n_phase: int) -> DevResult:
    """The overlapping Allan deviation from raw sums (:meth:`OadevAccumulator.raw_sums`), for
    every factor with at least one term; ``n_terms`` the terms the estimate stands for (the
    fully overlapping count when the sums are strided)."""
    ok = counts > 0
    tau = ms * tau0
    dev = np.sqrt(sums[ok] / (2.0 * tau[ok] ** 2 * counts[ok]))
    return DevResult("oadev", tau0, ms[ok], tau[ok], dev, np.asarray(n_terms)[ok], n_phase,
                     strides[ok])


# --------------------------------------------------------------------------- deviations
def oadev(data: np.ndarray, tau0: float = 1.0, taus: TauSpec = "octave",
          data_type: str = "rate", mode: str = "fast") -> DevResult:
    """Overlapping Allan deviation (see module docstring); ``mode`` "fast" or "exact".

    In fast mode (with at least ``FAST_MIN_POINTS`` phase points) a named or counted tau set
    is snapped to factors k * 2^j, 8 <= k < 16, so that long taus use stride m/16..m/8;
    explicitly listed factors are kept and use the largest admissible stride.

    ``n_terms`` is the term count of the fully overlapping estimator, N - 2m, in both modes;
    ``stride`` says which terms the fast mode actually summed.
    """
    if mode not in ("fast", "exact"):
        raise ValueError("mode must be 'fast' or 'exact'")
    arr = np.asarray(data)
    n_phase = arr.size + (1 if data_type != "phase" else 0)
    _check_length(n_phase)
    ms = tau_factors(n_phase, taus, "oadev")
    if mode == "exact" or n_phase < FAST_MIN_POINTS:
        x = _phase(arr, tau0, data_type)
        sums = _oadev_exact_sums(x, ms)
        n = x.size - 2 * ms
        tau = ms * tau0
        return DevResult("oadev", tau0, ms, tau, np.sqrt(sums / (2.0 * tau * tau * n)), n,
                         x.size, np.ones_like(ms))
    if isinstance(taus, (str, int, np.integer)):
        ms = snap_fast(ms)
        ms = ms[ms <= max_factor(n_phase, "oadev")]
    if data_type not in ("rate", "freq", "phase"):
        raise ValueError(f"data_type must be 'rate' or 'phase', not {data_type!r}")
    acc = OadevAccumulator(tau0, ms, "fast")
    add = acc.add_phase if data_type == "phase" else acc.add_rate
    acc.offset = float(arr[0]) if data_type == "phase" else float(np.mean(arr))
    step = 1 << 20
    for a in range(0, arr.size, step):
        add(arr[a: a + step])
    return acc.result()


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum a*b without BLAS (no thread pool for long vectors on a shared machine)."""
    return float(np.einsum("i,i->", a, b))


def _check_length(n_phase: int) -> None:
    if n_phase < 3:
        raise ValueError(f"need at least 3 phase points (2 rate samples), got {n_phase}")


def _second_diff(x: np.ndarray, m: int) -> np.ndarray:
    d = x[2 * m:] - x[m:-m]
    d -= x[m:-m]
    d += x[: x.size - 2 * m]
    return d


def adev(data: np.ndarray, tau0: float = 1.0, taus: TauSpec = "octave",
         data_type: str = "rate") -> DevResult:
    """Non-overlapping Allan deviation (terms at i = 0, m, 2m, ...)."""
    x = _phase(data, tau0, data_type)
    _check_length(x.size)
    ms = tau_factors(x.size, taus, "adev")
    devs, ns = [], []
    for m in ms:
        xs = x[:: m]
        d = xs[2:] - 2 * xs[1:-1] + xs[:-2]
        ns.append(d.size)
        devs.append(np.sqrt(_dot(d, d) / (2.0 * (m * tau0) ** 2 * d.size)))
    return DevResult("adev", tau0, ms, ms * tau0, np.array(devs), np.array(ns), x.size,
                     ms.copy())


def mdev(data: np.ndarray, tau0: float = 1.0, taus: TauSpec = "octave",
         data_type: str = "rate") -> DevResult:
    """Modified Allan deviation (see module docstring)."""
    x = _phase(data, tau0, data_type)
    _check_length(x.size)
    ms = tau_factors(x.size, taus, "mdev")
    devs, ns = [], []
    for m in ms:
        m = int(m)
        c = np.empty(x.size - 2 * m + 1)
        c[0] = 0.0
        np.cumsum(_second_diff(x, m), out=c[1:])
        s = c[m:] - c[:-m]
        ns.append(s.size)
        tau = m * tau0
        devs.append(np.sqrt(_dot(s, s) / (2.0 * m * m * tau * tau * s.size)))
    return DevResult("mdev", tau0, ms, ms * tau0, np.array(devs), np.array(ns), x.size,
                     np.ones_like(ms))


def tdev(data: np.ndarray, tau0: float = 1.0, taus: TauSpec = "octave",
         data_type: str = "rate") -> DevResult:
    """Time deviation TDEV = tau * MDEV / sqrt(3) (units of phase)."""
    r = mdev(data, tau0, taus, data_type)
    r.kind = "tdev"
    r.dev = r.tau_s * r.dev / np.sqrt(3.0)
    return r


def _third_diff(x: np.ndarray, m: int) -> np.ndarray:
    n = x.size - 3 * m
    return x[3 * m:] - 3.0 * x[2 * m: 2 * m + n] + 3.0 * x[m: m + n] - x[:n]


def ohdev(data: np.ndarray, tau0: float = 1.0, taus: TauSpec = "octave",
          data_type: str = "rate") -> DevResult:
    """Overlapping Hadamard deviation (see module docstring)."""
    x = _phase(data, tau0, data_type)
    _check_length(x.size)
    ms = tau_factors(x.size, taus, "ohdev")
    if K.HAVE_NUMBA:
        n = x.size - 3 * ms
        tau = ms * tau0
        dev = np.sqrt(K.diff_sums(x, ms, 3, THREADS) / (6.0 * tau * tau * n))
        return DevResult("ohdev", tau0, ms, tau, dev, n, x.size, np.ones_like(ms))
    devs, ns = [], []
    for m in ms:
        d = _third_diff(x, int(m))
        ns.append(d.size)
        devs.append(np.sqrt(_dot(d, d) / (6.0 * (m * tau0) ** 2 * d.size)))
    return DevResult("ohdev", tau0, ms, ms * tau0, np.array(devs), np.array(ns), x.size,
                     np.ones_like(ms))


def hdev(data: np.ndarray, tau0: float = 1.0, taus: TauSpec = "octave",
         data_type: str = "rate") -> DevResult:
    """Non-overlapping Hadamard deviation (every m-th term)."""
    x = _phase(data, tau0, data_type)
    _check_length(x.size)
    ms = tau_factors(x.size, taus, "hdev")
    devs, ns = [], []
    for m in ms:
        d = _third_diff(x[:: int(m)], 1)
        ns.append(d.size)
        devs.append(np.sqrt(_dot(d, d) / (6.0 * (m * tau0) ** 2 * d.size)))
    return DevResult("hdev", tau0, ms, ms * tau0, np.array(devs), np.array(ns), x.size,
                     ms.copy())


def totdev(data: np.ndarray, tau0: float = 1.0, taus: TauSpec = "octave",
           data_type: str = "rate") -> DevResult:
    """Total deviation (Howe; NIST SP 1065 eq. 25; see module docstring)."""
    x = _phase(data, tau0, data_type)
    n = x.size
    _check_length(n)
    ms = tau_factors(n, taus, "totdev")
    # extended series: reflections of n-2 points each side; index of x[0] is n-2
    head = 2.0 * x[0] - x[n - 2: 0: -1]
    tail = 2.0 * x[-1] - x[-2: 0: -1]
    xe = np.concatenate((head, x, tail))
    off = n - 2
    devs = []
    for m in ms:
        m = int(m)
        c = xe[off + 1: off + n - 1]
        d = xe[off + 1 - m: off + n - 1 - m] + xe[off + 1 + m: off + n - 1 + m] - 2.0 * c
        tau = m * tau0
        devs.append(np.sqrt(_dot(d, d) / (2.0 * tau * tau * (n - 2))))
    return DevResult("totdev", tau0, ms, ms * tau0, np.array(devs),
                     np.full(ms.size, n - 2), n, np.ones_like(ms))


DEVIATIONS = {"adev": adev, "oadev": oadev, "mdev": mdev, "tdev": tdev, "hdev": hdev,
              "ohdev": ohdev, "totdev": totdev}
