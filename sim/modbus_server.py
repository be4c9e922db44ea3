"""Emulated turntable behind the Modbus register map (docs/modbus-map.md), served by pymodbus 3.16.

One :class:`ModbusTableServer` owns an asyncio loop in a thread and can serve Modbus TCP (on
127.0.0.1, OS-picked port) and Modbus RTU over a pty null-modem pair at the same time; both see
the same register model, because the SimDevice ``action`` callback is the source of truth:
reads fill the requested registers from the model/table, writes are applied to the model.

pymodbus 3.16 notes (docs/protocols.md section 3): the new ``SimData``/``SimDevice`` datastore is used
(no deprecated ``ModbusSequentialDataBlock``, whose address 0 raises), addresses are the 0-based
PDU addresses, clients pass ``device_id=`` (not ``slave=``), the 4-tuple form keeps holding and
input registers apart, and the action runs *before* a write is stored, with the new values in
``set_values`` (returning an ``ExcCodes`` rejects the write).

Write semantics (per axis; HR 0 ``remote`` must be 1, else ILLEGAL_FUNCTION): rising SERVO_ON
closes the interlock and applies the mode register, falling opens it; NO_QUICK_STOP = 0 stops the
axis; HALT holds position / zero rate; a NEW_SETPOINT rising edge applies the position demand
(position mode) or the rate demand (rate mode) and echoes the sequence number; FAULT_RESET rising
resets interlocks. A refused request returns DEVICE_FAILURE and shows its code in the fault-code
register with the WARNING bit. Watchdog: with HR 1 > 0 ms and no write to HR 2 for that long,
every axis trips (fault code WATCHDOG) until a fault reset.
"""
from __future__ import annotations

import asyncio
import time

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from rigctl.drivers.modbus_map import (AXIS_BLOCK, PROTOCOL_VERSION, SCALE_ACCEL, SCALE_POSITION, SCALE_RATE,
                                       AxisInputs, ControlBit, FaultCode, GlobalStatusBit, Mode, StatusBit,
                                       decode_32, encode_32)

from .acl_server import IdealTable, TableRefused
from .modbus_endpoints import ModbusEndpoints

MODE_NAME = {Mode.OFF: "off", Mode.POSITION: "position", Mode.RATE: "rate"}


