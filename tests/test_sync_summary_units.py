"""`rigctl sync`'s summary gives the offset in the unit of its uncertainty: it printed
'offset -0.000172 s (1-sigma 0.271 ms, 95% +-0.572 ms)', one quantity in two units."""
from __future__ import annotations

from rigctl.analysis.sync import summary_lines


def test_offset_and_its_uncertainty_in_one_unit() -> None:
    s = {"offset_s": -0.000172, "offset_sigma_s": 0.000271, "offset_ci95_s": 0.000572, "drift_ppm": 82.442,
         "drift_sigma_ppm": 5.633, "drift_ci95_ppm": 11.884, "n_taps_detected": 20, "n_pulses": 19, "n_matched": 19,
         "n_inliers": 19, "n_outliers": 0, "n_taps_without_pulse": 1, "n_pulses_without_tap": 0,
         "residual_std_ms": 0.39, "outlier_limit_ms": 1.785, "counter_gaps": [], "residual_steps": []}
    line = summary_lines(s)[0]
    assert line.split() == ["offset", "-0.172", "ms", "(1-sigma", "0.271", "ms,", "95%", "+-0.572", "ms)"], line
