"""One spelling per sensor axis (rigctl.sensor_axes): ax, ay, az, gx, gy, gz in every command's
output, the old spellings still read where an axis is an input (the new-user audit found gyr_x
in `rigctl import`, gx in `rigctl allan`, gyro_x in `rigctl calibrate`). `rigctl calibrate`'s
text, JSON and report: tests/test_report_sections.py (test_calibration_names_each_axis_one_way)."""
from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from rigctl import cli
from rigctl.analysis.allan import AXES as ALLAN_AXES
from rigctl.sensor_axes import AXES, canonical
from rigctl.solvers.segments import CHANNELS

#: any older spelling of an axis, as output must no longer print it
OLD = re.compile(r"\b(?:accel|gyro|acc|gyr)_[xyz]\b|\b(?:accelerometer|gyro) [xyz]\b")


def test_one_definition_and_its_aliases() -> None:
    assert AXES == ("ax", "ay", "az", "gx", "gy", "gz")
    assert CHANNELS == AXES and set(ALLAN_AXES) == set(AXES)  # calibrate and allan use it
    for c, (a, g) in zip("xyz", zip(AXES[:3], AXES[3:])):
        assert {canonical(f"acc_{c}"), canonical(f"accel_{c}"), canonical(a), canonical(a.upper())} == {a}
        assert {canonical(f"gyr_{c}"), canonical(f"gyro_{c}"), canonical(g)} == {g}
    assert canonical("time") is None and canonical("gyro") is None


def _csv(path: Path) -> np.ndarray:
    rng = np.random.default_rng(8)
    data = np.column_stack([rng.normal(0, 0.01, (4000, 3)) + [0, 0, 1], rng.normal(0, 0.05, (4000, 3))])
    np.savetxt(path, data, delimiter=",", header="AccX,AccY,AccZ,GyrX,GyrY,GyrZ", comments="", fmt="%.6f")
    return np.round(data, 6)  # as written


@pytest.mark.parametrize("keys", [("ax", "ay", "gx"), ("acc_x", "acc_y", "gyr_x"), ("accel_x", "ACC_Y", "gyro_x")])
def test_import_reads_old_keys_and_prints_the_one_spelling(tmp_path: Path, capsys, keys) -> None:
    data = _csv(tmp_path / "log.csv")
    rec = tmp_path / "log.h5"
    cols = ",".join(f"{k}={c}" for k, c in zip(keys, ("AccX", "AccY", "GyrX")))
    assert cli.main(["import", str(tmp_path / "log.csv"), "-o", str(rec), "--rate", "100",
                     "--columns", cols, "--units", "acc=g,gyr=rad/s"]) == 0
    out = capsys.readouterr().out
    assert "not in the file, stored as NaN: az, gy, gz; rigctl allan analyses the columns present (ax,ay,gx)" in out
    assert not OLD.search(out), out
    with h5py.File(rec, "r") as f:
        assert json.loads(f["meta"].attrs["import_columns_json"]) == {"ax": "AccX", "ay": "AccY", "gx": "GyrX"}
        assert f["meta"].attrs["import_axes"] == "ax,ay,gx"
        np.testing.assert_allclose(f["imu/angular_rate"][:, 0], data[:, 3])
        np.testing.assert_allclose(f["imu/specific_force"][:, 1], data[:, 1] * 9.80665)
        assert np.isnan(f["imu/angular_rate"][:, 1:]).all()


def test_import_refuses_one_axis_under_two_spellings(tmp_path: Path, capsys) -> None:
    _csv(tmp_path / "log.csv")
    assert cli.main(["import", str(tmp_path / "log.csv"), "-o", str(tmp_path / "x.h5"), "--rate", "100",
                     "--columns", "gx=GyrX,gyr_x=GyrY", "--units", "gyr=rad/s"]) == 2
    err = capsys.readouterr().err.strip()
    assert "axis gx given twice ('gyr_x' is another spelling of it)" in err and "\n" not in err, err


def test_allan_takes_old_axis_names_and_writes_the_one_spelling(tmp_path: Path, capsys) -> None:
    """--axes gyro_x,gyr_y (old spellings) analyse gx, gy; text, JSON keys and CSV rows say gx, gy."""
    data = _csv(tmp_path / "log.csv")
    rec = tmp_path / "log.h5"
    assert cli.main(["import", str(tmp_path / "log.csv"), "-o", str(rec), "--rate", "100", "--columns",
                     "acc_x=AccX,acc_y=AccY,acc_z=AccZ,gyr_x=GyrX,gyr_y=GyrY,gyr_z=GyrZ",
                     "--units", "acc=g,gyr=rad/s"]) == 0
    capsys.readouterr()
    js, cs = tmp_path / "a.json", tmp_path / "a.csv"
    assert cli.main(["allan", str(rec), "--axes", "gyro_x,gyr_y", "--db", "none", "--taus", "octave",
                     "--json", str(js), "--csv", str(cs)]) == 0
    out = capsys.readouterr().out
    assert not OLD.search(out), OLD.search(out)
    assert re.search(r"^.*\bgx\b", out, re.M) and re.search(r"^.*\bgy\b", out, re.M), out
    assert list(json.loads(js.read_text())["axes"]) == ["gx", "gy"]
    with open(cs, newline="") as fh:
        assert {row["axis"] for row in csv.DictReader(fh)} == {"gx", "gy"}
    with h5py.File(rec, "r") as f:
        assert set(f["results/allan"]) >= {"gx", "gy"}
    # gx is the gyro's first column: its 1-sample deviation is that column's, by numpy
    res = json.loads(js.read_text())["axes"]["gx"]
    first_diff = np.diff(data[:, 3])
    adev_tau0 = float(np.sqrt(0.5 * np.mean(first_diff ** 2)))
    assert res["sensor"] == "gyro" and res["n_samples"] == 4000
    assert res["adev_rad/s"][0] == pytest.approx(adev_tau0, rel=1e-6), (res["adev_rad/s"][0], adev_tau0)


def test_allan_unknown_axis_lists_the_one_spelling(tmp_path: Path, capsys) -> None:
    rec = tmp_path / "log.h5"
    _csv(tmp_path / "log.csv")
    assert cli.main(["import", str(tmp_path / "log.csv"), "-o", str(rec), "--rate", "100",
                     "--columns", "gx=GyrX", "--units", "gyr=rad/s"]) == 0
    capsys.readouterr()
    assert cli.main(["allan", str(rec), "--axes", "gyro_w", "--db", "none"]) == 2
    err = capsys.readouterr().err
    assert "choose from gx,gy,gz,ax,ay,az" in err, err
