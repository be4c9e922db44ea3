"""The emulated chamber (sim/chamber.py) on real wires, as ``rigctl sim up`` serves it:

* :class:`WatlowF4TServer` -- a Watlow F4T's registers (rigctl.drivers.watlow_chamber) on
  Modbus RTU over a pty null-modem pair and on Modbus TCP (pymodbus 3.16 server);
* :class:`ScpiChamberServer` -- the generic SCPI command set (rigctl.drivers.scpi_chamber) on a
  TCP socket (127.0.0.1), one command per line, for PyVISA's ``TCPIP::...::SOCKET`` resources.

Both drive one :class:`ChamberAccess`: the physics at the world's current time, under the
hardware's lock. ``requests`` keeps the last requests seen (wall time, text) for tests.
"""
from __future__ import annotations

import socketserver
import threading
import time
from collections import deque
from typing import Any, Callable

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from rigctl.drivers.watlow_chamber import (RAMP_OFF, RAMP_SETPOINT, REGISTERS, SCALE_PER_MINUTE, float_to_regs,
                                           regs_to_float)

from .chamber import ChamberPhysics
from .modbus_endpoints import ModbusEndpoints


class ChamberAccess:
    """The chamber physics at ``now()`` (the world's time), under ``lock``."""

    def __init__(self, physics: ChamberPhysics, now: Callable[[], float], lock: Any) -> None:
        self.physics, self.now, self.lock = physics, now, lock
        self.requests: deque[tuple[float, str]] = deque(maxlen=5000)

    def state(self) -> dict[str, Any]:
        with self.lock:
            return self.physics.state(self.now())

    def set_setpoint(self, value_c: float, ramp_c_per_min: float | None) -> None:
        with self.lock:
            self.physics.set_setpoint(self.now(), value_c, ramp_c_per_min)

    def set_running(self, on: bool) -> None:
        with self.lock:
            if on:
                self.physics.running = True
            else:
                self.physics.stop(self.now(), None)


class WatlowF4TServer(ModbusEndpoints):
    """Watlow F4T registers over Modbus (asyncio loop in a thread)."""

    name = "watlow"
    default_baudrate = 9600

    def __init__(self, access: ChamberAccess, device_id: int = 1) -> None:
        self.access, self.device_id = access, device_id
        self.hr: dict[int, int] = {REGISTERS["ramp_action"]: RAMP_OFF, REGISTERS["ramp_scale"]: SCALE_PER_MINUTE}
        r = float_to_regs(0.0)
        self.hr[REGISTERS["ramp_rate"]], self.hr[REGISTERS["ramp_rate"] + 1] = r
        self._start_loop()

    def _device(self) -> SimDevice:
        blocks = [SimData(2782, count=30, values=0, datatype=DataType.REGISTERS),
                  SimData(4180, count=2, values=0, datatype=DataType.REGISTERS),
                  SimData(27586, count=2, values=0, datatype=DataType.REGISTERS)]
        bits = [SimData(0, count=16, datatype=DataType.BITS)]
        return SimDevice(self.device_id, simdata=(bits, list(bits), blocks, list(blocks)), action=self._action)

    def image(self) -> dict[int, int]:
        s = self.access.state()
        img = dict(self.hr)
        for key, value in (("setpoint", s["setpoint_c"]), ("working_setpoint", s["working_setpoint_c"]),
                           ("air", s["air_c"]), ("part", s["product_c"])):
            a = REGISTERS[key]
            img[a], img[a + 1] = float_to_regs(value)
        return img

    async def _action(self, fc: int, start: int, address: int, count: int, registers: list[int],
                      set_values) -> ExcCodes | None:
        if set_values is None:
            img = self.image()
            for i in range(count):
                registers[address - start + i] = img.get(address + i, 0)
            self.access.requests.append((time.monotonic(), f"read {address}+{count}"))
            return None
        if fc not in (6, 16):
            return None
        values = [int(v) for v in set_values]
        self.access.requests.append((time.monotonic(), f"write {address} {values}"))
        for i, v in enumerate(values):
            self.hr[address + i] = v
        sp = REGISTERS["setpoint"]
        if address <= sp < address + len(values) and address <= sp + 1 < address + len(values) + 1:
            value = regs_to_float([self.hr.get(sp, 0), self.hr.get(sp + 1, 0)])
            ramp = None
            if self.hr.get(REGISTERS["ramp_action"]) == RAMP_SETPOINT:
                rate = regs_to_float([self.hr[REGISTERS["ramp_rate"]], self.hr[REGISTERS["ramp_rate"] + 1]])
                ramp = rate if self.hr.get(REGISTERS["ramp_scale"]) == SCALE_PER_MINUTE else rate / 60.0
            try:
                self.access.set_setpoint(value, ramp)
            except ValueError:
                return ExcCodes.ILLEGAL_VALUE
        return None


class ScpiChamberServer:
    """The generic SCPI chamber on TCP (127.0.0.1): one line per command, replies for queries."""

    def __init__(self, access: ChamberAccess, host: str = "127.0.0.1", port: int = 0) -> None:
        self.access = access
        self.rate = 0.0
        self.error = '0,"No error"'
        outer = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                for raw in self.rfile:
                    line = raw.decode("ascii", "replace").strip()
                    if not line:
                        continue
                    reply = outer.handle(line)
                    if reply is not None:
                        self.wfile.write((reply + "\n").encode())
                        self.wfile.flush()

        class Server(socketserver.ThreadingTCPServer):
            daemon_threads = True
            allow_reuse_address = True

        self.server = Server((host, port), Handler)
        self.address = self.server.server_address[:2]
        self._thread = threading.Thread(target=self.server.serve_forever, name="scpi-chamber", daemon=True)
        self._thread.start()

    def handle(self, line: str) -> str | None:
        self.access.requests.append((time.monotonic(), line))
        head, _, arg = line.partition(" ")
        cmd = head.upper()
        s = self.access.state() if cmd.endswith("?") else None
        if cmd == "*IDN?":
            return "RIGCTL,EMULATED-CHAMBER,0,1.0"
        if cmd == "MEAS:TEMP?":
            return f"{s['air_c']:.4f}"
        if cmd == "MEAS:TEMP2?":
            return f"{s['product_c']:.4f}"
        if cmd == "SOUR:TEMP?":
            return f"{s['setpoint_c']:.4f}"
        if cmd == "SOUR:TEMP:RATE?":
            return f"{self.rate:.4f}"
        if cmd == "STAT?":
            return s["status"].upper() + (f":{s['fault']}" if s["fault"] else "")
        if cmd == "SYST:ERR?":
            err, self.error = self.error, '0,"No error"'
            return err
        try:
            if cmd == "SOUR:TEMP:RATE":
                self.rate = float(arg)
                if self.rate < 0:
                    raise ValueError("negative rate")
                return None
            if cmd == "SOUR:TEMP":
                self.access.set_setpoint(float(arg), self.rate or None)
                return None
            if cmd == "OUTP":
                self.access.set_running(arg.strip().upper() in ("ON", "1"))
                return None
        except ValueError as exc:
            self.error = f'-222,"Data out of range: {exc}"'
            return None
        self.error = f'-113,"Undefined header: {head}"'
        return None if not cmd.endswith("?") else "ERROR"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=5)
