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


@pytest.fixture(scope="module")
def reference_calibration(reference):
    """The in-process 24-position run's calibration: {parameter: (value, 1-sigma)}."""
    return _calibration(reference["24pos.yaml"][0])


def _calibration(recording) -> dict[str, tuple[float, float]]:
    from rigctl.analysis.calibration import calibrate
    payload, _, _ = calibrate(recording, store=False)
    assert payload["status"] == "ok", payload["reasons"]
    final = payload["results"]["closed_loop"]["final"]
    return {p["name"]: (p["value"], p["sigma"]) for p in final["parameters"]}


def truth_parameters(truth_imu: dict) -> dict[str, float]:
    """The emulator's declared IMU errors (``/truth`` imu, SI) under the calibration's parameter
    names, read off its vectors and matrices here (not from the calibration's own truth table)."""
    out: dict[str, float] = {}
    for i, a in enumerate("xyz"):
        out[f"accel_bias_{a}_m_s2"] = truth_imu["accel_bias_m_s2"][i]
        out[f"accel_quad_{a}_s2_per_m"] = truth_imu["accel_quadratic_per_m_s2"][i]
        out[f"gyro_bias_{a}_rad_s"] = truth_imu["gyro_bias_rad_s"][i]
        for j, b in enumerate("xyz"):
            out[f"accel_M_{a}{b}_ratio"] = truth_imu["accel_matrix"][i][j]
            out[f"gyro_M_{a}{b}_ratio"] = truth_imu["gyro_matrix"][i][j]
    return out


#: family-wise false-alarm level of one calibration check (all its parameters together); see
#: :func:`same_calibration` for why 1e-3 and what it still detects
FAMILY_ALPHA = 1e-3


def outside_band(cal: dict, truth: dict, family_alpha: float = FAMILY_ALPHA) -> tuple[float, dict[str, float]]:
    """(z threshold, {parameter: z} of the parameters outside the family-wise band)."""
    from scipy.stats import norm
    assert set(cal) == set(truth)
    zc = float(norm.ppf(1 - family_alpha / (2 * len(truth))))
    score = {k: (cal[k][0] - truth[k]) / cal[k][1] for k in truth}
    return zc, {k: v for k, v in score.items() if not abs(v) <= zc}


def same_calibration(cal: dict, truth: dict, family_alpha: float = FAMILY_ALPHA) -> None:
    """The run's calibration finds the emulator's truth within its own intervals, all m = 27
    parameters together at family-wise false-alarm level ``family_alpha`` (Bonferroni: each
    |value - truth| <= z sigma, z = z_(1 - alpha / 2m) = 4.13 for alpha = 1e-3).

    Measured on 47 wired runs (16 VectorNav, 15 frame, 16 Xsens at load 10-12; the CI failure's
    accel_M_zz_ratio 3.74 sigma was on VectorNav): z = (value - truth) / sigma has mean -0.56 ..
    +0.49 and pooled sd 0.98 per parameter, median largest |z| of a run 2.21 (2.24 for 27 N(0, 1)
    draws), accel_M_zz_ratio -0.28 +- 0.89 (VectorNav -0.10 +- 0.81): no protocol offset (the CI
    run's value, 1.0003231 +- 7.2e-6, is +3.2 sigma from the truth 1.0003: far in that tail, inside
    this band). So the false-alarm rate at z = 4.13 is 1.1e-3 per run (from those means and sd).

    Compared with the truth, not with the in-process run's calibration as before: that one is a
    single fixed noise realisation (virtual clock, seed 1: the same in every CI run), so a wired
    run's z against it was not N(0, 1) but centred on minus the reference's own error (its
    accel_M_zz_ratio lies 2.18 sigma below the truth: wired z +1.38 +- 0.62), and its sigma
    sqrt(s_w^2 + s_r^2) ~ 1.4 s_w carried the reference's noise, which cost power: a 5-sigma error
    in one parameter was flagged in 30 % of the cases at z = 4.13 (65 % at the old 3.11, where
    each run failed with probability 1.4 %, three such runs per CI run), against 81 % now. The
    in-process run meets the same band (:func:`test_inprocess_calibration_finds_the_truth`,
    deterministic), so wired and in-process calibrations agree through the truth.

    Why 1e-3 and not 5 %: three runs per CI run make this check (Xsens, VectorNav, frame); at
    5 % each (z = 3.11: 5.2 % per run measured) one CI run in seven would fail on noise alone.
    Power is checked on every run, on the dicts, by :func:`assert_detects_injected_errors`."""
    zc, bad = outside_band(cal, truth, family_alpha)
    score = {k: (cal[k][0] - truth[k]) / cal[k][1] for k in truth}
    worst = max(score, key=lambda k: abs(score[k]))
    assert not bad, (f"outside the family-wise {1 - family_alpha:.1%} band (z = {zc:.2f}): "
                     f"{ {k: (cal[k], truth[k], f'{v:+.2f} sigma') for k, v in bad.items()} }; "
                     f"worst {worst} {score[worst]:+.2f}")


def assert_detects_injected_errors(cal: dict, truth: dict, n_sigma: float = 5.0,
                                   family_alpha: float = FAMILY_ALPHA) -> None:
    """Power of :func:`same_calibration` on this very run, on the dicts (no second run): an
    error of ``n_sigma`` of its own 1-sigma added to one parameter, each of the 27 in turn and
    each sign (54 cases), must be flagged -- and named -- in at least 60 % of the cases (the
    expected share for z ~ N(0, 1) is 81 % at 5 sigma, z threshold 4.13; each parameter's error
    in the direction of its present deviation is always flagged, the other one when |z| < 0.87;
    fewer than 60 % is a 4-sigma shortfall of that count). A scale error of +-5 sigma in
    accel_M_zz_ratio (the parameter of the CI failure) must be flagged in at least one direction
    (that of its present deviation; a check of the machinery itself)."""
    flagged = {(k, sign): k in outside_band({**cal, k: (cal[k][0] + sign * n_sigma * cal[k][1], cal[k][1])},
                                            truth, family_alpha)[1]
               for k in truth for sign in (+1, -1)}
    assert flagged["accel_M_zz_ratio", +1] or flagged["accel_M_zz_ratio", -1], \
        f"a {n_sigma:g}-sigma scale error in accel_M_zz_ratio is not flagged"
    hits = sum(flagged.values())
    assert hits >= 0.6 * 2 * len(truth), f"only {hits} of {2 * len(truth)} injected {n_sigma:g}-sigma errors flagged"


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
    cal, truth = _calibration(rec), truth_parameters(info["truth"]["imu"])
    same_calibration(cal, truth)
    assert_detects_injected_errors(cal, truth)


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
    cal, truth = _calibration(rec), truth_parameters(info["truth"]["imu"])
    same_calibration(cal, truth)
    assert_detects_injected_errors(cal, truth)


def test_inprocess_calibration_finds_the_truth(reference, reference_calibration):
    """The in-process run (virtual clock, seed 1: deterministic) meets the band the wired runs
    are held to, so wired and in-process calibrations agree through the truth (its largest
    deviation: accel_M_zz_ratio -2.18 sigma)."""
    truth = truth_parameters(_inprocess_truth(reference["24pos.yaml"][0])["imu"])
    same_calibration(reference_calibration, truth)
    assert_detects_injected_errors(reference_calibration, truth)


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
