"""Emulator timing and truth fixes: the table moves on true (run) time and the IMU samples it at
its own clock's instants; power-on time shifts only the IMU's turn-on state; the recorded
warm-up reference is the one applied; profile overrides are checked against the schema; the tap
hammer's sign is +-1. (Taps in /truth: tests/test_sim_taps_rig.py.)"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from rigctl.config.config import load_config
from rigctl.engine.rig import open_rig
from rigctl.sim.error_model import ImuErrorModel
from rigctl.sim.profiles import get_profile
from rigctl.sim.table import POSITION, Profile, ServoParams, SimTurntable
from rigctl.yamlio import InputError

from helpers import ROOT

RATE_HZ = 100.0
TAU0 = 1.0 / RATE_HZ
ZERO3 = [0.0, 0.0, 0.0]
ZERO33 = [ZERO3, ZERO3, ZERO3]
AMAX_OUTER = math.radians(200.0)


def _clean_overrides(**effects: Any) -> dict:
    """declared_only without errors or noise (gyro = true body rate), 1 kHz internal rate."""
    sensor = {"bias_rad_per_s": ZERO3, "scale_error": ZERO3, "misalignment_rad": ZERO33}
    return {"frontend": {"internal_rate_hz": 1000.0},
            "gyro": {**sensor, "noise": {"N_rad_per_s_per_sqrt_hz": 0.0, "B_rad_per_s": 0.0,
                                         "K_rad_per_s2_per_sqrt_hz": 0.0}},
            "accel": {"bias_m_per_s2": ZERO3, "scale_error": ZERO3, "misalignment_rad": ZERO33,
                      "quadratic_per_m_per_s2": ZERO3,
                      "noise": {"N_m_per_s2_per_sqrt_hz": 0.0, "B_m_per_s2": 0.0,
                                "K_m_per_s3_per_sqrt_hz": 0.0}},
            "effects": effects}


def _config(tmp_path: Path, imu_sim: dict, name: str = "c.yaml", **top: Any) -> Path:
    data = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    data["imu"]["sim"] = imu_sim
    data.update(top)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _clock_world_run(tmp_path: Path, ppm: float, t_cmd: float = 500.0, after: float = 6.0,
                     delay_s: float = 0.0) -> dict:
    """Sit still until ``t_cmd`` (run time), move the outer axis 90 deg, poll the table every
    0.05 s for ``after`` seconds; the IMU's clock runs ``ppm`` slow (no wander, no drops)."""
    effects: dict[str, Any] = {"clock": {"enabled": True, "drift_ppm": ppm, "wander_ppm": 0.0,
                                         "drop_probability": 0.0}}
    if delay_s:
        effects["time_delay"] = {"enabled": True, "delay_s": delay_s}
    cfg = load_config(_config(tmp_path, {"profile": "declared_only", "seed": 2,
                                         "overrides": _clean_overrides(**effects)},
                              name=f"clock{ppm:+.0f}-{delay_s}.yaml"))
    with open_rig(cfg) as (rig, _truth):
        blocks = []
        rig.clock.sleep(t_cmd)
        blocks.append(rig.imu.read())
        rig.table.move(np.radians([90.0, 0.0, 0.0]))
        reads = []
        for _ in range(int(round(after / 0.05))):
            rig.clock.sleep(0.05)
            reads.append(rig.table.read())
        blocks.append(rig.imu.read())
        k_next = rig.table.world.k
        t_end = rig.clock.now()
    counter = np.concatenate([b.counter for b in blocks]).astype(np.float64)
    wz = np.concatenate([b.angular_rate[:, 2] for b in blocks])
    return {"counter": counter, "wz": wz, "reads": reads, "k_next": k_next, "t_end": t_end}


def _true_time(counter: np.ndarray, ppm: float) -> np.ndarray:
    """True run time of IMU sample ``counter`` for a constant-drift clock (docs/emulator.md:
    t_k = t_(k-1) + tau0 (1 + 1e-6 ppm), t_(-1) = -tau0)."""
    return (counter + 1.0) * TAU0 * (1.0 + 1e-6 * ppm) - TAU0


@pytest.fixture(scope="module")
def clock_runs(tmp_path_factory) -> dict[float, dict]:
    tmp = tmp_path_factory.mktemp("clock")
    return {ppm: _clock_world_run(tmp, ppm) for ppm in (0.0, 1000.0, -1000.0)}


