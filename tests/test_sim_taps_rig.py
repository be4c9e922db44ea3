"""Taps in the in-process rig: procedures/taps.yaml on configs/sim-taps.yaml, then `rigctl sync`."""
import io
import json

import h5py
import numpy as np
import pytest

from rigctl.clock import make_clock
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.engine.rig import open_rig
from rigctl.run.runner import run_procedure
from rigctl.devices import NoPulses
from rigctl.sim.world import SimWorld

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
    # counter 0 is at run time 0. The blow is the mount's second-order response, short
    # against the IMU's low-pass: the output sees it as an impulse at its centroid, 2 zeta / w_n
    # after the onset (-H'(0)/H(0)), which is the time the sync's impulse model finds.
    tp = t["pulses"]["taps"]
    centroid = 2 * tp["damping"] / (2 * np.pi * tp["natural_freq_hz"])
    offset = tp["latency_s"] - t["imu"]["time_delay_s"] - centroid
    assert s["timing"] == "subsample"
    assert abs(s["offset_s"] - offset) <= s["offset_ci95_s"]
    drift = t["imu"]["effects"]["clock"]["drift_ppm"]
    assert abs(s["drift_ppm"] - drift) <= s["drift_ci95_ppm"]


def test_individual_taps_are_recorded_in_the_truth(tap_run):
    """/truth/taps and /truth/edges hold every blow and edge drawn during the run: the logged
    edges are exactly /pulses/time, the missed pulse is flagged, bounces are counted."""
    with h5py.File(tap_run, "r") as f:
        taps = {k: f["truth/taps"][k][()] for k in f["truth/taps"]}
        edges = {k: f["truth/edges"][k][()] for k in f["truth/edges"]}
        units = {k: f["truth/taps"][k].attrs["units"] for k in f["truth/taps"]}
        pt = f["pulses/time"][()]
        seg = {k: f["segments"][k][()] for k in ("kind", "t_start", "t_end")}
        params = json.loads(f["truth"].attrs["params_json"])["pulses"]["taps"]
    assert units["time_s"] == "s" and units["amplitude_m_s2"] == "m/s^2"
    assert taps["time_s"].size == N_TAPS and np.all(taps["hammer"] == 1)
    w = np.flatnonzero(seg["kind"] == b"taps")[0]
    assert np.all((taps["time_s"] > seg["t_start"][w]) & (taps["time_s"] < seg["t_end"][w]))
    assert np.all(np.abs(np.log(np.abs(taps["amplitude_m_s2"]) / params["amplitude_median_m_s2"]))
                  < 5 * params["amplitude_log_sigma"])
    assert int(taps["missed"].sum()) == params["missed_count"]
    assert np.all(np.isnan(taps["edge_time_s"][taps["missed"] == 1]))
    fired = taps["missed"] == 0
    lag = taps["edge_time_s"][fired] - taps["time_s"][fired] - params["latency_s"]
    assert np.all(np.abs(lag) < 6 * params["jitter_s"])
    logged = edges["logged"] == 1
    assert np.array_equal(np.sort(edges["time_s"][logged]), pt)
    assert int((edges["kind"] == b"bounce").sum()) == int(taps["bounces"].sum()) > 0
    assert np.all(edges["kind"][logged] == b"tap")  # bounces fall in the receiver's dead time
    main = edges["kind"] == b"tap"
    assert np.array_equal(taps["edge_time_s"][edges["tap_row"][main]], edges["time_s"][main])


def test_sync_matches_agree_with_the_recorded_taps(tap_run):
    """Every tap `rigctl sync` matched is a recorded hammer tap: its pulse is that tap's logged
    edge, and its IMU time, mapped to run time through the true clock, is the tap's true time
    (plus the IMU's delay and the response centroid, as the clock fit says)."""
    r = run_rigctl("sync", str(tap_run))
    assert r.returncode == 0, r.stderr
    with h5py.File(tap_run, "r") as f:
        taps = {k: f["truth/taps"][k][()] for k in f["truth/taps"]}
        res = f["results/sync"]
        s = json.loads(res.attrs["json"])
        tap_imu, pulse = res["tap_time_imu"][()], res["pulse_time"][()]
        inlier = res["inlier"][()].astype(bool)
        t = json.loads(f["truth"].attrs["params_json"])
    rows = np.array([int(np.flatnonzero(taps["edge_time_s"] == p)[0]) for p in pulse])
    assert np.unique(rows).size == rows.size and np.all(taps["edge_logged"][rows] == 1)
    assert inlier.all() and rows.size == int(taps["edge_logged"].sum())
    assert s["n_taps_without_pulse"] == int((taps["edge_logged"] == 0).sum())
    ppm = t["imu"]["effects"]["clock"]["drift_ppm"]
    tau0 = 1.0 / t["imu"]["output_rate_hz"]
    true_imu = (tap_imu / tau0 + 1.0) * tau0 * (1 + 1e-6 * ppm) - tau0  # clock of docs/emulator.md
    tp = t["pulses"]["taps"]
    centroid = 2 * tp["damping"] / (2 * np.pi * tp["natural_freq_hz"])
    err = true_imu - (taps["time_s"][rows] + t["imu"]["time_delay_s"] + centroid)
    assert np.all(np.abs(err) < 4 * s["residual_std_ms"] * 1e-3 + 1e-4)


def test_default_config_has_no_pulses():
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    with open_rig(cfg) as (rig, truth):
        assert isinstance(rig.pulses, NoPulses) and rig.operator is None
        assert "pulses" not in truth
