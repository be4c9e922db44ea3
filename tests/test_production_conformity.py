"""Conformity decisions (rigctl.solvers.conformity) against hand-computed cases.

Expected numbers come from printed tables, not from scipy: Phi(1) = 0.841345, Phi(2) =
0.977250, z_0.975 = 1.959964, t_0.975(4) = 2.776445, t_0.975(1) = 12.706205, chi-square
quantiles chi2_0.025(10) = 3.246973, chi2_0.975(10) = 20.483177.
"""
from __future__ import annotations

import math

import pytest

from rigctl.display_units import display, format_value
from rigctl.solvers.conformity import FAIL, INDETERMINATE, PASS, Estimate, decide, overall
from rigctl.config.spec import load_spec
from rigctl.yamlio import InputError

Z = 1.959964


@pytest.mark.parametrize("y, verdict", [
    (4.80, PASS),            # hi = 4.80 + 1.96 * 0.05 = 4.898 <= 5
    (4.90, PASS),            # hi = 4.998 <= 5 (just)
    (4.91, INDETERMINATE),   # hi = 5.008 > 5, lo = 4.812 < 5
    (5.05, INDETERMINATE),   # outside by less than U = 0.098: lo = 4.952
    (5.10, FAIL),            # lo = 5.002 > 5
    (-5.2, FAIL),            # below the lower limit by more than U
])
def test_guarded_normal_two_sided(y, verdict):
    d = decide(Estimate(y, 0.05), -5.0, 5.0, "guarded")
    assert d.verdict == verdict
    assert d.lo == pytest.approx(y - Z * 0.05, abs=1e-6) and d.hi == pytest.approx(y + Z * 0.05, abs=1e-6)


def test_conformance_probability_and_simple_acceptance_risk():
    # y one u below the upper limit: P(conform) = Phi(1); simple acceptance passes it with a
    # false-accept risk of 1 - Phi(1) = 0.158655; guarded calls it indeterminate
    d = decide(Estimate(4.95, 0.05), None, 5.0, "simple")
    assert d.verdict == PASS and d.p_conform == pytest.approx(0.841345, abs=1e-6)
    assert d.risk == pytest.approx(0.158655, abs=1e-6)
    assert decide(Estimate(4.95, 0.05), None, 5.0, "guarded").verdict == INDETERMINATE
    # two u above: simple FAIL with a false-reject risk of 1 - Phi(2)
    d = decide(Estimate(5.10, 0.05), None, 5.0, "simple")
    assert d.verdict == FAIL and d.risk == pytest.approx(1 - 0.977250, abs=1e-6)
    # on the limit: a coin toss
    assert decide(Estimate(5.0, 0.05), None, 5.0, "simple").risk == pytest.approx(0.5, abs=1e-12)


def test_student_t_widens_the_guard_band():
    # 4 dof: U = 2.776445 u; y = 4.87 passes with a normal interval, not with t(4)
    assert decide(Estimate(4.87, 0.05), None, 5.0).verdict == PASS
    d = decide(Estimate(4.87, 0.05, dof=4), None, 5.0)
    assert d.verdict == INDETERMINATE and d.hi == pytest.approx(4.87 + 2.776445 * 0.05, abs=1e-6)
    assert Estimate(0.0, 1.0, dof=1).coverage_factor == pytest.approx(12.706205, abs=1e-5)


def test_chi2_noise_coefficient():
    # c = 0.2 from p = c^2 with 10 dof: 95 % interval c * sqrt(10 / chi2_q(10))
    e = Estimate(0.2, 0.2 / math.sqrt(20), dof=10, kind="chi2")
    lo, hi = e.interval()
    assert lo == pytest.approx(0.2 * math.sqrt(10 / 20.483177), rel=1e-6)
    assert hi == pytest.approx(0.2 * math.sqrt(10 / 3.246973), rel=1e-6)
    assert decide(e, None, 0.36).verdict == PASS          # hi = 0.351
    assert decide(e, None, 0.30).verdict == INDETERMINATE
    assert decide(e, None, 0.13).verdict == FAIL          # lo = 0.1397 > 0.13
    # P(c <= hi) = 0.975 by construction
    assert e.cdf(hi) == pytest.approx(0.975, abs=1e-9)