@pytest.mark.parametrize("ppm", [1000.0, -1000.0])
def test_table_motion_reaches_the_imu_at_its_true_instant(clock_runs, ppm):
    """A move commanded at run time 500 s shows in the IMU data exactly from that true instant
    (the IMU's time stamps mapped through its clock), neither cut (the IMU ahead, +ppm) nor
    started early by a profile run backwards (-ppm), and the whole 90 deg arrives."""
    r = clock_runs[ppm]
    t_cmd = 500.0
    tt = _true_time(r["counter"], ppm)
    rate = r["wz"] - r["wz"][0]  # table rate about z: Earth rate's z part is constant
    before = tt <= t_cmd
    assert before.sum() > 10 and np.all(np.abs(rate[before]) < 1e-12)
    first = np.flatnonzero(~before)[0]
    d = tt[first] - t_cmd
    assert 0.0 < d <= TAU0 * 1.01
    # the axis starts from rest: at most the profile's acceleration (+ servo overshoot) x d
    assert 0.0 < rate[first] <= 1.2 * AMAX_OUTER * d
    seen = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(tt))])
    assert math.degrees(seen[-1]) == pytest.approx(90.0, abs=1e-3)


def test_delayed_imu_sees_the_move_its_delay_after_the_command(tmp_path):
    """With a time delay d the samples taken just after the command still see the table before
    it (the replaced profile): the motion shows from true time t_cmd + d on."""
    d, ppm, t_cmd = 0.05, 1000.0, 20.0
    r = _clock_world_run(tmp_path, ppm, t_cmd=t_cmd, after=2.0, delay_s=d)
    tt = _true_time(r["counter"], ppm)
    rate = r["wz"] - r["wz"][0]
    before = tt <= t_cmd + d
    assert np.all(np.abs(rate[before]) < 1e-12)
    first = np.flatnonzero(~before)[0]
    assert 0.0 < rate[first] <= 1.2 * AMAX_OUTER * (tt[first] - t_cmd - d)


def _crossing(t: np.ndarray, angle: np.ndarray, level: float) -> float:
    i = int(np.flatnonzero(angle >= level)[0])
    return float(t[i - 1] + (level - angle[i - 1]) * (t[i] - t[i - 1]) / (angle[i] - angle[i - 1]))


def test_imu_sees_the_same_motion_on_the_run_timescale_whatever_its_clock(clock_runs):
    """The 45 deg point of the move, integrated from the gyro on each clock's true times, comes
    at the same run time for a perfect, a slow and a fast IMU clock (0.5 s apart before)."""
    cross = {}
    for ppm, r in clock_runs.items():
        tt = _true_time(r["counter"], ppm)
        rate = r["wz"] - r["wz"][0]
        seen = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(tt))])
        cross[ppm] = _crossing(tt, np.degrees(seen), 45.0)
    assert 500.0 < cross[0.0] < 502.0
    assert cross[1000.0] == pytest.approx(cross[0.0], abs=2e-4)
    assert cross[-1000.0] == pytest.approx(cross[0.0], abs=2e-4)


def test_table_reports_its_state_at_run_time_independent_of_the_imu_clock(clock_runs):
    """table.read() is the table's physics at the current run time: identical for every IMU
    clock, and it is the motion of a free-standing table commanded at the same time."""
    ref = clock_runs[0.0]["reads"]
    for ppm in (1000.0, -1000.0):
        for a, b in zip(ref, clock_runs[ppm]["reads"]):
            assert a.time == b.time
            assert np.array_equal(a.angle, b.angle) and np.array_equal(a.rate, b.rate)
            assert a.status == b.status
    cfg = load_config(ROOT / "configs" / "sim.yaml")  # same table section as the runs
    servos = [ServoParams(natural_hz=f, damping=0.6, encoder_lsb=math.radians(1e-5)) for f in (4.0, 5.0, 6.0)]
    h = 1e-3  # the runs' 1 kHz internal grid
    table = SimTurntable(servos, cfg.limits.rate, cfg.limits.accel, [True] * 3, h, np.random.default_rng(0))
    j_cmd = 500_000
    table.advance(np.arange(0, j_cmd + 1) * h)
    table.command(j_cmd * h, [POSITION] * 3, np.radians([90.0, 0.0, 0.0]))
    j = j_cmd + 1
    for state in ref:
        j_to = int(math.floor(state.time / h + 1e-9)) + 1
        table.advance(np.arange(j, j_to) * h)
        j = j_to
        ang, rate, status = table.measured(state.time)
        assert np.allclose(ang, state.angle, atol=1e-12) and np.allclose(rate, state.rate, atol=1e-12)
        assert status == state.status
    assert math.degrees(ref[-1].angle[0]) == pytest.approx(90.0, abs=2e-3)


