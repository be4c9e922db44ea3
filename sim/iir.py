"""The two scipy.signal operations every emulated run needs, without importing scipy.signal.

``import scipy.signal`` costs ~0.65 s of CPU per process (it pulls in scipy.stats, interpolate,
optimize, spatial, ...), and every ``rigctl run`` on the emulator, every ``rigctl sim up`` and
every resumed run imported it for two small things: the turntable's servo-error filter
(:mod:`rigctl.sim.table`: ``cont2discrete`` once per axis, ``lfilter`` on every block) and the
IMU clock's wander (:class:`rigctl.sim.effects.ClockModel`: a first-order ``lfilter``). Both
are here with scipy's own arithmetic, so the emulator's output is bit-for-bit what it was
(tests/test_sim_iir.py compares them with scipy.signal):

* :func:`lfilter`: scipy's ``lfilter`` recurrence for a 1-D signal with initial state, the
  transposed direct form II, in the operation order of scipy's C loop
  (scipy/signal/_lfilter.c)::

      y[k]     = z[0] + b[0] x[k]
      z[m]     = (z[m+1] + x[k] b[m+1]) - y[k] a[m+1]      m = 0 .. n-3
      z[n-2]   = x[k] b[n-1] - y[k] a[n-1]

  with b and a divided by a[0] and padded with zeros to the same length n. Compiled with numba
  (the ``fast`` extra; no fastmath: no reassociation, no fused multiply-add); without numba it
  is scipy's own ``lfilter`` (imported then).
* :func:`cont2discrete_zoh`: ``scipy.signal.cont2discrete((num, den), dt, method="zoh")``
  for a proper single-input transfer function: controller canonical form (``tf2ss``), the
  zero-order-hold discretisation ``[[Ad, Bd], [0, I]] = expm(dt [[A, B], [0, 0]])`` with
  scipy.linalg's ``expm`` (~0.17 s to import, against ~0.65 s for scipy.signal), and back to
  a transfer function (``ss2tf``: ``den = poly(Ad)``, ``num = poly(Ad - Bd C) + (D - 1) den``),
  the same numpy calls in the same order as scipy.

The rarer filters (the IMU front end's Butterworth low-pass, Gauss-Markov noise terms) still
import scipy.signal, when a configuration asks for them.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

try:  # the ``fast`` extra
    from rigctl.jit import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without the extra
    HAVE_NUMBA = False


if HAVE_NUMBA:
    @njit(cache=True, nogil=True)
    def _df2t(b, a, x, z, y):  # pragma: no cover - compiled
        """scipy's lfilter loop (transposed direct form II) over x, state z updated in place."""
        n = b.size
        for k in range(x.size):
            xn = x[k]
            yn = z[0] + b[0] * xn
            for m in range(n - 2):
                z[m] = z[m + 1] + xn * b[m + 1] - yn * a[m + 1]
            z[n - 2] = xn * b[n - 1] - yn * a[n - 1]
            y[k] = yn


