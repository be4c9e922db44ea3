"""Taps in the in-process rig: procedures/taps.yaml on configs/sim-taps.yaml, then `rigctl sync`."""
import io
import json

import h5py
import numpy as np
import pytest

from rigctl.clock import make_clock
from rigctl.config import load_config
from rigctl.procedure import load_procedure
from rigctl.rig import open_rig
from rigctl.runner import run_procedure
from rigctl.sim.world import NoPulses, SimWorld

from helpers import ROOT, run_rigctl

N_TAPS = 20


@pytest.fixture(scope="module")
def tap_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("taps")
    cfg = load_config(ROOT / "configs" / "sim-taps.yaml")
    proc = load_procedure(ROOT / "procedures" / "taps.yaml", {"taps": N_TAPS}, cfg.limits)
    res = run_procedure(proc, cfg, tmp, console=io.StringIO(), install_signals=False)
    assert res.exit_code == 0, res.message
    return res.recording


def test_pulses_recorded_in_the_taps_window(tap_run):
    with h5py.File(tap_run, "r") as f:
        pt = f["pulses/time"][()]
        src = f["pulses/source"][()]
        seg = {k: f["segments"][k][()] for k in f["segments"]}
        truth = json.loads(f["truth"].attrs["params_json"])["pulses"]["taps"]
    taps = np.flatnonzero(seg["kind"] == b"taps")
    assert taps.size == 1
    t0, t1 = seg["t_start"][taps[0]], seg["t_end"][taps[0]]
    assert np.all(src == b"sim")
    assert np.all((pt > t0) & (pt < t1))
    assert np.all(np.diff(pt) >= truth["timeguard_s"])  # bounces fall in the receiver dead time
    assert pt.size == N_TAPS - truth["missed_count"]


def _world_run(taps_s: list[float], amp: float = 40.0) -> tuple[object, np.ndarray, dict]:
    cfg = load_config(ROOT / "configs" / "sim-taps.yaml")
    clock = make_clock("virtual", 1.0)
    world = SimWorld(cfg, clock)
    if taps_s:
        u = np.zeros((len(taps_s), 3))
        u[:, 2] = 1.0
        world.operator.field.add(np.asarray(taps_s), np.full(len(taps_s), amp), u,
                                 np.ones(len(taps_s), bool))
    clock.sleep(9.0)
    return world.take_imu(), world.truth()


def test_taps_pass_the_sensor_low_pass():
    """Same seed with and without taps: the difference is the taps as the IMU outputs them,
    after its (30 Hz) low-pass and internal delay: causal, delayed, lower and spread in time."""
    taps_s = [2.0 + k + 0.00093 * k for k in range(6)]  # several sub-sample phases
    quiet, _ = _world_run([])
    tapped, truth = _world_run(taps_s)
    d = tapped.specific_force[:, 2] - quiet.specific_force[:, 2]
    t_out = tapped.time  # counter / rate; no clock offset at power-on 0, drift 85 ppm
    assert np.all(np.abs(d[t_out < taps_s[0]]) == 0.0)
    delay = truth["imu"]["time_delay_s"]
    for ti in taps_s:
        near = (t_out > ti - 0.5) & (t_out < ti + 0.5)
        dz, tt = d[near], t_out[near] * (1 + 85e-6)  # true time of each sample
        seen = tt[np.abs(dz) > 1e-9]
        assert seen[0] >= ti + delay  # nothing before the tap reaches the output
        peak = np.sort(dz)[::-1]
        assert peak[0] < 0.5 * 40.0  # the blow (~1.5 ms) is smoothed by the 30 Hz low-pass
        assert peak[1] > 0.1 * peak[0]  # ... and spread over more than one output sample


def test_sync_finds_taps_and_the_true_clock(tap_run):
    r = run_rigctl("sync", str(tap_run))
    assert r.returncode == 0, r.stderr
    with h5py.File(tap_run, "r") as f:
        s = json.loads(f["results/sync"].attrs["json"])
        t = json.loads(f["truth"].attrs["params_json"])
    missed = t["pulses"]["taps"]["missed_count"]
    assert s["n_taps_detected"] == N_TAPS
    assert s["n_matched"] == N_TAPS - missed and s["n_outliers"] == 0
    # pulse = tap + trigger latency; the IMU reports what happened time_delay_s earlier and its
    # counter 0 is at power_on_time_s. The blow is the mount's second-order response, short
    # against the IMU's low-pass: the output sees it as an impulse at its centroid, 2 zeta / w_n
    # after the onset (-H'(0)/H(0)), which is the time the sync's impulse model finds.
    tp = t["pulses"]["taps"]
    centroid = 2 * tp["damping"] / (2 * np.pi * tp["natural_freq_hz"])
    offset = t["imu"]["power_on_time_s"] + tp["latency_s"] - t["imu"]["time_delay_s"] - centroid
    assert s["timing"] == "subsample"
    assert abs(s["offset_s"] - offset) <= s["offset_ci95_s"]
    drift = t["imu"]["effects"]["clock"]["drift_ppm"]
    assert abs(s["drift_ppm"] - drift) <= s["drift_ci95_ppm"]


def test_default_config_has_no_pulses():
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    with open_rig(cfg) as (rig, truth):
        assert isinstance(rig.pulses, NoPulses) and rig.operator is None
        assert "pulses" not in truth