@pytest.mark.parametrize("ppm", [1000.0, -1000.0])
def test_clock_ppm_still_readable_from_the_sample_count(clock_runs, ppm):
    r = clock_runs[ppm]
    count = r["k_next"]  # samples whose true time has passed
    est = (r["t_end"] / (count * TAU0) - 1.0) * 1e6
    assert est == pytest.approx(ppm, abs=2 * 1e6 / count)


def test_profile_before_its_start_is_the_replaced_one():
    """A profile asked for a time before its start answers with the profile it replaced: no
    acceleration piece is run backwards from its start."""
    old = Profile.to_rate(0.0, 0.0, 0.0, 1.0, 2.0)  # accelerates to 1 rad/s by t = 0.5 s
    p0, v0, _ = (float(x[0]) for x in old.evaluate(np.array([2.0])))
    new = Profile.to_position(2.0, p0, v0, 5.0, 1.0, 2.0)
    new.prev = old
    t = np.array([0.25, 1.0, 1.999, 2.0, 2.1])
    p, v, a = new.evaluate(t)
    po, vo, ao = old.evaluate(t[:3])
    assert np.array_equal(p[:3], po) and np.array_equal(v[:3], vo) and np.array_equal(a[:3], ao)
    assert p[3] == p0 and v[3] == v0
    assert v[4] < v0  # after the command: decelerating, as commanded


def test_table_between_grid_points_is_the_exact_servo_state():
    """TableAxis.at: on the grid it is the grid, one step on it is the next grid point, and in
    between its angle integrates its rate."""
    h = 1e-3
    mk = lambda: SimTurntable([ServoParams(natural_hz=f, damping=z) for f, z in ((4.0, 0.6), (5.0, 1.0), (6.0, 1.5))],
                              np.radians([300.0] * 3), np.radians([200.0] * 3), [True] * 3, h,
                              np.random.default_rng(0))
    a, b = mk(), mk()
    for tab in (a, b):
        tab.command(0.0, [POSITION] * 3, np.radians([30.0, -20.0, 10.0]))
    grid = np.arange(0, 401) * h
    xa, wa, _ = a.advance(grid)
    xb, wb, acc_b = b.advance(np.arange(0, 402) * h)
    x0, w0, _ = a.at(grid[-5:])
    assert np.array_equal(x0, xa[-5:]) and np.array_equal(w0, wa[-5:])
    x1, w1, acc1 = a.at(np.array([grid[-1] + h]))
    assert np.allclose(x1, xb[-1:], rtol=0, atol=1e-12) and np.allclose(w1, wb[-1:], rtol=0, atol=1e-10)
    assert np.allclose(acc1, acc_b[-1:], rtol=0, atol=1e-8)
    d = np.linspace(0.1, 0.9, 9) * h
    x, w, _ = a.at(grid[-2] + d)
    dx = np.diff(x, axis=0) / np.diff(d)[:, None]
    # trapezoid rule: exact up to step^2 / 12 x the rate's second derivative (servo jerk < 500 rad/s^3)
    assert np.allclose(dx, 0.5 * (w[1:] + w[:-1]), rtol=0, atol=np.diff(d)[0] ** 2 / 12 * 500)
    # before the first grid point the table was at rest
    xr, wr, _ = a.at(np.array([-0.5]))
    assert np.all(xr == 0.0) and np.all(wr == 0.0)


