"""A chi-square beyond its 99 % point is a finding, never a pass: the run of taus that carries
it (rigctl.solvers.allan_fit.chi2_carrier) on arrays written here, and the HTML report's
sentence for it. Expected values are worked out by hand in each test."""
from __future__ import annotations

import numpy as np

from rigctl.report.report_html import _chi2_findings_html
from rigctl.solvers.allan_fit import chi2_carrier


def test_the_carrier_is_the_one_sided_run_with_the_largest_whitened_sum() -> None:
    # sides: below, below | above, above, above | below ; whitened residuals squared per tau
    # 1, 1 | 4, 9, 4 | 16 -> runs score 2, 17, 16 of 35: the middle run carries 17/35
    tau = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 32.0])
    total = np.ones(6)
    s2 = np.array([0.9, 0.95, 1.21, 1.44, 1.69, 0.5])  # deviation ratios 1.1, 1.2, 1.3 above
    r = np.array([-1.0, 1.0, 2.0, -3.0, 2.0, 4.0])  # the whitened signs need not follow sides
    c = chi2_carrier(tau, s2, total, r)
    assert (c["tau_from_s"], c["tau_to_s"], c["n_taus"], c["side"]) == (4.0, 16.0, 3, "data above")
    assert abs(c["chi2"] - 17.0) < 1e-12 and abs(c["chi2_share"] - 17.0 / 35.0) < 1e-12
    assert abs(c["data_over_fit_min"] - 1.1) < 1e-12 and abs(c["data_over_fit_max"] - 1.3) < 1e-12
    assert chi2_carrier(tau, s2, total, np.zeros(6)) is None  # nothing to name


def test_the_report_calls_it_a_finding_and_names_the_run() -> None:
    check = {"ok": False, "chi2_beyond_99": True, "n_outside_familywise": 0, "chi2": 179.6,
             "dof": 37, "p_value": 1.3e-20,
             "chi2_carried_by": {"tau_from_s": 33.0, "tau_to_s": 264.0, "n_taus": 14,
                                 "chi2": 119.4, "chi2_share": 0.665, "side": "data above",
                                 "data_over_fit_min": 1.03, "data_over_fit_max": 1.14}}
    html = "".join(_chi2_findings_html({"gx": {"fit": {"check": check}},
                                        "gy": {"fit": {"check": {"ok": True, "chi2": 30.0,
                                                                 "dof": 37, "p_value": 0.8}}}}))
    assert html.count("<p") == 1 and "gx:" in html and "gy" not in html
    assert "self-check failed" in html and "a finding, not a pass" in html
    assert "179.6 on 37 dof" in html and "tau 33-264 s" in html and "1.03-1.14x" in html
