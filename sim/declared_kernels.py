"""Compiled per-block arithmetic of the declared IMU model (the ``fast`` extra: numba), the same
floats as the numpy code it stands in for.

The emulator's declared model (:meth:`rigctl.sim.world.SimWorld._declared_until`) makes every
IMU block from the table's angles and rates with :func:`rigctl.frames.body_references` and
:meth:`rigctl.sim.imu.DeclaredImuModel.apply`: some sixty numpy calls on (n, 3) arrays, and a
BLAS call per sample for the stacked 3 x 3 products -- ~0.3-0.5 ms per block of 5-200 samples,
most of a virtual-time run's CPU. The kernels here do the same operations in the same order in
one compiled pass per block:

* :func:`body_references`: the rotations' cos and sin (libm's, numpy's own where numpy has no
  vectorised float64 sin/cos, as without AVX-512), ``R_z R_y`` (single products), ``(R_z R_y)
  R_x`` as the BLAS kernel forms each element (fused multiply-adds over k = 0, 1, 2 from +0.0,
  then ``1.0 acc + 0.0``), ``C^T (0, 0, g)`` and ``C^T Omega`` as numpy's loop (plain
  multiply-add from 0.0), and the gimbal rates' two einsums (products left to right, summed in
  index order);
* :func:`declared_deterministic`: the model's bias + matrix + quadratic terms and its thermal
  errors (``x @ M.T`` as BLAS' gemm: fused multiply-adds over k from +0.0, then ``1.0 acc +
  0.0``), in apply's order of additions.

Which operations numpy and its BLAS fuse is a property of the build and of the CPU (OpenBLAS
picks its kernels at run time), so the kernels are used only where :func:`exact` -- run once
per process, on a few thousand rows of generic and special values (signed zeros, quarter
turns, tiny angles) for several block lengths -- finds them equal to the numpy code bit for
bit; anywhere else, and without numba, the numpy code runs. Blocks of one sample (BLAS takes
another path for a 1 x 3 product) always take the numpy code. tests/test_sim_declared_kernels.py
compares them on more values and shows that a kernel with another summation order is caught.
"""
from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import NDArray

from .block_iir import HAVE_NUMBA

