"""The unit under test in every recording (/meta imu_device_id, imu_identity_json, imu_serial),
the rig config's ``imu.serial`` key, and `rigctl resume` refusing to continue a run on another
IMU -- in-process emulator, `rigctl run` / `rigctl resume` / `rigctl import` entry points and the
daemon's resume path. (Over the wire: tests/test_wire_xsens_identity.py.)"""
from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from rigctl import cli
from rigctl.service import control
from rigctl.config.config import load_config
from rigctl.service.daemon import Daemon
from rigctl.devices import imu_identity
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import RunOptions, resume_run, run_procedure
from rigctl.sim.world import emulated_imu_identity
from rigctl.config.suspenders import SuspenderSettings
from rigctl.yamlio import InputError, LocDict

from helpers import ROOT, make_cut_off

SIM = (ROOT / "configs" / "sim.yaml").read_text()
PROC = "procedure: id\nsteps:\n  - warmup:\n      duration: 5 s\n  - capture:\n      duration: 20 s\n"


def rig_config(tmp_path: Path, name: str = "rig.yaml", **imu: object) -> Path:
    """configs/sim.yaml with keys of its ``imu:`` section set (None removes one)."""
    d = yaml.safe_load(SIM)
    for k, v in imu.items():
        if v is None:
            d["imu"].pop(k, None)
        else:
            d["imu"][k] = v
    p = tmp_path / name
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


def meta(path: Path) -> dict:
    with h5py.File(path, "r") as f:
        return {k: f["meta"].attrs[k] for k in ("imu_device_id", "imu_identity_json", "imu_serial")
                if k in f["meta"].attrs}


def line_of(path: Path, needle: str) -> int:
    return next(i for i, ln in enumerate(path.read_text().splitlines(), 1) if needle in ln)


def only_run(runs: Path) -> Path:
    (d,) = [p for p in runs.iterdir() if p.is_dir() and not p.name.startswith(".")]
    return d


# ------------------------------------------------------------------------------- recording
def test_rigctl_run_records_the_emulated_unit_and_the_declared_serial(tmp_path):
    p = rig_config(tmp_path, serial="  SN-0042/B  ")
    assert cli.main(["run", "procedures/warmup.yaml", "-p", "warmup=3s", "--config", str(p),
                     "--out", str(tmp_path / "a")]) == 0
    m = meta(only_run(tmp_path / "a") / "recording.h5")
    unit = emulated_imu_identity(LocDict(yaml.safe_load(SIM)["imu"]["sim"]), 1)["device_id"]
    assert unit.startswith("EMU-declared-") and m["imu_device_id"] == unit   # configs/sim.yaml
    assert json.loads(m["imu_identity_json"]) == {"device_id": unit, "protocol": "in-process emulator"}
    assert m["imu_serial"] == "SN-0042/B"                   # stripped, otherwise as written
    # no serial: "" ; another imu.sim seed is the same unit on another day
    d = yaml.safe_load(SIM)
    d["imu"]["sim"]["seed"] = 7
    q = tmp_path / "seven.yaml"
    q.write_text(yaml.safe_dump(d))
    assert cli.main(["run", "procedures/warmup.yaml", "-p", "warmup=3s", "--config", str(q),
                     "--out", str(tmp_path / "b")]) == 0
    m = meta(only_run(tmp_path / "b") / "recording.h5")
    assert (m["imu_device_id"], m["imu_serial"]) == (unit, "")


def test_emulated_identity_is_the_units_fixed_settings():
    """The ID changes with what stays fixed across power-ons (profile, overrides, declared
    errors), not with the seed -- except for a random profile, whose seed draws the unit."""
    ids = {k: emulated_imu_identity(LocDict(v), 3)["device_id"] for k, v in {
        "mti": {"profile": "mti_class"}, "mti_seed5": {"profile": "mti_class", "seed": 5},
        "mti_over": {"profile": "mti_class", "overrides": {"effects": {"vibration": {"enabled": False}}}},
        "tac": {"profile": "tactical"},
        "rnd11": {"profile": "random", "seed": 11}, "rnd12": {"profile": "random", "seed": 12},
        "decl": {"gyro_bias_deg_h": [20, -15, 10]}, "decl2": {"gyro_bias_deg_h": [21, -15, 10]}}.items()}
    assert ids["mti"] == ids["mti_seed5"] and ids["mti"].startswith("EMU-mti_class-")
    assert len({ids[k] for k in ("mti", "mti_over", "tac", "rnd11", "rnd12", "decl", "decl2")}) == 7
    assert ids["rnd11"].startswith("EMU-random-") and ids["decl"].startswith("EMU-declared-")
    assert emulated_imu_identity(LocDict(), 0)["protocol"] == "in-process emulator"