# ---------------------------------------------------------------------------- power-on time
def test_power_on_time_shifts_only_the_warm_up_not_the_samples(tmp_path):
    """power_on_time_s is the time since the IMU was switched on when the run starts: counter 0
    is still at run time 0 (a move appears when it is made), the warm-up is that far along."""
    wu = {"enabled": True, "T0_degC": 20.0, "dT_degC": 10.0, "tau_s": 100.0}
    over = _clean_overrides(warmup=wu)
    over["power_on_time_s"] = 100.0
    cfg = load_config(_config(tmp_path, {"profile": "declared_only", "seed": 3, "overrides": over}))
    t_cmd = 3.0
    with open_rig(cfg) as (rig, truth):
        rig.clock.sleep(t_cmd)
        rig.table.move(np.radians([90.0, 0.0, 0.0]))
        b0 = rig.imu.read()
        rig.clock.sleep(5.0)
        b1 = rig.imu.read()
    t = np.concatenate([b0.time, b1.time])
    rate = np.concatenate([b0.angular_rate[:, 2], b1.angular_rate[:, 2]])
    rate = rate - rate[0]
    assert t[0] == 0.0 and np.all(np.diff(t) == pytest.approx(TAU0))
    moving = np.flatnonzero(np.abs(rate) > 1e-12)
    assert t_cmd < t[moving[0]] <= t_cmd + TAU0 + 1e-12
    assert b0.temperature[0] == pytest.approx(20.0 + 10.0 * (1 - math.exp(-1.0)), abs=1e-9)
    assert truth["imu"]["power_on_time_s"] == 100.0


def test_power_on_time_random_walk_and_ramp_have_run_since_power_on():
    """The K random walk and R ramp start at power-on: at run start they are a constant offset
    N(0, K^2 t_on) + R t_on, recorded in the truth, and seen in the first samples."""
    t_on, K, R = 3600.0, 1.0e-6, 1.0e-9
    prof = get_profile("declared_only").with_overrides(
        {"power_on_time_s": t_on, "gyro": {"noise": None, "bias_rad_per_s": ZERO3}, "accel": {"noise": None}}
    ).with_overrides({"gyro": {"noise": {"K_rad_per_s2_per_sqrt_hz": K, "R_rad_per_s2": R}}})
    offs = []
    for seed in range(40):
        model = ImuErrorModel.from_profile(prof, seed=seed)
        g = model.sample_grid(10)
        n = g.t_internal.size
        _, w, _ = model.apply(g.t_internal, np.tile([0.0, 0.0, 9.8], (n, 1)), np.zeros((n, 3)))
        off = np.asarray(model.truth()["gyro_noise_offset_at_run_start_rad_per_s"])
        # residual scale error M w = 0 at rest: the output is the offset plus 10 samples of walk
        assert np.allclose(w[0] @ np.linalg.inv(model.gyro_M).T, off, rtol=0, atol=5 * K * math.sqrt(0.1) + 5 * R * 0.1)
        offs.append(off - R * t_on)
    offs = np.concatenate(offs)
    assert np.std(offs) == pytest.approx(K * math.sqrt(t_on), rel=0.3)
    zero = ImuErrorModel.from_profile(get_profile("declared_only"), seed=1).truth()
    assert zero["gyro_noise_offset_at_run_start_rad_per_s"] == [0.0, 0.0, 0.0]


# ---------------------------------------------------------------------------- warm-up truth
def test_truth_records_the_warm_up_reference_temperature_that_is_applied():
    """A user-set T_ref_degC (not T0 + dT) is what apply() uses, and what /truth says."""
    c_b = 1.0e-4
    prof = get_profile("declared_only").with_overrides(
        {"gyro": {"noise": None}, "accel": {"noise": None}, "effects": None}
    ).with_overrides({"effects": {"warmup": {"enabled": True, "T0_degC": 20.0, "dT_degC": 8.0, "tau_s": 10.0,
                                             "T_ref_degC": 25.0, "gyro_bias_tc_rad_per_s_per_K": [c_b, 0.0, 0.0]}}})
    model = ImuErrorModel.from_profile(prof, seed=1)
    g = model.sample_grid(30_000)  # 300 s = 30 tau: settled at 28 degC
    n = g.t_internal.size
    _, w, T = model.apply(g.t_internal, np.tile([0.0, 0.0, 9.8], (n, 1)), np.zeros((n, 3)))
    t_ref = model.truth()["effects"]["warmup"]["T_ref_degC"]
    assert t_ref == 25.0
    expected = model.gyro_bias[0] + c_b * (T[-1] - t_ref)  # bias from the recorded truth
    assert w[-1, 0] == pytest.approx(expected, rel=1e-12, abs=1e-15)
    assert c_b * (T[-1] - t_ref) == pytest.approx(3.0e-4, rel=1e-6)


# ---------------------------------------------------------------------------- schema
def _input_error(tmp_path: Path, imu_sim: dict, name: str = "bad.yaml") -> InputError:
    path = _config(tmp_path, imu_sim, name=name)
    with pytest.raises(InputError) as info:
        with open_rig(load_config(path)):
            pass
    return info.value


