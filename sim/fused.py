"""The error model's internal-rate work in one compiled pass (numba, the ``fast`` extra).

:meth:`rigctl.sim.error_model.ImuErrorModel.apply` does, per internal-rate sample, the lever
arm, vibration, declared errors, thermal errors, scale asymmetry, gyro nonlinearity and
g-sensitivity (:mod:`rigctl.sim.effects`), then the front end's Butterworth low-pass and the
decimation (:mod:`rigctl.sim.frontend`). In numpy that is some forty passes over (n, 3) arrays
with temporaries; here it is one loop over the samples that keeps a sample's six axes in
registers, runs the low-pass sections (scipy's sosfilt recurrence, transposed direct form II,
same operation order) and stores only every L-th sample. Each expression is written in the
order numpy evaluates it (no ``fastmath``: no reassociation, no fused multiply-add), so the
result equals the numpy path up to the last bits of sin/cos/expm1 (libm versus numpy's SIMD
versions). State carried across calls: the previous (t, w) of dw/dt and the filter state, both
owned by the caller's objects, so chunking does not change the output.
"""
from __future__ import annotations

import numpy as np

try:
    from rigctl.jit import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without the extra
    HAVE_NUMBA = False

# Taylor coefficients of sin x / x and cos x in x^2, |x| <= pi/4: truncation below 2e-17
_SIN_C = tuple((-1.0) ** k / float(np.prod(np.arange(1, 2 * k + 2))) for k in range(8))
_COS_C = tuple((-1.0) ** k / float(np.prod(np.arange(1, 2 * k + 1))) for k in range(9))

#: internal samples per block of passes (a few kB per array: stays in L1/L2)
_BLOCK = 1024

