"""Cramer-Rao bounds of the IEEE 952 terms (rigctl.solvers.allan_crb) and the fit against them."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.solvers import allan as A
from rigctl.solvers import allan_cov as C
from rigctl.solvers import allan_crb as R
from rigctl.solvers import allan_edf as E
from rigctl.solvers import allan_fit as F

from allan_synth import synth_rate


def test_white_noise_bound_is_the_sample_variance_bound() -> None:
    """White noise alone: N^2 from n samples has sd sqrt(2/n) N^2, so sd(N)/N = 1/sqrt(2n)."""
    for seconds, fs in ((100.0, 10.0), (3600.0, 100.0), (43200.0, 100.0)):
        n = seconds * fs
        assert R.crb_rel_sd({"N": 3e-4}, seconds, fs)["N"] == pytest.approx(
            1.0 / math.sqrt(2.0 * n), rel=1e-3)


def test_bound_matches_the_allan_covariance_gls_bound() -> None:
    """The GLS on the overlapping Allan curve with its exact covariance (allan_cov) reaches
    the spectral bound: the curve holds the information, so no other estimator can do better
    (the reason K is reported as a bound when this number is large)."""
    coeffs = {"N": 8.73e-5, "B": 4.85e-5, "K": 2.0e-6}  # consumer MEMS gyro, SI
    fs, seconds = 20.0, 6 * 3600.0
    n_phase = int(seconds * fs) + 1
    ms = np.unique(np.round(np.geomspace(1, (n_phase - 1) // 4, 40)).astype(np.int64))
    cov = C.combine(C.term_covariances(1 / fs, ms, n_phase), {t: v * v for t, v in
                                                              coeffs.items()})
    a = F.design_matrix(ms / fs)[:, 1:4]
    pc = np.linalg.inv(a.T @ np.linalg.solve(cov, a))
    gls = {t: 0.5 * math.sqrt(pc[i, i]) / coeffs[t] ** 2 for i, t in enumerate("NBK")}
    crb = R.crb_rel_sd(coeffs, seconds, fs)
    for t in "NBK":
        assert gls[t] == pytest.approx(crb[t], rel=0.05), (t, gls[t], crb[t])
    assert 0.1 < crb["K"] < 0.5  # K is the hard one


def test_fit_scatter_reaches_the_bound() -> None:
    """30 seeds of white + random-walk noise: the joint fit's K scatter is close to the
    bound (efficient) and not below it (the bound is a bound)."""
    fs, n, n_arw, k = 10.0, int(3 * 3600 * 10.0), 1e-3, 2e-5
    crb = R.crb_rel_sd({"N": n_arw, "K": k}, n / fs, fs)["K"]
    ks, crbs = [], []
    for seed in range(30):
        y = synth_rate(n, fs, n_arw, 0.0, k, seed=100 + seed)
        r = A.oadev(y, 1 / fs, 40, "rate")
        c = E.confidence("oadev", A.phase_from_rate(y, 1 / fs), r.m, r.dev)
        fit = F.fit_terms(r.tau_s, r.dev, c["edf"], "gyro", tau0=1 / fs, n_phase=r.n_phase)
        assert fit["coefficients"].K.resolved
        crbs.append(fit["terms"]["K"]["crb_rel_sd"])  # at the fitted model
        ks.append(fit["coefficients"].K.value ** 2)
    sd = float(np.std(ks)) / k ** 2 / 2.0  # sd(K)/K from sd(K^2)/K^2
    assert 0.75 * crb < sd < 1.35 * crb, (sd, crb)
    assert float(np.median(crbs)) == pytest.approx(crb, rel=0.15)


def test_duration_and_probability() -> None:
    coeffs = {"N": 1.22e-4, "B": 3.88e-5, "K": 1.0e-6}  # industrial MEMS gyro
    t = R.duration_for(coeffs, "K", 0.25 / 1.96, 100.0)
    assert R.crb_rel_sd(coeffs, t, 100.0)["K"] == pytest.approx(0.25 / 1.96, rel=1e-3)
    assert R.crb_rel_sd(coeffs, 0.5 * t, 100.0)["K"] > 0.25 / 1.96
    assert 12 * 3600 < t < 200 * 3600  # 12 h is not enough for +-25 % at 95 %
    assert R.prob_within(0.25 / 1.959964, 0.25) == pytest.approx(0.95, abs=1e-6)
    assert R.duration_for({"N": 1e-3, "K": 1e-12}, "K", 0.1, 100.0) == math.inf


def test_dominance_crossover() -> None:
    """N and K only: K dominates above tau = sqrt(3) N / K."""
    frac, lo, hi = R.dominance({"N": 1e-3, "K": 1e-5}, "K", 0.01, 1e4)
    assert lo == pytest.approx(math.sqrt(3) * 1e-3 / 1e-5, rel=0.01) and hi == pytest.approx(1e4)
    assert 0 < frac < 1
    assert R.dominance({"N": 1e-3, "B": 1e-3, "K": 1e-9}, "K", 0.01, 1e4)[0] == 0.0


def test_fit_bounds_an_unidentifiable_term() -> None:
    """Tactical-like gyro for 1 h: the bound says K cannot be resolved (sd several times K),
    and the fit reports an upper bound that covers the truth, with the bound's own crb."""
    fs = 100.0
    truth = {"N": 4.36e-5, "B": 2.42e-6, "K": 8.1e-9}
    assert R.crb_rel_sd(truth, 3600.0, fs)["K"] > 5.0
    y = synth_rate(int(3600 * fs), fs, truth["N"], truth["B"], truth["K"], seed=21)
    r = A.oadev(y, 1 / fs, 60, "rate")
    c = E.confidence("oadev", A.phase_from_rate(y, 1 / fs), r.m, r.dev)
    fit = F.fit_terms(r.tau_s, r.dev, c["edf"], "gyro", tau0=1 / fs, n_phase=r.n_phase)
    k, co = fit["terms"]["K"], fit["coefficients"]
    assert not co.K.resolved and co.K.upper95 > truth["K"]
    assert 0 < k["crb_rel_sd"] < math.inf
    assert co.N.resolved and fit["terms"]["N"]["crb_rel_sd"] < 0.01
    # how long a capture would resolve K to +-25 % (95 %), if K were as large as its bound: the
    # bound at that length is the target, and at the truth's K it would take longer still
    need_h = k["capture_h_for_25pct"]
    at_bound = {**{t: co.value(t) for t in ("N", "B") if getattr(co, t).resolved}, "K": co.K.upper95}
    assert 1.0 < need_h < 1e5
    assert R.crb_rel_sd(at_bound, need_h * 3600 * 1.01, fs)["K"] <= F.TARGET_REL_SD
    assert R.crb_rel_sd(at_bound, need_h * 3600 * 0.9, fs)["K"] > F.TARGET_REL_SD
    assert R.duration_for(truth, "K", F.TARGET_REL_SD, fs) / 3600 > need_h
    assert "capture_h_for_25pct" not in fit["terms"]["N"]  # N is already resolved
