"""Modbus register map codecs, the emulated pymodbus table (TCP and RTU on a pty) and mbpoll interop."""
from __future__ import annotations

import math
import re
import shutil
import subprocess
import time

import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.framer import FramerType

from rigctl.drivers import modbus_map as M
from rigctl.sim.acl_server import IdealTable
from rigctl.sim.modbus_server import ModbusTableServer

from hil_support import wait_until

DEG = math.pi / 180


# -------------------------------------------------------------------------------- codecs

@pytest.mark.parametrize("v", [0, 1, -1, 45_000_000, -(2**31), 2**31 - 1])
@pytest.mark.parametrize("order", ["big", "little"])
def test_int32_register_pairs(v, order):
    regs = M.encode_32(v, True, order)
    assert all(0 <= r <= 0xFFFF for r in regs)
    assert M.decode_32(regs, True, order) == v
    big = M.encode_32(v, True, "big")
    assert big[0] == (v >> 16) & 0xFFFF and big[1] == v & 0xFFFF
    if order == "little":
        assert regs == big[::-1]


def test_scaling_and_overflow():
    assert M.to_counts(math.radians(90.0), M.SCALE_POSITION) == 90_000_000
    assert M.to_counts(math.radians(-12.3456), M.SCALE_RATE) == -123_456
    assert M.from_counts(1000, M.SCALE_ACCEL) == pytest.approx(math.radians(1.0))
    with pytest.raises(OverflowError):
        M.to_counts(math.radians(2148.0), M.SCALE_POSITION)
    assert M.wrap_angle(math.radians(190.0)) == pytest.approx(math.radians(-170.0))


def test_axis_blocks_round_trip():
    ai = M.AxisInputs(status=0x0507, mode=1, position=math.radians(-45.5), rate=math.radians(3.25),
                      acceleration=math.radians(0.5), following_error=math.radians(1e-5), fault_code=0,
                      applied_sequence=7, sample_time=12.345)
    for order in ("big", "little"):
        regs = ai.encode(order)
        assert len(regs) == M.AXIS_BLOCK
        back = M.AxisInputs.decode(regs, order)
        assert back.position == pytest.approx(ai.position, abs=M.SCALE_POSITION)
        assert back.rate == pytest.approx(ai.rate, abs=M.SCALE_RATE)
        assert (back.status, back.applied_sequence, back.sample_time) == (0x0507, 7, 12.345)
    ah = M.AxisHolding(control=0x13, mode=2, rate_demand=math.radians(-10.0), window=math.radians(1e-3),
                       dwell=0.25, sequence=9)
    assert M.AxisHolding.decode(ah.encode()).counts() == ah.counts()


def test_register_table_is_consistent():
    for table in ("input", "holding"):
        used: set[int] = set()
        for r in M.REGISTERS:
            if r.table == table:
                addrs = set(range(r.address(1) if r.per_axis else r.offset,
                                  (r.address(1) if r.per_axis else r.offset) + r.count))
                assert not used & addrs, r.name
                used |= addrs
        assert max(a for a in used if a >= 100) == 100 + M.AXIS_BLOCK - 1


# ----------------------------------------------------------------------------- servers

@pytest.fixture
def server():
    srv = ModbusTableServer(IdealTable(), dwell_ms=0)
    yield srv
    srv.close()


@pytest.fixture
def tcp_client(server):
    host, port = server.start_tcp()
    c = ModbusTcpClient(host, port=port, timeout=2)
    assert c.connect()
    yield c
    c.close()


def axis_inputs(client, axis: int) -> M.AxisInputs:
    r = client.read_input_registers(100 * axis, count=M.AXIS_BLOCK, device_id=1)
    assert not r.isError(), r
    return M.AxisInputs.decode(r.registers)


def enable(client, axis: int, mode: M.Mode) -> None:
    assert not client.write_register(0, 1, device_id=1).isError()
    ctl = M.ControlBit.SERVO_ON | M.ControlBit.NO_QUICK_STOP
    assert not client.write_registers(100 * axis, [int(ctl), int(mode)], device_id=1).isError()


def test_globals_and_remote_lockout(server, tcp_client):
    g = tcp_client.read_input_registers(0, count=6, device_id=1).registers
    assert g[:2] == [M.PROTOCOL_VERSION, 3]
    assert g[5] & M.GlobalStatusBit.ANY_INTERLOCK_OPEN and not g[5] & M.GlobalStatusBit.REMOTE
    r = tcp_client.write_register(100, 3, device_id=1)
    assert r.isError() and r.exception_code == 1                  # ILLEGAL_FUNCTION: not in remote
    assert tcp_client.read_input_registers(50, count=1, device_id=1).isError()   # unmapped address
    time.sleep(0.05)
    g2 = tcp_client.read_input_registers(0, count=6, device_id=1).registers
    assert g2[2] != g[2]                                           # heartbeat ticks


