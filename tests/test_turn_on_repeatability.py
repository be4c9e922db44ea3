"""An emulated IMU comes back from a power cycle with a new turn-on bias, drawn from its bias
repeatability (turn-on to turn-on, run-to-run: configs/sim.yaml ``*_turn_on_repeatability_*``, a
profile's ``turn_on_bias`` effect) from a seeded stream: reproducible.

Before: a power cycle changed nothing but the device time; a test had to set the bias step itself
(tests/hil_support.power_loss), and a run with a power loss and no hand-set step measured no jump.
"""
from __future__ import annotations

import io
import math

import h5py
import numpy as np

from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import run_procedure
from rigctl.sim.error_model import ImuErrorModel
from rigctl.sim.imu import build_declared_imu
from rigctl.yamlio import LocDict

from helpers import WHITE_NOISE_ONLY, derived_config
from hil_support import ROOT, RunPoints, point_options, sampling

G0 = 9.80665
DEG_H = math.pi / 180.0 / 3600.0


def _declared(seed: int, gyro_deg_h: float = 15.0, accel_mg: float = 0.5):
    return build_declared_imu(LocDict({"gyro_turn_on_repeatability_deg_h": gyro_deg_h,
                                       "accel_turn_on_repeatability_mg": accel_mg}), 100.0, seed)


def test_declared_power_cycles_draw_the_configured_repeatability_reproducibly():
    """2000 power cycles of the declared model: each axis' turn-on biases have the configured
    sigma (chi-square band of the sample variance, 2000 dof: +-3.2 %, 5 sigma) and mean zero; the
    same seed draws the same sequence; the white noise is the same with or without the draws."""
    m = _declared(seed=5)
    draws = np.array([np.concatenate(m.power_cycle()) for _ in range(2000)])
    sig = np.array([15.0 * DEG_H] * 3 + [0.5e-3 * G0] * 3)
    ratio = draws.std(axis=0, ddof=0) / sig
    assert np.all(np.abs(ratio - 1) < 5 * math.sqrt(1 / (2 * 2000))), ratio
    assert np.all(np.abs(draws.mean(axis=0)) < 5 * sig / math.sqrt(2000))
    again = _declared(seed=5)
    assert np.array_equal(np.concatenate(again.power_cycle()), draws[0])
    assert not np.array_equal(np.concatenate(_declared(seed=6).power_cycle()), draws[0])
    # the outputs move by the drawn turn-on bias, nothing else: same noise streams
    quiet, cycled = _declared(seed=9), _declared(seed=9)
    g, a = cycled.power_cycle()
    t, z = np.arange(50) / 100.0, np.zeros((50, 3))
    f0, w0, _ = quiet.apply(t, z, z)
    f1, w1, _ = cycled.apply(t, z, z)
    assert np.allclose(f1 - f0, a, rtol=0, atol=1e-12) and np.allclose(w1 - w0, g, rtol=0, atol=1e-12)
    assert np.any(np.abs(a) > 0) and cycled.truth()["accel_turn_on_bias_m_s2"] == a.tolist()


def test_a_profile_power_cycle_moves_the_output_by_the_new_turn_on_bias():
    """The profile model (its compiled path caches the biases): after a power cycle the output of
    the same input moves by exactly the change of turn-on bias (noise streams aside: two models of
    one seed, one cycled), drawn with the profile's ``turn_on_bias`` sigmas."""
    from rigctl.sim.profiles import get_profile
    prof = get_profile("mti_class")
    a_model, b_model = ImuErrorModel(prof, seed=3), ImuErrorModel(prof, seed=3)
    n = 200 * a_model.decimation
    t = np.arange(n) / a_model.internal_rate_hz
    f, w = np.tile([0.0, 0.0, G0], (n, 1)), np.zeros((n, 3))
    a_model.apply(t, f, w)
    b_model.apply(t, f, w)          # both warm (the compiled path's constants built)
    old_g, old_a = b_model.turn_on_gyro.copy(), b_model.turn_on_accel.copy()
    new_g, new_a = b_model.power_cycle()
    t2 = t + t[-1] + 1 / a_model.internal_rate_hz
    fa, wa, _ = a_model.apply(t2, f, w)
    fb, wb, _ = b_model.apply(t2, f, w)
    # the difference carries the front end's low-pass step response at the start: judge the settled part
    k = fa.shape[0] // 2
    assert np.allclose((fb - fa)[k:], new_a - old_a, rtol=1e-6, atol=1e-9)
    assert np.allclose((wb - wa)[k:], new_g - old_g, rtol=1e-6, atol=1e-12)
    on = prof.effects.turn_on_bias
    assert np.all(np.abs(new_a - old_a) > 0) and np.all(np.abs(new_a) < 5 * on.accel_sigma_m_per_s2)


