"""The covariance across taus of Allan variances that skip gaps (Stable32): the terms of every
gap-free stretch pooled (rigctl.solvers.allan_cov.gapped_term_covariances), used by the joint
fit whenever a recording has more than one stretch (issue 15).

* Monte Carlo in plain numpy: white FM + random walk FM, a record cut into nine stretches by
  gaps of 1-5 samples; the pooled estimator computed here from its definition, 3000 times; the
  empirical covariance of the estimates against the solver's (and against the covariance of
  one continuous record, which must fail the same checks).
* A continuous record: the fit is exactly what it was (the same function is called).
* The real Astro Pi Sense HAT record (tests/data/astropi-sensehat-static, 237 stretches):
  --taus octave and all agree within their intervals on all six axes, and the accelerometers'
  chi-square is within its 99 % band (it was 7561 for 36 dof on ax with the one-record
  covariance).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from astropi_support import import_xup, seconds, xup_rows
from rigctl.analysis import allan as AA
from rigctl.solvers import allan_cov as C
from rigctl.solvers import allan_fit as F

# --- Monte Carlo ---------------------------------------------------------------------------
LENGTHS = np.array([37, 64, 64, 90, 150, 150, 150, 300, 520])  # samples per stretch
GAPS = np.array([1, 3, 1, 2, 5, 1, 1, 4])  # samples dropped between them
MS = np.array([1, 2, 4, 8, 16, 32, 64, 128, 200])
N_COEF, K_COEF, TAU0 = 1.0, 0.02, 1.0
REPS = 3000


@pytest.fixture(scope="module")
def pooled() -> np.ndarray:
    """REPS pooled Allan variances at MS (rows), computed from the definition: white FM +
    random walk FM rate samples, one continuous series with the gap samples cut out; in each
    stretch the phase restarts (L + 1 points), every second difference inside it is a term,
    and s2(m) = sum of all terms^2 / (2 tau^2 * number of terms)."""
    rng = np.random.default_rng(7)
    tot = int(LENGTHS.sum() + GAPS.sum())
    y = (N_COEF / np.sqrt(TAU0) * rng.standard_normal((REPS, tot))
         + K_COEF * np.sqrt(TAU0) * np.cumsum(rng.standard_normal((REPS, tot)), axis=1))
    starts = np.concatenate([[0], np.cumsum(LENGTHS[:-1] + GAPS)])
    sums = np.zeros((REPS, MS.size))
    n_terms = np.zeros(MS.size)
    for s0, n in zip(starts, LENGTHS):
        x = np.concatenate([np.zeros((REPS, 1)), np.cumsum(y[:, s0:s0 + n], axis=1) * TAU0], axis=1)
        for j, m in enumerate(MS):
            if n + 1 - 2 * m <= 0:
                continue
            d = x[:, 2 * m:] - 2.0 * x[:, m:-m] + x[:, :-2 * m]
            sums[:, j] += np.sum(d * d, axis=1)
            n_terms[j] += n + 1 - 2 * m
    s2 = sums / (2.0 * (MS * TAU0) ** 2 * n_terms)
    # the estimator is unbiased: its mean is the model's AVAR N^2/tau + K^2 tau/3
    tau = MS * TAU0
    truth = N_COEF ** 2 / tau + K_COEF ** 2 * tau / 3.0
    se = s2.std(axis=0) / np.sqrt(REPS)
    assert np.all(np.abs(s2.mean(axis=0) - truth) < 4.0 * se)
    return s2


def _agreement(s2: np.ndarray, cov: np.ndarray) -> dict:
    """How well ``cov`` describes the empirical covariance of the rows of ``s2``: the mean
    Mahalanobis distance (n for the true covariance, whatever the distribution) and its MC
    error, each variance's z-score (MC error from the fourth moments), the eigenvalues of the
    whitened empirical covariance (~1 +- 2 sqrt(n / REPS)) and the largest difference of
    correlations."""
    dev = s2 - s2.mean(axis=0)
    emp = dev.T @ dev / (REPS - 1)
    d = np.einsum("ri,ij,rj->r", dev, np.linalg.inv(cov), dev)
    z_var = (np.diag(emp) - np.diag(cov)) / np.sqrt(np.var(dev ** 2, axis=0) / REPS)
    lw = np.linalg.cholesky(cov)
    white = np.linalg.solve(lw, np.linalg.solve(lw, emp).T)
    eig = np.linalg.eigvalsh(0.5 * (white + white.T))
    se, sc = np.sqrt(np.diag(emp)), np.sqrt(np.diag(cov))
    corr_diff = np.abs(emp / np.outer(se, se) - cov / np.outer(sc, sc)).max()
    return {"d": d.mean(), "d_se": d.std() / np.sqrt(REPS), "z_var": z_var,
            "eig": (eig.min(), eig.max()), "corr_diff": corr_diff}


def test_gapped_covariance_matches_monte_carlo(pooled) -> None:
    coeff = {"N": N_COEF ** 2, "K": K_COEF ** 2}
    g = _agreement(pooled, C.combine(C.gapped_term_covariances(TAU0, MS, LENGTHS), coeff))
    n = MS.size
    # measured (seed 7): mean distance 9.03 +- 0.11, |z| <= 1.7, eigenvalues 0.92 .. 1.09,
    # correlations within 0.038
    assert abs(g["d"] - n) < 4.0 * g["d_se"], g
    assert np.all(np.abs(g["z_var"]) < 4.0), g
    assert 0.8 < g["eig"][0] and g["eig"][1] < 1.25, g
    assert g["corr_diff"] < 0.08, g
    # the covariance of one continuous record of the same number of samples fails them
    # (measured: distance 21.1 +- 0.5, variance z up to 15 at the long taus, eigenvalue 8.3)
    c = _agreement(pooled, C.combine(C.term_covariances(TAU0, MS, int(LENGTHS.sum()) + 1), coeff))
    assert c["d"] - n > 10.0 * c["d_se"], c
    assert np.max(c["z_var"]) > 8.0 and c["eig"][1] > 3.0, c


def test_identical_stretches_average_and_one_stretch_is_todays() -> None:
    ms = np.array([1, 2, 4, 8, 16, 32, 64, 128, 200])
    # c independent identical stretches: the pooled estimate is their mean, covariance / c;
    # exact where both are summed over integer lags (m_a + m_b <= 64 in the one-record code)
    one = C.term_covariances(0.1, ms, 447)
    three = C.gapped_term_covariances(0.1, ms, np.array([446, 446, 446]))
    small = np.add.outer(ms, ms) <= C.DISCRETE_MAX
    for p in C.PAIRS:
        np.testing.assert_allclose(3.0 * three[p][small], one[p][small], rtol=1e-12, atol=0.0)
    # one stretch: the same object as the continuous record's covariance ...
    assert C.gapped_term_covariances(0.1, ms, np.array([446])) is one
    # ... and the fit with a single stretch is the fit without stretches, to the last bit
    rng = np.random.default_rng(2)
    y = 0.01 * rng.standard_normal(20_000) + 1e-4 * np.cumsum(rng.standard_normal(20_000))
    x = np.concatenate([[0.0], np.cumsum(y) * 0.1])
    tau = ms * 0.1
    s2 = np.array([np.mean((x[2 * m:] - 2 * x[m:-m] + x[:-2 * m]) ** 2) / (2 * t * t)
                   for m, t in zip(ms, tau)])
    edf = (20_001 - 2 * ms) / ms  # a rough EDF: only the first pass and the bands use it
    a = F.fit_terms(tau, np.sqrt(s2), edf, "gyro", tau0=0.1, n_phase=20_001)
    b = F.fit_terms(tau, np.sqrt(s2), edf, "gyro", tau0=0.1, n_phase=20_001,
                    stretch_samples=np.array([20_000]))
    assert a["coefficients"] == b["coefficients"]
    assert a["check"]["chi2"] == b["check"]["chi2"]


def test_long_stretches_pool_the_one_record_covariances() -> None:
    """Two long stretches (the Gauss-Legendre path, kinks of W inside the lag ranges): the
    summed pair count gives sum_s n_s(a) n_s(b) Cov_s(a, b) / (N(a) N(b)) with Cov_s the
    one-record covariance of each stretch (the same quadrature: GAPPED_DISCRETE_LAGS = 0).
    White and random-walk FM to 1e-9; flicker's log kernel to 1 % (the breakpoints differ)."""
    ms = np.unique(np.round(np.logspace(0, np.log10(90_000), 24)))
    st = np.array([200_000, 299_997])
    n_s = np.maximum(0.0, st[None, :] + 1 - 2 * ms[:, None])
    big_n = n_s.sum(axis=1)
    want = {p: np.zeros((ms.size, ms.size)) for p in C.PAIRS}
    for j, length in enumerate(st):
        ok = n_s[:, j] > 0
        cs = C.term_covariances(0.01, ms[ok], int(length) + 1)
        w = np.outer(n_s[ok, j], n_s[ok, j]) / np.outer(big_n[ok], big_n[ok])
        for p in C.PAIRS:
            want[p][np.ix_(ok, ok)] += w * cs[p]
    saved = C.GAPPED_DISCRETE_LAGS
    try:
        C.GAPPED_DISCRETE_LAGS = 0
        got = C._gapped(0.01, ms, st, np.array([1, 1]))
    finally:
        C.GAPPED_DISCRETE_LAGS = saved
    for p in C.PAIRS:
        if "Q" in p:  # the one-record code leaves Q out of the quadrature
            continue
        tol = 1e-2 if "B" in p else 1e-9
        np.testing.assert_allclose(got[p], want[p], rtol=tol, atol=0.0, err_msg=str(p))


