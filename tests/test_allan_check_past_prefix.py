"""The self-check judges the well-determined taus (informative up to the first that is not),
but a tau past them whose band is informative again and which the fitted total leaves is
still named: the Done-when of issue 15 ("the fitted total in the band wherever the band is
informative, else a warning naming the taus"). Bands computed here with scipy's chi-square
quantiles, independently of rigctl."""
from __future__ import annotations

import math

import numpy as np
from scipy.stats import chi2

from rigctl.analysis.allan import check_notes
from rigctl.solvers import allan_fit as F


def _band(dev: np.ndarray, edf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return dev * np.sqrt(edf / chi2.ppf(0.975, edf)), dev * np.sqrt(edf / chi2.ppf(0.025, edf))


def test_a_miss_past_the_well_determined_taus_is_named_not_judged() -> None:
    tau = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])
    n = 1e-3  # white noise only: sigma = N / sqrt(tau)
    dev = n / np.sqrt(tau)
    edf = np.array([4000.0, 2000.0, 1000.0, 500.0, 15.0, 17.5, 8.0])
    dev[5] *= 0.55  # a low deviation where the EDF rose again (a noise-ID switch)
    lo, hi = _band(dev, edf)
    inf = hi / lo <= 2.0
    assert inf.tolist() == [True, True, True, True, False, True, False]  # the setting
    fit = n / np.sqrt(tau)
    assert fit[5] > hi[5]  # the total leaves the informative band at 32 s
    chk = F.self_check(tau, dev, edf, {"N": n * n})
    assert chk["ok"] and chk["n_informative"] == 4  # not judged
    past = chk["outside_past_prefix"]
    assert [(o["tau_from_s"], o["tau_to_s"]) for o in past] == [(32.0, 32.0)]
    assert math.isclose(past[0]["data_over_fit"], 0.55, rel_tol=1e-12)
    assert chk["prefix_end_s"] == 16.0
    notes = " ".join(check_notes({"fit": {"check": chk}}))
    assert "past the well-determined taus (from 16 s" in notes and "tau 32 s" in notes


def test_nothing_named_past_the_prefix_when_the_total_is_inside() -> None:
    tau = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 32.0])
    dev = 1e-3 / np.sqrt(tau)
    edf = np.array([4000.0, 2000.0, 1000.0, 500.0, 15.0, 17.5])
    chk = F.self_check(tau, dev, edf, {"N": 1e-6})
    assert chk["ok"] and chk["outside_past_prefix"] == []
    assert not any("well-determined" in s for s in check_notes({"fit": {"check": chk}}))
