"""The Gauss-Markov term inside the joint fit (rigctl.solvers.allan_fit with ``gm``, added by the
pipeline when rigctl.solvers.allan_gm's candidate test finds it at a stationary bump).

Expected values come from the simulated truth and from reads written here in numpy: the series
are generated here (white noise, a first-order Gauss-Markov process as an AR(1), a random walk),
their overlapping Allan deviation computed here from cumulative sums, each tau's EDF from NIST SP
1065's simple form for white FM, the band from scipy's chi-square quantiles, and the fitted
total from the reported coefficients with the Allan variance of each term written out here.
"""
from __future__ import annotations

import io
import json
import math
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter
from scipy.stats import chi2

from rigctl.solvers import allan_edf as E
from rigctl.solvers import allan_fit as F
from rigctl.solvers import allan_gm as GM

from allan_independent import agree


def ar1(n: int, tc_samples: float, sd: float, rng: np.random.Generator) -> np.ndarray:
    """A stationary AR(1) of standard deviation ``sd``: a sampled Gauss-Markov process."""
    phi = math.exp(-1.0 / tc_samples)
    y0 = rng.standard_normal() * sd
    return lfilter([sd * math.sqrt(1 - phi * phi)], [1.0, -phi], rng.standard_normal(n),
                   zi=[phi * y0])[0]


def oadev(y: np.ndarray, tau0: float, ms: np.ndarray) -> np.ndarray:
    x = np.concatenate(([0.0], np.cumsum(y))) * tau0
    return np.array([math.sqrt(np.mean((x[2 * m:] - 2 * x[m:-m] + x[:-2 * m]) ** 2)
                               / (2.0 * (m * tau0) ** 2)) for m in ms])


def nist_white_fm_edf(n_phase: int, m: np.ndarray) -> np.ndarray:
    n = n_phase
    return (3.0 * (n - 1) / (2 * m) - 2.0 * (n - 2) / n) * 4.0 * m ** 2 / (4.0 * m ** 2 + 5.0)


def total_avar(tau: np.ndarray, co: dict) -> np.ndarray:
    """The reported model's Allan variance from the JSON coefficients (SI), written out here:
    resolved IEEE 952 terms (a bound counts 0) and the Gauss-Markov terms."""
    def v(t: str) -> float:
        c = co.get(t) or {}
        return 0.0 if c.get("upper95") is not None else float(c.get("value", 0.0))
    q, n, b, k, r = (v(t) for t in "QNBKR")
    s2 = (3 * q * q / tau ** 2 + n * n / tau + 2 * math.log(2) / math.pi * b * b
          + k * k * tau / 3 + r * r * tau ** 2 / 2)
    for g in co.get("gm") or []:
        if g["sigma"].get("upper95") is None:
            x = tau / g["tau_c_s"]
            s2 = s2 + g["sigma"]["value"] ** 2 * (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x)) / x ** 2
    return s2


def inside_bonferroni_band(tau: np.ndarray, dev: np.ndarray, edf: np.ndarray,
                           fit: np.ndarray) -> np.ndarray:
    """At the informative taus (hi95/lo95 <= 2): is the fitted deviation inside the band that
    holds at all of them with 95 % (Bonferroni over their number, as if independent: wider
    than rigctl's family-wise band, which counts their correlation), or within 10 % of the
    deviation (the self-check's departure)? Returns the mask over the informative taus."""
    inf = np.sqrt(chi2.ppf(0.975, edf) / chi2.ppf(0.025, edf)) <= 2.0
    q = 0.05 / max(int(np.count_nonzero(inf)), 1)
    lo = dev * np.sqrt(edf / chi2.ppf(1 - q / 2, edf))
    hi = dev * np.sqrt(edf / chi2.ppf(q / 2, edf))
    ok = ((fit >= lo) & (fit <= hi)) | (np.abs(fit / dev - 1.0) <= 0.10)
    return ok[inf]


TAU0_SIM, HOURS_SIM = 0.05, 4.0  # 20 Hz, 4 h
TRUTH = {"N": 1e-3, "sigma": 5e-4, "tc": 10.0, "K": 2e-5}  # u sqrt(s), u, s, u/sqrt(s)


