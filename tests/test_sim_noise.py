"""Noise generator: exact Allan signatures, chunk invariance, seeding (rigctl.sim.noise).

Allan deviations are computed with rigctl.solvers.allan.oadev when it imports (else allantools,
test-only). Confidence intervals: chi-square with the simple EDF approximations of NIST SP 1065
(table 5, Howe/Allan/Barnes) for the noise type that dominates the theoretical curve at each tau;
two-sided 99.9 % per point, because each profile test checks ~90 (tau, axis) points at once.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import signal
from scipy.stats import chi2

from rigctl.sim import noise as nz
from rigctl.sim import spectral_factor as sf
from rigctl.sim.block_iir import BlockCascade
from rigctl.sim.error_model import ImuErrorModel
from rigctl.sim.profiles import get_profile, profile_names
from rigctl.solvers.noise_coefficients import triad

try:  # prefer the project's own estimator
    from rigctl.solvers.allan import oadev as _oadev

    def oadev(y: np.ndarray, rate_hz: float, m: np.ndarray) -> np.ndarray:
        return _oadev(y, 1.0 / rate_hz, [int(v) for v in m]).dev  # default "fast" mode
except ImportError:  # pragma: no cover - fallback while the solver is absent
    import allantools

    def oadev(y: np.ndarray, rate_hz: float, m: np.ndarray) -> np.ndarray:
        return allantools.oadev(y, rate=rate_hz, data_type="freq", taus=m / rate_hz)[1]


CONF = 0.999
ALL_TERMS = {"Q": 2e-7, "N": 3e-5, "B": 1e-6, "K": 3e-8, "R": 1e-11,
             "flicker_tau_min_s": 1.0, "flicker_tau_max_s": 1e3}


def simple_edf(alpha: int, m: np.ndarray, n_phase: int) -> np.ndarray:
    """NIST SP 1065 table 5 simple EDF approximations for the overlapping Allan variance."""
    N, m = float(n_phase), np.asarray(m, dtype=float)
    if alpha == 2:
        return (N + 1) * (N - 2 * m) / (2 * (N - m))
    if alpha == 0:
        return (3 * (N - 1) / (2 * m) - 2 * (N - 2) / N) * 4 * m**2 / (4 * m**2 + 5)
    if alpha == -1:
        return np.where(m == 1, 2 * (N - 2) / (2.3 * N - 4.9), 5 * N**2 / (4 * m * (N + 3 * m)))
    return (N - 2) / m * ((N - 1) ** 2 - 3 * m * (N - 1) + 4 * m**2) / (N - 3) ** 2


def dominant_alpha(axes, m: np.ndarray, rate_hz: float, extra_white: np.ndarray, ax: int) -> np.ndarray:
    """Power-law exponent of the term contributing most Allan variance at each tau (R counts as RW)."""
    parts = []
    for key, alpha in (("Q", 2), ("N", 0), ("B", -1), ("K", -2), ("R", -2)):
        sub = [replace(a, **{t: 0.0 for t in nz.TERMS if t != key}) for a in axes]
        ew = extra_white if key == "N" else 0.0
        parts.append((nz.theoretical_avar(sub, m / rate_hz, rate_hz, ew)[:, ax], alpha))
    stack = np.stack([p for p, _ in parts])
    return np.array([parts[i][1] for i in np.argmax(stack, axis=0)])


def check_within_ci(y: np.ndarray, params, rate_hz: float, m: np.ndarray,
                    extra_white: np.ndarray | float = 0.0) -> None:
    """Assert every (tau, axis) theoretical deviation lies in the CONF interval of the estimate."""
    ew = np.broadcast_to(np.asarray(extra_white, dtype=float), (3,))
    theory = np.sqrt(nz.theoretical_avar(params, m / rate_hz, rate_hz, ew))
    p = (1 - CONF) / 2
    for ax in range(3):
        dev = oadev(y[:, ax], rate_hz, m)
        alphas = dominant_alpha(params, m, rate_hz, ew[ax], ax)
        edf = np.array([simple_edf(a, np.array([mi]), len(y) + 1)[0] for a, mi in zip(alphas, m)])
        lo = dev * np.sqrt(edf / chi2.ppf(1 - p, edf))
        hi = dev * np.sqrt(edf / chi2.ppf(p, edf))
        bad = (theory[:, ax] < lo) | (theory[:, ax] > hi)
        assert not bad.any(), (f"axis {ax}: tau {m[bad] / rate_hz} s, theory {theory[bad, ax]}, "
                               f"estimate {dev[bad]}, CI [{lo[bad]}, {hi[bad]}]")


def log_factors(n: int, lo: int, hi_div: int = 10, per_decade: int = 4) -> np.ndarray:
    return np.unique(np.round(np.geomspace(lo, n // hi_div, int(per_decade * math.log10(n / hi_div / lo)) + 1))).astype(int)


# ------------------------------------------------------------------------------------------
def test_chunked_output_is_bit_identical_to_one_piece() -> None:
    """Slices that cross the generator's internal chunk boundaries give the same bits as one piece."""
    n = 2 * nz.NoiseGenerator.CHUNK + 18_000
    one = nz.NoiseGenerator(triad(**ALL_TERMS), 100.0, seed=11).next(n)
    g = nz.NoiseGenerator(triad(**ALL_TERMS), 100.0, seed=11)
    sizes = (1, 2, 997, 12_000, nz.NoiseGenerator.CHUNK, n - 13_000 - nz.NoiseGenerator.CHUNK)
    parts = np.concatenate([g.next(k) for k in sizes])
    assert np.array_equal(one, parts)