def lfilter(b: NDArray[np.float64] | list[float], a: NDArray[np.float64] | list[float],
            x: NDArray[np.float64], zi: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``scipy.signal.lfilter(b, a, x, zi=zi)`` for a 1-D float signal x and an IIR filter
    (len(a) >= 2): (y, zf), y[k] = sum b[i] x[k-i] - sum_{i>=1} a[i] y[k-i] (a[0] = 1 after
    normalisation), zi and zf the max(len(a), len(b)) - 1 delay states. Same values, bit for
    bit, as scipy's."""
    if not HAVE_NUMBA:  # pragma: no cover - exercised only without the extra
        from scipy import signal
        return signal.lfilter(np.array(b, dtype=np.float64), np.array(a, dtype=np.float64), x, zi=zi)
    b, a = prepare(b, a)
    return lfilter_prepared(b, a, x, np.asarray(zi, dtype=np.float64).reshape(b.size - 1))


def lfilter_prepared(b: NDArray[np.float64], a: NDArray[np.float64], x: NDArray[np.float64],
                     zi: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`lfilter` for coefficients already in its normal form: b and a 1-D C-contiguous
    float64 arrays of one length n >= 2 with a[0] == 1 (as :func:`prepare` makes them), zi of n - 1
    float64 states. The same values bit for bit, without re-checking and copying the
    coefficients at every call (the emulated turntable filters a few samples per poll)."""
    if not HAVE_NUMBA:  # pragma: no cover - exercised only without the extra
        return lfilter(b, a, x, zi)
    # writeable C-contiguous float64 arrays: the one signature the cache holds (a read-only or
    # strided argument would make numba compile another, while the run clock runs)
    if not (x.dtype == np.float64 and x.ndim == 1 and x.flags.c_contiguous and x.flags.writeable
            and x.flags.aligned):
        x = np.require(x, np.float64, ["C", "A", "W"])
        if x.ndim != 1:
            raise ValueError("lfilter: x must be 1-D")
    z = np.array(zi, dtype=np.float64)
    y = np.empty_like(x)
    _df2t(b, a, x, z, y)
    return y, z


def prepare(b: NDArray[np.float64] | list[float], a: NDArray[np.float64] | list[float]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(b, a) in the form :func:`lfilter_prepared` takes: float64, padded to one length, divided
    by a[0] (what :func:`lfilter` does to them at each call; dividing by a[0] = 1 changes no bit
    and is skipped)."""
    b = np.array(b, dtype=np.float64)
    a = np.array(a, dtype=np.float64)
    if a.ndim != 1 or b.ndim != 1 or a.size < 2 or a[0] == 0.0:
        raise ValueError("lfilter: b and a must be 1-D, a of length >= 2 with a[0] != 0")
    n = max(a.size, b.size)
    if b.size != a.size or a[0] != 1.0:
        b = np.concatenate([b, np.zeros(n - b.size)]) / a[0]
        a = np.concatenate([a, np.zeros(n - a.size)]) / a[0]
    return np.ascontiguousarray(b), np.ascontiguousarray(a)


def cont2discrete_zoh(num: list[float], den: list[float], dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``scipy.signal.cont2discrete((num, den), dt, method="zoh")[:2]`` for a proper transfer
    function num(s)/den(s) (len(num) <= len(den), den of degree >= 1, num's leading coefficient
    not below 1e-14 in magnitude): the discrete (num (1, n+1), den (n+1,)) with a zero-order
    hold of step dt (s). The same numpy operations as scipy's tf2ss / zoh / ss2tf."""
    from scipy.linalg import expm

    den_a = np.atleast_1d(np.asarray(den, dtype=np.float64))
    num_a = np.atleast_2d(np.asarray(num, dtype=np.float64))
    den_a = np.trim_zeros(den_a, "f")
    num_a, den_a = num_a / den_a[0], den_a / den_a[0]  # scipy's normalize
    if num_a.shape[0] != 1 or np.all(np.abs(num_a[:, 0]) <= 1e-14):
        raise ValueError("cont2discrete_zoh: one numerator without leading zeros")
    M, K = num_a.shape[1], den_a.size
    if M > K or K < 2:
        raise ValueError("cont2discrete_zoh: a proper transfer function of degree >= 1")
    # tf2ss: controller canonical form
    num_a = np.hstack((np.zeros((1, K - M)), num_a))
    D = np.atleast_2d(num_a[:, 0])
    A = np.r_[-np.array([den_a[1:]]), np.eye(K - 2, K - 1)]
    B = np.eye(K - 1, 1)
    C = num_a[:, 1:] - np.outer(num_a[:, 0], den_a[1:])
    D = D.reshape((C.shape[0], B.shape[1]))
    # zero-order hold
    em = np.vstack((np.hstack((A, B)), np.hstack((np.zeros((1, K - 1)), np.zeros((1, 1))))))
    ms = expm(dt * em)[: K - 1, :]
    ad, bd = ms[:, 0: K - 1], ms[:, K - 1:]
    # ss2tf
    dden = np.poly(ad)
    dnum = np.empty((1, K), (ad[:, 0] + bd[:, 0] + C[0, :] + D + 0.0).dtype)
    dnum[0] = np.poly(ad - np.dot(bd, np.atleast_2d(C[0, :]))) + (D[0] - 1) * dden
    return dnum, dden