def _simulated(seed: int) -> tuple[np.ndarray, ...]:
    n = int(HOURS_SIM * 3600 / TAU0_SIM)
    rng = np.random.default_rng(seed)
    y = (TRUTH["N"] / math.sqrt(TAU0_SIM) * rng.standard_normal(n)
         + ar1(n, TRUTH["tc"] / TAU0_SIM, TRUTH["sigma"], rng)
         + np.cumsum(rng.standard_normal(n)) * TRUTH["K"] * math.sqrt(TAU0_SIM))
    ms = np.unique(np.round(np.logspace(0, math.log10(n // 9), 60)).astype(int))
    dev = oadev(y, TAU0_SIM, ms)
    return ms * TAU0_SIM, dev, ms, n


def _within(c, truth: float) -> bool:
    lo, hi = c.interval95
    return lo <= truth <= hi


def test_a_gauss_markov_process_is_fitted_beside_white_noise_and_random_walk() -> None:
    """White noise (N 1e-3 u sqrt(s)) + a Gauss-Markov process (sigma 5e-4 u, Tc 10 s) + a rate
    random walk (K 2e-5 u/sqrt(s)), 4 h at 20 Hz, six seeds: the candidate finds the process on
    every one and the joint fit with it (the Gauss-Markov kernel of allan_cov in its
    covariance) puts the truth inside its 95 % intervals -- Tc and sigma_GM in at least 5 of 6
    (measured, seeds 1-6: Tc 5, seed 4's 13.3 s [10.5, 17.6]; sigma_GM 6), N in at least 5
    (measured 6) and K in at least 4 (measured 4: GM swallows neither; before K was kept for the
    rise beside the term, seeds 2 and 4 dropped it at z ~ 1.8 and bounded it below the truth).
    K's count is what its coverage here allows, not a rule of thumb: over seeds 1-200 of this
    configuration (benchmarks/allan_interval_mc.py --config gm) the truth is inside K's 95 %
    interval or under its bound in 183 of 200 fits (91.5 %; resolved 180 of 194, the interval
    above the truth 7, below 7: Neyman's construction) -- 189 (94.5 %; 186 of 194, above 7,
    below 1) with nu read at the estimate -- so 5 of 6 fails a seed set with probability 8.6 %
    (3.9 % before) and 4 of 6 with 1.0 % (0.3 %), binomial; an interval covering 70 % passes
    4 of 6 with 74 %. Seeds 201-400 cover K 191/200, seeds 1-400 374/400 (93.5 %; N 374/400,
    sigma_GM 384/400): at 93.5 % 5 of 6 fails with 5.3 %, 4 of 6 with 0.5 %. Seeds 1-200's
    shortfall is not Tc's uncertainty (Tc held at the truth: K 184/200, N 185/200) nor the
    term's (docs/allan.md, "Coverage beside a Gauss-Markov term"), so the count stays 4. Seed 1 bounds K below the truth (1.82e-5, as 3 of the 6 bounds in those
    fits); seed 3's K^2 is 0.51 of the truth's, as low as in 3 % of the 194 resolved fits, and
    its interval [1.05, 1.93]e-5 rightly stops below the truth (the lowest 2.5 % must exclude
    it; with nu read at the estimate, [1.09, 2.04]e-5 held it). The fitted total with
    the term lies inside the band (Bonferroni over the informative taus, or within 10 %) at
    every informative tau in at least 5 of 6 (measured 6); the informative taus outside it,
    summed over the seeds, are at most a third of the IEEE 952 terms' alone (measured 0
    against 49 of 318), and rigctl's self-check passes on at least 5 (measured 6; IEEE-only 1
    of 6). Seed 2 has a B estimate where there is none (2.0e-4 [1.4e-4, 3.8e-4]): a finding."""
    n_tc = n_sig = n_n = n_k = n_total = n_check = n_check_ieee = 0
    out_gm = out_ieee = 0
    for seed in range(1, 7):
        tau, dev, ms, n = _simulated(seed)
        edf_r = np.array([E.edf("oadev", 0, int(m), n + 1) for m in ms])  # what rigctl feeds in
        cand = GM.gm_candidate(tau, dev, edf_r, TAU0_SIM, n + 1)
        assert cand["detected"], (seed, cand)
        fit = F.fit_terms(tau, dev, edf_r, tau0=TAU0_SIM, n_phase=n + 1,
                          gm={"tc_grid_s": cand["tc_grid_s"]})
        co = fit["coefficients"]
        assert len(co.gm) == 1 and fit["gm_term"]["tc_s"] == co.gm[0].tau_c_s
        g = co.gm[0]
        n_tc += g.tau_c_ci95[0] <= TRUTH["tc"] <= g.tau_c_ci95[1]
        n_sig += _within(g.sigma, TRUTH["sigma"])
        n_n += _within(co.N, TRUTH["N"])
        n_k += _within(co.K, TRUTH["K"])
        edf = nist_white_fm_edf(n + 1, ms)
        js = co.as_json()
        inside = inside_bonferroni_band(tau, dev, edf, np.sqrt(total_avar(tau, js)))
        n_total += bool(np.all(inside))
        out_gm += int(np.count_nonzero(~inside))
        ieee = F.fit_terms(tau, dev, edf_r, tau0=TAU0_SIM, n_phase=n + 1)
        assert not ieee["coefficients"].gm and "gm_term" not in ieee
        out_ieee += int(np.count_nonzero(~inside_bonferroni_band(
            tau, dev, edf, np.sqrt(total_avar(tau, ieee["coefficients"].as_json())))))
        n_check += fit["check"]["ok"]
        n_check_ieee += ieee["check"]["ok"]
    assert n_tc >= 5 and n_sig >= 5, (n_tc, n_sig)
    assert n_n >= 5 and n_k >= 4, (n_n, n_k)
    assert n_total >= 5 and 3 * out_gm <= out_ieee, (n_total, out_gm, out_ieee)
    assert n_check >= 5 and n_check > n_check_ieee, (n_check, n_check_ieee)


def _ieee_series(kind: str, n: int, tau0: float, rng: np.random.Generator) -> np.ndarray:
    y = 1e-3 / math.sqrt(tau0) * rng.standard_normal(n)  # N = 1e-3 u sqrt(s)
    y += np.cumsum(rng.standard_normal(n)) * 1e-5 * math.sqrt(tau0)  # K = 1e-5 u / sqrt(s)
    if kind == "nbk":  # a flicker floor: AR(1)s one per decade of Tc, 0.1 .. 1e5 s
        f = sum(ar1(n, 10.0 ** k / tau0, 1.0, rng) for k in range(-1, 6))
        y += 3e-5 * f / math.sqrt(7)
    return y


@pytest.mark.parametrize("kind", ["white_rw", "nbk"])
def test_no_gauss_markov_term_is_added_on_ieee_952_noise(kind: str, tmp_path: Path) -> None:
    """IEEE 952 noise through the whole pipeline (white + random walk; N + B + K with B a
    flicker floor made of one AR(1) per decade), 1 h at 100 Hz, two fixed seeds each: no
    Gauss-Markov term in the fit (no ``gm_term``, no ``coefficients.gm``), and where a candidate
    was tested it was not found (benchmarks/allan_gm.py measures the candidate's false-add rate:
    1 of 200 on each kind)."""
    import sys
    sys.path.insert(0, str(Path(__file__).parent))
    from recording_helpers import write_recording
    from rigctl.analysis import allan as AA

    n, tau0 = 360_000, 0.01
    for seed in (11, 12):
        rng = np.random.default_rng(seed)
        y = _ieee_series(kind, n, tau0, rng)
        rec = write_recording(tmp_path / f"{kind}{seed}.h5", 1 / tau0,
                              angular_rate=np.column_stack([y, y, y]))
        fit = AA.compute(str(rec), ["gx"])["axes"]["gx"]["fit"]
        assert "gm_term" not in fit and not fit["coefficients"].gm, (seed, fit.get("gm_term"))
        assert not (fit.get("gauss_markov") or {}).get("detected")


def _rigctl(*argv: str) -> str:
    from rigctl import cli

    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = cli.main(list(argv))
    assert code == 0, err.getvalue()[-2000:]
    return out.getvalue()


def test_the_mtig_gyro_through_the_cli_has_the_gauss_markov_term_in_its_fit(
        mtig_gx_allan: dict) -> None:
    """The real MTi-G gyro (1.39 h at 100 Hz) through `rigctl import` + `rigctl allan --json`:
    the Gauss-Markov term is in the fit, the statistical chi-square of the reported model is
    back within its 99 % point (measured 36.05 on 38 dof, p = 0.56; without the term 792.4 on
    39, and the IEEE-only fit needed a 25 % model error), the warning says the term was added
    with Tc in s and sigma_GM in deg/h, and the fitted total (written out here) follows the
    deviations computed here: inside the Bonferroni band or within 10 % at every informative
    tau but for at most the two the self-check names as chance (measured: 80 s, 0.85x).
    Tc and sigma_GM agree with a white + GM least-squares read written in
    tests/test_allan_gm_real.py (there: Tc 3.00 s [2.46, 3.68], 62.6 deg/h [59.1, 66.2];
    here measured Tc 3.35 s [2.48, 5.15], 62.0 deg/h [54.4, 70.1])."""
    # the run (import + allan --json, in process) and the independent read are made once per
    # session by tests/conftest.py's mtig_gx_allan, which test_allan_gm_real checks too
    y, text, res = mtig_gx_allan["y"], mtig_gx_allan["text"], mtig_gx_allan["res"]
    fit = res["fit"]
    t = fit["gm_term"]
    co = fit["coefficients"]
    assert len(co["gm"]) == 1 and co["gm"][0]["tau_c_s"] == pytest.approx(t["tc_s"])
    assert co["gm"][0]["tau_c_ci95_s"] == pytest.approx(t["tc_ci95_s"])
    ch = fit["check"]
    assert chi2.sf(ch["chi2"], ch["dof"]) >= 0.01, ch
    io_ = fit["ieee_only"]["check"]
    assert chi2.sf(io_["chi2"], io_["dof"]) < 0.01  # without the term: outside its band
    assert ch["ok"]
    assert "a first-order Gauss-Markov term was added to the fit: Tc" in text
    assert f"sigma_GM {t['sigma_deg_per_h']:.3g} deg/h" in text
    assert "Gauss-Markov sigma_GM, Tc:" in text  # the term table's row
    assert t["sigma_deg_per_h"] == pytest.approx(t["sigma_si"] * 180 / math.pi * 3600)
    # the independent read (white + GM)
    ind = mtig_gx_allan["ind"]
    assert agree(t["tc_s"], tuple(t["tc_ci95_s"]), ind["tc"], ind["tc_ci95"]), (t, ind["tc"])
    assert agree(t["sigma_si"], tuple(t["sigma_ci95_si"]), ind["sigma"], ind["sigma_ci95"])
    # the total against the deviations computed here
    ms = np.asarray(res["m"], dtype=int)
    tau = ms * 0.01
    dev = oadev(y, 0.01, ms)
    edf = nist_white_fm_edf(y.size + 1, ms)
    ok = inside_bonferroni_band(tau, dev, edf, np.sqrt(total_avar(tau, co)))
    assert np.count_nonzero(~ok) <= 2, tau[np.sqrt(chi2.ppf(0.975, edf) / chi2.ppf(0.025, edf)) <= 2][~ok]


def test_kalibr_writes_the_ieee_terms_and_says_the_gauss_markov_term_is_not_exported(
        tmp_path: Path) -> None:
    """Six axes, 30 min at 100 Hz: gyros white (N 1e-3 rad/sqrt(s)) + a Gauss-Markov process
    (sigma 1e-3 rad/s, Tc 5 s), accelerometers white (N 2e-3 m/s/sqrt(s)). `rigctl allan
    --kalibr`: the gyro noise density is the largest gyro N fitted with the term in the model
    (within 5 % of the truth, which the IEEE-only fit of such a curve misses: its N follows the
    process' tail), and the comment block says a Gauss-Markov term was fitted and not exported,
    with each gyro's sigma_GM and Tc."""
    import sys

    import yaml
    sys.path.insert(0, str(Path(__file__).parent))
    from recording_helpers import write_recording

    n, tau0 = 180_000, 0.01
    rng = np.random.default_rng(21)
    gyro = np.column_stack([1e-3 / math.sqrt(tau0) * rng.standard_normal(n)
                            + ar1(n, 5.0 / tau0, 1e-3, rng) for _ in range(3)])
    acc = 2e-3 / math.sqrt(tau0) * rng.standard_normal((n, 3)) + np.array([0, 0, 9.81])
    rec = write_recording(tmp_path / "six.h5", 1 / tau0, angular_rate=gyro, specific_force=acc)
    ky, js = tmp_path / "imu.yaml", tmp_path / "r.json"
    _rigctl("allan", str(rec), "--db", "none", "--kalibr", str(ky), "--json", str(js))
    doc = yaml.safe_load(ky.read_text())
    res = json.loads(js.read_text())["axes"]
    gyro_n = [res[a]["fit"]["coefficients"]["N"] for a in ("gx", "gy", "gz")]
    with_gm = [a for a in ("gx", "gy", "gz") if res[a]["fit"].get("gm_term")]
    assert len(with_gm) >= 2, [res[a]["fit"].get("gauss_markov") for a in ("gx", "gy", "gz")]
    top = max(c["upper95"] if c.get("upper95") is not None else c["value"] for c in gyro_n)
    assert doc["gyroscope_noise_density"] == pytest.approx(top, rel=1e-6)
    assert doc["gyroscope_noise_density"] == pytest.approx(1e-3, rel=0.05)
    text = ky.read_text()
    assert "Gauss-Markov term was fitted" in text and "NOT" in text
    for a in with_gm:
        g = res[a]["fit"]["coefficients"]["gm"][0]
        assert f"#   {a}: sigma_GM {g['sigma']['value']:.6e}" in text
        assert f"Tc {g['tau_c_s']:.4g} s" in text
    assert "gauss" not in " ".join(doc).lower()  # no key for it