def _line_of(path: Path, text: str) -> int:
    return next(i + 1 for i, line in enumerate(path.read_text().splitlines()) if text in line)


def test_misspelt_override_key_is_an_error_at_its_line(tmp_path):
    err = _input_error(tmp_path, {"profile": "mti_class",
                                  "overrides": {"effects": {"lever_arm": {"r_mm": [0.0, 0.0, 0.03]}}}})
    path = tmp_path / "bad.yaml"
    assert err.file == str(path) and err.line == _line_of(path, "r_mm")
    assert "'r_mm'" in err.message and "lever_arm" in err.message
    assert "did you mean 'r_m'" in err.hint


def test_misspelt_effect_name_is_an_error(tmp_path):
    err = _input_error(tmp_path, {"profile": "mti_class", "overrides": {"effects": {"vibrations": {"enabled": False}}}})
    assert err.line == _line_of(tmp_path / "bad.yaml", "vibrations")
    assert "did you mean 'vibration'" in err.hint


def test_enabled_effect_without_its_required_key_is_an_error_at_the_override(tmp_path):
    err = _input_error(tmp_path, {"profile": "declared_only",
                                  "overrides": {"effects": {"lever_arm": {"enabled": True}}}})
    path = tmp_path / "bad.yaml"
    assert err.file == str(path) and err.line == _line_of(path, "lever_arm")
    assert "'r_m'" in err.message and "enabled" in err.message
    assert "add 'r_m: ...'" in err.hint


@pytest.mark.parametrize("over, key, must", [
    ({"gyro": {"bias_rad_per_s": [1.0e-4, 0.0]}}, "bias_rad_per_s", "a list of 3 numbers"),
    ({"effects": {"time_delay": {"enabled": True, "delay_s": "soon"}}}, "delay_s", "a number >= 0"),
    ({"effects": {"clock": {"drop_probability": 1.5}}}, "drop_probability", "a probability"),
    ({"effects": {"warmup": {"enabled": "maybe"}}}, "enabled", "true or false"),
    ({"effects": {"lever_arm": 0.01}}, "lever_arm", "a mapping"),
])
def test_value_of_the_wrong_kind_is_an_error_at_its_line(tmp_path, over, key, must):
    err = _input_error(tmp_path, {"profile": "mti_class", "overrides": over})
    path = tmp_path / "bad.yaml"
    assert err.file == str(path) and err.line == _line_of(path, key)
    assert must in err.message


def test_misspelt_key_in_a_profiles_file_is_an_error_in_that_file(tmp_path):
    prof_file = tmp_path / "mine.yaml"
    prof_file.write_text("profiles:\n  p:\n    rate_hz: 100\n    gyro:\n      bias_rad_per_sec: [0.0, 0.0, 0.0]\n")
    err = _input_error(tmp_path, {"profile": "p", "profiles_file": "mine.yaml"})
    assert err.file == str(prof_file) and err.line == 5
    assert "did you mean 'bias_rad_per_s'" in err.hint


def test_valid_overrides_still_load(tmp_path):
    path = _config(tmp_path, {"profile": "declared_only",
                              "overrides": {"effects": {"lever_arm": {"enabled": True, "r_m": [0.01, 0.0, 0.0]}},
                                            "gyro": {"noise": {"N_rad_per_s_per_sqrt_hz": "1e-4"}}}})
    with open_rig(load_config(path)) as (_rig, truth):
        assert truth["imu"]["effects"]["lever_arm"]["r_m"] == [0.01, 0.0, 0.0]
        assert [m["N"]["value"] for m in truth["imu"]["gyro_noise"]] == [1e-4] * 3


# ---------------------------------------------------------------------------- tap sign
@pytest.mark.parametrize("sign, ok", [(-1, True), (1.0, True), (0.5, False), (0, False)])
def test_tap_sign_is_minus_or_plus_one(tmp_path, sign, ok):
    data = yaml.safe_load((ROOT / "configs" / "sim-taps.yaml").read_text())
    data["pulses"]["sim"]["sign"] = sign
    path = tmp_path / "taps.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    cfg = load_config(path)
    if ok:
        with open_rig(cfg) as (_rig, truth):
            assert truth["pulses"]["taps"]["sign"] == float(sign)
        return
    with pytest.raises(InputError) as info:
        with open_rig(cfg):
            pass
    assert info.value.file == str(path) and info.value.line == _line_of(path, "sign:")
    assert "-1 or +1" in info.value.message
