"""Which IMU is on the wire: the Xsens driver's ReqDID / DeviceID exchange against the emulator
on real ptys, a unit swapped during a reconnect, and a wired run that records, detects and
refuses to resume on another unit."""
from __future__ import annotations

import io
import json
import logging
import threading
import time

import h5py
import pytest
import yaml

from rigctl.clock import ScaledClock
from rigctl.config.config import load_config
from rigctl.drivers import xsens as X
from rigctl.drivers.xsens_imu import XsensImu, XsensUnitChanged
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import RunOptions, resume_run, run_procedure
from rigctl.sim.xsens_server import XsensServer
from rigctl.engine.states import StateMachine
from rigctl.progress import NullProgress
from rigctl.yamlio import InputError

from hil_support import wait_progress, wait_until, wired

SPEED = 20.0


class LoggingServer(XsensServer):
    """The emulator, noting every request with the state it arrived in; ``did_reply``: None =
    the normal DeviceID, "silent" = ReqDID is never answered."""

    did_reply: str | None = None

    def __init__(self, *a, **kw) -> None:
        self.requests: list[tuple[int, str]] = []
        super().__init__(*a, **kw)

    def _handle(self, mid: int, data: bytes) -> bytes:
        self.requests.append((mid, self.state))
        if mid == X.MID.REQ_DID and self.did_reply == "silent":
            return b""
        return super()._handle(mid, data)


def connect(srv: XsensServer, clock: ScaledClock) -> XsensImu:
    imu = XsensImu(srv.path, 100, clock, timeout_s=0.2)
    imu.connect()
    return imu


def streams(imu: XsensImu, srv, n: int) -> bool:
    """Read until more than ``n`` rows have come, for as long as the emulator ``srv`` keeps
    sending frames (it read for 0.3 s of wall time before: an emulator starved for that long on a
    loaded host sent nothing in it)."""
    rows = 0

    def more() -> bool:
        nonlocal rows
        rows += len(imu.read())
        return rows > n
    return wait_progress(more, lambda: srv.frames_sent, f"more than {n} IMU rows")


def test_device_id_messages():
    assert X.req_did() == bytes.fromhex("FAFF000001")
    assert X.decode_device_id(bytes.fromhex("03780001")) == "03780001"
    assert X.decode_device_id(X.encode_device_id(0x0378ABCD)) == "0378ABCD"
    assert X.decode_device_id(X.encode_device_id(0x1234_5678_9ABC_DEF0)) == "123456789ABCDEF0"
    for bad in (b"", b"\x01\x02", bytes(5)):
        with pytest.raises(X.XsensError, match="expected 4 or 8"):
            X.decode_device_id(bad)


@pytest.mark.parametrize("device_id, printed", [(0x0378ABCD, "0378ABCD"), (0x00FF_0000_0378_0001, "00FF000003780001")])
def test_driver_reads_the_device_id_in_config_mode(device_id, printed):
    clock = ScaledClock(1.0)
    with LoggingServer(clock=clock.now, device_id=device_id) as srv:
        imu = connect(srv, clock)
        try:
            assert imu.identity == {"device_id": printed, "protocol": "Xsens MT"}
            mids = [m for m, _ in srv.requests]
            assert (X.MID.REQ_DID, "config") in srv.requests
            assert mids.index(X.MID.GO_TO_CONFIG) < mids.index(X.MID.REQ_DID) < mids.index(X.MID.GO_TO_MEASUREMENT)
            assert streams(imu, srv, 10)
        finally:
            imu.close()


@pytest.mark.parametrize("reply", ["error", "silent"])
def test_a_device_without_an_id_gives_empty_and_still_streams(reply, caplog):
    clock = ScaledClock(1.0)
    with LoggingServer(clock=clock.now, device_id=None if reply == "error" else 0x03780001) as srv:
        srv.did_reply = None if reply == "error" else "silent"
        with caplog.at_level(logging.WARNING, logger="rigctl.drivers.xsens_imu"):
            imu = connect(srv, clock)
        try:
            assert imu.identity == {"device_id": "", "protocol": "Xsens MT"}
            tries = sum(m == X.MID.REQ_DID for m, _ in srv.requests)
            assert tries == (1 if reply == "error" else 3)       # an Error is an answer: no retry
            text = caplog.text
            assert ("error INVALID_MESSAGE" if reply == "error" else "no answer to ReqDID") in text
            assert "does not report its ID" in text
            assert streams(imu, srv, 10)
        finally:
            imu.close()