def test_a_24_position_run_across_a_power_cycle_measures_the_drawn_turn_on_bias_jump(tmp_path):
    """procedures/24pos.yaml (10 s windows) on configs/sim.yaml (white noise only), the power lost
    for 3 s 8 s into the 13th orientation's window, no bias step set by the test: the unit comes
    back with a turn-on bias drawn from configs/sim.yaml's repeatability (15 deg/h, 0.5 mg). The
    result is NOT TRUSTWORTHY, and the jump measured at that orientation -- the mean of the
    complete window sampled again after the re-warm less that of the 8 s cut off before the power
    loss, the same table orientation -- matches the drawn turn-on bias to its white-noise sigma."""
    from rigctl.analysis.calibration import calibrate
    cfg = load_config(derived_config(tmp_path, **WHITE_NOISE_ONLY))
    proc = load_procedure(ROOT / "procedures" / "24pos.yaml", {"warmup": "10 s", "sample": "10 s",
                                                             "discard": "0.5 s"}, cfg.limits)
    points = RunPoints([])

    def power_loss() -> None:
        world = points.engine.rig.imu.world
        world.faults.schedule("imu_power", world.t, 3.0)
    points.actions.append((sampling("orientation", after_samples=800, finished=12), power_loss))
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False,
                        options=point_options(points))
    assert res.exit_code == 0, res.message
    world = points.engine.rig.imu.world
    (cycle,) = world.imu_power_cycles
    with h5py.File(res.recording, "r") as f:
        seg = {k: f["segments"][k][()] for k in ("kind", "status", "step", "first_sample", "last_sample")}
        x = np.hstack([f["imu/specific_force"][()], f["imu/angular_rate"][()]])
        t_imu = f["imu/time"][()]
        # the draw is in the recording's /truth, where a user checking against the truth looks
        # (before: only in the emulator's truth(), the recording's params_json written before it)
        pc = f["truth/imu_power_cycles"]
        (t_cycle,), (g_on,), (a_on,) = (pc[k][()] for k in ("time_s", "gyro_turn_on_bias_rad_s",
                                                             "accel_turn_on_bias_m_s2"))
        units = {k: pc[k].attrs["units"] for k in pc}
    assert units == {"time_s": "s", "gyro_turn_on_bias_rad_s": "rad/s", "accel_turn_on_bias_m_s2": "m/s^2"}
    assert (t_cycle, g_on.tolist(), a_on.tolist()) == (cycle["t_s"], cycle["gyro_turn_on_bias_rad_s"],
                                                       cycle["accel_turn_on_bias_m_s2"])
    drawn = np.concatenate([a_on, g_on])
    rows = [i for i in range(len(seg["kind"])) if seg["kind"][i] == b"orientation" and seg["step"][i] == 13]
    assert [seg["status"][i] for i in rows] == [b"incomplete", b"complete"], rows
    (a0, z0), (a1, z1) = ((int(seg["first_sample"][i]), int(seg["last_sample"][i])) for i in rows)
    before, after = x[a0:z0], x[a1:z1]
    # it takes effect between the two windows: after the cut-off one, before the one sampled again
    assert t_imu[z0 - 1] < t_cycle < t_imu[a1], (t_imu[z0 - 1], t_cycle, t_imu[a1])
    assert len(before) >= 750 and len(after) >= 950, (len(before), len(after))
    measured = after.mean(axis=0) - before.mean(axis=0)
    sigma = np.sqrt(before.var(axis=0, ddof=1) / len(before) + after.var(axis=0, ddof=1) / len(after))
    z = (measured - drawn) / sigma
    assert np.all(np.abs(z) < 4.5), {"measured": measured, "drawn": drawn, "z": z}
    # the jump is there to be seen: at least one accelerometer axis beyond 5 sigma of the noise
    assert np.max(np.abs(drawn[:3] / sigma[:3])) > 5, drawn / sigma
    payload, text, _ = calibrate(res.recording, store=False)
    assert payload["trustworthy"] is False and payload["loop_status"] == "NOT TRUSTWORTHY"
    # the truth comparison knows the bias was not one value: the biases are left out, and said so
    compared = [e["name"] for e in payload["results"]["closed_loop"]["truth_errors"]]
    assert compared and not [n for n in compared if "_bias_" in n], compared
    assert "accel_M_xx_ratio" in compared
    assert f"power-cycled at t = {t_cycle:.1f} s" in payload["truth_note"], payload["truth_note"]
    assert f"note: {payload['truth_note']}" in text
    assert len(payload["device_restarts"]) == 1 and "STATUS: NOT TRUSTWORTHY: IMU restarted at t = " in text


