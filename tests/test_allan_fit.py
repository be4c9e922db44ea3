"""Joint IEEE 952 fit: recovers N, B, K on synthetic noise; bounds; units."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.solvers import allan as A
from rigctl.solvers import allan_cov as C
from rigctl.solvers import allan_edf as E
from rigctl.solvers import allan_fit as F
from rigctl.solvers.noise_coefficients import as_coefficients, in_field_units

from allan_synth import synth_rate


def fu(fit: dict, term: str):
    """A fitted term in its field unit (value, ci95, upper95, resolved)."""
    return in_field_units(as_coefficients(fit["coefficients"]), term)[0]

D2R = math.pi / 180.0


def _analyse(y: np.ndarray, fs: float, sensor: str = "gyro") -> tuple[dict, dict]:
    r = A.oadev(y, 1.0 / fs, 60, data_type="rate")
    x = A.phase_from_rate(y, 1.0 / fs)
    c = E.confidence("oadev", x, r.m, r.dev)
    fit = F.fit_terms(r.tau_s, r.dev, c["edf"], sensor, tau0=1.0 / fs, n_phase=r.n_phase)
    return fit, F.piecewise_readoffs(r.tau_s, r.dev, sensor)


def test_fit_recovers_white_and_random_walk() -> None:
    fs, hours = 50.0, 3.0
    n_true, k_true = 0.2 * D2R / 60.0, 20.0 * D2R / 3600.0 / 60.0  # 0.2 deg/rt-h, 20 deg/h/rt-h
    y = synth_rate(int(hours * 3600 * fs), fs, n_true, 0.0, k_true, seed=11)
    fit, pw = _analyse(y, fs)
    co = fit["coefficients"]
    assert co.N.resolved and co.K.resolved
    assert abs(fu(fit, "N").value / 0.2 - 1) < 0.05
    assert abs(fu(fit, "K").value / 20.0 - 1) < 0.25
    lo, hi = fu(fit, "N").ci95
    assert lo < fu(fit, "N").value < hi and hi - lo < 0.02  # coverage: benchmark
    assert not co.R.resolved and fu(fit, "R").upper95 > 0
    assert not co.Q.resolved and not co.B.resolved  # none in the data
    assert pw["terms"]["N"]["value_deg/sqrt(h)"] is not None


def test_fit_recovers_bias_instability() -> None:
    fs, hours = 50.0, 4.0
    n_true, b_true, k_true = 0.1 * D2R / 60.0, 5.0 * D2R / 3600.0, 10.0 * D2R / 3600.0 / 60.0
    y = synth_rate(int(hours * 3600 * fs), fs, n_true, b_true, k_true, seed=12)
    fit, _ = _analyse(y, fs)
    assert abs(fu(fit, "N").value / 0.1 - 1) < 0.05
    assert fit["coefficients"].B.resolved and abs(fu(fit, "B").value / 5.0 - 1) < 0.20


def test_accelerometer_units_and_upper_bound() -> None:
    fs = 100.0
    vrw = 0.05 / 60.0  # 0.05 m/s/sqrt(h) in m/s/sqrt(s)
    y = 9.80665 + synth_rate(int(3600 * fs), fs, vrw, 0.0, 0.0, seed=13)
    fit, _ = _analyse(y, fs, "accel")
    co = fit["coefficients"]
    assert co.sensor == "accel" and abs(fu(fit, "N").value / 0.05 - 1) < 0.05
    assert fu(fit, "N").value == co.N.value * 60.0  # m/s/sqrt(s) -> m/s/sqrt(h)
    assert not co.B.resolved
    assert fu(fit, "B").upper95 == co.B.upper95 * (1000.0 / 9.80665)  # m/s^2 -> mg


def test_model_roundtrip_exact_curve() -> None:
    """Noise-free model curve: the fit returns the generating coefficients."""
    tau = np.logspace(-2, 4, 50)
    true = {"Q": 1e-6, "N": 2e-5, "B": 3e-6, "K": 4e-8, "R": 0.0}
    dev = np.sqrt(F.model_avar(tau, true))
    fit = F.fit_terms(tau, dev, np.full(tau.size, 1e4))
    for t in ("Q", "N", "B", "K"):
        assert F.term_value_si(fit, t) == __import__("pytest").approx(true[t], rel=1e-6)


def test_covariance_diagonal_is_greenhall_edf() -> None:
    """The mixture covariance reduces to Greenhall's EDF for each pure noise type (for
    m > 33; below, Greenhall's algorithm smooths the phase over m points (F = m), which
    shifts its EDF by up to ~3 % from the exact value for sampled white FM)."""
    from rigctl.solvers import allan_cov as C

    tau0, n = 0.01, 400_001
    ms = np.array([40, 64, 256, 1024, 8192, 40000, 99999])
    ct = C.term_covariances(tau0, ms, n)
    for term, alpha in (("N", 0), ("B", -1), ("K", -2)):
        var = np.diag(C.combine(ct, {term: 1.0}))
        s2 = F.model_avar(ms * tau0, {term: 1.0})
        edf_cov = 2.0 * s2 ** 2 / var
        edf_g = np.array([E.edf("oadev", alpha, int(m), n) for m in ms])
        np.testing.assert_allclose(edf_cov, edf_g, rtol=0.01, err_msg=term)


def test_covariance_between_taus_monte_carlo() -> None:
    """Predicted correlation of sigma^2 estimates at neighbouring taus vs 600 simulations
    (white + random-walk FM), and the variances themselves."""
    from rigctl.solvers import allan_cov as C

    n, fs, seeds = 4096, 1.0, 600
    ms = np.array([4, 6, 8, 16, 64])
    coef = {"N": 1.0, "K": 0.05}
    est = []
    for seed in range(seeds):
        y = synth_rate(n, fs, coef["N"], 0.0, coef["K"], seed=5000 + seed)
        est.append(A.oadev(y, 1.0, ms, "rate", mode="exact").dev ** 2)
    est = np.array(est)
    cov = C.combine(C.term_covariances(1.0, ms, n + 1), {t: v * v for t, v in coef.items()})
    emp = np.cov(est.T)
    sd_p, sd_e = np.sqrt(np.diag(cov)), np.sqrt(np.diag(emp))
    np.testing.assert_allclose(sd_e, sd_p, rtol=0.12)  # sd of an sd estimate: ~3 %
    corr_p, corr_e = cov / np.outer(sd_p, sd_p), emp / np.outer(sd_e, sd_e)
    assert np.max(np.abs(corr_p - corr_e)) < 0.1
    assert corr_p[1, 2] > 0.7  # strongly correlated: why a diagonal fit is too confident


def test_interval_coverage_and_no_spurious_terms() -> None:
    """40 short white + random-walk captures: the 95 % intervals of N and K cover the truth
    in >= 85 % of cases; Q, B and R (absent) come out as upper bounds in >= 90 %."""
    fs, n = 20.0, 72_000
    n_true, k_true = 0.3 * D2R / 60.0, 40.0 * D2R / 3600.0 / 60.0
    cover, absent_ok = [], []
    for seed in range(40):
        y = synth_rate(n, fs, n_true, 0.0, k_true, seed=300 + seed)
        r = A.oadev(y, 1.0 / fs, 40, data_type="rate", mode="exact")
        c = E.confidence("oadev", A.phase_from_rate(y, 1.0 / fs), r.m, r.dev)
        fit = F.fit_terms(r.tau_s, r.dev, c["edf"], "gyro", tau0=1.0 / fs, n_phase=r.n_phase)
        for t, v in (("N", n_true), ("K", k_true)):
            c = getattr(fit["coefficients"], t)
            cover.append(c.ci95[0] <= v <= c.ci95[1] if c.resolved else v <= c.upper95)
        absent_ok += [not getattr(fit["coefficients"], t).resolved for t in ("Q", "B", "R")]
    assert np.mean(cover) >= 0.85, np.mean(cover)
    assert np.mean(absent_ok) >= 0.90, np.mean(absent_ok)


def test_curve_limit_read_off_well_determined_taus_only() -> None:
    """The curve's hard limit on a term (no bound reported above it) comes from the taus whose
    95 % band is informative, EDF >= 16.95 (hi95/lo95 <= 2), not from the last taus of a
    capture: there a handful of averages (EDF 3) put the true sigma anywhere in 0.57 .. 3.6 x
    the measured one. Seen on a 12 h consumer_mems gy (issue 15): the last octave tau, 3.1 EDF,
    0.23x the emulated K's line, cut the K bound to 5.86 deg/h/sqrt(h) (truth 24.7). Here: an
    IEEE 952 curve (N, B, K) on octave taus whose EDF falls as T/tau, the last three taus (EDF
    12, 6, 3) drawn 0.3x low; expected limits computed here in numpy over the taus with EDF
    >= 16.95 (scipy's chi-square)."""
    from scipy.stats import chi2

    tau = 2.0 ** np.arange(0, 14)  # 1 .. 8192 s
    n, b, k = 1e-4, 2e-5, 3e-7  # rad/sqrt(s), rad/s, rad/s/sqrt(s)
    dev = np.sqrt(n ** 2 / tau + 2 * math.log(2) / math.pi * b ** 2 + k ** 2 * tau / 3)
    edf = 3.0 * 8192.0 / tau
    dev[edf < 16] *= 0.3
    good = np.sqrt(chi2.ppf(0.975, edf) / chi2.ppf(0.025, edf)) <= 2.0
    assert good.sum() == 11  # tau <= 1024 s (EDF 24 .. 24576)
    cols = {"N": 1.0 / tau, "B": np.full(tau.size, 2 * math.log(2) / math.pi), "K": tau / 3.0}
    lim = {t: math.sqrt(np.min(dev[good] ** 2 / c[good])) for t, c in cols.items()}
    lim_every = {t: math.sqrt(np.min(dev ** 2 / c)) for t, c in cols.items()}
    assert lim["K"] > 3.0 * lim_every["K"]  # the low last taus would cut K to a third
    fit = F.fit_terms(tau, dev, edf, "gyro")
    for t in ("N", "B", "K"):
        e = fit["terms"][t]
        assert e[f"curve_limit_{F.SI_UNITS['gyro'][t]}"] == pytest.approx(lim[t], rel=1e-9), t
    assert fit["terms"]["K"]["curve_limit_tau_s"] == 1024.0
    for t, e in fit["terms"].items():
        c = getattr(fit["coefficients"], t)
        if not c.resolved:
            assert c.upper95 <= e[f"curve_limit_{F.SI_UNITS['gyro'][t]}"] * (1 + 1e-12)


def test_limit_band_holds_the_truth_at_every_tau_for_octave_and_dense_taus() -> None:
    """B, K and R are held in the fit within the curve's upper band at the informative taus.
    That band must hold the true curve at *every* such tau with 97.5 % probability, however
    densely the taus are sampled: the pointwise 97.5 % upper end, whose minimum over the
    128 informative taus of --taus all fell below the truth (a 12 h consumer_mems ax: B held
    at 0.128 mg [0.118, 0.138] against octave's 0.151, truth 0.153), does not. Checked here
    on 1000 plain-numpy white-FM series (sigma^2 = 1/tau exactly), octave and a dense set
    (every k 2^j, 8 <= k < 16: the fast mode's --taus all): the share of series whose true
    curve is above the band somewhere, against the design level 2.5 %."""
    from scipy.stats import chi2

    from rigctl.solvers import allan_cov as C

    n, reps = 4096, 1000
    rng = np.random.default_rng(7)
    x = np.zeros((reps, n + 1))
    np.cumsum(rng.standard_normal((reps, n)), axis=1, out=x[:, 1:])
    sets = {"octave": 2 ** np.arange(0, 9),
            "dense": np.unique(np.r_[np.arange(1, 16),
                                     [k * 2 ** j for j in range(1, 6) for k in range(8, 16)]])}
    miss, miss_pointwise, m_eff = {}, {}, {}
    for name, ms in sets.items():
        ms = ms[ms <= 300]
        s2 = np.stack([np.mean((x[:, 2 * m:] - 2 * x[:, m:-m] + x[:, :-2 * m]) ** 2, axis=1)
                       / (2.0 * m * m) for m in ms], axis=1)
        truth = 1.0 / ms
        edf = np.array([E.edf("oadev", 0, int(m), n + 1) for m in ms])
        good = np.sqrt(chi2.ppf(0.975, edf) / chi2.ppf(0.025, edf)) <= 2.0
        m_eff[name] = F._effective_taus(C.term_covariances(1.0, ms, n + 1),
                                        F.design_matrix(ms * 1.0), truth, edf, good)
        band = np.array([F._family_band(s, edf, m_eff[name]) for s in s2])
        miss[name] = np.mean(np.any(band[:, good] ** 2 < truth[good], axis=1))
        hi95 = s2 * edf / chi2.ppf(0.025, edf)  # the pointwise band (sigma^2)
        miss_pointwise[name] = np.mean(np.any(hi95[:, good] < truth[good], axis=1))
    assert len(sets["dense"]) > 5 * len(sets["octave"])
    assert m_eff["dense"] < 1.5 * m_eff["octave"]  # a property of the span, not the sampling
    for name in sets:
        assert 0.01 <= miss[name] <= 0.045, (name, miss[name])  # 2.5 % +- ~3 sd (1000 series)
        assert miss_pointwise[name] > 0.10, (name, miss_pointwise[name])
    assert abs(miss["dense"] - miss["octave"]) < 0.02


def test_a_chance_dip_of_the_floor_does_not_hold_b_below_the_truth() -> None:
    """The 12 h consumer_mems ax case as a curve: N 3.92e-3 m/s/sqrt(s) and B 1.5e-3 m/s^2 (the
    profile), 100 Hz, 12 h, the floor dipping smoothly to 0.36x in sigma^2 around 3000 s (0.6x
    in sigma; the capture: 0.38 at 2294 s, 0.33 at 2949 s, 0.36 at 4260 s). The pointwise 95 %
    band's minimum, read here with scipy, puts B's old limit at 0.915x the truth; with the
    family-wise band both tau sets give B with a 95 % interval that holds the truth and
    overlaps the other's."""
    from scipy.stats import chi2

    tau0, n_phase, nn, bb = 0.01, 4_320_001, 3.92e-3, 1.5e-3
    c_b = 2.0 * math.log(2.0) / math.pi
    sets = {"octave": 2 ** np.arange(0, 19),
            "all": np.unique(np.r_[np.arange(1, 16),
                                   [k * 2 ** j for j in range(1, 17) for k in range(8, 16)]])}
    ci = {}
    for name, ms in sets.items():
        ms = ms[ms <= (n_phase - 1) // 4]
        tau = ms * tau0
        s2 = nn ** 2 / tau + c_b * bb ** 2
        alpha = np.where(nn ** 2 / tau > c_b * bb ** 2, 0, -1)
        edf = np.array([E.edf("oadev", int(a), int(m), n_phase) for a, m in zip(alpha, ms)])
        s2 = s2 * (1.0 - 0.64 * np.exp(-0.5 * (np.log(tau / 3000.0) / 0.6) ** 2))
        dev = np.sqrt(s2)
        good = np.sqrt(chi2.ppf(0.975, edf) / chi2.ppf(0.025, edf)) <= 2.0
        old_limit = np.min(dev[good] * np.sqrt(edf[good] / chi2.ppf(0.025, edf[good]))) / math.sqrt(c_b)
        assert old_limit < 0.93 * bb
        fit = F.fit_terms(tau, dev, edf, "accel", tau0=tau0, n_phase=n_phase)
        b = fit["coefficients"].B
        assert b.resolved, name
        assert b.ci95[0] <= bb <= b.ci95[1], (name, b)
        ci[name] = b.ci95
    assert ci["octave"][0] <= ci["all"][1] and ci["all"][0] <= ci["octave"][1]


def _edf_simple(n: float, m: int) -> float:
    """NIST SP 1065 simple EDF of the overlapping ADEV (the smaller of white FM's and flicker FM's)."""
    wfm = (3 * (n - 1) / (2 * m) - 2 * (n - 2) / n) * 4 * m * m / (4 * m * m + 5)
    ffm = 2 * (n - 2) ** 2 / (2.3 * n - 4.9) if m == 1 else 5 * n * n / (4 * m * (n + 3 * m))
    return min(wfm, ffm)


def _gm_avar(tau: np.ndarray, s: float, t: float) -> np.ndarray:
    """Allan variance of a first-order Gauss-Markov rate (variance s^2, correlation time t):
    s^2 t^2 / tau^2 (2 tau / t - 3 + 4 exp(-tau / t) - exp(-2 tau / t)); ~ (2/3) s^2 tau / t
    (rising) well below t, 2 s^2 t / tau (a white-noise line, N^2 = 2 s^2 t) well above."""
    x = tau / t
    return s * s * t * t / tau ** 2 * (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x))


def test_a_rising_front_is_left_out_of_the_fit_for_every_tau_set() -> None:
    """A curve that rises from tau0 and then falls (a Gauss-Markov process of 1 s dominating
    the short taus over a weak white noise and a floor; on a real capture, a filtered output
    that dwells on its quantization levels: the Galaxy S5 in test_allan_real_phone) is no IEEE
    952 total: the taus before its top are left out of the fit, with octave and dense taus
    alike, so both give N compatible with each other. Expected here in numpy: the top (the
    curve's maximum below 100 s) and the asymptotic white level sqrt(N_w^2 + 2 s^2 t) the
    curve approaches after it. Curves whose first clear move is down (a bump later), that
    only rise (K), or that are IEEE 952 totals have no front."""
    tau0, n = 0.1, 1_000_000
    dh, drh = D2R / 3600.0, D2R / 60.0  # deg/h and deg/sqrt(h) in SI
    s, t, n_w, b = 100.0 * dh, 1.0, 0.02 * drh, 10.0 * dh
    n_inf = math.sqrt(n_w ** 2 + 2 * s * s * t)
    sets = {"octave": 2 ** np.arange(17),
            "dense": np.unique(np.round(np.logspace(0, math.log10(n / 4), 90))).astype(int)}
    got = {}
    for name, ms in sets.items():
        tau = ms * tau0
        edf = np.array([_edf_simple(n + 1, int(m)) for m in ms])
        avar = _gm_avar(tau, s, t) + n_w ** 2 / tau + F._B_FACTOR * b * b
        dev = np.sqrt(avar)
        top = int(np.argmax(np.where(tau < 100.0, dev, 0.0)))
        assert dev[top] > math.sqrt(2) * dev[0] and dev[top:].min() < dev[top] / math.sqrt(2)
        assert F.rising_front(tau, dev, edf) == top, name
        fit = F.fit_terms(tau, dev, edf, "gyro", tau0=tau0, n_phase=n + 1)
        assert fit["check"]["front_excluded"]["top_tau_s"] == tau[top]
        got[name] = fu(fit, "N")
        assert got[name].resolved, name
        # N read off the curve after its top: its 95 % interval meets the white levels the
        # curve shows there, from sigma sqrt(tau) at the top to the asymptote it approaches
        # from below (the Gauss-Markov line reaches 2 s^2 t / tau only for tau >> t; measured:
        # 2.10 [1.90, 2.35] octave, 2.14 [2.04, 2.24] dense, for 2.36; with the B hold of the
        # bfloor branch merged, octave 2.37 [2.13, 2.67])
        lo, hi = got[name].ci95
        assert lo * drh < n_inf and hi * drh > dev[top] * math.sqrt(tau[top]), (name, got[name], n_inf / drh)
        # no front: the same process under a white noise that makes the curve fall from tau0,
        # a K-only rise, an IEEE 952 total
        for other in (_gm_avar(tau, s, 30.0) + (1.0 * drh) ** 2 / tau,
                      (0.01 * drh) ** 2 / tau + (5.0 * dh / math.sqrt(3600)) ** 2 * tau / 3,
                      F.model_avar(tau, {"N": 0.2 * drh, "B": 5 * dh, "K": 2 * dh / 60})):
            assert F.rising_front(tau, np.sqrt(other), edf) == 0, name
    o, d = got["octave"], got["dense"]
    assert o.ci95[0] <= d.ci95[1] and d.ci95[0] <= o.ci95[1], (o, d)


def test_bvls_is_scipys_lsq_linear_bit_for_bit() -> None:
    """allan_fit.bvls is scipy's lsq_linear(method="bvls") without its wrapper: on the fits'
    kind of problem (40 taus x 4-6 scaled Allan columns Q, N, B, K, R, GM; Q free or >= 0,
    the others >= 0, with and without finite upper limits, noisy curves that put terms on
    their bounds) the same solution, compared bit for bit with scipy's (the reference)."""
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(7)
    loops = 0
    for case in range(600):
        tau = np.geomspace(0.01, 3000.0, 40) * rng.uniform(0.5, 2.0)
        k = int(rng.integers(4, 7))
        cols = [3.0 / tau ** 2, 1.0 / tau, np.full(tau.shape, 0.44), tau / 3.0, tau ** 2 / 2.0,
                1.0 / (1.0 + (tau / rng.uniform(0.1, 100.0)) ** 2)][:k]
        a = np.column_stack(cols)
        truth = rng.uniform(0.0, 1.0, k) * (rng.uniform(size=k) < 0.6)
        truth[1] += 0.01  # white noise always there: a curve > 0
        y = (a @ truth) * np.exp(rng.normal(0.0, rng.choice([0.01, 0.1, 0.5]), tau.size))
        w = 1.0 / np.maximum(y, 1e-300)
        aw, bw = a * w[:, None], y * w
        sc = np.linalg.norm(aw, axis=0)
        aw = aw / sc
        lb = np.zeros(k)
        if case % 2:
            lb[0] = -np.inf
        ub = np.full(k, np.inf)
        if case % 3 == 0:
            ub = np.where(rng.uniform(size=k) < 0.5, rng.uniform(0.01, 2.0, k) * sc, np.inf)
            ub = np.maximum(ub, 1e-300)
        ref = lsq_linear(aw, bw, bounds=(lb, ub), method="bvls")
        loops += ref.nit > 0
        np.testing.assert_array_equal(F.bvls(aw, bw, lb, ub), ref.x)
    assert loops > 100  # the bounded loop, not only the unbounded solution, is compared


def test_solve_triangular_is_scipys_bit_for_bit() -> None:
    """allan_fit.solve_triangular is scipy.linalg.solve_triangular(lw, b, lower=True) without
    its wrapper: on the fits' kind of problem (the lower Cholesky factor of a 40-tau Allan
    covariance, C- and Fortran-ordered, from _whiten; b a design of 1-6 columns or one curve)
    the same numbers bit for bit, compared with scipy's (the reference); the same errors for
    a non-finite input (ValueError) and a singular factor (LinAlgError); other inputs (ints,
    lower=False) handed to scipy's function."""
    from scipy.linalg import solve_triangular as scipy_st

    rng = np.random.default_rng(3)
    tau = np.geomspace(0.01, 900.0, 40)  # a 1 h record at 100 Hz: up to T / 4
    ms = np.round(tau / 0.01)
    ct = C.term_covariances(0.01, ms, 360_001)
    for case in range(60):
        coeff = {t: float(v) for t, v in zip(C.TERMS4, rng.uniform(0.0, 1.0, 4) ** 4)}
        coeff["N"] += 1e-2
        lw = F._whiten(C.combine(ct, coeff))
        assert np.all(np.diag(lw) > 0)
        lw = np.asfortranarray(lw) if case % 2 else np.ascontiguousarray(lw)
        assert lw.flags.f_contiguous == bool(case % 2)
        k = int(rng.integers(1, 7))
        for b in (rng.standard_normal((40, k)) * 10.0 ** rng.uniform(-20, 5, k),
                  rng.standard_normal(40)):
            np.testing.assert_array_equal(F.solve_triangular(lw, b, lower=True),
                                          scipy_st(lw, b, lower=True))
    bad = np.array(lw)
    bad[3, 1] = np.nan
    for args in ((bad, b), (lw, np.where(np.arange(40) == 5, np.inf, b))):
        with pytest.raises(ValueError):
            scipy_st(*args, lower=True)
        with pytest.raises(ValueError):
            F.solve_triangular(*args, lower=True)
    sing = np.array(lw)
    sing[7, 7] = 0.0
    with pytest.raises(np.linalg.LinAlgError):
        scipy_st(sing, b, lower=True)
    with pytest.raises(np.linalg.LinAlgError):
        F.solve_triangular(sing, b, lower=True)
    ints = np.tril(rng.integers(1, 5, (6, 6)))
    np.testing.assert_array_equal(F.solve_triangular(ints, np.arange(6.0)),
                                  scipy_st(ints, np.arange(6.0), lower=True))
    np.testing.assert_array_equal(F.solve_triangular(lw.T, b, lower=False),
                                  scipy_st(lw.T, b, lower=False))


def test_cholesky_is_scipys_bit_for_bit() -> None:
    """allan_fit.cholesky is scipy.linalg.cholesky(a, lower=True) without its wrapper: on
    _whiten's kind of input (a 40-tau Allan correlation plus a small jitter, C- and
    Fortran-ordered) the same factor bit for bit (scipy's the reference); the same errors for
    a non-finite input (ValueError) and an indefinite one (LinAlgError); ints and lower=False
    through scipy's function."""
    from scipy.linalg import cholesky as scipy_ch

    rng = np.random.default_rng(5)
    tau = np.geomspace(0.01, 900.0, 40)
    ct = C.term_covariances(0.01, np.round(tau / 0.01), 360_001)
    for case in range(60):
        coeff = {t: float(v) for t, v in zip(C.TERMS4, rng.uniform(0.0, 1.0, 4) ** 4)}
        coeff["N"] += 1e-2
        cov = C.combine(ct, coeff)
        d = np.sqrt(np.diag(cov))
        corr = cov / np.outer(d, d) + 10.0 ** rng.uniform(-9, -3) * np.eye(40)
        corr = np.asfortranarray(corr) if case % 2 else np.ascontiguousarray(corr)
        np.testing.assert_array_equal(F.cholesky(corr, lower=True), scipy_ch(corr, lower=True))
    bad = np.array(corr)
    bad[2, 3] = bad[3, 2] = np.inf
    indefinite = np.array(corr)
    indefinite[9, 9] = -1.0
    for arg, err in ((bad, ValueError), (indefinite, np.linalg.LinAlgError)):
        with pytest.raises(err):
            scipy_ch(arg, lower=True)
        with pytest.raises(err):
            F.cholesky(arg, lower=True)
    spd = np.array([[4, 2], [2, 3]])
    np.testing.assert_array_equal(F.cholesky(spd), scipy_ch(spd, lower=True))
    np.testing.assert_array_equal(F.cholesky(corr, lower=False), scipy_ch(corr, lower=False))