def test_reconnect_rereads_the_id_and_stops_on_another_unit(tmp_path):
    with wired(tmp_path, SPEED) as (hw, _cfg):
        imu = XsensImu(hw.endpoints["imu_xsens_pty"], 100, ScaledClock(SPEED), link_timeout_s=0.2)
        imu.connect()
        try:
            assert imu.identity["device_id"] == "03780001"
            assert streams(imu, hw.xsens, 0)
            hw.disconnect("imu", 0.1)                           # same unit back: streams on
            wait_until(lambda: imu.configurations == 2, 10, "the reconfiguration")
            assert streams(imu, hw.xsens, 0)                    # the stream back
            assert len(hw.xsens.measurement_starts) == 2
            hw.xsens.device_id = 0x0378BEEF                     # another unit on the same port
            hw.disconnect("imu", 0.1)

            def fault():
                try:
                    imu.read()
                except XsensUnitChanged as exc:
                    return exc
                except ConnectionError:                         # LinkLost while it is down
                    pass
                return None
            exc = wait_until(fault, 10, "the unit change to be reported")
            assert "device ID 0378BEEF" in str(exc) and "started with 03780001" in str(exc)
            assert imu.identity["device_id"] == "03780001"
            time.sleep(0.3)
            assert len(hw.xsens.measurement_starts) == 2        # never put back into measurement
            assert hw.xsens.state == "config"
            with pytest.raises(XsensUnitChanged):
                imu.read()
        finally:
            imu.close()


def test_wired_run_records_the_unit_stops_on_a_swap_and_resumes_only_on_it(tmp_path):
    proc_path = tmp_path / "p.yaml"
    proc_path.write_text("procedure: swap\nsteps:\n  - warmup:\n      duration: 10 s\n"
                         "  - capture:\n      duration: 60 s\n")
    with wired(tmp_path, SPEED, suspenders={"min_free_mib": 0}) as (hw, cfg_path):
        d = yaml.safe_load(cfg_path.read_text())
        d["imu"]["serial"] = "lab-7"
        cfg_path.write_text(yaml.safe_dump(d, sort_keys=False))
        cfg = load_config(cfg_path)
        proc = load_procedure(proc_path, limits=cfg.limits)
        swapped = threading.Event()

        class SwapAtCapture(NullProgress):
            """The unit is swapped as the capture step starts, in the engine's thread, before
            it polls the step's first sample: the step cannot finish on the old unit's data.
            (A thread that swapped once the warm-up segment was written had the capture's 3 s
            of wall time at 20x to do it in.)"""

            def step_started(self, step) -> None:
                super().step_started(step)
                if step.kind == "capture" and not swapped.is_set():
                    hw.xsens.device_id = 0x0378BEEF
                    hw.disconnect("imu", 0.1)
                    swapped.set()

        states = StateMachine()
        res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False,
                            options=RunOptions(progress=SwapAtCapture(io.StringIO()), states=states))
        assert swapped.is_set()
        # a device fault (no traceback): the rig waits for an operator
        assert res.status == "failed" and res.message.startswith("imu: a different unit is now on"), res.message
        assert "device ID 0378BEEF, but the run started with 03780001" in res.message
        assert states.state == "faulted"
        with h5py.File(res.recording, "r") as f:
            m = f["meta"].attrs
            assert (m["imu_device_id"], m["imu_serial"]) == ("03780001", "lab-7")
            assert json.loads(m["imu_identity_json"]) == {"device_id": "03780001", "protocol": "Xsens MT"}
            assert f["run/status"][0] == b"failed"
            assert any(b"0378BEEF" in e for e in f["events/message"][()])
            # the safe state still read the table (the IMU's fault does not stop that)
            assert any(b"table stopped, servo off" in e for e in f["events/message"][()])
        assert "could not read the table" not in (res.run_dir / "run.log.jsonl").read_text()
        # the other unit is still connected: resume refuses before anything moves
        with pytest.raises(InputError, match="recorded with IMU 03780001 but the connected IMU is 0378BEEF"):
            resume_run(res.run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False)
        hw.xsens.device_id = 0x03780001                         # the original unit back
        again = resume_run(res.run_dir, tmp_path / "runs", console=io.StringIO(), install_signals=False)
        assert again.status == "complete", again.message
        with h5py.File(res.recording, "r") as f:
            assert f["meta"].attrs["imu_device_id"] == "03780001"
            done = f["segments/status"][()] == b"complete"
            assert sorted(f["segments/kind"][()][done].tolist()) == [b"capture", b"warmup"]