def test_identity_is_optional_for_third_party_imus():
    class Bare:  # an Imu with read() only
        def read(self):
            raise AssertionError("not called")

    class Odd:
        identity = {"device_id": 1234, "protocol": None, "firmware": "1.2"}

    assert imu_identity(Bare()) == {"device_id": "", "protocol": ""}
    assert imu_identity(Odd()) == {"device_id": "1234", "protocol": "", "firmware": "1.2"}


def test_import_writes_an_unknown_unit(tmp_path):
    csv = tmp_path / "log.csv"
    rng = np.random.default_rng(3)
    n = 3000
    rows = np.column_stack([rng.normal(0, 1e-3, (n, 2)), 1 + rng.normal(0, 1e-3, n), rng.normal(0, 0.01, (n, 3))])
    np.savetxt(csv, rows, delimiter=",", header="ax,ay,az,gx,gy,gz", comments="", fmt="%.6f")
    out = tmp_path / "o.h5"
    assert cli.main(["import", str(csv), "-o", str(out), "--columns",
                     "acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz",
                     "--units", "acc=g,gyr=deg/s", "--rate", "200", "--t-init", "2"]) == 0
    m = meta(out)
    assert (m["imu_device_id"], m["imu_serial"]) == ("", "")
    assert json.loads(m["imu_identity_json"]) == {"device_id": "", "protocol": ""}


# -------------------------------------------------------------------------- config key
@pytest.mark.parametrize("value, message", [
    ("0123", "'serial' must be text, got 83"),           # YAML reads 0123 as octal 83: refused
    ("12345", "'serial' must be text, got 12345"),
    ("\"" + "x" * 65 + "\"", "at most 64 printable characters"),
    ("\"SN\\t1\"", "at most 64 printable characters"),
])
def test_bad_serial_names_file_and_line(tmp_path, value, message):
    p = tmp_path / "rig.yaml"
    p.write_text(SIM.replace("  rate_hz: 100\n", f"  rate_hz: 100\n  serial: {value}\n"))
    with pytest.raises(InputError) as exc:
        load_config(p)
    assert str(exc.value).startswith(f"{p}:{line_of(p, 'serial:')}: ") and message in str(exc.value)
    if "must be text" in message:
        assert 'quote it' in str(exc.value)


def test_misspelt_imu_key_and_wired_serial(tmp_path, capsys):
    p = tmp_path / "rig.yaml"
    p.write_text(SIM.replace("  rate_hz: 100\n", "  rate_hz: 100\n  serail: SN-1\n"))
    assert cli.main(["run", "procedures/warmup.yaml", "--config", str(p), "--out", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"rigctl run: error: {p}:{line_of(p, 'serail')}: unknown key 'serail' in 'imu' (sim)"), err
    assert not (tmp_path / "runs").exists()
    # a wired Xsens section takes the key too (nothing is opened by loading the config)
    d = yaml.safe_load(SIM)
    d["clock"] = "real"
    d["table"] = {"driver": "acl", "port": "/dev/ttyUSB0", "limits": d["table"]["limits"]}
    d["imu"] = {"driver": "xsens", "port": "/dev/ttyUSB1", "rate_hz": 100, "serial": "MTi-630 #12"}
    w = tmp_path / "wired.yaml"
    w.write_text(yaml.safe_dump(d))
    assert load_config(w).imu_serial == "MTi-630 #12"
    assert load_config(ROOT / "configs" / "sim.yaml").imu_serial == ""


# ------------------------------------------------------------------------------- resume
def cut_off_run(tmp_path: Path) -> tuple[Path, Path]:
    """A run of PROC on configs/sim.yaml made to look cut off during its capture (as the kill
    tests leave it: checkpoint after step 1, file status running, one complete segment)."""
    cfg = load_config(rig_config(tmp_path))
    proc_path = tmp_path / "p.yaml"
    proc_path.write_text(PROC)
    proc = load_procedure(proc_path, limits=cfg.limits)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False)
    assert res.status == "complete", res.message
    make_cut_off(res.run_dir, res.recording)
    return res.run_dir, res.recording


