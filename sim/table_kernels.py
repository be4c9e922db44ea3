"""Compiled per-block arithmetic of the emulated turntable's axes (the ``fast`` extra: numba), the
same floats as the numpy code of :class:`rigctl.sim.table.TableAxis` it stands in for.

Every emulator poll advances the three axes on their grid (:meth:`TableAxis.advance`: the
profile, the two servo filters, the actual motion, the in-position window, the kept history)
and reads them at the IMU's instants (:meth:`TableAxis.at`: the profile and the servo error
propagated from the grid point before): some forty numpy calls per axis on a few samples,
~0.1-0.3 ms of a poll. :func:`advance` and :func:`at` do the same operations in the same
order in one compiled call per axis, in their common case -- no jerk limit, no rate ripple,
times not before the axis' first grid point or its profile's start (the caller checks; any
other case runs the numpy code). Only IEEE additions, multiplications and divisions and
libm's cos, sin, cosh, sinh and exp (which are numpy's where numpy has no vectorised float64
versions of its own, as without AVX-512): :func:`exact` checks, once per process, that a
scripted axis (moves, rates, stops, every damping regime) gives numpy's floats bit for bit in
every output and state; where it does not, and without numba, the numpy code runs.
tests/test_sim_table_kernels.py compares them on more and shows a wrong kernel is caught.
"""
from __future__ import annotations

import functools
import math

import numpy as np

from .block_iir import HAVE_NUMBA

#: the kernels in use (tests set it False to run the numpy code)
ENABLED = True
_probing = False  # compare() runs: the kernels are on wherever ENABLED, exact() or not

