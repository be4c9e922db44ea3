"""The Gauss-Markov candidate on a real gyro, against a fit written here.

tests/data/mtig-static-contaminated (1.39 h of an XSens MTi-G X gyro at rest, 100 Hz) has a bump
of a correlated process between ~1 and ~40 s that no IEEE 952 term follows. rigctl offers a
first-order Gauss-Markov (GM) candidate for it (``fit.gauss_markov`` in ``rigctl allan --json``) and,
when its test finds the process, puts the term into the joint fit (``fit.gm_term``: ``tc_s``,
``tc_ci95_s``, ``sigma_si``, ``sigma_ci95_si``). The expected values come from an
analysis written here with numpy and scipy only:

* the fully overlapping Allan variance at octave factors m = 4 .. 2^16 (cumulative sums);
* each tau's EDF from NIST SP 1065's simple approximation for white FM noise (the curve's main
  noise), and only the taus whose 95 % chi-square band is informative (hi95/lo95 <= 2);
* white noise + GM on sigma^2 by weighted least squares (scipy.optimize.least_squares, in log
  parameters, var(sigma^2) = 2 sigma^4 / EDF with the model's sigma^2, iterated), with the GM
  Allan variance written out: sigma_GM^2 (Tc/tau)^2 (2 tau/Tc - 3 + 4 e^(-tau/Tc) - e^(-2 tau/Tc));
* 95 % intervals of Tc and sigma_GM from the Jacobian (log parameters), the correlation of the
  octave taus' estimates neglected (that makes them narrower, the comparison stricter).

rigctl's and this fit's values must agree within their combined intervals, in log: |ln(a/b)|
<= sqrt(h_a^2 + h_b^2), h the log half-width of each interval on the side facing the other
value. Measured when written: rigctl's candidate Tc 3.50 s [2.59, 4.62], sigma_GM 61.1 deg/h
[54.8, 68.6]; the joint fit's term (main after the GM term went in) Tc 3.42 s [2.59, 4.52],
61.9 deg/h [55.7, 69.2], since Tc is chosen by -2 ln L and sigma_GM's interval is the marginal
one (27 Nov) Tc 3.01 s [2.28, 4.07], 62.7 deg/h [57.6, 68.8]; here Tc 3.00 s [2.46, 3.68], sigma_GM 62.6 deg/h [59.1, 66.2], chi2 9.1 on 11 dof. The same
comparison rejects a Tc or a sigma_GM 2x off (asserted), so it can fail.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from rigctl.display_units import capture_text

import allan_whittle as W
from allan_independent import assert_gm_agrees, white_gm_fit

TAU0 = 0.01


def _gm_fields(axis_result: dict, source: str) -> dict:
    """rigctl's Gauss-Markov values as (tc, tc interval, sigma, sigma interval), SI: the one
    place that knows where ``rigctl allan --json`` puts them. ``source`` "term": the term of the
    joint fit (``fit.gm_term``, reported since the GM term went into the fit); "candidate": the
    candidate test's own values (``fit.gauss_markov``)."""
    fit = axis_result["fit"]
    if source == "term":
        t = fit["gm_term"]
        return {"tc": t["tc_s"], "tc_ci95": tuple(t["tc_ci95_s"]), "sigma": t["sigma_si"],
                "sigma_ci95": tuple(t["sigma_ci95_si"]), "ok": bool(fit["gauss_markov"]["in_fit"])}
    g = fit["gauss_markov"]
    return {"tc": g["tc_s"], "tc_ci95": tuple(g["tc_ci95_s"]), "sigma": g["sigma_gm_si"],
            "sigma_ci95": tuple(g["sigma_gm_ci95_si"]), "ok": g["tested"] and g["detected"]}


def independent_fit(y: np.ndarray) -> dict:
    """White + GM on the overlapping Allan variance (module docstring)."""
    x = np.concatenate(([0.0], np.cumsum(y - y.mean()))) * TAU0
    ms = 2 ** np.arange(2, 17)
    ms = ms[2 * ms < y.size]
    s2 = np.array([np.mean((x[2 * m:] - 2.0 * x[m:-m] + x[:-2 * m]) ** 2) / (2.0 * (m * TAU0) ** 2)
                   for m in ms])
    n = y.size + 1  # phase points
    edf = (3.0 * (n - 1) / (2 * ms) - 2.0 * (n - 2) / n) * 4.0 * ms ** 2 / (4.0 * ms ** 2 + 5.0)
    informative = np.sqrt(chi2.ppf(0.975, edf) / chi2.ppf(0.025, edf)) <= 2.0
    tau, s2, edf = (ms * TAU0)[informative], s2[informative], edf[informative]
    return white_gm_fit(tau, s2, edf)


