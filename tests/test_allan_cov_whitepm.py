"""The covariance of overlapping Allan-variance estimates where white PM (Q) matters past
m_a + m_b = 64 (an OCXO's curve: Q dominates to tau ~30 s), and the goodness-of-fit line it
feeds. Until this test, Q's pairs were left out past DISCRETE_MAX: the covariance was
indefinite (correlation eigenvalues to -0.064) and the OCXO quiet half's chi-square came out
2.8e5 on 37 dof while its self-check said "passed"."""
from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from rigctl.analysis import allan_text as T
from rigctl.cli import main
from rigctl.solvers import allan_cov as C

DATA = Path(__file__).parent / "data" / "ocxo-frequency-stable32" / "ocxo_frequency.txt.gz"


def oavar(x: np.ndarray, m: int) -> np.ndarray:
    """Overlapping Allan variance of phase rows x (records x samples), tau0 = 1."""
    d = x[:, 2 * m:] - 2.0 * x[:, m:-m] + x[:, :-2 * m]
    return np.mean(d * d, axis=1) / (2.0 * m * m)


def test_white_pm_pairs_past_discrete_max_give_chi2_per_dof_near_one():
    # white PM + white FM, tau0 = 1 s, 3000 phase points; Q dominates to tau ~20 s and the
    # taus (m up to 200) put most pairs past DISCRETE_MAX
    rng = np.random.default_rng(7)
    q, n_, n_phase, reps = 1.0, 0.3, 3000, 400
    ms = np.array([1, 3, 8, 20, 33, 50, 80, 130, 200])
    x = (q * rng.standard_normal((reps, n_phase))
         + np.cumsum(n_ * rng.standard_normal((reps, n_phase)), axis=1))
    s2 = np.column_stack([oavar(x, int(m)) for m in ms])
    truth = 3 * q * q / ms ** 2 + n_ * n_ / ms  # exact for sampled white PM and white FM
    cov = C.combine(C.term_covariances(1.0, ms, n_phase), {"Q": q * q, "N": n_ * n_})
    d = np.sqrt(np.diag(cov))
    assert np.linalg.eigvalsh(cov / np.outer(d, d)).min() > 0  # a covariance
    # its diagonal against the ensemble's variance (Q and N alone, written here: Isserlis)
    emp = s2.var(axis=0, ddof=1)
    assert np.all(np.abs(np.diag(cov) / emp - 1) < 0.3), np.diag(cov) / emp
    r = s2 - truth
    chi = np.einsum("ij,ij->i", r @ np.linalg.inv(cov), r)
    k = ms.size
    # mean chi2/dof within 4 standard errors of 1 (sd of chi2 ~ sqrt(2k), a little more for
    # the quadratic forms' heavier tail), and the p-values roughly uniform
    assert abs(chi.mean() / k - 1) < 4 * np.sqrt(2 * k) / k / np.sqrt(reps) * 1.5, chi.mean() / k
    p = stats.chi2.sf(chi, k)
    assert stats.kstest(p, "uniform").pvalue > 1e-3
    assert 0.05 < np.mean(p < 0.1) < 0.16


def test_ocxo_quiet_half_goodness_and_self_check_agree(tmp_path):
    rows = [ln for ln in gzip.decompress(DATA.read_bytes()).decode().splitlines()
            if ln.strip() and not ln.lstrip().startswith(("#", "%"))]
    src = tmp_path / "quiet.txt"
    src.write_text("\n".join(rows[9991:19982]) + "\n")  # the quiet stretch rigctl names
    rec, js = tmp_path / "quiet.h5", tmp_path / "quiet.json"
    assert main(["import", str(src), "-o", str(rec), "--force", "--columns", "gyr_x=0",
                 "--units", "gyr=counts:1e-07 rad/s", "--rate", "1"]) in (0, None)
    assert main(["allan", str(rec), "--db", "none", "--json", str(js)]) in (0, None)
    ax = json.loads(js.read_text())["axes"]["gx"]
    check = ax["fit"]["check"]
    # the chi-square's diagonal part, written here: the fit's taus, var 2 sigma^4 / EDF
    m = np.asarray(ax["m"], float)
    tau, dev, edf = np.asarray(ax["tau_s"]), np.asarray(ax["adev_rad/s"]), np.asarray(ax["edf"])
    co = ax["fit"]["coefficients"]
    def val(t):
        c = co.get(t) or {}
        return c.get("value", 0.0) if "ci95" in c else 0.0  # a bounded term is 0 in the total
    total = (3 * val("Q") ** 2 / tau ** 2 + val("N") ** 2 / tau + 2 * np.log(2) / np.pi * val("B") ** 2
             + val("K") ** 2 * tau / 3)
    z2 = (dev ** 2 - total) ** 2 / (2 * total ** 2 / edf)
    diag = float(np.sum(z2) * check["dof"] / m.size)  # per tau, scaled to the fit's dof
    # correlated taus can raise it over the diagonal's, not by 3000x (2.8e5 against ~50)
    assert check["chi2"] < 20 * max(diag, check["dof"]), (check["chi2"], diag)
    # beyond its 99 % point the self-check names it: never "passed"
    if check["p_value"] < 0.01:
        assert check["chi2_beyond_99"]
        assert "passed" not in T.quiet_check_text(check)
        assert "beyond its 99 % point" in T.quiet_check_text(check)


