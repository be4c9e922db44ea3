"""Watlow F4T chamber controller over Modbus RTU or Modbus TCP (pymodbus 3.16).

Register map: the F4T's own map ("Data Map 1", as Watlow's F4T documentation and TestEquity's
F4T manual list the common registers for automation). 32-bit IEEE floats occupy two registers,
low-order word first (the F4T default). Addresses are used as given (0-based PDU addresses)::

    register  name                         type   access
    2782      temperature set point        float  RW
    2794      ramp action                  u16    RW   off = 62, set point = 85
    2796      ramp scale                   u16    RW   degrees/minute = 57, degrees/hour = 39
    2798      ramp rate                    float  RW
    2810      closed-loop (working) set pt float  R    instantaneous set point during a ramp
    27586     actual chamber temperature   float  R
    4180      actual part temperature      float  R    (F4T with cascade control; a second input)

Any register can be moved per installation (``registers:`` in the config, e.g. an F4T whose part
probe is on another input); ``part: null`` means there is no product input (reads NaN).
Status: the F4T has no single "done" flag in this map, so the state is derived: ``running`` while
the working set point differs from the target or the air is more than ``band_c`` from it,
``idle`` otherwise. A lost link raises :class:`rigctl.devices.LinkLost` (the engine's 'chamber'
suspender); a refused write raises :class:`rigctl.devices.DeviceFault`.
"""
from __future__ import annotations

import math
import struct
import threading
from typing import Any

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException
from pymodbus.framer import FramerType

from rigctl.config.chamber import ChamberState
from rigctl.devices import Clock, DeviceFault, LinkLost

REGISTERS = {"setpoint": 2782, "ramp_action": 2794, "ramp_scale": 2796, "ramp_rate": 2798,
             "working_setpoint": 2810, "air": 27586, "part": 4180}
RAMP_OFF, RAMP_SETPOINT = 62, 85
SCALE_PER_MINUTE = 57


def float_to_regs(value: float) -> list[int]:
    """An IEEE-754 single as two registers, low-order word first (F4T default)."""
    hi, lo = struct.unpack(">HH", struct.pack(">f", float(value)))
    return [lo, hi]


def regs_to_float(regs: list[int]) -> float:
    lo, hi = regs[0], regs[1]
    return struct.unpack(">f", struct.pack(">HH", hi & 0xFFFF, lo & 0xFFFF))[0]


class WatlowF4T:
    """Chamber protocol (rigctl.config.chamber) on a Watlow F4T."""

    name = "chamber"

    def __init__(self, clock: Clock, *, transport: str = "rtu", port: str | None = None, baudrate: int = 9600,
                 parity: str = "N", host: str = "127.0.0.1", tcp_port: int = 502, unit_id: int = 1,
                 timeout_s: float = 1.0, registers: dict[str, Any] | None = None, safe_c: float = 25.0,
                 band_c: float = 0.5) -> None:
        self.clock, self.unit_id, self.safe_c, self.band_c = clock, int(unit_id), float(safe_c), float(band_c)
        self.reg = dict(REGISTERS, **(registers or {}))
        if transport == "tcp":
            self.where = f"Modbus TCP {host}:{tcp_port}"
            self._make = lambda: ModbusTcpClient(host, port=tcp_port, timeout=timeout_s, retries=1)
        else:
            self.where = f"Modbus RTU {port}"
            self._make = lambda: ModbusSerialClient(port, framer=FramerType.RTU, baudrate=baudrate, parity=parity,
                                                    timeout=timeout_s, retries=1)
        self.client: Any = None
        self.lock = threading.Lock()
        self.identity = {"device_id": "", "protocol": f"Watlow F4T ({self.where})"}

    # -- link ------------------------------------------------------------------------------
    def _open(self) -> None:
        """Make the client if there is none and connect it (LinkLost if it cannot); under the lock."""
        if self.client is None:
            self.client = self._make()
        if not self.client.connect():
            self.client.close()
            self.client = None
            raise LinkLost(self.name, f"cannot connect to {self.where}")

    def connect(self) -> None:
        with self.lock:
            self._open()
        self.read()  # the controller answers: the map is there

    def close(self) -> None:
        with self.lock:
            if self.client is not None:
                self.client.close()
                self.client = None

    def _call(self, what: str, method: str, *args: Any, **kw: Any) -> Any:
        with self.lock:
            if self.client is None:
                self._open()
            try:
                rr = getattr(self.client, method)(*args, device_id=self.unit_id, **kw)
            except (ConnectionException, ModbusException, OSError) as exc:
                self.client.close()
                self.client = None
                raise LinkLost(self.name, f"{what} on {self.where} failed: {exc}") from exc
        if rr.isError():
            raise DeviceFault(f"chamber: {what} refused by the controller ({rr})")
        return rr

    def _read_float(self, key: str) -> float:
        addr = self.reg.get(key)
        if addr is None:
            return math.nan
        rr = self._call(f"read {key} (register {addr})", "read_holding_registers", int(addr), count=2)
        if len(rr.registers) < 2:
            raise LinkLost(self.name, f"short reply from {self.where}")
        return regs_to_float(rr.registers)

    def _write(self, key: str, values: list[int]) -> None:
        addr = int(self.reg[key])
        self._call(f"write {key} (register {addr})", "write_registers", addr, values)

    # -- chamber protocol ------------------------------------------------------------------------
    def set_setpoint(self, value_c: float, ramp_c_per_min: float | None = None) -> None:
        if ramp_c_per_min:
            self._write("ramp_scale", [SCALE_PER_MINUTE])
            self._write("ramp_rate", float_to_regs(ramp_c_per_min))
            self._write("ramp_action", [RAMP_SETPOINT])
        else:
            self._write("ramp_action", [RAMP_OFF])
        self._write("setpoint", float_to_regs(value_c))

    def read(self) -> ChamberState:
        t = self.clock.now()
        a, b = self.reg.get("setpoint"), self.reg.get("working_setpoint")
        if a is not None and b is not None and 0 < int(b) - int(a) < 100:  # one read for both
            rr = self._call(f"read registers {a}..{int(b) + 1}", "read_holding_registers", int(a),
                            count=int(b) - int(a) + 2)
            if len(rr.registers) < int(b) - int(a) + 2:
                raise LinkLost(self.name, f"short reply from {self.where}")
            sp = regs_to_float(rr.registers[0:2])
            work = regs_to_float(rr.registers[int(b) - int(a):int(b) - int(a) + 2])
        else:
            sp, work = self._read_float("setpoint"), self._read_float("working_setpoint")
        air = self._read_float("air")
        part = self._read_float("part")
        ramping = math.isfinite(work) and abs(work - sp) > 1e-3
        status = "running" if ramping or abs(air - sp) > self.band_c else "idle"
        return ChamberState(time=t, air_c=air, product_c=part, setpoint_c=sp, status=status)

    def stop(self) -> None:
        self.set_setpoint(self.safe_c, None)

    def identify(self) -> str:
        """Connect and read the chamber temperature (rigctl validate --devices)."""
        self.connect()
        s = self.read()
        return f"Watlow F4T ({self.where}): air {s.air_c:.2f} degC, set point {s.setpoint_c:.2f} degC"
