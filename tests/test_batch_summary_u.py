"""The lot summary of `rigctl batch` shows the units' own uncertainties beside the spread, and
names a parameter whose units' uncertainties differ by more than 10x: a lot of a 24-position
run (gyro scale from Earth rate alone, 1-sigma 2.2e5 ppm) and a full calibration (7.4 ppm)
printed 'gyro_scale_error_x ppm 2 -100000 140000 ...' with nothing to tell the mean is one
unit's undetermined value."""
from __future__ import annotations

import math

from rigctl.analysis import batch as B


def _summary() -> dict:
    def p(unit: str, vals: list[float], us: list[float]) -> dict:
        return {"unit": unit, "n": len(vals), "mean": sum(vals) / len(vals),
                "sd": math.sqrt(sum((v - sum(vals) / len(vals)) ** 2 for v in vals) / (len(vals) - 1)),
                "min": min(vals), "max": max(vals), "median_u": sorted(us)[len(us) // 2],
                "min_u": min(us), "max_u": max(us)}
    return {"runs": {"recordings": 2, "analysed": 2, "failed": [],
                     "verdicts": {"PASS": 0, "FAIL": 0, "INDETERMINATE": 0}, "yield": None,
                     "parameters": {"accel_bias_x": p("mg", [2.088, 1.996], [0.069, 0.13]),
                                    "gyro_scale_error_x": p("ppm", [-190000.0, 1000.3], [220000.0, 7.4])}}}


def test_summary_shows_unit_uncertainties_and_names_the_uneven_parameter() -> None:
    text = B.summary_text(_summary())
    head = next(ln for ln in text.splitlines() if ln.strip().startswith("parameter"))
    assert head.split()[-4:] == ["u", "min", "u", "max"]
    row = next(ln for ln in text.splitlines() if ln.strip().startswith("gyro_scale_error_x"))
    assert row.split()[-2:] == ["7.4", "220000"]
    row = next(ln for ln in text.splitlines() if ln.strip().startswith("accel_bias_x"))
    assert row.split()[-2:] == ["0.069", "0.13"]
    warn = [ln for ln in text.splitlines() if "warning:" in ln]
    assert len(warn) == 1 and "(gyro_scale_error_x)" in warn[0] and "accel_bias_x" not in warn[0]
