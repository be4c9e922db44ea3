"""A fit with no resolved total: the presence test must not crash, and the words must not
print 300-digit factors.

Both found on the Allan analysis of a 24-position run taken whole (`rigctl allan REC --whole
--taus octave`, the table turning: the curve rises as tau^2 to 0.64 s then falls), which
tests/test_cli_hostile.py runs as its warm-up:

* the B presence test's alternative (a signed c / tau^2 term free) took the fitted total to 0
  at the shortest tau; its covariance, floored at 1e-300, squared to 0, and the Cholesky factor
  was singular: "internal error: LinAlgError: singular matrix";
* where every term is a bound the check's total is floored at 1e-300, and the text printed
  "its deviation 1.37e+148-5.21e+150x the fitted total's" and a 300-digit "x..." factor.
"""
from __future__ import annotations

import math
import re

import numpy as np

from rigctl.analysis import allan as AP
from rigctl.solvers import allan_fit as F

# the gx axis of that recording, octave taus: tau (s), sigma^2 ((rad/s)^2), EDF
TAU = np.array([0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.28, 2.56, 5.12, 10.24])
S2 = np.array([9.41162205e-05, 3.69050228e-04, 1.44327549e-03, 5.40227057e-03,
               1.83186998e-02, 4.94769988e-02, 7.18981291e-02, 5.52325446e-02,
               3.33881597e-02, 6.57050934e-04, 8.41327981e-04])
EDF = np.array([3883.20043834, 2235.35151323, 1161.41058143, 586.28914288, 293.23108282,
                145.95805302, 117.09861618, 57.43193368, 27.60750084, 12.71833601,
                5.35661597])


def test_presence_test_on_a_curve_its_model_cannot_follow_returns_a_p_value():
    # the curve rises as tau^2 over the first five octaves (slope of sigma^2 in log-log ~2:
    # a turning table, not noise): read independently here
    slope = np.polyfit(np.log(TAU[:5]), np.log(S2[:5]), 1)[0]
    assert 1.8 < slope < 2.1
    out = F.b_presence_test(TAU, S2, EDF, tau0=0.01, n_phase=13576)
    assert out["tested"] is True
    assert 0.0 <= out["p_value"] <= 1.0 and math.isfinite(out["statistic"])


def test_a_run_over_a_zero_total_is_said_in_words():
    huge = 1.37e148
    carrier = {"chi2_carried_by": {"tau_from_s": 0.64, "tau_to_s": 20.5, "n_taus": 6,
                                   "side": "data above", "data_over_fit_min": huge,
                                   "data_over_fit_max": 5.21e150, "chi2": 299.6,
                                   "chi2_share": 1.0}}
    text = AP.chi2_carrier_text(carrier)
    assert "no total there" in text and not re.search(r"e\+\d{3}", text)
    assert AP.over_fit_text(huge, 2.56) == "no fitted total there: every term is a bound"
    assert AP.over_fit_text(1.47, 2.56) == "x1.47 at 2.56 s"
    check = {"ok": False, "bounded_terms": {"K": {"fraction_of_bound": 1.0, "value_si": 1e-3,
                                                  "upper95_si": 1e-3}},
             "needs_bounds": [{"tau_from_s": 0.01, "tau_to_s": 0.01, "worst_tau_s": 0.01,
                               "data_over_fit": 9.7e298, "term": "K"}]}
    words = " ".join(AP.bounds_sentence(check, "gyro"))
    assert "the resolved terms have no total at 0.01 s" in words
    assert not re.search(r"\d{13}", words) and not re.search(r"e\+\d{3}", words)