# --- the real Astro Pi record --------------------------------------------------------------
AXES = ["ax", "ay", "az", "gx", "gy", "gz"]


@pytest.fixture(scope="module")
def astro(ref_data, tmp_path_factory) -> tuple[np.ndarray, Path]:
    """(time stamps s, recording): the x-up section imported as rigctl import would."""
    rows = xup_rows(ref_data)
    rec = import_xup(rows, tmp_path_factory.mktemp("astro_gc"),
                     ("accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z"))
    t = seconds(rows)
    return t, rec


@pytest.fixture(scope="module")
def astro_fits(astro) -> dict:
    _, rec = astro
    return {taus: AA.compute(str(rec), AXES, taus) for taus in ("octave", "all")}


def _apart(fa, fb) -> list[str]:
    """Terms on which two fits disagree beyond their 95 % intervals / bounds."""
    bad = []
    for t in ("Q", "N", "B", "K", "R"):
        a, b = getattr(fa["coefficients"], t), getattr(fb["coefficients"], t)
        if a.resolved and b.resolved:
            if a.ci95[0] > b.ci95[1] or b.ci95[0] > a.ci95[1]:
                bad.append(t)
        elif a.resolved != b.resolved:
            s, u = (a, b) if a.resolved else (b, a)
            if s.ci95[0] > u.upper95:
                bad.append(t)
    return bad