if HAVE_NUMBA:
    from rigctl.jit import njit

    from .iir import _df2t

    @njit(cache=True, nogil=True)
    def _profile(t, pieces, p, v, a):  # pragma: no cover - compiled
        """Profile.evaluate(t) without times before the profile's start, into p, v, a."""
        n = t.size
        m = pieces.shape[1]
        tmin = np.inf
        for k in range(n):
            if t[k] < tmin:
                tmin = t[k]
        if n and tmin >= pieces[0, m - 1]:
            tp, pp, vp, ap = pieces[0, m - 1], pieces[1, m - 1], pieces[2, m - 1], pieces[3, m - 1]
            if vp == 0.0 and ap == 0.0:
                c0, c1 = pp + vp + 0.5 * ap, vp + ap
                for k in range(n):
                    p[k] = c0
                    v[k] = c1
                    a[k] = ap
                return
            h = 0.5 * ap
            for k in range(n):
                dt = t[k] - tp
                p[k] = pp + vp * dt + h * dt * dt
                v[k] = vp + ap * dt
                a[k] = ap
            return
        for k in range(n):
            i = np.searchsorted(pieces[0], t[k], side="right") - 1
            if i < 0:
                i = 0
            tp, pp, vp, ap = pieces[0, i], pieces[1, i], pieces[2, i], pieces[3, i]
            dt = t[k] - tp
            p[k] = pp + vp * dt + 0.5 * ap * dt * dt
            v[k] = vp + ap * dt
            a[k] = ap

    @njit(cache=True, nogil=True)
    def _advance(t, pieces, b_e, a_e, zi_e, b_de, a_de, zi_de, c2zwn, wn2, hist, mode, target, window,
                 x, w, acc):  # pragma: no cover - compiled
        """TableAxis.advance's common case: x, w, acc filled, the filters' states (zi_e, zi_de)
        carried in place; returns the new history (hist with the rows t, e, de, a, 0 appended),
        the index of the last sample outside the window (-1: none), whether the last is inside,
        and whether the new rows are quiet (table._quiet)."""
        n = t.size
        p, v, a = np.empty(n), np.empty(n), np.empty(n)
        _profile(t, pieces, p, v, a)
        e, de = np.empty(n), np.empty(n)
        _df2t(b_e, a_e, a, zi_e, e)
        _df2t(b_de, a_de, a, zi_de, de)
        m = hist.shape[1]
        out = np.empty((5, m + n))
        out[:, :m] = hist
        last_out = -1
        inside = False
        quiet = True
        for k in range(n):
            x[k] = p[k] + e[k]
            w[k] = v[k] + de[k]
            acc[k] = -c2zwn * de[k] - wn2 * e[k]
            if mode == 1:
                inside = abs(x[k] - target) <= window
            elif mode == 2:
                inside = abs(w[k] - target) <= window
            else:
                inside = abs(w[k]) <= window
            if not inside:
                last_out = k
            if e[k] != 0.0 or de[k] != 0.0 or a[k] != 0.0 or math.copysign(1.0, e[k]) < 0.0 \
                    or math.copysign(1.0, de[k]) < 0.0:
                quiet = False
            out[0, m + k] = t[k]
            out[1, m + k] = e[k]
            out[2, m + k] = de[k]
            out[3, m + k] = a[k]
            out[4, m + k] = 0.0
        return out, last_out, inside, quiet

    @njit(cache=True, nogil=True)
    def _at(t, pieces, hist, eps, c2zwn, wn2, sig, om, regime, x, w, acc):  # pragma: no cover - compiled
        """TableAxis.at's common case (no ripple, no time before the first grid point or the
        profile's start): x, w, acc filled; the servo error propagated as _propagate."""
        n = t.size
        p, v, a = np.empty(n), np.empty(n), np.empty(n)
        _profile(t, pieces, p, v, a)
        h0 = hist[0]
        for k in range(n):
            j = np.searchsorted(h0, t[k] + eps, side="right") - 1
            if j < 0:
                j = 0
            tj, e0, de0, u = hist[0, j], hist[1, j], hist[2, j], hist[3, j]
            d = t[k] - tj
            e, de = e0, de0
            if d != 0.0 and (e0 != 0.0 or de0 != 0.0 or u != 0.0):
                estar = -u / wn2
                E, D = e0 - estar, de0
                if regime == 0:
                    C, S = math.cos(om * d), math.sin(om * d) / om
                elif regime == 1:
                    C, S = math.cosh(om * d), math.sinh(om * d) / om
                else:
                    C, S = 1.0, d
                ex = math.exp(-sig * d)
                e = estar + ex * (C * E + S * (sig * E + D))
                de = ex * (C * D - S * (wn2 * E + sig * D))
            x[k] = p[k] + e
            w[k] = v[k] + de
            acc[k] = -c2zwn * de - wn2 * e


def _regime(axis) -> tuple[float, float, float, int]:
    """(sig, om, wn2, regime) of the axis' servo as TableAxis._propagate computes them."""
    wn2 = axis._wn2
    sig = 0.5 * axis._2zwn
    z = axis.servo.damping
    if z < 1.0:
        return sig, math.sqrt(wn2) * math.sqrt(1.0 - z * z), wn2, 0
    if z > 1.0:
        return sig, math.sqrt(wn2) * math.sqrt(z * z - 1.0), wn2, 1
    return sig, 1.0, wn2, 2


def advance(axis, t: np.ndarray):
    """:func:`_advance` for ``axis`` (a TableAxis in the common case) on the grid ``t``: x, w,
    acc and the kernel's bookkeeping (see TableAxis.advance)."""
    n = t.size
    x, w, acc = np.empty(n), np.empty(n), np.empty(n)
    sv = axis.servo
    window = sv.in_position_window if axis.mode == 1 else sv.at_rate_window
    b_e, a_e = axis._f_e
    b_de, a_de = axis._f_de
    zi_e, zi_de = np.array(axis._zi_e, dtype=np.float64), np.array(axis._zi_de, dtype=np.float64)
    hist, last_out, inside, quiet = _advance(
        np.ascontiguousarray(t, dtype=np.float64), axis.profile._arrays(), b_e, a_e, zi_e, b_de, a_de, zi_de,
        float(axis._2zwn), float(axis._wn2), axis._hist, int(axis.mode), float(axis.target), float(window),
        x, w, acc)
    return x, w, acc, zi_e, zi_de, hist, last_out, inside, quiet