def test_chunked_with_signal_is_bit_identical_to_one_piece() -> None:
    """With a signal (integrated before quantization) and the ramp, slicing does not change a bit either."""
    n = nz.NoiseGenerator.CHUNK + 5_000
    t = np.arange(n)[:, None] / 100.0
    sig = np.sin(0.7 * t + np.array([0.0, 1.0, 2.0])) * 1e-4 + np.array([0.0, 5e-5, 9.8])
    one = nz.NoiseGenerator(triad(**ALL_TERMS), 100.0, seed=12).next(n, sig)
    g = nz.NoiseGenerator(triad(**ALL_TERMS), 100.0, seed=12)
    cuts = [0, 3, 40_000, 40_001, n]
    parts = np.concatenate([g.next(b - a, sig[a:b]) for a, b in zip(cuts[:-1], cuts[1:])])
    assert np.array_equal(one, parts)


def test_same_seed_same_data_other_seed_differs() -> None:
    a = nz.NoiseGenerator(triad(**ALL_TERMS), 100.0, seed=3).next(1000)
    b = nz.NoiseGenerator(triad(**ALL_TERMS), 100.0, seed=3).next(1000)
    c = nz.NoiseGenerator(triad(**ALL_TERMS), 100.0, seed=4).next(1000)
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)


def test_axes_are_independent_streams() -> None:
    y = nz.NoiseGenerator(triad(N=1.0), 100.0, seed=5).next(200_000)
    r = np.corrcoef(y.T)
    assert np.max(np.abs(r - np.eye(3))) < 5 / math.sqrt(len(y))


def test_flicker_cascade_theory_matches_its_impulse_response() -> None:
    """The exact Allan variance from partial fractions equals the brute-force autocovariance sum."""
    d = nz.design_flicker(0.05, 2.0, 100.0, 2)
    imp = np.zeros(100_000)
    imp[0] = 1.0
    h = signal.sosfilt(d.sos(), imp)
    R = np.array([np.dot(h[: len(h) - j], h[j:]) for j in range(400)])
    for m in (1, 2, 7, 30, 150):
        j = np.arange(1, 2 * m)
        r = np.where(j <= m, 2 * m - 3 * j, -(2 * m - j))
        brute = (2 * m * R[0] + 2 * np.sum(r * R[1 : 2 * m])) / (2 * m**2)
        exact = nz._cascade_avar(d.a_pole, d.a_zero, np.array([float(m)]))[0]
        assert exact == pytest.approx(brute, rel=1e-9)


@pytest.mark.parametrize("tau_min, tau_max, rate", [(1.0, 1e4, 100.0), (0.1, 1e3, 100.0), (0.01, 100.0, 1000.0)])
def test_flicker_plateau_is_flat_over_configured_decades(tau_min: float, tau_max: float, rate: float) -> None:
    taus = np.geomspace(tau_min, tau_max, 40)
    dev = np.sqrt(nz.theoretical_avar(triad(B=1.0, flicker_tau_min_s=tau_min, flicker_tau_max_s=tau_max), taus, rate)[:, 0])
    ratio = dev / math.sqrt(nz.PLATEAU)  # 0.664 B
    assert ratio.min() > 0.99 and ratio.max() < 1.035
    # a single first-order Gauss-Markov process with the same peak is nowhere near flat
    T = math.sqrt(tau_min * tau_max) / 1.89
    gm = np.array([nz._exp_avar(np.array([t * rate]), 1 / (T * rate))[0] for t in taus])
    gm_ratio = np.sqrt(gm / gm.max())
    assert gm_ratio.min() < 0.5