def test_position_move_with_new_setpoint_handshake(server, tcp_client):
    enable(tcp_client, 2, M.Mode.POSITION)
    demand = M.encode_32(M.to_counts(math.radians(123.456), M.SCALE_POSITION))
    assert not tcp_client.write_registers(202, demand, device_id=1).isError()
    assert not tcp_client.write_register(213, 42, device_id=1).isError()
    assert axis_inputs(tcp_client, 2).position == 0.0               # not applied before the edge
    ctl = M.ControlBit.SERVO_ON | M.ControlBit.NO_QUICK_STOP
    assert not tcp_client.write_register(200, int(ctl | M.ControlBit.NEW_SETPOINT), device_id=1).isError()
    ai = axis_inputs(tcp_client, 2)
    assert ai.position == pytest.approx(math.radians(123.456), abs=M.SCALE_POSITION)
    assert server.table.read(2)["angle"] == pytest.approx(math.radians(123.456), abs=1e-12)
    assert ai.applied_sequence == 42 and ai.mode == M.Mode.POSITION
    for bit in (M.StatusBit.SETPOINT_ACK, M.StatusBit.TARGET_REACHED, M.StatusBit.OPERATION_ENABLED):
        assert ai.status & bit
    tcp_client.write_register(200, int(ctl), device_id=1)
    assert not axis_inputs(tcp_client, 2).status & M.StatusBit.SETPOINT_ACK


def test_rate_mode_quick_stop_and_refusal(server, tcp_client):
    ctl = M.ControlBit.SERVO_ON | M.ControlBit.NO_QUICK_STOP
    tcp_client.write_register(0, 1, device_id=1)
    r = tcp_client.write_register(300, int(ctl | M.ControlBit.NEW_SETPOINT), device_id=1)
    assert r.isError() and r.exception_code == 4                    # axis off: setpoint refused
    assert axis_inputs(tcp_client, 3).fault_code == 221
    enable(tcp_client, 3, M.Mode.RATE)
    tcp_client.write_registers(304, M.encode_32(M.to_counts(math.radians(15.0), M.SCALE_RATE)), device_id=1)
    tcp_client.write_register(300, int(ctl | M.ControlBit.NEW_SETPOINT), device_id=1)
    ai = axis_inputs(tcp_client, 3)
    assert ai.rate == pytest.approx(math.radians(15.0)) and ai.status & M.StatusBit.MOVING
    assert ai.fault_code == 0 and not ai.status & M.StatusBit.WARNING
    tcp_client.write_register(300, int(M.ControlBit.SERVO_ON), device_id=1)   # quick stop (bit 1 low)
    ai = axis_inputs(tcp_client, 3)
    assert ai.rate == 0.0 and ai.status & M.StatusBit.QUICK_STOP and ai.mode == M.Mode.OFF


#: the watchdog in test_watchdog_trips_and_fault_reset, ms: the test's kicks 40 ms apart must
#: each reach the emulator within it. At 100 ms a test thread or server loop held up for 0.1 s
#: on a loaded host tripped it between kicks, and a server loop held up past the 0.3 s the test
#: then slept had not tripped it yet: both measured the host, not the watchdog
WATCHDOG_MS = 1500


def test_watchdog_trips_and_fault_reset(server, tcp_client):
    enable(tcp_client, 1, M.Mode.POSITION)
    tcp_client.write_register(1, WATCHDOG_MS, device_id=1)
    for _ in range(3):
        time.sleep(0.04)
        kicked = time.monotonic()
        tcp_client.write_register(2, 1, device_id=1)
    assert not axis_inputs(tcp_client, 1).status & M.StatusBit.FAULT
    ai = wait_until(lambda: (a := axis_inputs(tcp_client, 1)).status & M.StatusBit.FAULT and a, 30,
                    "the watchdog to trip")
    assert time.monotonic() - kicked >= WATCHDOG_MS * 1e-3      # not before the watchdog ran out
    assert ai.fault_code == M.FaultCode.WATCHDOG
    tcp_client.write_register(1, 0, device_id=1)
    ctl = M.ControlBit.NO_QUICK_STOP
    tcp_client.write_register(100, int(ctl | M.ControlBit.FAULT_RESET), device_id=1)
    tcp_client.write_register(100, int(ctl), device_id=1)
    enable(tcp_client, 1, M.Mode.POSITION)
    ai = axis_inputs(tcp_client, 1)
    assert not ai.status & M.StatusBit.FAULT and ai.status & M.StatusBit.SERVO_ON


