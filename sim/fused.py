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
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without the extra
    HAVE_NUMBA = False

if HAVE_NUMBA:

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
        f = np.empty(3)
        w = np.empty(3)
        F = np.empty(3)
        W = np.empty(3)
        fv = np.empty(3)
        wv = np.empty(3)
        e = np.empty(3)
        two_pi = 2 * np.pi
        n_sec_a = sos_a.shape[0]
        n_sec_g = sos_g.shape[0]
        j_out = 0
        phase_l = 0
        for i in range(n):
            for ax in range(3):
                f[ax] = f_true[i, ax]
                w[ax] = w_true[i, ax]
            if lever:
                if dw_in:
                    d0, d1, d2 = dw_given[i, 0], dw_given[i, 1], dw_given[i, 2]
                else:
                    dt = t[i] - prev_tw[0]
                    d0 = (w[0] - prev_tw[1]) / dt
                    d1 = (w[1] - prev_tw[2]) / dt
                    d2 = (w[2] - prev_tw[3]) / dt
                    prev_tw[0] = t[i]
                    prev_tw[1] = w[0]
                    prev_tw[2] = w[1]
                    prev_tw[3] = w[2]
                r0, r1, r2 = r_lever[0], r_lever[1], r_lever[2]
                wr = w[0] * r0 + w[1] * r1 + w[2] * r2
                ww = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
                l0 = w[0] * wr - r0 * ww + (d1 * r2 - d2 * r1)
                l1 = w[1] * wr - r1 * ww + (d2 * r0 - d0 * r2)
                l2 = w[2] * wr - r2 * ww + (d0 * r1 - d1 * r0)
                f[0] += l0
                f[1] += l1
                f[2] += l2
            if vib:
                for ax in range(3):
                    fv[ax] = 0.0
                    wv[ax] = 0.0
                for k in range(vib_f.size):
                    cyc = vib_f[k] * t[i]
                    cyc -= np.floor(cyc)
                    cyc *= two_pi
                    s = np.sin(cyc)
                    c = np.cos(cyc)
                    for ax in range(3):
                        if vib_fon[k, ax]:
                            fv[ax] += s * vib_fa[k, ax] + c * vib_fb[k, ax]
                        if vib_won[k, ax]:
                            wv[ax] += s * vib_wa[k, ax] + c * vib_wb[k, ax]
                for ax in range(3):
                    f[ax] += fv[ax]
                    w[ax] += wv[ax]
            for ax in range(3):
                F[ax] = ((a_M[ax, 0] * f[0] + a_M[ax, 1] * f[1] + a_M[ax, 2] * f[2])
                         + a_k2[ax] * f[ax] * f[ax]) + a_bias[ax]
                W[ax] = (g_M[ax, 0] * w[0] + g_M[ax, 1] * w[1] + g_M[ax, 2] * w[2]) + g_bias[ax]
            if warm:
                dT = T[i] - T_ref
                for ax in range(3):
                    F[ax] += dT * (wu_ab[ax] + wu_as[ax] * f[ax])
                for ax in range(3):
                    W[ax] += dT * (wu_gb[ax] + wu_gs[ax] * w[ax])
            if asym:
                for ax in range(3):
                    F[ax] += asym_h[ax] * abs(f[ax])
            if nonlin:
                for ax in range(3):
                    W[ax] += w[ax] * w[ax] * (nl_k2[ax] + nl_k3[ax] * w[ax])
            if gsens:
                for ax in range(3):
                    e[ax] = gs_G[ax, 0] * f[0] + gs_G[ax, 1] * f[1] + gs_G[ax, 2] * f[2]
                if gs_a:
                    for ax in range(3):
                        e[ax] += (gs_A[ax, 0] * (f[0] * f[0]) + gs_A[ax, 1] * (f[1] * f[1])
                                  + gs_A[ax, 2] * (f[2] * f[2]))
                for ax in range(3):
                    W[ax] += e[ax]
            if filt_a:
                for ax in range(3):
                    x = F[ax]
                    for s_ in range(n_sec_a):
                        y = sos_a[s_, 0] * x + zi_a[s_, ax, 0]
                        zi_a[s_, ax, 0] = sos_a[s_, 1] * x - sos_a[s_, 4] * y + zi_a[s_, ax, 1]
                        zi_a[s_, ax, 1] = sos_a[s_, 2] * x - sos_a[s_, 5] * y
                        x = y
                    F[ax] = x
            if filt_g:
                for ax in range(3):
                    x = W[ax]
                    for s_ in range(n_sec_g):
                        y = sos_g[s_, 0] * x + zi_g[s_, ax, 0]
                        zi_g[s_, ax, 0] = sos_g[s_, 1] * x - sos_g[s_, 4] * y + zi_g[s_, ax, 1]
                        zi_g[s_, ax, 1] = sos_g[s_, 2] * x - sos_g[s_, 5] * y
                        x = y
                    W[ax] = x
            phase_l += 1
            if phase_l == L:  # the last of each group of L (no integer division per sample)
                phase_l = 0
                for ax in range(3):
                    out_f[j_out, ax] = F[ax]
                    out_w[j_out, ax] = W[ax]
                j_out += 1
