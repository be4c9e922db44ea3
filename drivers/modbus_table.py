"""Turntable driver for the Modbus register map (docs/modbus-map.md) with the pymodbus 3.16 client,
over Modbus TCP or Modbus RTU (the RTU port is a pyserial URL: ``/dev/ttyUSB0``, a pty,
``socket://host:port`` for RTU over TCP).

Implements :class:`rigctl.devices.Turntable`. pymodbus 3.16 usage (docs/protocols.md section 3):
keyword-only ``device_id=`` (not ``slave=``), 0-based PDU addresses, 32-bit values as register
pairs in the configured word order, each demand written in ONE FC16 together with the control
word (so it cannot tear), then the NEW_SETPOINT bit cleared again (the server applies a demand on
its rising edge).

Per command and axis: ``write_registers(B+0, [control | NEW_SETPOINT, mode, pos_hi, pos_lo,
rate_hi, rate_lo])`` then ``write_register(B+0, control)``; ``read`` is one FC4 read of the 14
input registers of each axis (coherent snapshot: status, mode, position, rate, acceleration,
following error, fault code, sequence, sample time). Settling comes from the status word
(TARGET_REACHED / AT_RATE, the controller's window and dwell, optionally set with ``window_deg``
/ ``dwell_s``) plus the engine's measured-window check.

Time: ``TableState.time`` = controller sample time (IR B+12..13, ms) + an offset kept on the lower
envelope of the probes at connect and of every ``read``, as in :mod:`rigctl.drivers.acl_table`.

Errors: no reply within ``timeout_s`` -> :class:`~rigctl.drivers.serial_link.ReplyTimeout`
naming the request (the client is closed and reopened, with backoff, on the next call); a refused
setpoint (exception DEVICE_FAILURE) -> :class:`rigctl.devices.DeviceFault` with the fault code;
ILLEGAL_VALUE -> ValueError; a lost connection -> :class:`rigctl.devices.LinkLost`.
"""
from __future__ import annotations

import logging
import math
import socket
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerType

from rigctl.config.config import TableLimits
from rigctl.devices import Clock, DeviceFault, LinkLost, TableState

from .modbus_map import (AXIS_BLOCK, SCALE_ACCEL, SCALE_POSITION, SCALE_RATE, AxisInputs, ControlBit,
                         FaultCode, Mode, decode_32, encode_32, to_counts)
from .probe_offset import ProbeOffset
from .serial_link import Backoff, ReplyTimeout

log = logging.getLogger(__name__)
RUN = int(ControlBit.SERVO_ON | ControlBit.NO_QUICK_STOP)
EXC_ILLEGAL_FUNCTION, EXC_ILLEGAL_VALUE, EXC_DEVICE_FAILURE = 1, 3, 4


@dataclass
class ModbusCounters:
    requests: int = 0
    timeouts: int = 0
    exceptions: int = 0
    reconnects: int = 0