def at(axis, t: np.ndarray):
    """:func:`_at` for ``axis`` (a TableAxis in the common case) at times ``t``: x, w, acc."""
    n = t.size
    x, w, acc = np.empty(n), np.empty(n), np.empty(n)
    sig, om, wn2, regime = axis.__dict__.get("_regime") or axis.__dict__.setdefault("_regime", _regime(axis))
    _at(np.ascontiguousarray(t, dtype=np.float64), axis.profile._arrays(), axis._hist, 1e-9 * axis.dt,
        float(axis._2zwn), wn2, sig, om, regime, x, w, acc)
    return x, w, acc


OFF, POSITION, RATE = 0, 1, 2  # rigctl.sim.table's modes


def compare(axis_type, seed: int = 20261128, blocks: int = 16) -> bool:
    """Scripted axes of ``axis_type`` (TableAxis; each damping regime; moves, rates, stops and
    rests; blocks of 1 to 40 grid points; reads at the grid, between and just past it) run with
    the kernels and with the numpy code: every output and state equal bit for bit."""
    global ENABLED, _probing
    dt = 0.001
    same = True
    was = ENABLED
    _probing = True
    try:
        for z in (0.6, 1.0, 1.7):
            axes = [(use, axis_type.probe(4.7, z, dt)) for use in (True, False)]
            k = 0
            script = np.random.default_rng(seed + int(z * 10))
            for b in range(blocks):
                n = int(script.integers(1, 41))
                t = (k + np.arange(n)) * dt
                k += n
                cmd = script.random()
                tc = float(t[0])
                q = script.uniform(-1, 1) * 3 if cmd < 0.3 else None
                outs = []
                for use, ax in axes:
                    ENABLED = use
                    if cmd < 0.15:
                        ax.command(tc, POSITION, q)
                    elif cmd < 0.22:
                        ax.command(tc, RATE, q)
                    elif cmd < 0.26:
                        ax.command(tc, OFF, 0.0)
                    r = ax.advance(t)
                    ts = np.concatenate([t, t - 0.37 * dt, t + 0.5 * dt, [t[-1] + dt]])
                    ts = ts[ts >= max(ax._t_first, ax.profile.t[0], ax._hist[0, 0])]
                    ra = ax.at(ts)
                    ax.forget_before(float(t[max(0, n - 3)]))
                    outs.append(b"".join(np.ascontiguousarray(y).tobytes() for y in (*r, *ra, ax._hist, ax._zi_e, ax._zi_de))
                                + repr((ax.last, ax.last_t, ax.in_window_since, ax._hist_quiet)).encode())
                same &= outs[0] == outs[1]
    finally:
        ENABLED, _probing = was, False
    return bool(same)


@functools.lru_cache(maxsize=4)
def exact(axis_type) -> bool:
    """Whether the kernels give numpy's floats here for ``axis_type`` (TableAxis; module
    docstring); False without numba."""
    if not HAVE_NUMBA:
        return False
    try:
        return compare(axis_type)
    except Exception:  # pragma: no cover - a kernel that cannot run here: the numpy code runs
        return False


#: calls of :func:`on` before the kernels are loaded and probed (~0.1-0.2 s of CPU, numba's
#: cache included): a short session (a few hundred polls) never pays it, a long one saves that
#: many times over (~0.1 ms per call)
WARM_UP_CALLS = 2000
_calls = [0]


def on(axis_type) -> bool:
    """The kernels run (TableAxis asks at each call): after :data:`WARM_UP_CALLS` calls, where
    :func:`exact` (probed once) finds them numpy's."""
    if _probing:
        return ENABLED
    if _calls[0] < WARM_UP_CALLS:
        _calls[0] += 1
        return False
    return ENABLED and exact(axis_type)
