"""`rigctl history`: a drift per year is stated only when the calibrations resolve it.

The audit case: two calibrations two minutes apart gave "drift: 28000 +- 40000 mg/year". Here
the expected slope, its uncertainty and its 95 % interval come from numpy's weighted polyfit
(independent of rigctl's fit_linear), and the printed line is checked against them.
"""
from __future__ import annotations

import datetime as dt
import re
from types import SimpleNamespace

import numpy as np

from rigctl.commands.history_cmd import history_text

YEAR_S = 365.25 * 86400.0
T0 = dt.datetime(2025, 1, 1, tzinfo=dt.timezone.utc)


def _analyses(offsets_s: list[float], values_mg: list[float], u_mg: list[float]) -> list[SimpleNamespace]:
    out = []
    for i, (t, v, u) in enumerate(zip(offsets_s, values_mg, u_mg)):
        when = (T0 + dt.timedelta(seconds=t)).isoformat()
        r = SimpleNamespace(parameter="accel_bias_x", unit="mg", value=v, u=u, verdict=None)
        out.append(SimpleNamespace(kind="calibration", run=f"cal{i}", recorded_utc=when, analysed_utc=when,
                                   results=[r]))
    return out


def _numpy_slope(offsets_s, values, u) -> tuple[float, float]:
    t = np.asarray(offsets_s, float) / YEAR_S
    coef, cov = np.polyfit(t - t.mean(), values, 1, w=1 / np.asarray(u, float), cov="unscaled")
    return float(coef[0]), float(np.sqrt(cov[0, 0]))


def _drift_line(text: str) -> str:
    (line,) = [x for x in text.splitlines() if "drift:" in x]
    return line.strip()


def test_two_calibrations_minutes_apart_state_no_drift_per_year():
    """The audit's case: 2 min apart, values 0.15 mg apart with u 0.1 mg -> numpy's slope is
    ~4e4 mg/year; the line must not state it, and says why (the span)."""
    off, v, u = [0.0, 120.0], [1.00, 1.15], [0.1, 0.1]
    slope, _ = _numpy_slope(off, v, u)
    assert abs(slope) > 1e4  # what the old line printed as a drift
    line = _drift_line(history_text("SN-1", _analyses(off, v, u)))
    assert line.startswith("drift: not resolved yet"), line
    assert "2 min 00 s" in line and "24 h 00 min" in line, line
    assert "/year" not in line, line


def test_a_drift_whose_interval_includes_zero_is_not_stated_as_resolved():
    """400 days apart, a change smaller than its uncertainty: the slope and u are printed (as
    numpy's), labelled not resolved because its 95 % interval includes zero."""
    off, v, u = [0.0, 200 * 86400.0, 400 * 86400.0], [1.00, 1.05, 1.02], [0.1, 0.1, 0.1]
    slope, us = _numpy_slope(off, v, u)
    assert abs(slope) < 1.96 * us  # the premise: zero is inside the interval
    line = _drift_line(history_text("SN-1", _analyses(off, v, u)))
    m = re.match(r"drift: not resolved: (\S+) \+- (\S+) mg/year, its 95 % interval includes zero", line)
    assert m, line
    assert float(m.group(1)) == np_round(slope, m.group(1))
    assert float(m.group(2)) == np_round(us, m.group(2))


def test_a_resolved_drift_is_stated_per_year():
    """400 days apart, 1 mg change with u 0.01 mg: resolved, printed as numpy's slope."""
    off, v, u = [0.0, 200 * 86400.0, 400 * 86400.0], [1.00, 1.50, 2.00], [0.01, 0.01, 0.01]
    slope, us = _numpy_slope(off, v, u)
    line = _drift_line(history_text("SN-1", _analyses(off, v, u)))
    m = re.match(r"drift: (\S+) \+- (\S+) mg/year \(dof 1", line)
    assert m, line
    assert float(m.group(1)) == np_round(slope, m.group(1))
    assert float(m.group(2)) == np_round(us, m.group(2))


def np_round(x: float, printed: str) -> float:
    """``x`` rounded to as many decimals as ``printed`` shows."""
    dec = len(printed.split(".")[1]) if "." in printed else 0
    return round(x, dec)