class ModbusTable:
    """Turntable behind the Modbus register map; see the module docstring."""

    def __init__(self, limits: TableLimits, clock: Clock, *, transport: str = "tcp", host: str | None = None,
                 tcp_port: int = 502, port: str | None = None, baudrate: int = 19200, parity: str = "N",
                 unit_id: int = 1, word_order: str = "big", timeout_s: float = 0.5, retries: int = 1,
                 watchdog_ms: int = 0, window_deg: float | None = None, dwell_s: float | None = None,
                 name: str = "table") -> None:
        self.limits, self.clock, self.name = limits, clock, name
        self.transport, self.unit_id, self.word_order = transport, unit_id, word_order
        self.timeout_s, self.retries, self.watchdog_ms = timeout_s, retries, watchdog_ms
        self.window_deg, self.dwell_s = window_deg, dwell_s
        self.host, self.tcp_port = host, tcp_port
        if transport == "tcp":
            self.where = f"modbus tcp {host}:{tcp_port}"
            self._make = lambda: ModbusTcpClient(host, port=tcp_port, timeout=timeout_s, retries=retries)
        else:
            self.where = f"modbus rtu {port}"
            self._make = lambda: ModbusSerialClient(port, framer=FramerType.RTU, baudrate=baudrate, parity=parity,
                                                    timeout=timeout_s, retries=retries)
        self.client = None
        self.backoff = Backoff()
        self.counters = ModbusCounters()
        self.time_base = ProbeOffset(name)
        self._opened = 0

    # ------------------------------------------------------------------------- transport
    def _ensure(self):
        if self.client is not None:
            return self.client
        if not self.backoff.ready():
            raise LinkLost(self.name, f"{self.where} down; next reconnect attempt in {self.backoff.wait_s():.2f} s")
        client = self._make()
        if not client.connect():
            client.close()
            self.backoff.failed()
            raise LinkLost(self.name, f"cannot connect to {self.where}")
        self.client = client
        self.backoff.reset()
        self._opened += 1
        if self._opened > 1:
            self.counters.reconnects += 1
            log.info("%s: reconnected to %s", self.name, self.where)
        return client

    def _drop(self) -> None:
        client, self.client = self.client, None
        if client is not None:
            client.close()
        self.backoff.failed()

    def _call(self, what: str, method: str, *args, **kw):
        client = self._ensure()
        self.counters.requests += 1
        try:
            rr = getattr(client, method)(*args, device_id=self.unit_id, **kw)
        except ModbusIOException as exc:
            self.counters.timeouts += 1
            self._drop()
            raise ReplyTimeout(self.name, f"no reply to {what} from {self.where} within {self.timeout_s:g} s "
                                          f"(controller stalled or link down): {exc}") from exc
        except (ConnectionException, ModbusException, OSError) as exc:
            self._drop()
            raise LinkLost(self.name, f"{what} on {self.where} failed: {exc}") from exc
        if rr.isError():
            self.counters.exceptions += 1
            code = getattr(rr, "exception_code", None)
            if code == EXC_DEVICE_FAILURE:
                raise DeviceFault(f"{self.name}: controller refused {what} ({self._fault_text()})")
            if code == EXC_ILLEGAL_VALUE:
                raise ValueError(f"{self.name}: controller refused {what}: value out of range")
            raise DeviceFault(f"{self.name}: {what} answered with Modbus exception {code}"
                              + (" (remote control not enabled?)" if code == EXC_ILLEGAL_FUNCTION else ""))
        return rr

    def _fault_text(self) -> str:
        try:
            codes = [self._inputs(ax).fault_code for ax in (1, 2, 3)]
        except (LinkLost, DeviceFault):
            return "fault code unavailable"
        names = [FaultCode(c).name if c in FaultCode._value2member_map_ else str(c) for c in codes]
        return "fault codes " + ", ".join(f"axis {i + 1}: {n}" for i, n in enumerate(names))

    def _write(self, address: int, values: list[int], what: str) -> None:
        self._call(f"{what} (write registers {address}..{address + len(values) - 1})", "write_registers",
                   address, values)

    def _inputs(self, ax: int) -> AxisInputs:
        b = 100 * ax
        rr = self._call(f"read input registers {b}..{b + AXIS_BLOCK - 1}", "read_input_registers", b,
                        count=AXIS_BLOCK)
        if len(rr.registers) != AXIS_BLOCK:
            raise LinkLost(self.name, f"short reply from {self.where}: {len(rr.registers)} registers")
        return AxisInputs.decode(list(rr.registers), self.word_order)

    def _pair(self, value_si: float, scale: float) -> list[int]:
        return encode_32(to_counts(value_si, scale), True, self.word_order)

    # -------------------------------------------------------------------------- set-up
    def identify(self) -> str:
        """Connect and read axis 1's input block (nothing is written): who answers. Modbus TCP
        first opens a plain socket, so a refused or unreachable port raises its OSError."""
        if self.transport == "tcp":
            socket.create_connection((self.host, self.tcp_port), timeout=self.timeout_s).close()
        ai = self._inputs(1)
        return f"Modbus unit {self.unit_id} answers (axis 1 status 0x{int(ai.status):04x})"

    def connect(self) -> None:
        """Connect, take remote control, set limits/window, servo on, estimate the time offset."""
        self._ensure()
        self._write(0, [1, self.watchdog_ms], "remote on + watchdog")
        for ax in (1, 2, 3):
            b = 100 * ax
            self._write(b + 6, self._pair(self.limits.rate[ax - 1], SCALE_RATE)
                        + self._pair(self.limits.accel[ax - 1], SCALE_ACCEL), f"axis {ax} limits")
            if self.window_deg is not None or self.dwell_s is not None:
                cur = self._call(f"read holding registers {b + 10}..{b + 12}", "read_holding_registers",
                                 b + 10, count=3).registers
                win = self._pair(math.radians(self.window_deg), SCALE_POSITION) if self.window_deg is not None \
                    else list(cur[:2])
                dwell = int(round(self.dwell_s * 1e3)) if self.dwell_s is not None else int(cur[2])
                self._write(b + 10, win + [dwell], f"axis {ax} in-position window")
            self._write(b, [RUN], f"axis {ax} servo on")
        for _ in range(8):
            t0 = self.clock.now()
            ai = self._inputs(1)
            t1 = self.clock.now()
            self.time_base.probe(t0, t1, ai.sample_time)
        self.time_base.connected()
        log.info("%s: %s, controller time offset %.6f s (probe round trip %.3g s)", self.name, self.where,
                 self.time_base.offset, self.time_base.best_rtt)

    def close(self) -> None:
        client, self.client = self.client, None
        if client is not None:
            client.close()

    # ---------------------------------------------------------------------- Turntable API
    def _setpoint(self, ax: int, mode: Mode, angle: float, rate: float) -> None:
        b = 100 * ax
        regs = [RUN | ControlBit.NEW_SETPOINT, int(mode)] + self._pair(angle, SCALE_POSITION) \
            + self._pair(rate, SCALE_RATE)
        try:
            self._write(b, regs, f"axis {ax} {mode.name.lower()} setpoint")
        finally:
            if self.client is not None:
                self._write(b, [RUN], f"axis {ax} clear new-setpoint")

    def move(self, angles: NDArray[np.float64]) -> None:
        angles = np.asarray(angles, float)
        self.check_value(angles, None)
        for ax in (1, 2, 3):
            self._setpoint(ax, Mode.POSITION, float(angles[ax - 1]), 0.0)

    def set_rate(self, rates: NDArray[np.float64]) -> None:
        rates = np.asarray(rates, float)
        self.check_value(None, rates)
        for ax in (1, 2, 3):
            r = float(rates[ax - 1])
            if not math.isnan(r):
                self._setpoint(ax, Mode.RATE, 0.0, r)

    def stop(self) -> None:
        """Controlled stop: mode OFF on every axis (the controller ramps the rate to zero)."""
        for ax in (1, 2, 3):
            self._write(100 * ax, [RUN, int(Mode.OFF)], f"axis {ax} stop")

    def reset_faults(self) -> None:
        """Fault reset (rising FAULT_RESET) and servo on again on every axis."""
        for ax in (1, 2, 3):
            self._write(100 * ax, [RUN | ControlBit.FAULT_RESET], f"axis {ax} fault reset")
            self._write(100 * ax, [RUN], f"axis {ax} servo on")

    @property
    def time_offset(self) -> float:
        """Controller time -> run time offset, s (:mod:`rigctl.drivers.probe_offset`)."""
        return self.time_base.offset or 0.0

    def read(self) -> TableState:
        if self.watchdog_ms:
            self._call("watchdog kick", "write_register", 2, 1)
        t0 = self.clock.now()
        snaps = [self._inputs(1)]
        t1 = self.clock.now()
        snaps += [self._inputs(ax) for ax in (2, 3)]
        self.time_base.probe(t0, t1, snaps[0].sample_time)
        return TableState(time=self.time_base.stamp(snaps[0].sample_time),
                          angle=np.array([s.position for s in snaps]), rate=np.array([s.rate for s in snaps]),
                          status=tuple(int(s.status) for s in snaps))  # type: ignore[arg-type]

    def check_value(self, angles: NDArray | None, rates: NDArray | None) -> None:
        self.limits.check(angles, rates)


__all__ = ["ModbusTable", "ModbusCounters", "decode_32"]
