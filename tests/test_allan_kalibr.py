"""`rigctl allan --kalibr/--json/--csv` on an emulated capture, and the robotics round trip
(recording -> rosbag2 -> `rigctl import` -> `rigctl allan --kalibr`).

The capture: 1 h at 100 Hz of the emulator's declared_only profile (white noise N, flicker B,
random walk K) with K raised ten-fold so that a 1-hour capture resolves it (K dominates beyond
~30 s) and N different on each axis: conftest's declared_only_hour, analysed once per session by
conftest's declared_only_hour_allan (`rigctl allan --kalibr --json --csv` with the defaults), whose
stored results test_noise_coefficients checks too (copies of the recording and the exports
here). Truth from the recording's /truth. Checks, independent of
rigctl's conversion code:

* noise densities within 5 % of the truth of the axis with the largest N, the one Kalibr's single
  value must cover (the fit's 95 % interval is about +-0.3 % here, so 5 % would catch any unit
  slip -- a factor 60, sqrt(2), 2 pi, g -- and the 20-50 % between the axes' N a wrong axis);
* each random walk's written value has a 95 % interval that contains the truth, and every
  axis' K interval in the JSON contains it;
* Kalibr units: N (rad/sqrt(s)) equals the density in rad/s/sqrt(Hz), checked here against the
  white-noise level read off the curve in the CSV with plain numpy: sigma(tau0) * sqrt(tau0)
  at the shortest tau, where N dominates;
* the CSV's bands are the stored ones in SI; the JSON holds the whole result.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from helpers import copy_recording, rigctl_in_process, run_rigctl

K_GYRO, K_ACC = 1e-5, 3e-5  # rad/s^2/sqrt(Hz), m/s^3/sqrt(Hz): ten times the profile's


@pytest.fixture(scope="module")
def capture(declared_only_hour_allan, tmp_path_factory) -> tuple[Path, dict]:
    """(this file's copy of the recording, with the default run's /results/allan; /truth's imu)"""
    rec, truth, _ = declared_only_hour_allan
    return copy_recording(rec, tmp_path_factory.mktemp("kalibr")), truth


@pytest.fixture(scope="module")
def default_run(declared_only_hour_allan, tmp_path_factory) -> tuple[dict, dict, str, Path]:
    """`rigctl allan REC --kalibr --json --csv --db none` with the defaults (the session's run,
    conftest's declared_only_hour_allan; its files copied here): (imu.yaml, JSON, yaml text, dir)."""
    import shutil

    out = tmp_path_factory.mktemp("allan")
    for name in ("imu.yaml", "allan.json", "allan.csv"):
        shutil.copy2(declared_only_hour_allan[2] / name, out / name)
    text = (out / "imu.yaml").read_text()
    return yaml.safe_load(text), json.loads((out / "allan.json").read_text()), text, out


def _allan(rec: Path, out: Path, *extra: str) -> tuple[dict, dict, str]:
    """(in this process: what the command computes and writes; the refusals below, about the
    console, run the real command)"""
    r = rigctl_in_process("allan", str(rec), "--kalibr", str(out / "imu.yaml"), "--json",
                          str(out / "allan.json"), "--csv", str(out / "allan.csv"), "--db", "none",
                          *extra)
    assert r.returncode == 0, r.stderr[-2000:]
    text = (out / "imu.yaml").read_text()
    return yaml.safe_load(text), json.loads((out / "allan.json").read_text()), text


def test_kalibr_values_match_the_emulator_truth(capture, default_run):
    rec, truth = capture
    # /truth: each sensor's three axes as rigctl.solvers.noise_coefficients.to_json (SI); x axis
    g, a = truth["gyro_noise"][0], truth["accel_noise"][0]
    assert g["K"]["value"] == K_GYRO and g["units"]["K"] == "rad/s/sqrt(s)"
    kal, doc, text, out = default_run
    assert set(kal) == {"accelerometer_noise_density", "accelerometer_random_walk", "gyroscope_noise_density",
                        "gyroscope_random_walk", "rostopic", "update_rate"}
    assert kal["rostopic"] == "/imu0" and kal["update_rate"] == 100.0
    n_top = {s: max(d["N"]["value"] for d in truth[f"{s}_noise"]) for s in ("gyro", "accel")}
    assert n_top["gyro"] > 1.2 * g["N"]["value"]  # the largest N is not the x axis': the right axis counts
    for key, true in (("gyroscope_noise_density", n_top["gyro"]),
                      ("accelerometer_noise_density", n_top["accel"])):
        assert abs(kal[key] / true - 1) < 0.05, (key, kal[key], true)
    for key, true in (("gyroscope_random_walk", g["K"]["value"]),
                      ("accelerometer_random_walk", a["K"]["value"])):
        k = doc["kalibr"][key]
        assert k["supported"] and k["written"] == pytest.approx(kal[key], rel=1e-6), (key, k)
        assert k["ci95"][0] <= true <= k["ci95"][1], (key, k, true)
    # every axis' K interval holds the truth; the written value is the largest axis
    for axis, r in doc["axes"].items():
        true = K_GYRO if r["sensor"] == "gyro" else K_ACC
        lo, hi = r["fit"]["coefficients"]["K"]["ci95"]  # SI, as stored (to_json)
        assert lo <= true <= hi, (axis, lo, hi)
    kg = [r["fit"]["coefficients"]["K"]["value"] for r in doc["axes"].values() if r["sensor"] == "gyro"]
    assert kal["gyroscope_random_walk"] == pytest.approx(max(kg), rel=1e-6)
    assert "# inflation: none" in text and "95 % interval" in text
    # the density read off the curve (CSV, plain numpy): sigma(tau0) sqrt(tau0), white-noise dominated
    rows = np.genfromtxt(out / "allan.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    gx = rows[rows["axis"] == "gx"]
    assert gx["unit"][0] == "rad/s" and gx["tau_s"][0] == pytest.approx(0.01)
    n_read = gx["sigma"][0] * math.sqrt(gx["tau_s"][0])
    n_fit = doc["axes"]["gx"]["fit"]["coefficients"]["N"]["value"]  # rad/sqrt(s)
    assert n_read == pytest.approx(n_fit, rel=0.01)
    # CSV bands = the stored bands (deg/h) in SI; JSON = the stored curve
    with h5py.File(rec, "r") as f:
        hi95 = f["results/allan/gx/hi95_deg_per_h"][()]
        dev = f["results/allan/gx/adev_rad_per_s"][()]
    assert np.allclose(gx["hi95"], hi95 * math.pi / 180 / 3600, rtol=1e-12)
    assert np.array_equal(gx["sigma"], dev) and doc["axes"]["gx"]["adev_rad/s"] == dev.tolist()
    assert np.all((gx["lo68"] < gx["sigma"]) & (gx["sigma"] < gx["hi68"]) & (gx["hi68"] < gx["hi95"]))


def test_inflation_is_stated_and_applied(capture, default_run, tmp_path):
    rec, _ = capture
    kal1, doc1, _, _ = default_run
    kal5, doc5, text = _allan(rec, tmp_path, "--kalibr-inflate", "5", "--kalibr-topic", "/imu/data")
    assert "# inflation: x5 chosen by the user" in text and kal5["rostopic"] == "/imu/data"
    for key in ("gyroscope_noise_density", "gyroscope_random_walk", "accelerometer_noise_density",
                "accelerometer_random_walk"):
        assert kal5[key] == pytest.approx(5 * kal1[key], rel=1e-6)
        assert doc5["kalibr"][key]["fitted"] == doc1["kalibr"][key]["fitted"]
    for args, text in ((("--kalibr-inflate", "0"), "--kalibr-inflate 0: give a factor > 0"),
                       (("--axes", "gx,gy,gz"), "--kalibr needs all six axes")):
        r = run_rigctl("allan", str(rec), "--kalibr", str(tmp_path / "x.yaml"), "--db", "none", *args)
        assert r.returncode == 2 and text in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert not (tmp_path / "x.yaml").exists()


def test_recording_to_rosbag2_to_kalibr(capture, default_run, tmp_path):
    """What a robotics user does: the capture as a rosbag2 (written with rosbags), imported with
    `rigctl import`, analysed with `--kalibr`: the same samples, the bag's topic in imu.yaml and
    the same values as from the recording itself."""
    pytest.importorskip("rosbags")
    from rigctl.sim.imu_bag import write_imu_bag

    rec, _ = capture
    with h5py.File(rec, "r") as f:
        s0, s1 = int(f["segments/first_sample"][0]), int(f["segments/last_sample"][0])
        t = f["imu/time"][s0:s1]
        acc, gyr = f["imu/specific_force"][s0:s1], f["imu/angular_rate"][s0:s1]
    stamp = 1_700_000_000_000_000_000 + np.rint(t * 1e9).astype(np.int64)
    bag = tmp_path / "capture_bag"
    write_imu_bag(bag, stamp, gyr, acc, topic="/vio/imu", frame_id="imu", receive_delay_ns=2_000_000)
    imported = tmp_path / "imported.h5"
    r = rigctl_in_process("import", str(bag), "-o", str(imported))
    assert r.returncode == 0, r.stderr[-2000:]
    assert "gaps: none" in r.stdout and "sample rate 100 Hz" in r.stdout
    with h5py.File(imported, "r") as f:
        assert np.array_equal(f["imu/specific_force"][()], acc) and np.array_equal(f["imu/angular_rate"][()], gyr)
    direct = default_run[0]
    via_bag, _, text = _allan(imported, tmp_path)
    assert via_bag["rostopic"] == "/vio/imu" and "from imported.h5, whole recording" in text
    for key, v in direct.items():
        if key != "rostopic":
            assert via_bag[key] == pytest.approx(v, rel=1e-6), key