if HAVE_NUMBA:
    _S0, _S1, _S2, _S3, _S4, _S5, _S6, _S7 = _SIN_C
    _C0, _C1, _C2, _C3, _C4, _C5, _C6, _C7, _C8 = _COS_C

    @njit(cache=True, nogil=True, error_model="numpy")
    def _sincos_cycles(f, t, s_out, c_out):  # pragma: no cover - compiled
        """s_out[i], c_out[i] = sin, cos of 2 pi frac(f t[i]): the fraction of a cycle is split
        into a quarter turn q = round(4u) and r = u - q/4 in [-1/8, 1/8] (exact), sin and cos of
        x = 2 pi r by their Taylor series to x^15 / x^16 (error below 2e-17), rotated by q.
        Branch-free, so the loop is vectorised (libm's sin and cos cost ~25 ns per call here).
        Differs from sin(2 pi u) computed in double by the rounding of 2 pi r (~1e-16)."""
        two_pi = 2.0 * np.pi
        for i in range(t.size):
            u = f * t[i]
            u -= np.floor(u)
            q = np.floor(4.0 * u + 0.5)
            x = two_pi * (u - 0.25 * q)
            x2 = x * x
            sn = x * (_S0 + x2 * (_S1 + x2 * (_S2 + x2 * (_S3 + x2 * (_S4 + x2 * (
                _S5 + x2 * (_S6 + x2 * _S7)))))))
            cs = _C0 + x2 * (_C1 + x2 * (_C2 + x2 * (_C3 + x2 * (_C4 + x2 * (_C5 + x2 * (
                _C6 + x2 * (_C7 + x2 * _C8)))))))
            qi = int(q) & 3
            sw = (qi & 1) == 1
            a = cs if sw else sn  # quarter turns: (s, c) -> (c, -s) -> (-s, -c) -> (-c, s)
            b = sn if sw else cs
            s_out[i] = -a if qi >= 2 else a
            c_out[i] = -b if (qi == 1 or qi == 2) else b

    @njit(cache=True, nogil=True, error_model="numpy")
    def _vibration(t, vib_f, vib_fa, vib_fb, vib_wa, vib_wb, vib_fon, vib_won, fv, wv, s, c
                   ):  # pragma: no cover - compiled
        """fv, wv (n, 3) = sum_k sin(2 pi f_k t) a_k + cos(2 pi f_k t) b_k (k ascending, the
        terms with zero amplitude skipped, as sim.effects.vibration_many). s, c: (K, >= n)."""
        n = t.size
        nk = vib_f.size
        for k in range(nk):
            _sincos_cycles(vib_f[k], t, s[k, :n], c[k, :n])
        for ax in range(3):
            for i in range(n):
                fv[i, ax] = 0.0
                wv[i, ax] = 0.0
            for k in range(nk):
                if vib_fon[k, ax]:
                    fa = vib_fa[k, ax]
                    fb = vib_fb[k, ax]
                    sk = s[k]
                    ck = c[k]
                    for i in range(n):
                        fv[i, ax] += sk[i] * fa + ck[i] * fb
                if vib_won[k, ax]:
                    wa = vib_wa[k, ax]
                    wb = vib_wb[k, ax]
                    sk = s[k]
                    ck = c[k]
                    for i in range(n):
                        wv[i, ax] += sk[i] * wa + ck[i] * wb

    @njit(cache=True, nogil=True, error_model="numpy")
    def _internal(t, f_true, w_true, T, dw_given, flags, prev_tw, r_lever, vib_f, vib_fa, vib_fb,
                  vib_wa, vib_wb, vib_fon, vib_won, a_bias, a_M, a_k2, g_bias, g_M, T_ref, wu_ab,
                  wu_as, wu_gb, wu_gs, asym_h, nl_k2, nl_k3, gs_G, gs_A, sos_a, zi_a, sos_g, zi_g,
                  L, out_f, out_w):  # pragma: no cover - compiled
        """flags: lever, lever with given dw, vibration, warmup, asym, nonlin, gsens, gsens_A,
        filter_a, filter_g. prev_tw: (t, w0, w1, w2) of the previous sample (dw/dt)."""
        n = t.size
        lever, dw_in, vib, warm, asym, nonlin, gsens, gs_a, filt_a, filt_g = (
            flags[0], flags[1], flags[2], flags[3], flags[4], flags[5], flags[6], flags[7],
            flags[8], flags[9])
        r0, r1, r2 = r_lever[0], r_lever[1], r_lever[2]
        aM00, aM01, aM02 = a_M[0, 0], a_M[0, 1], a_M[0, 2]
        aM10, aM11, aM12 = a_M[1, 0], a_M[1, 1], a_M[1, 2]
        aM20, aM21, aM22 = a_M[2, 0], a_M[2, 1], a_M[2, 2]
        gM00, gM01, gM02 = g_M[0, 0], g_M[0, 1], g_M[0, 2]
        gM10, gM11, gM12 = g_M[1, 0], g_M[1, 1], g_M[1, 2]
        gM20, gM21, gM22 = g_M[2, 0], g_M[2, 1], g_M[2, 2]
        ak0, ak1, ak2 = a_k2[0], a_k2[1], a_k2[2]
        ab0, ab1, ab2 = a_bias[0], a_bias[1], a_bias[2]
        gb0, gb1, gb2 = g_bias[0], g_bias[1], g_bias[2]
        d0 = d1 = d2 = 0.0
        n_sec_a = sos_a.shape[0]
        n_sec_g = sos_g.shape[0]
        j_out = 0
        phase_l = 0
        blk = max(1, min(n, _BLOCK))
        vib_sum_f = np.empty((3, blk))  # axis-major: the passes over samples are contiguous
        vib_sum_w = np.empty((3, blk))
        vs = np.empty((vib_f.size, blk))
        vc = np.empty((vib_f.size, blk))
        Fb = np.empty((3, blk))  # the block's F and W before the low-pass
        Wb = np.empty((3, blk))
        for b0 in range(0, n, blk):
            nb = min(blk, n - b0)
            if vib:  # the vibration of the block in vectorised passes
                _vibration(t[b0:b0 + nb], vib_f, vib_fa, vib_fb, vib_wa, vib_wb, vib_fon,
                           vib_won, vib_sum_f.T, vib_sum_w.T, vs, vc)
            for ib in range(nb):
                i = b0 + ib
                # scalars (registers), the operations and their order as the numpy path
                f0 = f_true[i, 0]
                f1 = f_true[i, 1]
                f2 = f_true[i, 2]
                w0 = w_true[i, 0]
                w1 = w_true[i, 1]
                w2 = w_true[i, 2]
                if lever:
                    if dw_in:
                        d0, d1, d2 = dw_given[i, 0], dw_given[i, 1], dw_given[i, 2]
                    else:
                        dt = t[i] - prev_tw[0]
                        d0 = (w0 - prev_tw[1]) / dt
                        d1 = (w1 - prev_tw[2]) / dt
                        d2 = (w2 - prev_tw[3]) / dt
                        prev_tw[0] = t[i]
                        prev_tw[1] = w0
                        prev_tw[2] = w1
                        prev_tw[3] = w2
                    wr = w0 * r0 + w1 * r1 + w2 * r2
                    ww = w0 * w0 + w1 * w1 + w2 * w2
                    f0 += w0 * wr - r0 * ww + (d1 * r2 - d2 * r1)
                    f1 += w1 * wr - r1 * ww + (d2 * r0 - d0 * r2)
                    f2 += w2 * wr - r2 * ww + (d0 * r1 - d1 * r0)
                if vib:
                    f0 += vib_sum_f[0, ib]
                    w0 += vib_sum_w[0, ib]
                    f1 += vib_sum_f[1, ib]
                    w1 += vib_sum_w[1, ib]
                    f2 += vib_sum_f[2, ib]
                    w2 += vib_sum_w[2, ib]
                F0 = ((aM00 * f0 + aM01 * f1 + aM02 * f2) + ak0 * f0 * f0) + ab0
                F1 = ((aM10 * f0 + aM11 * f1 + aM12 * f2) + ak1 * f1 * f1) + ab1
                F2 = ((aM20 * f0 + aM21 * f1 + aM22 * f2) + ak2 * f2 * f2) + ab2
                W0 = (gM00 * w0 + gM01 * w1 + gM02 * w2) + gb0
                W1 = (gM10 * w0 + gM11 * w1 + gM12 * w2) + gb1
                W2 = (gM20 * w0 + gM21 * w1 + gM22 * w2) + gb2
                if warm:
                    dT = T[i] - T_ref
                    F0 += dT * (wu_ab[0] + wu_as[0] * f0)
                    F1 += dT * (wu_ab[1] + wu_as[1] * f1)
                    F2 += dT * (wu_ab[2] + wu_as[2] * f2)
                    W0 += dT * (wu_gb[0] + wu_gs[0] * w0)
                    W1 += dT * (wu_gb[1] + wu_gs[1] * w1)
                    W2 += dT * (wu_gb[2] + wu_gs[2] * w2)
                if asym:
                    F0 += asym_h[0] * abs(f0)
                    F1 += asym_h[1] * abs(f1)
                    F2 += asym_h[2] * abs(f2)
                if nonlin:
                    W0 += w0 * w0 * (nl_k2[0] + nl_k3[0] * w0)
                    W1 += w1 * w1 * (nl_k2[1] + nl_k3[1] * w1)
                    W2 += w2 * w2 * (nl_k2[2] + nl_k3[2] * w2)
                if gsens:
                    e0 = gs_G[0, 0] * f0 + gs_G[0, 1] * f1 + gs_G[0, 2] * f2
                    e1 = gs_G[1, 0] * f0 + gs_G[1, 1] * f1 + gs_G[1, 2] * f2
                    e2 = gs_G[2, 0] * f0 + gs_G[2, 1] * f1 + gs_G[2, 2] * f2
                    if gs_a:
                        q0 = f0 * f0
                        q1 = f1 * f1
                        q2 = f2 * f2
                        e0 += (gs_A[0, 0] * q0 + gs_A[0, 1] * q1 + gs_A[0, 2] * q2)
                        e1 += (gs_A[1, 0] * q0 + gs_A[1, 1] * q1 + gs_A[1, 2] * q2)
                        e2 += (gs_A[2, 0] * q0 + gs_A[2, 1] * q1 + gs_A[2, 2] * q2)
                    W0 += e0
                    W1 += e1
                    W2 += e2
                Fb[0, ib] = F0
                Fb[1, ib] = F1
                Fb[2, ib] = F2
                Wb[0, ib] = W0
                Wb[1, ib] = W1
                Wb[2, ib] = W2
            # the low-pass, section by section over the block (each section's output depends
            # only on its input sequence: the same values as sample-by-sample), state in
            # registers; then every L-th sample
            na = n_sec_a if filt_a else 0
            ng = n_sec_g if filt_g else 0
            for s_ in range(max(na, ng)):  # six (or three) recurrences interleaved
                if s_ < na and s_ < ng:
                    _sections6(Fb, Wb, nb, sos_a[s_], zi_a[s_], sos_g[s_], zi_g[s_])
                elif s_ < na:
                    _sections3(Fb, nb, sos_a[s_], zi_a[s_])
                else:
                    _sections3(Wb, nb, sos_g[s_], zi_g[s_])
            first = L - 1 - phase_l  # index in the block of the next output sample
            for ib in range(first, nb, L):
                for ax in range(3):
                    out_f[j_out, ax] = Fb[ax, ib]
                    out_w[j_out, ax] = Wb[ax, ib]
                j_out += 1
            phase_l = (phase_l + nb) % L

    @njit(cache=True, nogil=True, error_model="numpy")
    def _sections3(X, nb, sos, zi):  # pragma: no cover - compiled
        """One second-order section over X[ax, :nb] in place for the three axes at once
        (scipy's sosfilt: transposed direct form II, the same operations per axis), states
        zi (3, 2) carried; the three recurrences interleave (their latencies overlap)."""
        b0, b1, b2, a1, a2 = sos[0], sos[1], sos[2], sos[4], sos[5]
        p0, p1, q0, q1, r0, r1 = zi[0, 0], zi[0, 1], zi[1, 0], zi[1, 1], zi[2, 0], zi[2, 1]
        for i in range(nb):
            x = X[0, i]
            y = b0 * x + p0
            p0 = b1 * x - a1 * y + p1
            p1 = b2 * x - a2 * y
            X[0, i] = y
            x = X[1, i]
            y = b0 * x + q0
            q0 = b1 * x - a1 * y + q1
            q1 = b2 * x - a2 * y
            X[1, i] = y
            x = X[2, i]
            y = b0 * x + r0
            r0 = b1 * x - a1 * y + r1
            r1 = b2 * x - a2 * y
            X[2, i] = y
        zi[0, 0], zi[0, 1], zi[1, 0], zi[1, 1], zi[2, 0], zi[2, 1] = p0, p1, q0, q1, r0, r1

    @njit(cache=True, nogil=True, error_model="numpy")
    def _sections6(X, Y, nb, sx, zx, sy, zy):  # pragma: no cover - compiled
        """:func:`_sections3` for X (section sx, states zx) and Y (sy, zy) in one loop: six
        interleaved recurrences."""
        b0, b1, b2, a1, a2 = sx[0], sx[1], sx[2], sx[4], sx[5]
        c0, c1, c2, d1, d2 = sy[0], sy[1], sy[2], sy[4], sy[5]
        p0, p1, q0, q1, r0, r1 = zx[0, 0], zx[0, 1], zx[1, 0], zx[1, 1], zx[2, 0], zx[2, 1]
        u0, u1, v0, v1, w0, w1 = zy[0, 0], zy[0, 1], zy[1, 0], zy[1, 1], zy[2, 0], zy[2, 1]
        for i in range(nb):
            x = X[0, i]
            y = b0 * x + p0
            p0 = b1 * x - a1 * y + p1
            p1 = b2 * x - a2 * y
            X[0, i] = y
            x = X[1, i]
            y = b0 * x + q0
            q0 = b1 * x - a1 * y + q1
            q1 = b2 * x - a2 * y
            X[1, i] = y
            x = X[2, i]
            y = b0 * x + r0
            r0 = b1 * x - a1 * y + r1
            r1 = b2 * x - a2 * y
            X[2, i] = y
            x = Y[0, i]
            y = c0 * x + u0
            u0 = c1 * x - d1 * y + u1
            u1 = c2 * x - d2 * y
            Y[0, i] = y
            x = Y[1, i]
            y = c0 * x + v0
            v0 = c1 * x - d1 * y + v1
            v1 = c2 * x - d2 * y
            Y[1, i] = y
            x = Y[2, i]
            y = c0 * x + w0
            w0 = c1 * x - d1 * y + w1
            w1 = c2 * x - d2 * y
            Y[2, i] = y
        zx[0, 0], zx[0, 1], zx[1, 0], zx[1, 1], zx[2, 0], zx[2, 1] = p0, p1, q0, q1, r0, r1
        zy[0, 0], zy[0, 1], zy[1, 0], zy[1, 1], zy[2, 0], zy[2, 1] = u0, u1, v0, v1, w0, w1
