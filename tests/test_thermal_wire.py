"""The soak procedure over the wire: the emulated Watlow F4T on Modbus RTU over a pty and the
emulated SCPI chamber on TCP through PyVISA (pyvisa-py), with the table and the IMU also on
their wires (ACL on a pty, Xsens on a pty), one physics world at 200x real time."""
from __future__ import annotations

import io

import h5py
import numpy as np
import pytest
import yaml

from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import run_procedure
from rigctl.sim.hardware import start_hardware
from rigctl.sim.wire_config import write_wire_config

from hil_support import ROOT, SIM

SPEED = 100.0
FAST_CHAMBER = {"heat_max_c_per_min": 30, "cool_max_c_per_min": 30, "air_period_s": 20,
                "product_tau_s": 15}
SOAK = {"t1": 15, "t2": 25, "t3": 35, "t4": 45, "stable_band_c": 0.3, "stable_for": "20 s", "sample": "2 s",
        "count": 2, "step_deg": 180, "revolutions": 1}


@pytest.mark.parametrize("link", ["watlow-rtu", "scpi"])
def test_soak_over_the_wire(tmp_path, link):
    pytest.importorskip("pyvisa_py")
    raw = yaml.safe_load(SIM.read_text())
    raw["chamber"]["sim"] = dict(raw["chamber"]["sim"], **FAST_CHAMBER)
    phys = tmp_path / "physics.yaml"
    phys.write_text(yaml.safe_dump(raw))
    hw = start_hardware(load_config(phys), SPEED, link_dir=tmp_path / "ports")
    try:
        cfg_path = write_wire_config(tmp_path / "wired.yaml", raw, hw, table="acl", link="pty", pulses="none",
                                     chamber=link)
        cfg = load_config(cfg_path)
        assert cfg.chamber.driver == ("watlow" if link == "watlow-rtu" else "scpi")
        from rigctl.engine.device_check import check_devices
        checks = {c.role: c for c in check_devices(cfg).checks}
        assert checks["chamber"].ok and ("air 25.00 degC" in checks["chamber"].text
                                         or "EMULATED-CHAMBER" in checks["chamber"].text), checks["chamber"]
        proc = load_procedure(ROOT / "procedures" / "thermal-soak.yaml", SOAK, cfg.limits)
        res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False)
        assert res.exit_code == 0, res.message
        requests = [r for _, r in hw.chamber.requests]
        final_sp = hw.chamber.state()["setpoint_c"]
    finally:
        hw.close()
    # the set points went over the wire, in the procedure's order, and the chamber ended safe
    if link == "scpi":
        sets = [float(r.split()[1]) for r in requests if r.startswith("SOUR:TEMP ")]
        assert any(r.startswith("MEAS:TEMP?") for r in requests)
    else:
        from rigctl.drivers.watlow_chamber import regs_to_float
        sets = [regs_to_float(eval(r.split(" ", 2)[2])) for r in requests if r.startswith("write 2782 ")]
    assert sets[:4] == [15.0, 25.0, 35.0, 45.0] and sets[-1] == 25.0 and final_sp == 25.0
    with h5py.File(res.recording, "r") as f:
        seg = {k: f["segments"][k][()] for k in ("kind", "first_sample", "last_sample", "status")}
        T = f["imu/temperature"][()]
        ch = f["chamber"]
        assert ch["time"].shape[0] > 20 and np.isfinite(ch["air_c"][()]).all()
        waits = np.flatnonzero(seg["kind"] == b"chamber-wait")
        assert waits.size == 4
        # each soak point's windows: the IMU at the soak temperature (stable), over the Xsens wire
        orient = np.flatnonzero(seg["kind"] == b"orientation")
        assert orient.size == 4 * 6
        for p, target in enumerate((15, 25, 35, 45)):
            rows = orient[6 * p:6 * p + 6]
            temps = np.concatenate([T[seg["first_sample"][i]:seg["last_sample"][i]] for i in rows])
            assert abs(temps.mean() - target) < 0.6 and np.ptp(temps) < 0.6, (target, temps.mean(), np.ptp(temps))


def test_device_check_names_an_unreachable_chamber(tmp_path):
    import socket

    # bound and never listening, held open: a connection is refused, and neither another process
    # nor the driver's own outgoing connection (a TCP self-connect, when the kernel picks the
    # destination port as the source port) can take the port, as with a port looked up and closed
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    raw = yaml.safe_load((ROOT / "configs" / "sim-wire.yaml").read_text())
    raw["table"]["port"] = str(tmp_path / "no-table")
    raw["imu"]["port"] = str(tmp_path / "no-imu")
    raw["pulses"] = {"driver": "none"}
    raw["chamber"] = {"driver": "watlow", "transport": "tcp", "host": "127.0.0.1", "tcp_port": port,
                      "timeout_s": 0.3}
    p = tmp_path / "wired.yaml"
    p.write_text(yaml.safe_dump(raw))
    from rigctl.engine.device_check import check_devices
    try:
        c = {c.role: c for c in check_devices(load_config(p)).checks}["chamber"]
    finally:
        s.close()
    assert not c.ok and f"127.0.0.1:{port}" in c.text, c


def test_watlow_driver_over_modbus_tcp_sets_ramps_reads_and_goes_safe():
    """The F4T driver against the emulated F4T's registers on Modbus TCP (no rig): a ramp writes
    scale, rate and action before the set point; reads follow the physics; stop is a step to
    safe_c. Floats low word first, as the F4T sends them."""
    import threading

    from rigctl.clock import make_clock
    from rigctl.drivers.watlow_chamber import WatlowF4T, float_to_regs, regs_to_float
    from rigctl.sim.chamber import ChamberParams, ChamberPhysics
    from rigctl.sim.chamber_servers import ChamberAccess, WatlowF4TServer

    assert float_to_regs(25.0) == [0x0000, 0x41C8] and regs_to_float([0x0000, 0x41C8]) == 25.0
    phys = ChamberPhysics(ChamberParams())
    now = {"t": 0.0}
    srv = WatlowF4TServer(ChamberAccess(phys, lambda: now["t"], threading.RLock()))
    host, port = srv.start_tcp()
    drv = WatlowF4T(make_clock("real", 1.0), transport="tcp", host=host, tcp_port=port, safe_c=20.0)
    try:
        drv.connect()
        drv.set_setpoint(40.0, 2.0)
        assert phys.target == 40.0 and phys.ramp_c_per_min == pytest.approx(2.0)
        now["t"] = 300.0  # 5 min into a 2 degC/min ramp: the working set point is 35 degC
        s = drv.read()
        assert s.setpoint_c == 40.0 and s.status == "running"
        assert s.air_c == pytest.approx(phys.air, abs=1e-4) and s.product_c == pytest.approx(phys.product, abs=1e-4)
        assert phys.working == pytest.approx(35.0, abs=0.01)
        drv.stop()
        assert phys.target == phys.working == 20.0 and phys.ramp_c_per_min == 0.0
    finally:
        drv.close()
        srv.close()