def test_rtu_over_pty_shares_the_model_with_tcp(server, tcp_client):
    path = server.start_rtu(baudrate=19200)
    rc = ModbusSerialClient(path, framer=FramerType.RTU, baudrate=19200, timeout=2)
    try:
        assert rc.connect()
        enable(rc, 1, M.Mode.POSITION)
        rc.write_registers(102, M.encode_32(-30_000_000), device_id=1)
        ctl = M.ControlBit.SERVO_ON | M.ControlBit.NO_QUICK_STOP | M.ControlBit.NEW_SETPOINT
        assert not rc.write_register(100, int(ctl), device_id=1).isError()
        assert axis_inputs(rc, 1).position == pytest.approx(math.radians(-30.0), abs=M.SCALE_POSITION)
        assert axis_inputs(tcp_client, 1).position == pytest.approx(math.radians(-30.0), abs=M.SCALE_POSITION)
    finally:
        rc.close()


def test_little_word_order_server():
    srv = ModbusTableServer(IdealTable(), word_order="little")
    try:
        host, port = srv.start_tcp()
        c = ModbusTcpClient(host, port=port, timeout=2)
        c.connect()
        enable(c, 1, M.Mode.POSITION)
        c.write_registers(102, M.encode_32(5_000_000, True, "little"), device_id=1)
        c.write_register(100, int(M.ControlBit.SERVO_ON | M.ControlBit.NO_QUICK_STOP | M.ControlBit.NEW_SETPOINT),
                         device_id=1)
        regs = c.read_input_registers(100, count=M.AXIS_BLOCK, device_id=1).registers
        assert M.AxisInputs.decode(regs, "little").position == pytest.approx(math.radians(5.0))
        c.close()
    finally:
        srv.close()


# ---------------------------------------------------------------------- mbpoll interop

def mbpoll(*args: str) -> str:
    out = subprocess.run(["mbpoll", *args], capture_output=True, text=True, timeout=20, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def mbpoll_values(text: str) -> list[int]:
    return [int(v) for v in re.findall(r"^\[\d+\]:\s+(-?\d+)", text, flags=re.M)]


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="mbpoll (Debian package 'mbpoll') not installed; "
                    ".ci/run installs it with apt-get")
def test_mbpoll_interop_reads_status_writes_demand_table_moves(server):
    host, port = server.start_tcp()
    common = ["-m", "tcp", "-p", str(port), "-a", "1", "-0", "-1"]
    status = mbpoll_values(mbpoll(*common, "-t", "3", "-r", "100", "-c", "1", host))[0]
    assert status & M.StatusBit.INTERLOCK_OPEN and status & M.StatusBit.READY
    mbpoll(*common, "-t", "4", "-r", "0", host, "1")                           # remote
    mbpoll(*common, "-t", "4", "-r", "100", host, "3", "1")                   # servo on + position mode
    mbpoll(*common, "-t", "4:int", "-B", "-r", "102", host, "--", "-30000000")  # -30 deg demand, one FC16
    mbpoll(*common, "-t", "4", "-r", "100", host, "19")                       # new-setpoint edge
    assert server.table.read(1)["angle"] == pytest.approx(math.radians(-30.0), abs=1e-12)
    pos = mbpoll_values(mbpoll(*common, "-t", "3:int", "-B", "-r", "102", "-c", "1", host))[0]
    assert pos == -30_000_000
    status = mbpoll_values(mbpoll(*common, "-t", "3", "-r", "100", "-c", "1", host))[0]
    assert status & M.StatusBit.TARGET_REACHED and status & M.StatusBit.SERVO_ON


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="mbpoll not installed")
def test_mbpoll_rtu_over_pty(server):
    path = server.start_rtu(baudrate=19200)
    server.table.interlock_close(2)
    server.table.set_mode(2, "position")
    server.table.move_to(2, math.radians(12.5))
    out = mbpoll("-m", "rtu", "-b", "19200", "-P", "none", "-a", "1", "-0", "-1", "-t", "3:int", "-B",
                 "-r", "202", "-c", "1", path)
    assert mbpoll_values(out) == [12_500_000]
