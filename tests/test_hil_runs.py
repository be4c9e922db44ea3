"""Hardware in the loop: procedures run over real ptys / TCP / pymodbus against the emulated
servers (one physics world at 100x-200x real time), through the ASCII and the Modbus table; the
recordings carry the same segments as an in-process run and their means follow the model."""
from __future__ import annotations

import json
import math
import threading

import h5py
import numpy as np
import pytest

from rigctl.frames import body_references

from cal_band import Calibration, calibration_of, check_calibration, no_library_effects, truth_parameters
from hil_support import repeated_samples, run, segments, white_noise_only, white_sim, window_means, wired_run

SPEED = 200.0        # rates
SPEED_24 = 100.0     # 24pos with its 15-minute warm-up: ~1300 s of rig time, ~14 s of wall time
LAG = 3.0            # s of rig time: poll latency (a few ms of wall time, more on a loaded machine)
P24 = {"sample": "5 s"}                      # keeps the 15-minute warm-up
PRATES = {"revolutions": 1}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """In-process (virtual time) runs of the same procedures, for comparison."""
    tmp = tmp_path_factory.mktemp("ref")
    out = {}
    for name, params in (("24pos.yaml", P24), ("rates.yaml", PRATES)):
        res, cfg = run(name, white_sim(tmp), tmp, params)  # as the wired runs: white noise
        out[name] = (res.recording, segments(res.recording))
    return out


def _calibration(recording) -> Calibration:
    """The closed loop's calibration of ``recording`` (tests/cal_band.py)."""
    from rigctl.analysis.calibration import calibrate
    payload, _, _ = calibrate(recording, store=False)
    assert payload["status"] == "ok", payload["reasons"]
    return calibration_of(payload["results"]["closed_loop"])


def check_run_calibration(recording, truth: dict) -> None:
    """The run's calibration against the emulator's whole /truth ``truth``: the declared
    parameters in the family-wise band with its power on this run, and any effect the closed loop
    added 0 within its uncertainty (tests/cal_band.py: the loop adds one in ~1 % of the runs by
    design; the CI failure at c5cf9c7 was such a table_levelling on the frame run)."""
    from rigctl.solvers.effect_library import LIBRARY
    no_library_effects(truth)
    check_calibration(_calibration(recording), truth_parameters(truth["imu"]), len(LIBRARY))


def same_segments(wired: dict, ref: dict) -> None:
    assert list(wired["kind"]) == list(ref["kind"])
    assert list(wired["label"]) == list(ref["label"])
    assert list(wired["step"]) == list(ref["step"])
    if "status" in ref:
        assert set(wired["status"]) == {b"complete"}


def each_sample_once(rec, info) -> None:
    """Every world sample reached the recording once: no run of repeated samples (the tap fix,
    tests/test_hil_tap.py: before it, 30-180 frames of one sample several times per run, and one
    such run inside a window moved its mean by 9 sigma: the CI failure of 07702e9) and no frame
    asked the emulator's tap for a sample it no longer had."""
    assert repeated_samples(rec) == []
    assert info["hw"].tap.clamped == 0


def check_24pos(rec, cfg, info, ref_segments) -> None:
    each_sample_once(rec, info)
    seg = segments(rec)
    same_segments(seg, ref_segments)
    warm = np.flatnonzero(seg["kind"] == b"warmup")
    # the warm-up window is the 900 s the procedure asks for, to the clock's resolution: the
    # engine no longer stretches a window by the wall time of its last poll x speed (a loaded host
    # gave 902-918 s at 100x); the IMU samples in it span it (to the edge lag of the wire)
    assert warm.size == 1
    w = warm[0]
    assert seg["t_end"][w] - seg["t_start"][w] == pytest.approx(900.0, abs=1e-6)
    assert 900.0 - LAG <= (seg["last_sample"][w] - seg["first_sample"][w]) / cfg.imu_rate_hz <= 900.0 + 1.0 / cfg.imu_rate_hz
    truth = info["truth"]["imu"]
    white_noise_only(truth)     # so 5 sigma of white noise is the window mean's whole noise model
    b, m = np.array(truth["accel_bias_m_s2"]), np.array(truth["accel_matrix"])
    k2 = np.array(truth["accel_quadratic_per_m_s2"])
    means = window_means(rec, seg, b"orientation", "specific_force")
    assert len(means) == 24
    rows = np.flatnonzero(seg["kind"] == b"orientation")
    with h5py.File(rec, "r") as f:
        t_imu = f["imu/time"][()]
    for i, mean in zip(rows, means):
        a, z = int(seg["first_sample"][i]), int(seg["last_sample"][i])
        n = z - a
        # the engine takes the window as the samples recorded between two polls, so at 200x its
        # edges move by the poll latency (a few ms of wall time, up to ~1.5 s of rig time)
        assert seg["t_end"][i] - seg["t_start"][i] == pytest.approx(5.0, abs=1e-6)
        assert seg["t_start"][i] - LAG <= t_imu[a] and t_imu[z - 1] <= seg["t_end"][i] + LAG
        assert 5.0 - LAG <= n / cfg.imu_rate_hz <= 5.0 + 1.0 / cfg.imu_rate_hz
        f_ref, _ = body_references(seg["commanded_angle"][i], None, cfg.latitude, cfg.height_m, cfg.gravity)
        predicted = b + m @ f_ref + k2 * f_ref**2
        sigma = truth["accel_noise"][0]["N"]["value"] * math.sqrt(cfg.imu_rate_hz) / math.sqrt(n)
        np.testing.assert_allclose(mean, predicted, atol=5 * sigma + 5e-5)
    assert info["imu_overflow"] == 0