if HAVE_NUMBA:
    from llvmlite import ir
    from numba import types
    from numba.extending import intrinsic

    from rigctl.jit import njit

    @intrinsic
    def _fma(typingctx, a, b, c):  # pragma: no cover - compiled
        """round(a b + c) once (llvm.fma: the CPU's fused multiply-add)."""
        sig = types.float64(types.float64, types.float64, types.float64)

        def codegen(context, builder, signature, args):
            d = ir.DoubleType()
            fn = builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d]))
            return builder.call(fn, args)
        return sig, codegen

    @njit(cache=True, nogil=True)
    def _gemm3(X, Y, out):  # pragma: no cover - compiled
        """out = X @ Y for 3 x 3 C-contiguous matrices as BLAS forms each element."""
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for q in range(3):
                    acc = _fma(X[i, q], Y[q, j], acc)
                out[i, j] = acc * 1.0 + 0.0

    @njit(cache=True, nogil=True)
    def _inner_gimbals(a1, a2, Ry, Rx):  # pragma: no cover - compiled
        """Ry = R_y(a1), Rx = R_x(a2) (frames' rotation matrices; the zeros already in place)."""
        c, s = math.cos(a1), math.sin(a1)
        Ry[1, 1] = 1.0
        Ry[2, 2] = c
        Ry[2, 0] = -s
        Ry[0, 2] = s
        Ry[0, 0] = c
        c, s = math.cos(a2), math.sin(a2)
        Rx[0, 0] = 1.0
        Rx[1, 1] = c
        Rx[1, 2] = -s
        Rx[2, 1] = s
        Rx[2, 2] = c

    @njit(cache=True, nogil=True)
    def _gimbal_rate_row(Rx, Ry, r0, r1, r2, i):  # pragma: no cover - compiled
        """Component i of gimbal_rate_body: sum_jk Rx^T[i, j] Ry^T[j, k] (0, 0, r0)[k]
        + sum_j Rx^T[i, j] (0, r1, 0)[j] + (r2, 0, 0)[i] (numpy's einsums: products left to
        right, summed in index order from 0.0)."""
        e3 = 0.0
        for j in range(3):
            for k in range(3):
                e3 += Rx[j, i] * Ry[k, j] * (r0 if k == 2 else 0.0)
        e2 = 0.0
        for j in range(3):
            e2 += Rx[j, i] * (r1 if j == 1 else 0.0)
        return e3 + e2 + (r2 if i == 0 else 0.0)

    @njit(cache=True, nogil=True)
    def _gravity_earth_rate(C, g, w_site, i):  # pragma: no cover - compiled
        """Component i of C^T (0, 0, g) and of C^T Omega (numpy's loop: multiply-adds from 0.0)."""
        f = 0.0
        f += C[0, i] * 0.0
        f += C[1, i] * 0.0
        f += C[2, i] * g
        w = 0.0
        for q in range(3):
            w += C[q, i] * w_site[q]
        return f, w

    @njit(cache=True, nogil=True)
    def _body_references(ang, rates, g, w_site, f_out, w_out):  # pragma: no cover - compiled
        """frames.body_references(ang, rates, ...) row by row (module docstring)."""
        P = np.empty((3, 3))
        D = np.empty((3, 3))
        Rz = np.zeros((3, 3))
        Ry = np.zeros((3, 3))
        Rx = np.zeros((3, 3))
        for r in range(ang.shape[0]):
            c, s = math.cos(ang[r, 0]), math.sin(ang[r, 0])
            Rz[2, 2] = 1.0
            Rz[0, 0] = c
            Rz[0, 1] = -s
            Rz[1, 0] = s
            Rz[1, 1] = c
            _inner_gimbals(ang[r, 1], ang[r, 2], Ry, Rx)
            for i in range(3):
                for j in range(3):
                    acc = 0.0
                    for k in range(3):
                        acc += Rz[i, k] * Ry[k, j]
                    P[i, j] = acc
            _gemm3(P, Rx, D)
            r0, r1, r2 = rates[r, 0], rates[r, 1], rates[r, 2]
            for i in range(3):
                f_out[r, i], w = _gravity_earth_rate(D, g, w_site, i)
                w_out[r, i] = w + _gimbal_rate_row(Rx, Ry, r0, r1, r2, i)

    @njit(cache=True, nogil=True)
    def _gimbal_rate_body(ang, rates, out):  # pragma: no cover - compiled
        """frames.gimbal_rate_body(ang, rates) row by row (as in _body_references)."""
        Ry = np.zeros((3, 3))
        Rx = np.zeros((3, 3))
        for r in range(ang.shape[0]):
            _inner_gimbals(ang[r, 1], ang[r, 2], Ry, Rx)
            r0, r1, r2 = rates[r, 0], rates[r, 1], rates[r, 2]
            for i in range(3):
                out[r, i] = _gimbal_rate_row(Rx, Ry, r0, r1, r2, i)

    @njit(cache=True, nogil=True)
    def _table_body_references(ang, rates, ax, base, Ks, KKs, g, w_site, f_out, w_out):  # pragma: no cover
        """effects.table_body_references(ang, rates, ...) row by row: each axis' Rodrigues
        rotation (EYE + sin(a) K + (1 - cos(a)) K^2), C = ((base R_o) R_m) R_i as BLAS' gemm,
        the table rate's einsums (summed in index order from 0.0), C^T (0, 0, g) and C^T Omega as
        numpy's loop."""
        R = np.empty((3, 3, 3))
        A = np.empty((3, 3))
        B = np.empty((3, 3))
        C = np.empty((3, 3))
        u = np.empty(3)
        for r in range(ang.shape[0]):
            for k in range(3):
                s = math.sin(ang[r, k])
                c1 = 1.0 - math.cos(ang[r, k])
                for i in range(3):
                    for j in range(3):
                        R[k, i, j] = ((1.0 if i == j else 0.0) + s * Ks[k, i, j]) + c1 * KKs[k, i, j]
            _gemm3(base, R[0], A)
            _gemm3(A, R[1], B)
            _gemm3(B, R[2], C)
            r0, r1, r2 = rates[r, 0], rates[r, 1], rates[r, 2]
            for i in range(3):  # u = R_m^T (r0 a_o)
                acc = 0.0
                for j in range(3):
                    acc += R[1, j, i] * (r0 * ax[0, j])
                u[i] = acc
            for i in range(3):
                e1 = 0.0
                for j in range(3):
                    e1 += R[2, j, i] * u[j]
                e2 = 0.0
                for j in range(3):
                    e2 += R[2, j, i] * (r1 * ax[1, j])
                wt = (e1 + e2) + r2 * ax[2, i]
                f_out[r, i], w = _gravity_earth_rate(C, g, w_site, i)
                w_out[r, i] = w + wt

    @njit(cache=True, nogil=True)
    def _gemm_t(x, M, r, i):  # pragma: no cover - compiled
        """(x @ M.T)[r, i] as BLAS' gemm forms it."""
        acc = 0.0
        for k in range(3):
            acc = _fma(x[r, k], M[i, k], acc)
        return acc * 1.0 + 0.0

    @njit(cache=True, nogil=True)
    def _thermal(x, dT, H, R, terms, r, i):  # pragma: no cover - compiled
        """ThermalErrors.error(sensor, x, T, H, R)[r, i] (dT = T - reference); terms: the
        sensor's row of :func:`_thermal_terms`."""
        out = 0.0
        p = 1.0
        for j in range(2):
            p = p * dT[r]
            if terms[36 + j] != 0.0:
                acc = 0.0  # (x @ M_j.T)[r, i] as _gemm_t
                for k in range(3):
                    acc = _fma(x[r, k], terms[6 + 9 * j + 3 * i + k], acc)
                out += p * (terms[3 * j + i] + (acc * 1.0 + 0.0))
        if terms[38] != 0.0:
            out += H[r] * terms[24 + i]
        if terms[39] != 0.0:
            out += R[r] * terms[27 + i]
        return out

    @njit(cache=True, nogil=True)
    def _deterministic(f_true, w_true, dHR, par, th, out):  # pragma: no cover - compiled
        """out[0] = f, out[1] = w of DeclaredImuModel.deterministic_numpy; par: :func:`_params`;
        th: :func:`_thermal_terms` (no rows: no thermal errors); dHR: rows T - reference, H, R."""
        a_bias, a_mat, a_quad = par[0:3], par[3:12].reshape(3, 3), par[12:15]
        g_bias, g_mat = par[15:18], par[18:27].reshape(3, 3)
        thermal_on = th.shape[0] == 2
        dT, H, R = dHR[0], dHR[1], dHR[2]
        ta = th[0] if thermal_on else par
        tg = th[1] if thermal_on else par
        for r in range(f_true.shape[0]):
            for i in range(3):
                x = f_true[r, i]
                f = (a_bias[i] + _gemm_t(f_true, a_mat, r, i)) + a_quad[i] * (x * x)
                w = g_bias[i] + _gemm_t(w_true, g_mat, r, i)
                if thermal_on:
                    f = f + _thermal(f_true, dT, H, R, ta, r, i)
                    w = w + _thermal(w_true, dT, H, R, tg, r, i)
                out[0, r, i] = f
                out[1, r, i] = w