@pytest.fixture(scope="module")
def mtig(mtig_gx_allan: dict) -> dict:
    """import + allan --json of the real gyro, and the independent fit (tests/conftest.py's
    session fixture, shared with test_allan_gm_fit)."""
    return mtig_gx_allan


def test_independent_white_plus_gm_fit_describes_the_curve(mtig: dict) -> None:
    """The expected values' own check: white + GM leaves a chi-square inside its 99.9 % range
    (measured 9.1 on 11 dof), white noise alone does not (a GM term is needed here), and the
    hump's Tc lies inside the informative taus."""
    ind = mtig["ind"]
    assert chi2.ppf(0.0005, ind["dof"]) <= ind["chi2"] <= chi2.ppf(0.9995, ind["dof"]), ind["chi2"]
    tau, s2, edf = ind["tau"], ind["s2"], ind["edf"]
    w = edf / (2.0 * s2 ** 2)
    n2 = np.sum(w * s2 / tau) / np.sum(w / tau ** 2)  # white noise alone, weighted least squares
    chi_white = float(np.sum(w * (s2 - n2 / tau) ** 2))
    assert chi_white > chi2.ppf(0.9995, tau.size - 1), chi_white
    assert tau[0] < ind["tc"] < tau[-1]


@pytest.mark.parametrize("source", ["term", "candidate"])
def test_rigctl_gm_agrees_with_the_independent_fit(mtig: dict, source: str) -> None:
    """rigctl's Tc and sigma_GM (the joint fit's term, and the candidate test's) against the fit
    written here, within the combined intervals; a Tc or sigma_GM 2x off (either way) would
    fail the same comparison."""
    gm, ind = _gm_fields(mtig["res"], source), mtig["ind"]
    assert gm["ok"]
    assert_gm_agrees(gm, ind)


def test_capture_length_figures_include_the_gm_term(mtig: dict) -> None:
    """The Cramer-Rao figures of the fit with its GM term (``crb_rel_sd``, ``capture_h_for_25pct``
    of each term at the fitted model, a bounded term at its upper bound, the term's sigma_GM and
    Tc beside it) against tests/allan_whittle.py's independent Whittle sum with the same model
    (to 1e-6; at the printed length the bound is the +-25 % target, to 1e-4). B and K are bounds
    here; with the GM term's parameters in, B's figure is 9.1 h (2.4 h without them: a B that
    large would then be known to +-25 % in 4.5 h already, asserted) and K's 9.4 h (5.4 h), and
    the text says so ("+-25 % would need at least 9.1 h of capture")."""
    fit, text = mtig["res"]["fit"], mtig["text"]
    t = fit["gm_term"]
    assert t["resolved"]
    gm = {"sg": t["sigma_si"], "tc": t["tc_s"]}
    co = fit["coefficients"]
    base = {k: co[k]["value"] for k in "QNBK" if "upper95" not in co[k] and co[k]["value"] > 0}
    target = 0.25 / 1.959964
    figures = {}
    for k in "QNBK":
        e = fit["terms"][k]
        model = base if k in base else {**base, k: co[k]["upper95"]}
        seconds = e["capture_h"] * 3600.0
        assert e["crb_rel_sd"] == pytest.approx(W.rel_sd({**model, **gm}, seconds, 1 / TAU0)[k],
                                                rel=1e-6), k
        assert e["crb_rel_sd"] >= W.rel_sd(model, seconds, 1 / TAU0)[k], k
        need_h = e.get("capture_h_for_25pct")
        if need_h:
            figures[k] = need_h
            need = need_h * 3600.0
            assert W.rel_sd({**model, **gm}, need, 1 / TAU0)[k] == pytest.approx(target, rel=1e-4), k
            line = next(x for x in text.splitlines() if f"{fit['terms'][k]['name']}:" in x)
            assert f"at least {capture_text(need_h)} of capture" in line, line
    assert set(figures) == {"B", "K"}, figures
    b_model = {**base, "B": co["B"]["upper95"]}
    assert W.rel_sd(b_model, figures["B"] * 3600.0 / 2.0, 1 / TAU0)["B"] < target