def test_the_truth_readers_leave_out_the_bias_only_when_a_cycle_changed_it(tmp_path):
    """/truth/imu_power_cycles written by hand (tests/recording_helpers.py): a cycle that drew the
    same turn-on bias again (a repeatability of 0) changes nothing; one that drew another makes
    the constant biases (calibration's and the thermal fit's names) no single truth, and only
    them: a temperature coefficient of the bias is still compared."""
    from recording_helpers import write_recording
    from rigctl.analysis.restarts import truth_across_power_cycles, truth_power_cycles
    from rigctl.sim.world import POWER_CYCLE_TABLE
    path = write_recording(tmp_path / "r.h5", 100.0, angular_rate=np.zeros((10, 3)),
                           truth_json='{"imu": {"model": "declared", "gyro_turn_on_bias_rad_s": [0, 0, 0], '
                                      '"accel_turn_on_bias_m_s2": [0, 0, 0]}}')
    rows = {"time_s": [1.0, 2.5], "gyro_turn_on_bias_rad_s": [[0, 0, 0], [1e-5, 0, -2e-5]],
            "accel_turn_on_bias_m_s2": [[0, 0, 0], [3e-3, 0, 0]]}
    truth = {"accel_bias_x_m_s2": 0.01, "gyro_bias_z_rad_s": 1e-4, "accel_bias_x_m_s2_per_K": 1e-5,
             "accel_M_xx_ratio": 1.001}
    with h5py.File(path, "r+") as f:
        for k, (shape, dtype, units) in POWER_CYCLE_TABLE["imu_power_cycles"].items():
            f.create_dataset(f"truth/imu_power_cycles/{k}", data=np.asarray(rows[k][:1], dtype)).attrs["units"] = units
    with h5py.File(path, "r") as f:
        assert truth_power_cycles(f).size == 0 and truth_across_power_cycles(f, truth) == (truth, "")
    with h5py.File(path, "r+") as f:
        for k in rows:
            del f[f"truth/imu_power_cycles/{k}"]
            f.create_dataset(f"truth/imu_power_cycles/{k}", data=np.asarray(rows[k], float))
    with h5py.File(path, "r") as f:
        assert truth_power_cycles(f).tolist() == [2.5]
        kept, note = truth_across_power_cycles(f, truth)
    assert kept == {"accel_bias_x_m_s2_per_K": 1e-5, "accel_M_xx_ratio": 1.001}
    assert "power-cycled at t = 2.5 s" in note