# spectral factorisation (one white sequence for N + B + K) and its block evaluation ------------------
FACTOR_CASES = [  # (rate_hz, tau_min, tau_max, pairs/decade, N, B, K): profile-like, extreme ratios, terms off
    (100.0, 1.0, 1e4, 2, 4.36e-5, 2.42e-6, 8.1e-9),
    (100.0, 1.0, 1e4, 2, 1e-3, 4.9e-4, 1e-6),
    (100.0, 0.1, 1e3, 2, 1e-8, 1e-3, 1e-12),
    (1000.0, 0.01, 100.0, 2, 1e-3, 1e-6, 0.0),
    (100.0, 1.0, 1e5, 2, 0.0, 1e-6, 1e-6),
    (100.0, 1.0, 1e4, 2, 1e-3, 0.0, 1e-6),
    (100.0, 0.01, 10.0, 1, 2e-4, 3e-5, 1e-7),
]


def _sums(rate: float, tmin: float, tmax: float, ppd: int, N: float, B: float, K: float):
    d = nz.design_flicker(tmin, tmax, rate, ppd)
    return d, N**2 * rate, (B * d.input_std_per_B) ** 2, K**2 / rate


def _u_form(u: np.ndarray, a: np.ndarray) -> np.ndarray:
    """|1 - e^{-a} e^{-jw}|^2 = e^{-a} (4 sinh^2(a/2) + u), u = 4 sin^2(w/2), per row of a (finite a only)."""
    a = np.asarray(a, float)[np.isfinite(a)][:, None]
    return np.prod(np.exp(-a) * (4 * np.sinh(a / 2) ** 2 + u), axis=0)


@pytest.mark.parametrize("case", FACTOR_CASES)
def test_combined_filter_spectrum_is_the_sum_of_the_terms(case: tuple) -> None:
    """g^2 |G|^2 = N^2 fs + (B c_B)^2 |H|^2 + K^2 tau0/|1 - e^-jw|^2: by complex arithmetic for w >= 1e-3,
    and in the cancellation-free u-form down to 1e-9 rad/sample (below the slowest pole)."""
    d, sn2, sb2, sk2 = _sums(*case)
    f = sf.factor(sn2, sb2, sk2, d.a_pole, d.a_zero)
    zeros = np.exp(-np.concatenate([f.b_stable, [f.b_integrator] if f.integrator else []]))
    poles = np.exp(-f.a_stable)
    w = np.geomspace(1e-3, np.pi, 300)
    z1 = np.exp(-1j * w)
    G = f.gain * np.prod(1 - zeros[:, None] * z1, axis=0) / np.prod(1 - poles[:, None] * z1, axis=0)
    if f.integrator:
        G = G / (1 - z1)
    H = np.prod(1 - np.exp(-d.a_zero)[:, None] * z1, axis=0) / np.prod(1 - np.exp(-d.a_pole)[:, None] * z1, axis=0)
    target = sn2 + sb2 * np.abs(H) ** 2 + sk2 / np.abs(1 - z1) ** 2
    assert np.allclose(np.abs(G) ** 2, target, rtol=1e-9, atol=0)
    w = np.geomspace(1e-9, np.pi, 400)
    u = 4 * np.sin(w / 2) ** 2
    target = sn2 + sk2 / u + (sb2 * _u_form(u, d.a_zero) / _u_form(u, d.a_pole) if sb2 > 0 else 0.0)
    fac = f.gain**2 * _u_form(u, np.concatenate([f.b_stable, [f.b_integrator]])) / _u_form(u, f.a_stable)
    fac = fac / u if f.integrator else fac
    assert np.allclose(fac, target, rtol=1e-11, atol=0)


def test_combined_filter_allan_variance_is_the_sum_of_the_terms() -> None:
    """With K = 0 the combined filter is a stable cascade: its exact Allan variance (partial fractions)
    equals N^2/tau + the flicker cascade's, i.e. theoretical_avar, to rounding."""
    rate = 100.0
    params = triad(N=2e-4, B=3e-5, flicker_tau_min_s=0.1, flicker_tau_max_s=1e3)
    d, sn2, sb2, _ = _sums(rate, 0.1, 1e3, 2, 2e-4, 3e-5, 0.0)
    f = sf.factor(sn2, sb2, 0.0, d.a_pole, d.a_zero)
    M = np.array([1.0, 3.0, 10.0, 100.0, 1e3, 1e4, 1e5])
    combined = f.gain**2 * nz._cascade_avar(f.a_stable, f.b_stable, M)
    assert np.allclose(combined, nz.theoretical_avar(params, M / rate, rate)[:, 0], rtol=1e-9, atol=0)


