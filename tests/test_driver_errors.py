"""The drivers' own errors are in rigctl.errors' one hierarchy: a run that ends on one gives its
one line and its exit code (docs/troubleshooting.md), never a traceback.

A setting of the rig config that the device cannot take -> InputError (exit 2); a device that
answers wrongly, refuses or needs an operator -> DeviceError (exit 1)."""
from __future__ import annotations

import importlib
import inspect
import json
import pkgutil

import pytest
import yaml

import rigctl.drivers
import rigctl.sim
from rigctl.cli import report_error
from rigctl.devices import DeviceFault, LinkLost
from rigctl.drivers.acl import AclError
from rigctl.drivers.novatel import NovatelError
from rigctl.drivers.novatel_marks import NovatelConfigError
from rigctl.drivers.serial_link import BadReply, ReplyTimeout
from rigctl.drivers.stream_imu import StreamImuConfigError, StreamImuUnitChanged
from rigctl.drivers.vectornav import VectorNavError
from rigctl.drivers.vectornav_imu import VectorNavConfigError, VectorNavUnitChanged
from rigctl.drivers.xsens import RateDoesNotFitError, XsensError
from rigctl.drivers.xsens_imu import XsensConfigError, XsensUnitChanged
from rigctl.errors import DeviceError, InputError, RigctlError
from rigctl.sim.hardware import start_hardware
from rigctl.sim.wire_config import write_wire_config

from helpers import run_rigctl
from hil_support import sim_config

# (error, the rigctl.errors class it must be, the builtin class code may still catch it as)
CASES = [
    (XsensConfigError("imu: device refused the output configuration (2000 Hz): error X"), InputError, RuntimeError),
    (StreamImuConfigError("imu: device refused"), InputError, RuntimeError),
    (VectorNavConfigError("imu: $VNERR,12"), InputError, RuntimeError),
    (NovatelConfigError("pulses: receiver refused 'MARKCONTROL'"), InputError, RuntimeError),
    (RateDoesNotFitError("2000 Hz needs more than 921,600 baud"), InputError, ValueError),
    (AclError(-100, "expected OK, got 'XX'"), DeviceError, Exception),
    (XsensError("checksum mismatch"), DeviceError, ValueError),
    (VectorNavError("checksum mismatch"), DeviceError, ValueError),
    (NovatelError("CRC mismatch"), DeviceError, ValueError),
    (XsensUnitChanged("imu: a different unit is now on the port"), DeviceError, DeviceFault),
    (StreamImuUnitChanged("imu: a different unit"), DeviceError, DeviceFault),
    (VectorNavUnitChanged("imu: a different unit"), DeviceError, DeviceFault),
    (DeviceFault("table: controller refused ':MODE:POSITION 1'"), DeviceError, RuntimeError),
    (LinkLost("table", "no reply"), DeviceError, ConnectionError),
    (ReplyTimeout("imu", "no reply to ReqDID"), DeviceError, ConnectionError),
    (BadReply("table", "garbled reply to ':READ:ALL? 1'"), DeviceError, ConnectionError),
]


@pytest.mark.parametrize("exc, base, builtin", CASES, ids=lambda v: type(v).__name__ if isinstance(v, Exception)
                         else None)
def test_driver_errors_map_to_one_line_and_their_exit_code(exc, base, builtin, capsys):
    assert isinstance(exc, base) and isinstance(exc, builtin)
    code = report_error("rigctl run", exc)
    err = capsys.readouterr().err
    want = 2 if base is InputError else 1
    word = "error" if want == 2 else "failed"
    assert code == want
    assert err == f"rigctl run: {word}: {exc}\n"          # one line, the message kept, no class name
    assert "internal error" not in err and "Traceback" not in err


def test_acl_error_keeps_its_code_and_text():
    e = AclError(-221, "axis 1 interlock not closed")
    assert (e.code, e.text, str(e)) == (-221, "axis 1 interlock not closed", "-221,axis 1 interlock not closed")


def test_every_exception_class_of_the_drivers_and_the_emulator_is_a_rigctl_error():
    """A new driver error outside the hierarchy would end a run as 'internal error' with a
    traceback: list every exception class defined in rigctl.drivers and rigctl.sim."""
    #: raised and caught inside the emulator only (turned into an ERR / exception reply on the wire)
    internal = {"rigctl.sim.acl_server.TableRefused"}
    found, outside, skipped = [], [], []
    for pkg in (rigctl.drivers, rigctl.sim):
        for m in pkgutil.iter_modules(pkg.__path__, pkg.__name__ + "."):
            try:
                mod = importlib.import_module(m.name)
            except ImportError as exc:  # an optional extra not installed (e.g. gpiod)
                skipped.append(f"{m.name}: {exc}")
                continue
            for name, cls in inspect.getmembers(mod, inspect.isclass):
                if cls.__module__ != mod.__name__ or not issubclass(cls, BaseException):
                    continue
                qual = f"{cls.__module__}.{name}"
                found.append(qual)
                if not issubclass(cls, RigctlError) and qual not in internal:
                    outside.append(qual)
    assert len(found) >= 15, (found, skipped)
    assert not outside, f"exception classes outside rigctl.errors: {outside}"


def test_run_with_a_driver_setting_the_device_refuses_is_one_line_exit_2(tmp_path):
    """The Xsens baud rate in the config (4,000,000) is not the device's (921,600): the identity
    check passes, and the device refuses the 2000 Hz output only when the rig opens."""
    cfg, raw = sim_config(tmp_path, rate_hz=2000)
    hw = start_hardware(cfg, 10.0, link_dir=tmp_path / "ports", imu_baudrate=921_600)
    try:
        cfg_path = write_wire_config(tmp_path / "wired.yaml", raw, hw, table="acl", link="pty", pulses="none")
        d = yaml.safe_load(cfg_path.read_text())
        assert d["imu"]["driver"] == "xsens" and d["imu"]["baudrate"] == 921_600
        d["imu"]["baudrate"] = 4_000_000
        cfg_path.write_text(yaml.safe_dump(d, sort_keys=False))
        runs = tmp_path / "runs"
        r = run_rigctl("run", "procedures/warmup.yaml", "--config", str(cfg_path), "-p", "warmup=5 s",
                       "--out", str(runs), timeout=180)
    finally:
        hw.close()
    assert "921,600 baud" in hw.xsens.last_error          # the device did refuse it, for this reason
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "Traceback" not in r.stdout + r.stderr and "internal error" not in r.stderr
    lines = r.stderr.splitlines()
    final = [line for line in lines if line.startswith("rigctl run:")]
    assert len(final) == 1, r.stderr
    assert final[0].startswith("rigctl run: error: the run did not start: imu: device refused the output "
                               "configuration (2000 Hz)"), final[0]
    assert "XsensConfigError" not in r.stderr             # its message, not its class name
    # the run log has the same line and no traceback; the checkpoint says failed
    (run_dir,) = list(runs.iterdir())
    entries = [json.loads(x) for x in (run_dir / "run.log.jsonl").read_text().splitlines()]
    errors = [e for e in entries if e.get("kind") == "error"]
    assert errors and not any(e.get("traceback") for e in errors), errors
    assert any("device refused the output configuration" in e.get("message", "") for e in errors), errors
    assert json.loads((run_dir / "checkpoint.json").read_text())["status"] == "failed"