def test_unresolved_term_passes_or_is_indeterminate_never_fails():
    e = Estimate(0.0, 0.1, kind="bound", upper=0.25)
    assert e.interval() == (0.0, 0.25)
    assert decide(e, None, 0.3).verdict == PASS
    assert decide(e, None, 0.2).verdict == INDETERMINATE
    assert decide(e, None, 0.01).verdict == INDETERMINATE


def test_overall():
    assert overall([PASS, PASS]) == PASS
    assert overall([PASS, INDETERMINATE]) == INDETERMINATE
    assert overall([INDETERMINATE, FAIL, PASS]) == FAIL
    assert overall([]) == INDETERMINATE


def test_display_units_and_digits():
    d = display("accel_bias_x_m_s2")
    assert (d.base, d.unit) == ("accel_bias_x", "mg")
    assert d.value(9.80665e-3) == pytest.approx(1.0)
    d = display("gyro_M_yy_ratio")
    assert (d.base, d.unit) == ("gyro_scale_error_y", "ppm") and d.value(1.0005) == pytest.approx(500.0)
    d = display("gyro_noise_N_z")
    assert (d.base, d.unit) == ("gyro_angle_random_walk_z", "deg/sqrt(h)")
    assert d.value(math.radians(1) / 60) == pytest.approx(1.0)  # 1 deg/sqrt(h) = pi/180/60 rad/sqrt(s)
    assert display("accel_noise_N_x").unit == "m/s/sqrt(h)"
    assert format_value(0.0039118, 0.00021) == ("0.00391", "0.00021")
    assert format_value(7.9495, 0.0867) == ("7.949", "0.087")
    assert format_value(808.41, 28.0) == ("808", "28")
    assert format_value(4.9884, 0.0996) == ("4.99", "0.10")   # u rounds up to 0.10
    assert format_value(225170.0, 238000.0) == ("230000", "240000")


def test_spec_errors_name_file_and_line(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text("spec: t\nparameters:\n  accel_bias_x: {within: 5 mg}\n  gyro_bias_x: {upper: 3 furlong}\n")
    with pytest.raises(InputError) as e:
        load_spec(p)
    assert e.value.line == 4 and "furlong" in str(e.value)
    p.write_text("spec: t\ndecision_rule: lenient\nparameters: {}\n")
    with pytest.raises(InputError) as e:
        load_spec(p)
    assert e.value.line == 2
    p.write_text("spec: t\nparameters:\n  accel_bias_x: {within: 5 deg/h}\n")
    spec = load_spec(p)
    with pytest.raises(InputError) as e:
        spec.limits[0].si(display("accel_bias_x_m_s2"))
    assert e.value.line == 3 and "mg" in str(e.value)


def test_spec_example_loads_and_converts():
    spec = load_spec("configs/spec-example.yaml")
    lim = spec.limit_for("accel_bias_y")
    lo, hi = lim.si(display("accel_bias_y_m_s2"))
    assert hi == pytest.approx(5e-3 * 9.80665) and lo == pytest.approx(-5e-3 * 9.80665)
    lo, hi = spec.limit_for("gyro_scale_error_z").si(display("gyro_M_zz_ratio"))
    assert hi == pytest.approx(1.005) and lo == pytest.approx(0.995)


def test_chi2_interval_of_a_vanishing_dof_is_everything():
    """A noise coefficient whose Satterthwaite dof is ~0 (a term held at its curve limit where
    the model needs 135 % of sigma^2 as its own error: test_cli_hostile's recordings of a
    moving table) has chi-square quantiles that underflow to 0: the interval is [0, inf), not
    a division by zero. A sane dof keeps its interval (scipy's quantiles, computed here)."""
    from scipy.stats import chi2

    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert Estimate(2.0, dof=1e-300, kind="chi2").interval() == (0.0, math.inf)
    lo, hi = Estimate(2.0, dof=10.0, kind="chi2").interval()
    assert math.isclose(lo, 2.0 * math.sqrt(10.0 / chi2.ppf(0.975, 10.0)))
    assert math.isclose(hi, 2.0 * math.sqrt(10.0 / chi2.ppf(0.025, 10.0)))
