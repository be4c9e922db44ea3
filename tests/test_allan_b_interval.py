"""A resolved term's interval from Neyman's construction: its spread read at each candidate
value, not at the estimate (issue 15).

The quickstart's 5-minute capture (configs/sim.yaml) resolves B in about half of the gyro fits;
31 of those 319 intervals lay wholly above the truth (benchmarks/allan_quickstart_cov.py, seeds
0-199; 2.5 % per side allowed). The interval was chi-square with Satterthwaite's
nu = 2 p^2 / sd(p)^2 taken at the estimate p_hat, and the sd there came from the covariance of
the sigma^2 estimates at the fitted model: a chance high B makes B's taus dominant and its own
relative sd small, so the highest estimates got the narrowest intervals (reported nu 25-35:
mean log(B / truth) +0.31, 20 of 22 above; nu < 15: -0.06, none). Now the ends solve
p_hat = p chi2_q(nu(p)) / nu(p) with nu at the candidate p (the Neyman construction that the
one-sided bounds already use).

Checked here independently with scipy: the ends satisfy their defining equations for a spread
that grows with p, and reduce to the plain Satterthwaite interval where the relative spread is
constant; and on one quickstart seed whose B interval lay above the truth.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from helpers import ROOT
from recording_helpers import write_recording

from rigctl.analysis import allan as AA
from rigctl.solvers import allan_fit as F
from rigctl.solvers.noise_coefficients import as_coefficients

sys.path.insert(0, str(ROOT / "benchmarks"))
from allan_quickstart_cov import default_noise  # noqa: E402 - the quickstart's noise, one place


def test_the_ends_solve_their_equations_with_nu_at_the_candidate() -> None:
    p_hat = 1.0

    def sd(p: float) -> float:  # an absolute floor plus a share of p (the other terms + itself)
        return 0.1 + 0.25 * p

    for conf in (0.683, 0.95):
        q = (1.0 - conf) / 2.0
        lo, hi = F._neyman_chi2_ci(p_hat, sd, conf)
        for v, quant in ((lo * lo, 1.0 - q), (hi * hi, q)):
            nu = 2.0 * v * v / sd(v) ** 2
            assert abs(v * chi2.ppf(quant, nu) / nu - p_hat) < 1e-4, (conf, v, nu)
        # ... and the interval lies lower than the one with nu taken at p_hat
        nu_hat = 2.0 * p_hat ** 2 / sd(p_hat) ** 2
        lo0 = math.sqrt(p_hat * nu_hat / chi2.ppf(1.0 - q, nu_hat))
        hi0 = math.sqrt(p_hat * nu_hat / chi2.ppf(q, nu_hat))
        assert lo < lo0 and hi < hi0


def test_a_constant_relative_spread_gives_the_satterthwaite_interval() -> None:
    p_hat, c = 2.0, 0.3
    nu = 2.0 / c ** 2
    lo, hi = F._neyman_chi2_ci(p_hat, lambda p: c * p, 0.95)
    assert math.isclose(lo, math.sqrt(p_hat * nu / chi2.ppf(0.975, nu)), rel_tol=1e-9)
    assert math.isclose(hi, math.sqrt(p_hat * nu / chi2.ppf(0.025, nu)), rel_tol=1e-9)


def test_a_quickstart_b_interval_holds_the_truth(tmp_path: Path) -> None:
    from rigctl.sim.noise import NoiseGenerator

    fs, noise = default_noise()
    seed, axis = 86, 0  # gx: B 6.50 [5.01, 9.23] deg/h before, truth 5
    g = NoiseGenerator(noise["gyro"], fs, np.random.SeedSequence([seed, 1])).next(int(300 * fs))
    rec = write_recording(tmp_path / "q.h5", fs, angular_rate=g + np.array([3e-5, 0.0, 5e-5]))
    r = AA.compute(str(rec), ["gx"], 95, False, None, gaps="skip")["axes"]["gx"]
    b = as_coefficients(r["fit"]["coefficients"]).B
    truth = noise["gyro"][axis].B.value
    assert b.resolved, b
    assert b.ci95[0] <= truth <= b.ci95[1], (b, truth)
    assert b.ci68[0] <= b.value <= b.ci68[1]