def test_block_filter_equals_the_direct_recursion() -> None:
    """BlockCascade (BLAS blocks, closed-form block recursion: slow batch, grouped fast poles, a pole so fast
    its carry is dropped, identity / random-walk / running-sum integrators, per-axis residues and gains) over
    three chunks equals the first-order cascade run sample by sample (sosfilt)."""
    a = np.array([1e-7, 3e-5, 2e-3, 0.05, 0.9, 4.0, 5.0])
    b_axes = [a * 1.7, np.r_[a[:-1] * 2.5, np.inf], np.full(6, np.inf)]
    c_int = np.array([[0.0, 1.0], [1 - np.exp(-2e-6), 1.0], [0.3, 0.0]])
    gain = np.array([1.3, 0.02, 7.0])
    res = np.array([sf.residues(a, b) for b in b_axes])
    L, chunk = 64, 1024
    blk = BlockCascade(a, res, c_int, gain, L)
    rng = np.random.default_rng(3)
    s0 = rng.standard_normal((3, len(a))) * 50.0  # a non-zero stable start
    blk.state[:, : len(a)] = s0
    eps = rng.standard_normal((3, 3 * chunk))
    out = np.concatenate([blk.run(eps[:, i * chunk:(i + 1) * chunk]).copy() for i in range(3)], axis=1)
    for ax in range(3):
        # direct: parallel stable part with the same start, then the integrator sections one by one
        p = np.exp(-a)
        s = s0[ax].copy()
        x = np.empty(eps.shape[1])
        for t, e in enumerate(eps[ax]):
            x[t] = e + np.dot(res[ax] * p, s)
            s = p * s + e
        for c in c_int[ax]:
            x = signal.lfilter([1.0, c - 1.0], [1.0, -1.0], x)
        ref = gain[ax] * x
        assert np.max(np.abs(out[ax] - ref)) <= 1e-10 * np.max(np.abs(ref))
    # the same stable part from the pole/zero cascade form agrees with the partial fractions
    sos = np.array([[1.0, -np.exp(-bb), 0.0, 1.0, -np.exp(-aa), 0.0] for aa, bb in zip(a, b_axes[0])])
    imp = np.zeros(400)
    imp[0] = 1.0
    blk0 = BlockCascade(a, res[:1], np.zeros((1, 0)), np.ones(1), 16)
    assert np.allclose(blk0.run(imp[None, :])[0], signal.sosfilt(sos, imp), rtol=0, atol=1e-13)


def test_axes_with_different_terms_keep_their_own_signatures() -> None:
    """Per-axis terms (white only; flicker + random walk; quantization + random walk + ramp): axes without a
    term get identity sections, and each axis still follows its own theoretical curve."""
    params = triad(N=[1e-3, 1e-4, 1e-3], B=[0.0, 5e-5, 0.0], K=[0.0, 1e-5, 1e-5], Q=[0.0, 0.0, 1e-5],
                   R=[0.0, 0.0, 1e-7], flicker_tau_min_s=0.1, flicker_tau_max_s=1e3)
    rate, n = 100.0, 400_000
    y = nz.NoiseGenerator(params, rate, seed=31).next(n)
    check_within_ci(y, params, rate, log_factors(n, 10))


def test_exact_discrete_theory_agrees_with_ieee_formulas() -> None:
    tau = np.geomspace(0.1, 4e3, 20)
    M = np.round(tau * 100.0)
    exact = nz.theoretical_avar(triad(**(ALL_TERMS | {"B": 0.0})), tau, 100.0)
    ieee = nz.theoretical_avar(triad(**(ALL_TERMS | {"B": 0.0})), M / 100.0)
    assert np.allclose(exact, ieee, rtol=1e-6)
    # only the discrete random walk differs from IEEE: K^2 tau/3 (1 + 1/(2 M^2))
    k_only = nz.theoretical_avar(triad(K=1.0), tau, 100.0)[:, 0] / nz.theoretical_avar(triad(K=1.0), M / 100.0)[:, 0]
    assert np.allclose(k_only - 1.0, 1.0 / (2 * M**2), rtol=1e-9)