def test_astro_pi_pooling_weights_are_the_stretches(astro, astro_fits) -> None:
    """The stretches read off the CSV's time stamps (a step above 1.5 x the 10 s interval is a
    gap) give, per factor m, the pipeline's term counts sum_s max(0, L_s + 1 - 2m): the
    weights the gapped covariance pools with."""
    t, _ = astro
    step = np.diff(t)
    edges = np.concatenate([[0], np.flatnonzero(step > 15.0) + 1, [t.size]])
    lengths = np.diff(edges)
    assert lengths.size == 237 and lengths.max() == 446
    for taus in ("octave", "all"):
        x = astro_fits[taus]["axes"]["ax"]
        want = [int(np.sum(np.maximum(0, lengths + 1 - 2 * int(m)))) for m in x["m"]]
        assert list(map(int, x["n_terms"])) == want


def test_astro_pi_octave_and_all_agree(astro_fits) -> None:
    out = {}
    for a in AXES:
        fo, fa = astro_fits["octave"]["axes"][a]["fit"], astro_fits["all"]["axes"][a]["fit"]
        out[a] = _apart(fo, fa)
    assert not any(out.values()), out
    # the accelerometers' joint chi-square (statistical covariance, the model as reported)
    # within its 99 % band, no model error needed: measured ax 3.7 / 5 (octave) and 25.2 / 37
    # (all), az 7.3 / 5 and 43.6 / 37, ay 5.3 / 5 (octave). ay all is 78.9 / 37 (p 7e-5,
    # outside; 44.5 / 37 with --temperature remove): a finding in docs/allan.md, not asserted
    for taus, axes in (("octave", ("ax", "ay", "az")), ("all", ("ax", "az"))):
        for a in axes:
            ck = astro_fits[taus]["axes"][a]["fit"]["check"]
            assert stats.chi2.sf(ck["chi2"], ck["dof"]) >= 0.01, (taus, a, ck["chi2"], ck["dof"])
            assert ck["model_error_rel"] == 0.0, (taus, a, ck["model_error_rel"])
    # the gyros gx and gz are outside IEEE 952 (RTIMULib's bias tracking shapes their curve):
    # chi-square hundreds of times its dof. Never passed as OK: the check fails and names taus
    for taus in ("octave", "all"):
        for a in ("gx", "gz"):
            ck = astro_fits[taus]["axes"][a]["fit"]["check"]
            assert stats.chi2.sf(ck["chi2"], ck["dof"]) < 1e-10
            assert not ck["ok"] and ck["outside"], (taus, a)


def test_astro_pi_chi_square_printed_and_called_out_beyond_its_band(astro_fits) -> None:
    """rigctl allan's text gives each fit's chi-square; beyond its 99 % point (scipy here) it
    says so even when no tau leaves its band (ay all: 78.9 / 37, the self-check's taus all in)."""
    from rigctl.analysis.allan_text import format_table

    for taus in ("octave", "all"):
        for a in AXES:
            r = astro_fits[taus]["axes"][a]
            # the record's fit, then (a record its stationarity test finds not stationary) the
            # quiet stretch's own fit below "quiet stretch:", each with its own line
            record, _, quiet = format_table(a, r).partition("\nquiet stretch:")
            fits = [(record, r["fit"]["check"])]
            if (r.get("quiet_stretch") or {}).get("fitted"):
                fits.append((quiet, r["quiet_stretch"]["fit"]["check"]))
            else:
                assert not quiet, (taus, a)
            for text, ck in fits:
                line = [s for s in text.splitlines() if s.startswith("goodness of fit:")]
                assert len(line) == 1 and f"on {ck['dof']} dof" in line[0], (taus, a, line)
                beyond = stats.chi2.sf(ck["chi2"], ck["dof"]) < 0.01
                assert ("beyond its 99 % point" in line[0]) == beyond, (taus, a, line)
    assert "beyond its 99 % point" in [s for s in format_table("ay", astro_fits["all"]["axes"]["ay"])
                                       .splitlines() if s.startswith("goodness")][0]
