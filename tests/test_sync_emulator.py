"""Tap-hammer emulator (sim/taps.py): clock, receiver, data loss, response, determinism."""
from __future__ import annotations

import json

import numpy as np
import pytest

from rigctl.sim import taps


def test_clock_inverse_and_drift_sign() -> None:
    clk = taps.ClockParams(offset_s=0.3, drift_ppm=85.0, wander_amplitude_s=2e-3,
                           wander_period_s=900.0, wander_phase_rad=0.4)
    c = np.array([0.0, 1234.5, 1.0e6])
    t = clk.time_of_counter(c, 100.0)
    np.testing.assert_allclose(clk.counter_of_time(t, 100.0), c, atol=1e-6)
    # slow clock (positive ppm): 1e6 counts last longer than 1e4 s
    plain = taps.ClockParams(drift_ppm=85.0)
    assert plain.time_of_counter(1e6, 100.0) == pytest.approx(1e4 * (1 + 85e-6), rel=1e-12)


def test_same_seed_same_session_and_truth_json() -> None:
    a, b = taps.experiment1(seed=5), taps.experiment1(seed=5)
    np.testing.assert_array_equal(a.specific_force, b.specific_force)
    np.testing.assert_array_equal(a.pulse_time, b.pulse_time)
    c = taps.experiment1(seed=6)
    assert not np.array_equal(a.pulse_time[:5], c.pulse_time[:5])
    params = json.loads(a.truth.params_json())
    assert params["n_taps_hammer"] == 140 and params["n_pulses_missed"] == 2
    assert params["dropouts"] == [[a.truth.dropouts[0][0], 32]]


def test_experiment1_shape_missed_pulses_and_loss() -> None:
    s = taps.experiment1(seed=1)
    tr = s.truth
    assert tr.tap_time.size == 140 and s.pulse_time.size == 138
    assert np.sum(tr.tap_pulse_index < 0) == 2
    gaps = np.diff(s.counter.astype(np.int64))
    assert np.sum(gaps != 1) == 1 and gaps.max() == 33  # one 32-sample loss
    assert s.counter.size == tr.n_samples_total - 32
    # pulses are tap times plus jitter of the configured size (within 4 standard errors)
    j = s.pulse_time[tr.tap_pulse_index[tr.tap_pulse_index >= 0]] - tr.tap_time[tr.tap_pulse_index >= 0]
    assert abs(np.std(j) - taps.PAPER_JITTER_S) < 4 * taps.PAPER_JITTER_S / np.sqrt(2 * j.size)


def test_timeguard_suppresses_bounce_and_fast_taps() -> None:
    sched = taps.ScheduleParams((10.0,), 20, (0.25, 0.35))  # taps faster than the timeguard
    p = taps.TapParams(bounce_probability=1.0, timeguard_s=0.4)
    s = taps.simulate_taps(100.0, 30.0, sched, p, seed=3)
    assert np.all(np.diff(s.pulse_time) >= 0.4)
    assert np.all(s.truth.pulse_kind == "tap")
    assert np.sum(s.truth.tap_pulse_index < 0) > 0  # some taps fell in the dead time
    p0 = taps.TapParams(bounce_probability=1.0, timeguard_s=0.0)
    s0 = taps.simulate_taps(100.0, 30.0, sched, p0, seed=3)
    assert np.sum(s0.truth.pulse_kind == "bounce") >= 20


def test_response_none_is_first_sample_after_tap() -> None:
    p = taps.TapParams(cross_axis_fraction=0.0)
    s = taps.simulate_taps(100.0, 40.0, taps.ScheduleParams((5.0,), 10, (1.0, 3.0)), p,
                           taps.ClockParams(offset_s=0.0123), noise_std_m_s2=0.0, seed=4)
    tr = s.truth
    t_samples = tr.time_of_counter(s.counter.astype(float))
    for ti, ai in zip(tr.tap_time, tr.tap_amplitude):
        k = np.searchsorted(t_samples, ti)
        assert s.specific_force[k, 2] - 9.81 == pytest.approx(ai)
        assert s.specific_force[k - 1, 2] == pytest.approx(9.81)
        assert 0.0 <= t_samples[k] - ti < 0.01


def test_second_order_response_and_saturation() -> None:
    p = taps.TapParams(response="second_order", range_m_s2=30.0, amplitude_median_m_s2=60.0,
                       amplitude_log_sigma=0.0, cross_axis_fraction=0.0)
    s = taps.simulate_taps(100.0, 20.0, taps.ScheduleParams((5.0,), 3, (2.0, 3.0)), p,
                           noise_std_m_s2=0.0, seed=7)
    assert s.specific_force[:, 2].max() == 30.0  # clipped
    g = taps.unit_peak_second_order(np.linspace(0, 0.2, 20001), 30.0, 0.7)
    assert g.max() == pytest.approx(1.0, abs=1e-6)
    assert taps.unit_peak_second_order(np.array([-1e-3]), 30.0, 0.7)[0] == 0.0


def test_spurious_spikes_and_pulses_in_truth() -> None:
    s = taps.experiment1(seed=1, spurious_spikes=6, spurious_pulses=4)
    tr = s.truth
    assert np.sum(~tr.tap_is_hammer) == 6 and np.all(tr.tap_pulse_index[~tr.tap_is_hammer] < 0)
    assert np.sum(tr.pulse_kind == "spurious") <= 4
    assert np.all(tr.pulse_tap_index[tr.pulse_kind == "spurious"] == -1)


def test_experiment2_clock_and_counter_start() -> None:
    s = taps.experiment2(seed=2)
    assert s.truth.clock.drift_ppm == 85.0
    dur = 3 * 3600 + 20 * 60
    first = s.truth.clock.offset_s  # sample 0 is at the clock offset
    assert s.counter.size == pytest.approx((dur - first) * 100 / (1 + 85e-6), abs=1.0)
    s2 = taps.simulate_taps(100.0, 60.0, taps.ScheduleParams((5.0,), 5, (1, 2)),
                            taps.TapParams(), taps.ClockParams(0.5, 40.0), counter_start=10**6,
                            seed=1)
    # truth clock maps the shifted counter to the same reference times
    assert s2.truth.time_of_counter(float(s2.counter[0])) == pytest.approx(0.5, abs=1e-9)
