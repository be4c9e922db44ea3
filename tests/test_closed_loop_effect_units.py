"""The closed loop's effect lines in `rigctl calibrate` are in the field's units, as the
parameter table above them: they printed SI ('gyro_drift_rate_x_rad_s2 +1.203e-07 +- 9e-08
95% [-1.027e-06, +1.267e-06]') under a table that showed the same parameter as
'gyro_drift_rate_x deg/h/h 89 67 -762 941'."""
from __future__ import annotations

import math

from rigctl.analysis.calibration_text import effect_parameter_line
from rigctl.solvers.closed_loop import ClosedLoopResult, format_report

DEG_H_H = 180.0 / math.pi * 3600.0 * 3600.0  # (deg/h/h) per (rad/s^2), written out here


def test_effect_parameters_are_printed_in_field_units() -> None:
    v, s, lo, hi = 1.203e-07, 9.0e-08, -1.027e-06, 1.267e-06
    effect = {"name": "gyro_time_drift", "description": "gyro drift changes linearly in time", "p_adj": 2.7e-9,
              "dBIC": -37.8, "excess_chi2_explained": 1.04, "attribution": "confirmed",
              "parameters": [{"name": "gyro_drift_rate_x_rad_s2", "value": v, "sigma": s, "ci95": [lo, hi]}]}
    res = ClosedLoopResult(declared=None, final=None, effects=[effect], explain=[], rms_table=[],  # type: ignore[arg-type]
                           unexplained=[], not_available={})
    # as rigctl calibrate calls it (rigctl.analysis.calibration.calibrate_table)
    line = next(ln for ln in format_report(res, effect_line=effect_parameter_line).splitlines()
                if "gyro_drift_rate_x" in ln)
    assert "rad_s2" not in line and "e-0" not in line, line
    # sigma 66.8 deg/h/h -> two significant digits, no decimals; the value and the interval alike
    want = [f"{v * DEG_H_H:.0f}", f"{s * DEG_H_H:.0f}", f"{lo * DEG_H_H:.0f}", f"{hi * DEG_H_H:.0f}"]
    assert want == ["89", "67", "-763", "941"]
    assert line.split() == ["gyro_drift_rate_x", "deg/h/h", want[0], "+-", want[1], "95%",
                            f"[{want[2]},", f"{want[3]}]"], line