def test_stationary_start_has_full_flicker_variance() -> None:
    """The flicker state is drawn from its steady state: sample 0 already has the full stationary
    variance (a zero start would give only the input variance, about half of it)."""
    p = triad(B=1.0, flicker_tau_min_s=1.0, flicker_tau_max_s=1e4)
    n_seeds = 400
    first = np.concatenate([nz.NoiseGenerator(p, 100.0, seed=s).next(1)[0] for s in range(n_seeds)])
    var = float(nz.flicker_variance(p, 100.0)[0])
    dof = first.size
    lo, hi = var * chi2.ppf(0.0005, dof) / dof, var * chi2.ppf(0.9995, dof) / dof
    assert lo < np.mean(first**2) < hi
    zero_start = nz.design_flicker(1.0, 1e4, 100.0, 2).input_std_per_B ** 2
    assert zero_start < lo


def test_rate_random_walk_starts_at_zero_with_variance_k2_t() -> None:
    """K alone: a walk from 0 at power-on with increments of variance K^2 tau0 (uniform, |dW| <= sqrt(3) K
    sqrt(tau0)); across seeds Var W_t = K^2 tau0 (t + 1), i.e. no stationary offset at power-on."""
    K, rate, n, seeds = 2e-4, 100.0, 3000, 200
    W = np.stack([nz.NoiseGenerator(triad(K=K), rate, seed=s).next(n)[:, 0] for s in range(seeds)])
    step = K * math.sqrt(1 / rate)
    dW = np.diff(np.concatenate([np.zeros((seeds, 1)), W], axis=1), axis=1)
    assert np.max(np.abs(dW)) <= math.sqrt(3) * step
    dof = dW.size
    assert chi2.ppf(0.0005, dof) / dof < np.mean(dW**2) / step**2 < chi2.ppf(0.9995, dof) / dof
    for t in (0, 99, n - 1):
        ratio = np.mean(W[:, t] ** 2) / (step**2 * (t + 1))
        assert chi2.ppf(0.0005, seeds) / seeds < ratio < chi2.ppf(0.9995, seeds) / seeds


@pytest.mark.parametrize("terms", [{"N": 1e-3}, {"Q": 1e-5, "N": 1e-3}, {"K": 1e-4, "N": 1e-3},
                                   {"B": 1e-4, "N": 1e-4, "flicker_tau_min_s": 0.1, "flicker_tau_max_s": 1e3},
                                   {"R": 1e-6, "N": 1e-4}])
def test_single_term_allan_signature_within_ci(terms: dict) -> None:
    terms = triad(**terms)
    rate, n = 100.0, 400_000
    y = nz.NoiseGenerator(terms, rate, seed=21).next(n)
    check_within_ci(y, terms, rate, log_factors(n, 10))


# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", profile_names())
def test_profile_12h_allan_within_ci_of_theory(name: str) -> None:
    """12 h static capture per profile: noise + ADC through the model's own generators and front
    end (a constant input passes the low-pass unchanged), OADEV within the CI at 10 tau0 .. T/10."""
    prof = get_profile(name, seed=5)
    model = ImuErrorModel.from_profile(prof, seed=2)
    rate = model.output_rate_hz
    n = int(12 * 3600 * rate)
    m = log_factors(n, 10, per_decade=3)
    for gen, fe, const, params in (
        (model.gyro_noise, model.gyro_fe, [0.0, 5.0e-5, 4.0e-5], model.gyro_coefficients),
        (model.accel_noise, model.accel_fe, [0.0, 0.0, 9.80665], model.accel_coefficients),
    ):
        y = fe.digitize(gen.next(n, np.broadcast_to(np.asarray(const), (n, 3))))
        check_within_ci(y, params, rate, m, fe.quantization_white_var())


def test_model_output_through_front_end_keeps_the_allan_signature() -> None:
    """1 h static capture through ImuErrorModel.apply (1 kHz internal rate, 42 Hz low-pass,
    decimation, ADC): the noise is added after the low-pass, so the output's OADEV is still the
    theoretical curve (plus LSB^2/12 white) within its CI from 10 tau0 to T/10."""
    prof = get_profile("consumer_mems").with_overrides({"effects": None})
    model = ImuErrorModel.from_profile(prof, seed=8)
    n = 360_000
    Ws = []
    for _ in range(n // 40_000):
        g = model.sample_grid(40_000)
        k = len(g.t_internal)
        Ws.append(model.apply(g.t_internal, np.tile([0.0, 0.0, 9.80665], (k, 1)), np.tile([0.0, 5e-5, 4e-5], (k, 1)))[1])
    W = np.concatenate(Ws)
    assert model.decimation == 10
    check_within_ci(W, model.gyro_coefficients, 100.0, log_factors(n, 10), model.gyro_fe.quantization_white_var())