def check_rates(rec, info, ref) -> None:
    each_sample_once(rec, info)
    white_noise_only(info["truth"]["imu"])
    ref_rec, ref_seg = ref
    seg = segments(rec)
    same_segments(seg, ref_seg)
    wired = window_means(rec, seg, b"rate", "angular_rate")
    inproc = window_means(ref_rec, ref_seg, b"rate", "angular_rate")
    assert len(wired) == 18
    truth = info["truth"]["imu"]
    for i, (w, r) in zip(np.flatnonzero(seg["kind"] == b"rate"), zip(wired, inproc)):
        n = int(seg["last_sample"][i] - seg["first_sample"][i])
        sigma = truth["gyro_noise"][0]["N"]["value"] * math.sqrt(100.0) / math.sqrt(n)
        # the commanded rate dominates; both runs see the same model within noise (+ window-edge
        # effects of Earth rate over a fraction of a revolution, < 2e-6 rad/s)
        np.testing.assert_allclose(w, r, atol=5 * math.sqrt(2) * sigma + 2e-6)
        axis = int(np.argmax(np.abs(seg["commanded_rate"][i])))
        assert abs(w).max() > math.radians(35)


def test_24pos_with_warmup_over_acl_pty(tmp_path, reference):
    """Xsens MT over a pty (and the ACL table over a pty)."""
    rec, cfg, info = wired_run(tmp_path, "24pos.yaml", P24, "acl", "pty", SPEED_24)
    check_24pos(rec, cfg, info, reference["24pos.yaml"][1])
    assert info["truth"] == _inprocess_truth(reference["24pos.yaml"][0])
    check_run_calibration(rec, info["truth"])


@pytest.mark.parametrize("protocol", ["vectornav", "frame"])
def test_24pos_over_each_imu_protocol(tmp_path, reference, protocol):
    """The same run with the IMU speaking VectorNav binary (configured over $VNWRG) or the
    declarative frame of docs/hardware.md, each over a pty: same segments, window means on the
    model, the calibration agrees with the in-process run's, and every frame sent arrived.

    The IMU-gap suspender waits 10 s of rig time here (default 2 s): at 100x that is 0.1 s of
    wall time instead of 0.02 s, so a host busy with other work (load 8-12 on 2 cores) does not
    pause the run and re-run its warm-up; pauses are the subject of the daemon and fault tests,
    not of this one. (The Xsens runs above keep the default and do pause at that load.)"""
    rec, cfg, info = wired_run(tmp_path, "24pos.yaml", P24, "acl", "pty", SPEED_24,
                               hw_kw={"imu_protocol": protocol}, suspenders={"imu_timeout_s": 10})
    check_24pos(rec, cfg, info, reference["24pos.yaml"][1])
    assert cfg.imu.driver == protocol
    with h5py.File(rec, "r") as f:
        n, counter = f["imu/time"].shape[0], f["imu/counter"][()]
        ident = json.loads(f["meta"].attrs["imu_identity_json"])
    assert np.all(np.diff(counter.astype(np.int64)) == 1)        # no sample lost on the wire
    assert n >= 0.99 * (counter[-1] - counter[0] + 1)
    if protocol == "vectornav":
        assert ident == {"device_id": "0100012345", "model": "VN-100T-CR", "firmware": "2.1.0.0",
                         "protocol": "VectorNav binary"}
    else:
        assert ident["protocol"] == "declarative frame (binary, AA 55)"
    check_run_calibration(rec, info["truth"])


def test_inprocess_calibration_finds_the_truth(reference):
    """The in-process run (virtual clock, seed 1: deterministic) meets the band the wired runs
    are held to, so wired and in-process calibrations agree through the truth (its largest
    deviation: accel_M_zz_ratio -2.18 sigma; the closed loop adds no effect on it)."""
    check_run_calibration(reference["24pos.yaml"][0], _inprocess_truth(reference["24pos.yaml"][0]))


def test_24pos_with_warmup_over_modbus_tcp(tmp_path, reference):
    rec, cfg, info = wired_run(tmp_path, "24pos.yaml", P24, "modbus", "tcp", SPEED_24)
    check_24pos(rec, cfg, info, reference["24pos.yaml"][1])


#: the IMU-gap suspender's wait for the 200x rate runs: 10 s of rig time = 50 ms of wall time
#: (the default 2 s is 10 ms there: a host at load 8-9 on 2 cores paused a run on it, 'IMU data
#: gap: no samples for 2.9 s', and the step it re-ran made 19 segments for 18); as for the
#: VectorNav and frame runs above, pauses are the subject of the daemon and fault tests
RATE_SUSPENDERS = {"imu_timeout_s": 10}


def test_rates_over_acl_tcp(tmp_path, reference):
    rec, _, info = wired_run(tmp_path, "rates.yaml", PRATES, "acl", "tcp", SPEED, suspenders=RATE_SUSPENDERS)
    check_rates(rec, info, reference["rates.yaml"])


def test_rates_over_modbus_rtu(tmp_path, reference):
    rec, _, info = wired_run(tmp_path, "rates.yaml", PRATES, "modbus", "rtu", SPEED, suspenders=RATE_SUSPENDERS)
    check_rates(rec, info, reference["rates.yaml"])
    assert not [t for t in threading.enumerate() if t.name.startswith(("imu-", "pulses-", "hardware-"))]


def _inprocess_truth(recording):
    import json

    import h5py
    with h5py.File(recording, "r") as f:
        return json.loads(f["truth"].attrs["params_json"])