def body_references(ang: NDArray[np.float64], rates: NDArray[np.float64], g: float,
                    w_site: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`rigctl.frames.body_references` of (n, 3) C-contiguous float64 angles and gimbal
    rates at a site of gravity ``g`` and Earth rate ``w_site`` (ENU, (3,)): (f_b, w_b)."""
    n = ang.shape[0]
    f_out, w_out = np.empty((n, 3)), np.empty((n, 3))
    _body_references(np.ascontiguousarray(ang, dtype=np.float64), np.ascontiguousarray(rates, dtype=np.float64),
                     float(g), np.ascontiguousarray(w_site, dtype=np.float64), f_out, w_out)
    return f_out, w_out


def gimbal_rate_body(ang: NDArray[np.float64], rates: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`rigctl.frames.gimbal_rate_body` of (n, 3) angles and gimbal rates (or accelerations)."""
    out = np.empty((ang.shape[0], 3))
    _gimbal_rate_body(np.ascontiguousarray(ang, dtype=np.float64), np.ascontiguousarray(rates, dtype=np.float64), out)
    return out


def table_body_references(ang: NDArray[np.float64], rates: NDArray[np.float64], latitude_rad: float, g: float,
                          nonorth_rad=(0.0, 0.0, 0.0), level_x_rad: float = 0.0, level_y_rad: float = 0.0,
                          north_rad: float = 0.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`rigctl.sim.effects.table_body_references` of (n, 3) angles and gimbal rates (the same
    arguments): (f_b, w_b)."""
    from rigctl.frames import earth_rate_enu

    from .effects import _rodrigues_terms, _table_frames

    key = (tuple(float(v) for v in nonorth_rad), float(level_x_rad), float(level_y_rad), float(north_rad))
    frames = _TABLE_FRAMES.get(key)
    if frames is None:
        ax, base = _table_frames(np.array([*key[0], *key[1:]], dtype=float).tobytes())
        terms = [_rodrigues_terms(np.ascontiguousarray(ax[k], dtype=float).tobytes()) for k in range(3)]
        frames = _TABLE_FRAMES[key] = (np.ascontiguousarray(ax), np.ascontiguousarray(base),
                                       np.array([t[0] for t in terms]), np.array([t[1] for t in terms]))
    n = ang.shape[0]
    f_out, w_out = np.empty((n, 3)), np.empty((n, 3))
    _table_body_references(np.ascontiguousarray(ang, dtype=np.float64), np.ascontiguousarray(rates, dtype=np.float64),
                           *frames, float(g), earth_rate_enu(latitude_rad), f_out, w_out)
    return f_out, w_out


_TABLE_FRAMES: dict = {}


def _thermal_terms(thermal) -> NDArray[np.float64]:
    """(2, 40): per sensor (accel, gyro) the bias coefficients per K and K^2 (6), the matrices
    per K and K^2 (18), hysteresis (3) and rate (3) coefficients, 6 zeros, then 1.0 / 0.0 for
    the K term, the K^2 term, hysteresis and rate being non-zero (ThermalErrors._nonzero)."""
    rows = np.zeros((2, 40))
    for k, sensor in enumerate(("accel", "gyro")):
        poly_on, hyst_on, rate_on = thermal._nonzero[sensor]
        (b1, M1), (b2, M2) = thermal.poly[sensor]
        rows[k, :36] = np.concatenate([b1, b2, np.ravel(M1), np.ravel(M2), thermal.hyst[sensor],
                                       thermal.rate[sensor], np.zeros(6)])
        rows[k, 36:] = [float(poly_on[0]), float(poly_on[1]), float(hyst_on), float(rate_on)]
    return rows


_NO_THERMAL = np.zeros((0, 40))


def declared_deterministic(model, f_true: NDArray, w_true: NDArray, T: NDArray, H: NDArray | None,
                           R: NDArray | None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The deterministic part of :meth:`DeclaredImuModel.apply` (before its noise): (f, w) (n, 3)
    -- bias and turn-on bias, matrix, quadratic term and, when ``model.thermal`` is active, the
    thermal errors at temperature T (n,) with hysteresis H and temperature rate R (None: 0), as
    :meth:`DeclaredImuModel.deterministic_numpy`."""
    n = f_true.shape[0]
    th = model.thermal
    dHR = np.zeros((3, n))
    if th is not None and th.active:
        if len(th.poly["accel"]) != 2 or len(th.poly["gyro"]) != 2:  # pragma: no cover - K and K^2 only
            return model.deterministic_numpy(f_true, w_true, T, H, R)
        cached = th.__dict__.get("_kernel_terms")
        if cached is None:
            cached = th._kernel_terms = _thermal_terms(th)
        terms = cached
        np.subtract(T, th.reference_c, out=dHR[0])
        if H is not None:
            dHR[1] = H
        if R is not None:
            dHR[2] = R
    else:
        terms = _NO_THERMAL
    par = np.concatenate([model.accel_bias + model.turn_on_accel, np.ravel(model.accel_matrix),
                          model.accel_quadratic, model.gyro_bias + model.turn_on_gyro,
                          np.ravel(model.gyro_matrix)]).astype(np.float64, copy=False)
    out = np.empty((2, n, 3))
    _deterministic(np.ascontiguousarray(f_true, dtype=np.float64), np.ascontiguousarray(w_true, dtype=np.float64),
                   dHR, par, terms, out)
    return out[0], out[1]


def _probe_inputs(rng: np.random.Generator, n: int) -> tuple[NDArray, NDArray]:
    """Angles and rates (n, 3): generic values with a share of special ones."""
    special_ang = np.array([0.0, -0.0, math.pi / 2, -math.pi / 2, math.pi, math.pi / 4, 1e-300, 2 * math.pi, 1e-9])
    special_rate = np.array([0.0, -0.0, 1e-310, -1.0, 1e-12, 5.0])
    ang = np.where(rng.random((n, 3)) < 0.35, rng.choice(special_ang, (n, 3)), rng.uniform(-7.0, 7.0, (n, 3)))
    rates = np.where(rng.random((n, 3)) < 0.35, rng.choice(special_rate, (n, 3)), rng.normal(size=(n, 3)))
    return ang, rates


def compare(model, lengths: tuple[int, ...] = (2, 3, 5, 8, 50, 257), seed: int = 20261128,
            body=None, deterministic=None, table_refs=None) -> bool:
    """The kernels (or the ``body`` / ``deterministic`` / ``table_refs`` functions given) equal to
    the numpy code bit for bit on probe inputs of each block length: body references at a generic
    site, the gimbal rates in the body frame, the profile model's table references (a perfect
    table and one with axis, levelling and north errors), and the deterministic part of ``model``
    with temperatures around its thermal reference."""
    from rigctl.frames import _earth_rate_cached, _normal_gravity_cached
    from rigctl.frames import body_references as numpy_body_references
    from rigctl.frames import gimbal_rate_body as numpy_gimbal_rate_body

    from .effects import table_body_references as numpy_table_body_references

    body = body or body_references
    table_refs = table_refs or table_body_references
    deterministic = deterministic or declared_deterministic
    rng = np.random.default_rng(seed)
    lat, h = 0.7853981633974483, 100.0
    g, w_site = _normal_gravity_cached(lat, h), _earth_rate_cached(lat)
    same = True
    for n in lengths:
        ang, rates = _probe_inputs(rng, n)
        f0, w0 = numpy_body_references(ang, rates, lat, h, None)
        f1, w1 = body(ang, rates, g, w_site)
        same &= f0.tobytes() == f1.tobytes() and w0.tobytes() == w1.tobytes()
        same &= numpy_gimbal_rate_body(ang, rates).tobytes() == gimbal_rate_body(ang, rates).tobytes()
        for geometry in ({}, {"nonorth_rad": [1e-4, -2e-4, 3e-4], "level_x_rad": 1e-4, "level_y_rad": -5e-5,
                              "north_rad": 2e-3}):
            f0, w0 = numpy_table_body_references(ang, rates, lat, g, **geometry)
            f1, w1 = table_refs(ang, rates, lat, g, **geometry)
            same &= f0.tobytes() == f1.tobytes() and w0.tobytes() == w1.tobytes()
        f0, w0 = numpy_body_references(ang, rates, lat, h, None)
        ref = getattr(getattr(model, "thermal", None), "reference_c", 25.0)
        T = ref + np.where(rng.random(n) < 0.2, 0.0, rng.normal(0.0, 20.0, n))
        H, R = rng.uniform(-1.0, 1.0, n), rng.normal(0.0, 0.01, n)
        f_true, w_true = f0 * np.where(rng.random((n, 3)) < 0.1, 0.0, 1.0), w0 * 1e3
        fa, wa = model.deterministic_numpy(f_true, w_true, T, H, R)
        fb, wb = deterministic(model, f_true, w_true, T, H, R)
        same &= fa.tobytes() == fb.tobytes() and wa.tobytes() == wb.tobytes()
    return bool(same)


def probe_model(model_type):
    """A ``model_type`` (DeclaredImuModel) with every deterministic term non-zero, thermal
    hysteresis and rate terms and turn-on biases included, for :func:`exact`."""
    from .thermal_imu import HysteresisSettings, RateSettings, ThermalErrors, ThermalSettings

    thermal = ThermalSettings(
        reference_c=25.0, accel_bias_mg_per_K=(0.05, -0.03, 0.04), accel_bias_mg_per_K2=(0.001, 0.0005, -0.0008),
        accel_scale_ppm_per_K=(30.0, -20.0, 25.0), accel_scale_ppm_per_K2=(0.5, 0.3, -0.4),
        accel_misalignment_urad_per_K=((0.0, 2.0, -1.5), (1.0, 0.0, 2.5), (-2.0, 1.5, 0.0)),
        gyro_bias_deg_h_per_K=(2.0, -1.5, 1.0), gyro_bias_deg_h_per_K2=(0.02, 0.01, -0.015),
        gyro_scale_ppm_per_K=(50.0, -40.0, 30.0), gyro_scale_ppm_per_K2=(0.5, 0.4, -0.3),
        gyro_misalignment_urad_per_K=((0.0, 3.0, -2.0), (2.0, 0.0, 3.0), (-3.0, 2.0, 0.0)),
        hysteresis=HysteresisSettings(width_K=2.0, accel_bias_mg=(0.01, -0.02, 0.03), gyro_bias_deg_h=(0.5, -0.4, 0.3)),
        rate=RateSettings(accel_bias_mg_per_K_per_min=(0.01, 0.02, -0.01), gyro_bias_deg_h_per_K_per_min=(0.2, -0.1, 0.3)))
    mis = np.array([[0.0, 500e-6, -300e-6], [200e-6, 0.0, 400e-6], [-600e-6, 100e-6, 0.0]])
    model = model_type(rate_hz=100.0, accel_bias=np.array([0.0196, -0.0147, 0.0294]),
                       accel_matrix=np.eye(3) + np.diag([800e-6, -500e-6, 300e-6]) + mis,
                       accel_quadratic=np.array([5.1e-6, -3.1e-6, 4.1e-6]),
                       gyro_bias=np.array([9.7e-5, -7.3e-5, 4.8e-5]),
                       gyro_matrix=np.eye(3) + np.diag([1000e-6, -700e-6, 500e-6]) + mis.T * 1.3,
                       thermal=ThermalErrors(thermal), seed=1)
    model.turn_on_accel, model.turn_on_gyro = np.array([1e-3, -2e-3, 0.0]), np.array([1e-6, 0.0, -3e-6])
    return model


#: calls of :func:`ready` before the kernels are loaded and probed (~0.1 s of CPU, numba's cache
#: included): a short session never pays it, a long one saves that many times over
WARM_UP_CALLS = 600
_calls = [0]


def ready(model_type) -> bool:
    """Whether to use the kernels now for a ``model_type`` (DeclaredImuModel) model (the emulator
    asks at each block): after :data:`WARM_UP_CALLS` calls, where :func:`exact` (probed once)
    finds them numpy's."""
    if _calls[0] < WARM_UP_CALLS:
        _calls[0] += 1
        return False
    return exact(model_type)


@functools.lru_cache(maxsize=4)
def exact(model_type) -> bool:
    """Whether the kernels give numpy's floats here (module docstring) for ``model_type``
    (DeclaredImuModel); False without numba."""
    if not HAVE_NUMBA:
        return False
    try:
        return compare(probe_model(model_type))
    except Exception:  # pragma: no cover - a kernel that cannot run here: the numpy code runs
        return False