def test_the_gm_terms_own_capture_figures(mtig: dict) -> None:
    """The GM term's own Cramer-Rao figures (``fit.gm_term.crb``: sigma_GM's and Tc's
    crb_rel_sd at this capture, and the capture for +-25 % where this one is short of it) against
    tests/allan_whittle.py's independent Whittle sum with the fitted model (to 1e-6; at the named
    length the bound is the target, to 1e-4), shown in the text and the HTML report as the IEEE
    terms' are. Sane for this capture (measured: sigma_GM +-4.5 % sd, no longer capture needed;
    Tc +-14.0 % sd, +-25 % needs about 1.7 h, 1.2x the 1.39 h capture)."""
    from rigctl.report import report_build

    fit, text = mtig["res"]["fit"], mtig["text"]
    t = fit["gm_term"]
    crb = t["crb"]
    co = fit["coefficients"]
    base = {k: co[k]["value"] for k in "QNBK" if "upper95" not in co[k] and co[k]["value"] > 0}
    model = {**base, "sg": t["sigma_si"], "tc": t["tc_s"]}
    seconds = crb["tc"]["capture_h"] * 3600.0
    assert seconds == pytest.approx((mtig["y"].size) * TAU0, rel=1e-9)
    ind = W.rel_sd(model, seconds, 1 / TAU0)
    target = 0.25 / 1.959964
    assert crb["sigma"]["crb_rel_sd"] == pytest.approx(ind["sg"], rel=1e-6)
    assert crb["tc"]["crb_rel_sd"] == pytest.approx(ind["tc"], rel=1e-6)
    assert not crb["sigma"]["bounded"] and not crb["tc"]["bounded"]
    # sigma_GM: this capture gives it within +-25 %; Tc: not quite, a capture a little longer does
    assert ind["sg"] < target and "capture_h_for_25pct" not in crb["sigma"]
    assert ind["tc"] > target
    need_h = crb["tc"]["capture_h_for_25pct"]
    assert seconds < need_h * 3600.0 < 2.0 * seconds, need_h
    assert W.rel_sd(model, need_h * 3600.0, 1 / TAU0)["tc"] == pytest.approx(target, rel=1e-4)
    line = next(x for x in text.splitlines() if "Gauss-Markov sigma_GM, Tc:" in x)
    tc_ci = t["tc_ci95_s"]
    assert (f"Tc {t['tc_s']:.4g} s [{tc_ci[0]:.4g}, {tc_ci[1]:.4g}] (this capture: "
            f"+-{100 * ind['tc']:.0f} % at best (Cramer-Rao); +-25 % needs about "
            f"{capture_text(need_h)})") in line, line
    assert line.count("Cramer-Rao") == 1, line  # none for sigma_GM
    page = report_build.build_report(mtig["rec"], mtig["rec"].parent / "rep").read_text()
    assert ("<td>Gauss-Markov correlation time Tc</td><td>s</td><td>"
            f"{t['tc_s']:.4g} [{tc_ci[0]:.4g}, {tc_ci[1]:.4g}]</td><td>n/a</td>"
            f"<td>{capture_text(need_h)}</td>") in page


def test_the_gm_intervals_against_the_bound(mtig: dict) -> None:
    """The GM term's 95 % intervals against the Cramer-Rao bound at this capture (the
    independent Whittle sum), each as an sd: its mean log half-width / 1.96. sigma_GM's is the
    bound's within 0.95-1.2x (measured 1.04: the marginal sd, Tc's uncertainty in quadrature;
    the old union of each Tc's conditional interval gave 1.41x, while the fit's sigma_GM
    scatters as the bound on simulated captures of this model, benchmarks/allan_gm_crb.py:
    0.0455 +- 0.0032 against 0.0452). Tc's is the bound's within 1.0-1.2x (measured 1.05, since
    Tc is chosen by -2 ln L, chi-square + ln det C; 1.30x with the chi-square alone, when the
    fit's Tc scattered at 0.181 +- 0.013 on those captures against the bound's 0.141, now 0.145
    +- 0.010, its interval covering 95 of 100)."""
    fit = mtig["res"]["fit"]
    t = fit["gm_term"]
    co = fit["coefficients"]
    base = {k: co[k]["value"] for k in "QNBK" if "upper95" not in co[k] and co[k]["value"] > 0}
    ind = W.rel_sd({**base, "sg": t["sigma_si"], "tc": t["tc_s"]}, mtig["y"].size * TAU0, 1 / TAU0)

    def as_sd(value: float, ci: list[float]) -> float:
        return (math.log(ci[1] / value) + math.log(value / ci[0])) / (2.0 * 1.959964)

    ratio_sigma = as_sd(t["sigma_si"], t["sigma_ci95_si"]) / ind["sg"]
    assert 0.95 <= ratio_sigma <= 1.2, ratio_sigma
    ratio_tc = as_sd(t["tc_s"], t["tc_ci95_s"]) / ind["tc"]
    assert 1.0 <= ratio_tc <= 1.2, ratio_tc