def swap_unit(run_dir: Path, other: bool) -> str:
    """Edit the run's config snapshot: another emulated unit (another declared gyro bias) or,
    with ``other`` False, the original one back. Returns the connected unit's ID."""
    snap = run_dir / "config.yaml"
    d = yaml.safe_load(snap.read_text())
    d["imu"]["sim"]["gyro_bias_deg_h"] = [21.0 if other else 20.0, -15.0, 10]  # 20.0 == 20
    snap.write_text(yaml.safe_dump(d, sort_keys=False))
    return emulated_imu_identity(LocDict(d["imu"]["sim"]), 1)["device_id"]


def file_state(run_dir: Path, recording: Path) -> tuple:
    with h5py.File(recording, "r") as f:
        return (f["run/status"][0], f["segments/status"].shape[0], f["events/time"].shape[0],
                f["imu/time"].shape[0], (run_dir / "checkpoint.json").read_text())


def test_resume_refuses_another_imu_and_continues_on_the_same_one(tmp_path, capsys):
    run_dir, recording = cut_off_run(tmp_path)
    runs = tmp_path / "runs"
    unit = meta(recording)["imu_device_id"]
    assert unit.startswith("EMU-declared-")
    before = file_state(run_dir, recording)
    other = swap_unit(run_dir, True)
    assert other != unit
    with pytest.raises(InputError) as exc:
        resume_run(run_dir, runs, console=io.StringIO(), install_signals=False)
    msg = str(exc.value)
    assert f"recorded with IMU {unit}" in msg and f"connected IMU is {other}" in msg
    assert f"reconnect IMU {unit}" in msg and "start a new run" in msg
    assert file_state(run_dir, recording) == before      # recording and checkpoint untouched
    assert "resume refused" in (run_dir / "run.log.jsonl").read_text()
    # the CLI: exit 2, the message on stderr (no daemon on this socket)
    assert cli.main(["resume", str(run_dir), "--runs", str(runs), "--socket", str(tmp_path / "none.sock")]) == 2
    assert f"connected IMU is {other}" in capsys.readouterr().err
    # the daemon's resume job fails with the same message and leaves the rig idle
    base = Path(tempfile.mkdtemp(prefix="rigctl-test-", dir="/tmp"))
    sock = base / "ctl" / "rigctl.sock"
    d = Daemon(runs, rig_config(tmp_path), sock, console=io.StringIO(),
               options=RunOptions(suspenders=SuspenderSettings(min_free_bytes=0)))
    d.start()
    try:
        assert control.wait_for_socket(sock, 10)
        assert control.request(sock, "resume", {"run": str(run_dir)})["ok"]
        end = time.monotonic() + 30
        while (job := control.request(sock, "queue")["jobs"][-1])["state"] in ("queued", "running"):
            assert time.monotonic() < end, job
            time.sleep(0.02)
        assert job["state"] == "failed" and f"connected IMU is {other}" in job["message"], job
        assert control.request(sock, "status")["state"] == "idle"
    finally:
        d.stop("test over")
        shutil.rmtree(base, ignore_errors=True)
    assert file_state(run_dir, recording) == before
    # the original unit back: the run completes, still naming it
    assert swap_unit(run_dir, False) == unit
    again = resume_run(run_dir, runs, console=io.StringIO(), install_signals=False)
    assert again.status == "complete", again.message
    assert meta(recording)["imu_device_id"] == unit
    with h5py.File(recording, "r") as f:
        assert sorted(f["segments/kind"][()][f["segments/status"][()] == b"complete"].tolist()) == \
            [b"capture", b"warmup"]


def test_recording_without_an_id_still_resumes(tmp_path):
    """Recordings made before rigctl kept the unit (no imu_device_id) resume as before."""
    run_dir, recording = cut_off_run(tmp_path)
    with h5py.File(recording, "r+") as f:
        for k in ("imu_device_id", "imu_identity_json", "imu_serial"):
            del f["meta"].attrs[k]
    swap_unit(run_dir, True)
    again = resume_run(run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False)
    assert again.status == "complete", again.message
    assert os.path.getsize(recording) > 0 and "imu_device_id" not in meta(recording)
