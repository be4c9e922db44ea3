"""The Gauss-Markov kernel of the covariance of overlapping Allan-variance estimates
(rigctl.solvers.allan_cov: term_covariances / gapped_term_covariances with ``tc``).

Expected values come from plain numpy written here, not from the kernel:
* the exact covariance of the phase of a first-order Gauss-Markov rate from its state-space
  form (the exact discretisation of dy = -y / Tc dt + q dW, dx = y dt: Phi and the step
  covariance written out below), plus white FM (N^2 tau0 min(i, j)) and random-walk FM
  (K^2 (s^2 t / 2 - s^3 / 6)); the second differences' covariance D_a P D_b^T built from it and
  the Isserlis sum 2 ||D_a P D_b^T||^2 / (4 tau_a^2 tau_b^2 M_a M_b);
* a Monte Carlo of the same process (the same exact discretisation, simulated) with the
  overlapping AVAR computed with cumulative sums;
* for gaps, the same brute force on the whole time axis, gaps included, the pooled estimator's
  terms summed over stretches (gaps of 60 Tc: the correlation the kernel neglects across a gap
  is e^-60 there).
"""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from scipy.signal import lfilter

from rigctl.solvers import allan_cov as C

TAU0 = 0.01


def gm_step(tc: float, var: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact one-step transition and noise covariance of the state (y, x)."""
    a = math.exp(-dt / tc)
    phi = np.array([[a, 0.0], [tc * (1.0 - a), 1.0]])
    qyy = var * (1.0 - a * a)
    qxy = var * tc * (1.0 - a) ** 2
    qxx = 2.0 * var * tc * (dt - 2.0 * tc * (1.0 - a) + 0.5 * tc * (1.0 - a * a))
    return phi, np.array([[qyy, qxy], [qxy, qxx]])


def gm_phase_cov(n: int, tc: float, var: float, dt: float) -> np.ndarray:
    """Cov(x_i, x_j), i, j = 0..n-1, x_0 = 0 and y_0 stationary (the increments are)."""
    phi, q = gm_step(tc, var, dt)
    p = np.array([[var, 0.0], [0.0, 0.0]])
    pyx, pxx = np.zeros(n), np.zeros(n)
    for i in range(n):
        pyx[i], pxx[i] = p[1, 0], p[1, 1]
        p = phi @ p @ phi.T + q
    a = math.exp(-dt / tc)
    i = np.arange(n)
    d = np.abs(i[:, None] - i[None, :]).astype(float)
    lo = np.minimum(i[:, None], i[None, :])
    # Cov(x_j, x_i) for j >= i: [Phi^(j-i) P_i]_xx = Tc (1 - a^(j-i)) P_i[y,x] + P_i[x,x]
    return tc * (1.0 - a ** d) * pyx[lo] + pxx[lo]


def other_phase_cov(n: int, n2: float, k2: float, dt: float) -> np.ndarray:
    t = np.arange(n) * dt
    s, u = np.minimum.outer(t, t), np.maximum.outer(t, t)
    return n2 * s + k2 * (s * s * u / 2.0 - s ** 3 / 6.0)


def brute_cov(p: np.ndarray, ms: list[int], dt: float,
              stretches: list[tuple[int, int]] | None = None) -> np.ndarray:
    """Covariance of the (pooled) overlapping AVAR estimates from the phase covariance p:
    stretches as (first phase index, phase points)."""
    if stretches is None:
        stretches = [(0, p.shape[0])]

    def diff2(q: np.ndarray, m: int, axis: int) -> np.ndarray:
        """The second differences D_m applied along ``axis`` (rows of D: the terms of every
        stretch), by slicing: D_m q without forming D_m."""
        parts = []
        for first, npts in stretches:
            nt = npts - 2 * m
            if nt <= 0:
                continue
            take = [np.take(q, np.arange(first + j * m, first + j * m + nt), axis=axis)
                    for j in range(3)]
            parts.append(take[0] - 2.0 * take[1] + take[2])
        return np.concatenate(parts, axis=axis)

    out = np.zeros((len(ms), len(ms)))
    for a in range(len(ms)):
        dpa = diff2(p, ms[a], 0)
        for b in range(a, len(ms)):
            cab = diff2(dpa, ms[b], 1)
            ta, tb = ms[a] * dt, ms[b] * dt
            out[a, b] = out[b, a] = (2.0 * np.sum(cab * cab)
                                     / (4.0 * ta ** 2 * tb ** 2 * cab.shape[0] * cab.shape[1]))
    return out


MS = [1, 3, 10, 30, 50, 120, 250]


@pytest.mark.parametrize("h", [0.7, 6.0, 60.0, 600.0])
def test_covariance_matches_the_exact_brute_force(h: float) -> None:
    """GM + white FM + RW FM, 1200 samples, Tc = h samples: the kernel's matrix against the
    brute force. Pairs with m_a + m_b <= 64 are exact sums (agree to 1e-7: the brute force's
    own rounding, phase variances ~1e4 times the second differences'); the rest are
    Gauss-Legendre integrals of the lag sum (measured when written: the diagonal within 1.3e-4
    (the white FM part's sum-vs-integral, as for N alone), every entry within 8e-3 of the
    brute force at its scale sqrt(C_aa C_bb))."""
    n = 1200
    tc, var, n2, k2 = h * TAU0, 1.0, 0.3 * h * TAU0, 0.2 / (h * TAU0)
    p = gm_phase_cov(n + 1, tc, var, TAU0) + other_phase_cov(n + 1, n2, k2, TAU0)
    want = brute_cov(p, MS, TAU0)
    ct = C.term_covariances(TAU0, np.array(MS), n + 1, tc)
    got = C.combine(ct, {"N": n2, "K": k2, "G": var})
    scale = np.sqrt(np.outer(np.diag(want), np.diag(want)))
    ms = np.array(MS)
    exact = (ms[:, None] + ms[None, :]) <= C.DISCRETE_MAX
    err = np.abs(got - want) / scale
    assert np.max(err[exact]) < 1e-7, err
    assert np.max(err) < 8e-3, err
    assert np.max(np.abs(np.diag(got) / np.diag(want) - 1.0)) < 2e-3, np.diag(got) / np.diag(want)
    # GM alone: the diagonal is the exact variance of its AVAR estimate
    pg = gm_phase_cov(n + 1, tc, var, TAU0)
    want_g = np.diag(brute_cov(pg, MS, TAU0))
    got_g = np.diag(C.combine(ct, {"G": var}))
    assert np.all(np.abs(got_g / want_g - 1.0) < 2e-3), got_g / want_g


def test_without_tc_nothing_changes_and_cache_is_per_tc() -> None:
    ms = np.array([2, 8, 40, 200])
    base = C.term_covariances(TAU0, ms, 5001)
    assert C.term_covariances(TAU0, ms, 5001) is base
    with_gm = C.term_covariances(TAU0, ms, 5001, 0.5)
    for k, v in base.items():
        assert with_gm[k] is v
    assert set(with_gm) - set(base) == set(C.GPAIRS)
    again = C.term_covariances(TAU0, ms, 5001, 0.5)
    assert again[("G", "G")] is with_gm[("G", "G")]
    other = C.term_covariances(TAU0, ms, 5001, 1.0)
    assert not np.allclose(other[("G", "G")], with_gm[("G", "G")])
    # combine ignores the GM pairs without a G coefficient
    np.testing.assert_array_equal(C.combine(with_gm, {"N": 1.0, "K": 2.0}),
                                  C.combine(base, {"N": 1.0, "K": 2.0}))


def simulate(n: int, reps: int, tc: float, var: float, n2: float,
             rng: np.random.Generator) -> np.ndarray:
    """Phase (reps, n + 1) of GM + white FM, GM by its exact discretisation."""
    phi, q = gm_step(tc, var, TAU0)
    a = phi[0, 0]
    lq = np.linalg.cholesky(q)
    e = rng.standard_normal((2, reps, n))
    wy = lq[0, 0] * e[0]
    wx = lq[1, 0] * e[0] + lq[1, 1] * e[1]
    y0 = math.sqrt(var) * rng.standard_normal((reps, 1))
    # y_i, i = 0..n-1: y_{i+1} = a y_i + wy_i
    y = lfilter([1.0], [1.0, -a], np.concatenate([y0, wy[:, :-1]], axis=1), axis=1)
    dx = tc * (1.0 - a) * y + wx + math.sqrt(n2 * TAU0) * rng.standard_normal((reps, n))
    return np.concatenate([np.zeros((reps, 1)), np.cumsum(dx, axis=1)], axis=1)


def test_monte_carlo_covariance_across_taus() -> None:
    """4000 simulated series of 4096 samples (Tc = 20 samples, white FM beside it): the
    empirical variances and correlations of the AVAR at m = 1, 2, 4, 16, 64, 128 against the
    kernel's. Monte Carlo error, computed here from the samples: a variance's standard error
    from the fourth moment, a correlation's (1 - r^2) / sqrt(R); both within 4 of them."""
    rng = np.random.default_rng(20261127)
    n, reps, tc, var, n2 = 4096, 4000, 20 * TAU0, 1.0, 0.2
    ms = np.array([1, 2, 4, 16, 64, 128])
    est = np.zeros((reps, ms.size))
    for c0 in range(0, reps, 500):
        x = simulate(n, 500, tc, var, n2, rng)
        for j, m in enumerate(ms):
            d = x[:, 2 * m:] - 2 * x[:, m:-m] + x[:, :-2 * m]
            est[c0:c0 + 500, j] = np.mean(d * d, axis=1) / (2.0 * (m * TAU0) ** 2)
    ct = C.term_covariances(TAU0, ms, n + 1, tc)
    model = C.combine(ct, {"N": n2, "G": var})
    dev = est - est.mean(axis=0)
    emp = dev.T @ dev / (reps - 1)
    v_se = np.sqrt((np.mean(dev ** 4, axis=0) - np.diag(emp) ** 2) / reps)
    z_var = (np.diag(emp) - np.diag(model)) / v_se
    assert np.all(np.abs(z_var) < 4.0), z_var
    sd_m = np.sqrt(np.diag(model))
    r_model = model / np.outer(sd_m, sd_m)
    sd_e = np.sqrt(np.diag(emp))
    r_emp = emp / np.outer(sd_e, sd_e)
    iu = np.triu_indices(ms.size, 1)
    z_r = (r_emp[iu] - r_model[iu]) / ((1.0 - r_model[iu] ** 2) / math.sqrt(reps))
    assert np.all(np.abs(z_r) < 4.0), (z_r, r_model[iu], r_emp[iu])
    # the correlations are not trivial: the test could tell a wrong kernel apart
    assert np.max(r_model[iu]) > 0.4
    # and the means are the Allan variance of the mixture
    avar = n2 / (ms * TAU0) + var * (tc / (ms * TAU0)) ** 2 * (
        2 * ms * TAU0 / tc - 3 + 4 * np.exp(-ms * TAU0 / tc) - np.exp(-2 * ms * TAU0 / tc))
    assert np.all(np.abs(est.mean(axis=0) - avar) < 4.0 * np.sqrt(np.diag(model) / reps))


@functools.lru_cache(maxsize=1)
def _three_stretches() -> tuple:
    """Three stretches of 300, 520 and 180 samples separated by gaps of 600 samples (60 Tc),
    GM + white FM: (tc, var, n2, lengths, ms, the pooled estimator's covariance by brute
    force on the whole time axis). Shared by the two gapped tests (the brute force costs)."""
    tc_samples, var, n2 = 10.0, 1.0, 2.0 * TAU0
    tc = tc_samples * TAU0
    lengths, gap = [300, 520, 180], 600
    starts, pos = [], 0
    for ln in lengths:
        starts.append(pos)
        pos += ln + gap
    total = pos - gap + 1
    p = gm_phase_cov(total, tc, var, TAU0) + other_phase_cov(total, n2, 0.0, TAU0)
    ms = [1, 4, 16, 50, 100]
    want = brute_cov(p, ms, TAU0, [(s0, ln + 1) for s0, ln in zip(starts, lengths)])
    return tc, var, n2, lengths, ms, want


def test_gapped_covariance_matches_the_brute_force() -> None:
    """Three stretches of 300, 520 and 180 samples separated by gaps of 600 samples (60 Tc):
    the pooled estimator's covariance from the brute force on the whole time axis against
    gapped_term_covariances with tc (exact sums here: within 1e-8 of it), and against the
    contiguous record's, which it is not (the check could fail)."""
    tc, var, n2, lengths, ms, want = _three_stretches()
    ct = C.gapped_term_covariances(TAU0, np.array(ms), np.array(lengths), tc)
    got = C.combine(ct, {"N": n2, "G": var})
    scale = np.sqrt(np.outer(np.diag(want), np.diag(want)))
    assert np.max(np.abs(got - want) / scale) < 1e-8
    one = C.combine(C.term_covariances(TAU0, np.array(ms), sum(lengths) + 1, tc),
                    {"N": n2, "G": var})
    assert np.max(np.abs(one / want - 1.0)) > 0.05


def test_gapped_long_stretches_through_the_contiguous_kernel(monkeypatch: pytest.MonkeyPatch
                                                              ) -> None:
    """Without the compiled pair loop, long stretches (C.GM_LONG_MIN samples and more) enter the
    gapped Gauss-Markov pairs through the contiguous kernel of their own length; here the
    threshold is lowered so that two of the three stretches (520 and 300 samples) go that way
    and the third (180) through
    the pair loop. Against the brute force on the whole time axis (gaps of 60 Tc): the
    contiguous kernel's own accuracy (test_covariance_matches_the_exact_brute_force: exact sums
    where m_a + m_b <= 64, every entry within 8e-3, the diagonal within 2e-3)."""
    monkeypatch.setattr(C, "GM_LONG_MIN", 250)
    # the contiguous kernel serves long stretches where the pair loop is not compiled
    monkeypatch.setattr(C._kc(), "HAVE_NUMBA", False)
    C._gm_gapped_cached.cache_clear()
    try:
        tc, var, n2, lengths, ms, want = _three_stretches()
        ct = C.gapped_term_covariances(TAU0, np.array(ms), np.array(lengths), tc)
        got = C.combine(ct, {"N": n2, "G": var})
    finally:
        C._gm_gapped_cached.cache_clear()
    scale = np.sqrt(np.outer(np.diag(want), np.diag(want)))
    err = np.abs(got - want) / scale
    m = np.array(ms)
    exact = (m[:, None] + m[None, :]) <= C.DISCRETE_MAX
    assert np.max(err[exact]) < 1e-7, err
    assert np.max(err) < 8e-3, err
    assert np.max(np.abs(np.diag(got) / np.diag(want) - 1.0)) < 2e-3, np.diag(got) / np.diag(want)


def test_compiled_gauss_legendre_sums_are_the_numpy_ones() -> None:
    """The contiguous kernel's Gauss-Legendre pairs are summed by a compiled loop
    (allan_cov_kernels.gm_gl_sums) where numba is there, by numpy (allan_cov._gm_gl_numpy)
    otherwise: the same numbers. Compared here pair by pair on a 1 h record's 40 factors from
    4 to 4e4 samples (the Gauss-Legendre pairs: m_a + m_b > 64), for Tc from 0.02 s to
    5e4 s (the last ones where the kernel is evaluated directly, h > 1e3 (m_a + m_b), which
    stays numpy): bit for bit where numpy's exp is libm's (no AVX-512, as on the CI machine;
    checked on a probe here), else within numpy's vectorized exp's rounding (1e-8 of the
    largest sum of the kind: some are differences of large terms)."""
    kc = pytest.importorskip("rigctl.solvers.allan_cov_kernels")
    if not kc.HAVE_NUMBA:
        pytest.skip("the compiled loop needs numba")
    n_phase = 360_001
    ms = np.unique(np.round(np.geomspace(4, 4e4, 40)))
    g = C._gm_nodes(TAU0, ms.tobytes(), n_phase)["gl"]
    probe = -np.geomspace(1e-6, 700.0, 5000)
    libm = np.array_equal(np.exp(probe), [math.exp(v) for v in probe])
    rows = np.arange(g["s"].size)
    n_direct = 0
    for tc in (0.02, 0.3, 2.0, 17.0, 150.0, 5e4):
        h = tc / TAU0
        direct = h > C._GM_SPLIT_MAX * g["s"]
        n_direct += int(np.count_nonzero(direct))
        ref = C._gm_gl_numpy(g, rows, direct, TAU0, tc, h)
        got = kc.gm_gl_sums(tc, h, g["d_tap"], g["left"], g["coef"], g["k"], g["a_i"], g["b_i"],
                            g["r"]["N"], g["r"]["B"], g["r"]["K"], g["wq"], direct)
        assert np.all(got[direct] == 0.0)  # left to numpy
        for i, pair in enumerate(C.GPAIRS[1:]):
            a, b = ref[pair][~direct], got[~direct, i]
            if libm:
                np.testing.assert_array_equal(b, a, err_msg=f"{pair} at Tc {tc}")
            else:
                np.testing.assert_allclose(b, a, rtol=1e-8, atol=1e-8 * np.max(np.abs(a)))
    assert n_direct > 0  # the direct range was reached (and left to numpy)