class ModbusTableServer(ModbusEndpoints):
    """Modbus front end of a table object (table API: see :mod:`rigctl.sim.acl_server`)."""

    def __init__(self, table=None, device_id: int = 1, word_order: str = "big", tick_s: float = 0.01,
                 window_udeg: int = 1000, dwell_ms: int = 100) -> None:
        self.table = table if table is not None else IdealTable()
        self.device_id, self.word_order, self.tick_s = device_id, word_order, tick_s
        self.n_axes = self.table.n_axes
        self.hr: dict[int, int] = {0: 0, 1: 0, 2: 0}
        self.heartbeat = 0
        self._last_kick = time.monotonic()
        self._wd_tripped = False
        self._ack = {a: False for a in self._axes()}
        self._refusal = {a: 0 for a in self._axes()}
        self._applied_seq = {a: 0 for a in self._axes()}
        for a in self._axes():
            b = 100 * a
            for off in range(AXIS_BLOCK):
                self.hr[b + off] = 0
            rate, acc = self.table.get_limits(a, "position")
            self._put32(b + 6, round(rate / SCALE_RATE))
            self._put32(b + 8, round(acc / SCALE_ACCEL))
            self._put32(b + 10, window_udeg)
            self.hr[b + 12] = dwell_ms
            self.table.set_window(a, window_udeg * SCALE_POSITION, dwell_ms * 1e-3)
        self._start_loop()

        async def start_ticker() -> asyncio.Task:
            return asyncio.get_running_loop().create_task(self._ticker())
        self._tick_task = self._run(start_ticker())

    def _axes(self) -> range:
        return range(1, self.n_axes + 1)

    # ---------------------------------------------------------------------- endpoints
    def _device(self) -> SimDevice:
        bits = [SimData(0, count=16, datatype=DataType.BITS)]
        hr = [SimData(0, count=3, values=0, datatype=DataType.REGISTERS)]
        ir = [SimData(0, count=6, values=0, datatype=DataType.REGISTERS)]
        for a in self._axes():
            hr.append(SimData(100 * a, count=AXIS_BLOCK, values=0, datatype=DataType.REGISTERS))
            ir.append(SimData(100 * a, count=AXIS_BLOCK, values=0, datatype=DataType.REGISTERS))
        return SimDevice(self.device_id, simdata=(bits, list(bits), hr, ir), action=self._action)

    async def _shutdown(self) -> None:
        self._tick_task.cancel()
        await super()._shutdown()
        try:
            await self._tick_task
        except asyncio.CancelledError:
            pass

    # ------------------------------------------------------------------------- model
    def _put32(self, addr: int, value: int, signed: bool = True) -> None:
        self.hr[addr], self.hr[addr + 1] = encode_32(value, signed, self.word_order)

    def _get32(self, addr: int, signed: bool = True) -> int:
        return decode_32([self.hr[addr], self.hr[addr + 1]], signed, self.word_order)

    async def _ticker(self) -> None:
        while True:
            await asyncio.sleep(self.tick_s)
            self.heartbeat = (self.heartbeat + 1) & 0xFFFF
            wd = self.hr[1]
            if wd and not self._wd_tripped and time.monotonic() - self._last_kick > wd * 1e-3:
                self._wd_tripped = True
                for a in self._axes():
                    self.table.trip(a, FaultCode.WATCHDOG)

    def input_image(self) -> dict[int, int]:
        """Current input registers {address: value} (globals and every axis block)."""
        img: dict[int, int] = {}
        any_open = any_fault = False
        for a in self._axes():
            r = self.table.read(a)
            st = int(r["status"])
            b = 100 * a
            ctl = self.hr[b]
            if not ctl & ControlBit.NO_QUICK_STOP and st & StatusBit.SERVO_ON:
                st |= StatusBit.QUICK_STOP
            if self._ack[a]:
                st |= StatusBit.SETPOINT_ACK
            fault = int(r.get("fault_code", 0)) or self._refusal[a]
            if self._refusal[a]:
                st |= StatusBit.WARNING
            any_open |= bool(st & StatusBit.INTERLOCK_OPEN)
            any_fault |= bool(st & StatusBit.FAULT)
            mode = {"off": Mode.OFF, "position": Mode.POSITION, "rate": Mode.RATE}[self.table.get_mode(a)]
            regs = AxisInputs(status=st, mode=int(mode), position=r["angle"], rate=r["rate"],
                              acceleration=r["accel"], following_error=r.get("following_error", 0.0),
                              fault_code=fault, applied_sequence=self._applied_seq[a],
                              sample_time=r["t"]).encode(self.word_order)
            img.update({b + i: v for i, v in enumerate(regs)})
        gs = (GlobalStatusBit.ANY_INTERLOCK_OPEN if any_open else 0) | \
             (GlobalStatusBit.ANY_FAULT if any_fault else 0) | (GlobalStatusBit.REMOTE if self.hr[0] == 1 else 0)
        t_ms = int(self.table.time() * 1e3) % (1 << 32)
        img.update({0: PROTOCOL_VERSION, 1: self.n_axes, 2: self.heartbeat, 5: int(gs)})
        img[3], img[4] = encode_32(t_ms, False, self.word_order)
        return img

    async def _action(self, fc: int, start: int, address: int, count: int, registers: list[int],
                      set_values) -> ExcCodes | None:
        if set_values is None:
            src = self.input_image() if fc == 4 else self.hr
            for i in range(count):
                registers[address - start + i] = src.get(address + i, 0)
            return None
        if fc not in (6, 16):
            return None                      # internal updates (not used) or coils
        return self._write(address, [int(v) for v in set_values])

    def _write(self, address: int, values: list[int]) -> ExcCodes | None:
        addrs = range(address, address + len(values))
        if any(a >= 100 for a in addrs) and self.hr[0] != 1:
            return ExcCodes.ILLEGAL_FUNCTION
        old = dict(self.hr)
        for a, v in zip(addrs, values):
            self.hr[a] = v & 0xFFFF
        if 1 in addrs or 2 in addrs:
            self._last_kick = time.monotonic()
        try:
            for ax in self._axes():
                b = 100 * ax
                touched = {a - b for a in addrs if b <= a < b + AXIS_BLOCK}
                if touched:
                    self._apply_axis(ax, touched, old[b], self.hr[b])
        except TableRefused as e:
            self.hr = old
            self._refusal[ax] = abs(e.code)
            return ExcCodes.DEVICE_FAILURE
        except OverflowError:
            self.hr = old
            self._refusal[ax] = FaultCode.OUT_OF_RANGE
            return ExcCodes.ILLEGAL_VALUE
        return None

    def _apply_axis(self, ax: int, touched: set[int], old_ctl: int, ctl: int) -> None:
        t, b = self.table, 100 * ax
        rise, fall = ctl & ~old_ctl, old_ctl & ~ctl
        if rise & ControlBit.FAULT_RESET:
            t.interlock_reset()
            self._wd_tripped = False
            self._refusal[ax] = 0
            self._last_kick = time.monotonic()
        if rise & ControlBit.SERVO_ON:
            t.interlock_close(ax)
        if fall & ControlBit.SERVO_ON:
            t.interlock_open(ax)
        if touched & {6, 7, 8, 9}:
            rate, acc = self._get32(b + 6) * SCALE_RATE, self._get32(b + 8) * SCALE_ACCEL
            for m in ("position", "rate"):
                t.set_limits(ax, m, rate=rate, accel=acc)
        if touched & {10, 11, 12}:
            t.set_window(ax, abs(self._get32(b + 10)) * SCALE_POSITION, self.hr[b + 12] * 1e-3)
        running = ctl & ControlBit.SERVO_ON and ctl & ControlBit.NO_QUICK_STOP
        mode = self.hr[b + 1]
        if mode not in MODE_NAME:
            raise TableRefused(-222, f"mode {mode} not supported")
        if running and (1 in touched or rise & (ControlBit.SERVO_ON | ControlBit.NO_QUICK_STOP)):
            t.set_mode(ax, MODE_NAME[Mode(mode)])
        if ctl & ControlBit.SERVO_ON and fall & ControlBit.NO_QUICK_STOP:
            t.stop(ax)
        if running and rise & ControlBit.HALT:
            if t.get_mode(ax) == "rate":
                t.set_rate(ax, 0.0)
            elif t.get_mode(ax) == "position":
                t.move_to(ax, t.read(ax)["angle"])
        if fall & ControlBit.NEW_SETPOINT:
            self._ack[ax] = False
        if rise & ControlBit.NEW_SETPOINT:
            m = t.get_mode(ax)
            if m == "position":
                t.move_to(ax, self._get32(b + 2) * SCALE_POSITION)
            elif m == "rate":
                t.set_rate(ax, self._get32(b + 4) * SCALE_RATE)
            else:
                raise TableRefused(-221, f"axis {ax} is off; select a mode and enable first")
            self._ack[ax] = True
            self._refusal[ax] = 0
            self._applied_seq[ax] = self.hr[b + 13]