def test_white_pm_pairs_equal_the_integer_lag_sum_past_discrete_max():
    # the lag sum written here over every integer lag (R_ab from the phase kernels of the
    # module docstring: white PM a unit impulse, white FM -|t|/2, a first-order Gauss-Markov
    # rate -Tc^2 (e^(-|t|/Tc) - 1 + |t|/Tc); a quadratic cancels), against
    # term_covariances and gm_term_covariances for pairs with m_a + m_b > 64
    n_phase, tc, ms = 1500, 7.0, np.array([30, 41, 90])
    c = np.array([1.0, -2.0, 1.0])

    def phi(term, t):
        a = np.abs(t)
        if term == "Q":
            return (a < 0.5).astype(float)
        if term == "N":
            return -0.5 * a
        # G: Gauss-Markov rate of unit variance, -1/2 its phase's structure function
        return -tc * tc * (np.exp(-a / tc) - 1.0 + a / tc)

    def r(term, ma, mb, k):
        return sum(c[j] * c[l] * phi(term, j * ma - l * mb - k) for j in range(3) for l in range(3))

    cov = C.term_covariances(1.0, ms, n_phase)
    gcov = C.gm_term_covariances(1.0, ms, n_phase, tc)
    for i, ma in enumerate(ms):
        for j, mb in enumerate(ms):
            na, nb = n_phase - 2 * ma, n_phase - 2 * mb
            k = np.arange(-na, nb + 1, dtype=float)
            w = np.maximum(0.0, np.minimum(na, nb - k) - np.maximum(0.0, -k))
            norm = 2.0 / (4.0 * ma * ma * na * mb * mb * nb)
            for u, got in (("Q", cov[("Q", "Q")]), ("N", cov[("Q", "N")]), ("G", gcov[("Q", "G")])):
                want = norm * np.sum(r("Q", ma, mb, k) * r(u, ma, mb, k) * w)
                assert got[i, j] == pytest.approx(want, rel=1e-9, abs=1e-12 * abs(norm)), (u, ma, mb)


def test_fit_chi2_on_simulated_ocxo_like_records_is_near_its_dof():
    # records of the OCXO quiet half's length and taus (9992 phase points, tau0 = 1 s, taus
    # 1-2497 s) with its white PM, a white FM below it and its random-walk FM, written here;
    # the curve in plain numpy; rigctl's joint fit. Before the white-PM taps: chi2/dof median
    # ~7600, every p-value below 0.01 (60 records)
    from rigctl.solvers import allan_fit as F
    rng = np.random.default_rng(11)
    n, q, wn, k = 9992, 4.38e-11, 2e-12, 1.9e-13
    ms = np.unique(np.round(np.logspace(0, np.log10(2497), 76))).astype(int)
    cov = C.combine(C.term_covariances(1.0, ms.astype(float), n), {"Q": q * q, "N": wn * wn, "K": k * k})
    truth = 3 * q * q / ms ** 2 + wn * wn / ms + k * k * ms / 3
    edf = 2 * truth ** 2 / np.diag(cov)
    red, pv = [], []
    for _ in range(30):
        x = (q * rng.standard_normal(n) + np.cumsum(wn * rng.standard_normal(n))
             + np.cumsum(np.cumsum(k * rng.standard_normal(n))))
        s2 = np.array([np.mean((x[2 * m:] - 2 * x[m:-m] + x[:-2 * m]) ** 2) / (2.0 * m * m) for m in ms])
        c = F.fit_terms(ms * 1.0, np.sqrt(s2), edf, "gyro", tau0=1.0, n_phase=n)["check"]
        red.append(c["chi2"] / c["dof"])
        pv.append(c["p_value"])
    red, pv = np.array(red), np.array(pv)
    # 30 draws of chi2(37)/37 (sd 0.23 each): their mean within 0.7-1.3, p-values roughly uniform
    assert 0.7 < red.mean() < 1.3, red
    assert np.count_nonzero(pv < 0.01) <= 3, pv
    assert 0.25 < np.mean(pv < 0.5) < 0.85, pv
