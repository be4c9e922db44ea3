"""Modbus register map of the turntable (docs/modbus-map.md), as data plus codecs.

Servo-drive style: 0-based PDU addresses (``mbpoll -0``), 32-bit values in two consecutive
registers (default big-endian word order = ``mbpoll -B``; "little" swaps the two words), written
with one FC16 so they cannot tear. Fixed-point scaling on the wire:

    position      INT32, 1 count = 1e-6 deg    (udeg)
    rate          INT32, 1 count = 1e-4 deg/s
    acceleration  INT32, 1 count = 1e-3 deg/s^2

Values are SI inside rigctl (rad, rad/s, rad/s^2); :func:`to_counts` / :func:`from_counts` convert.
Per-axis blocks start at ``100 * axis`` (axis = 1..3) in both the holding (FC3/6/16) and the
input (FC4) register tables. See docs/modbus-map.md for the full table.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass, fields
from enum import IntEnum, IntFlag

from rigctl.devices import AxisStatus

PROTOCOL_VERSION = 1
N_AXES = 3
AXIS_BLOCK = 14          # registers per axis block (both tables)
DEG = math.pi / 180.0

#: SI value (rad, rad/s, rad/s^2) of one count, and the wire unit name.
SCALE_POSITION = 1e-6 * DEG
SCALE_RATE = 1e-4 * DEG
SCALE_ACCEL = 1e-3 * DEG


#: Per-axis status word (IR B+0; also the ACL ``:STATus:AXIS?`` word). One definition serves the
#: engine, the drivers and the emulators: :class:`rigctl.devices.AxisStatus` (INTERNAL_LIMIT and
#: FOLLOWING_ERROR_TRIP are its aliases of LIMIT_ACTIVE and FOLLOWING_ERROR).
StatusBit = AxisStatus


class ControlBit(IntFlag):
    """Per-axis control word (HR B+0). Bit 1 is active-low as in CiA 402: keep it 1 to run."""

    SERVO_ON = 1 << 0
    NO_QUICK_STOP = 1 << 1
    NEW_SETPOINT = 1 << 4
    FAULT_RESET = 1 << 7
    HALT = 1 << 8


class Mode(IntEnum):
    """HR B+1 / IR B+1."""

    OFF = 0
    POSITION = 1
    RATE = 2
    SYNTHESIS = 3   # reserved


class GlobalStatusBit(IntFlag):
    """IR 5."""

    ESTOP = 1 << 0
    ANY_INTERLOCK_OPEN = 1 << 1
    ANY_FAULT = 1 << 2
    REMOTE = 1 << 3


class FaultCode(IntEnum):
    """IR B+10."""

    NONE = 0
    WATCHDOG = 1
    FOLLOWING_ERROR = 2
    INTERLOCK_TRIP = 3
    SETTINGS_CONFLICT = 221    # a setpoint was refused (e.g. interlock open, wrong mode)
    OUT_OF_RANGE = 222         # a setpoint was outside the limits


@dataclass(frozen=True)
class Reg:
    """One register (or register pair) of the map."""

    name: str
    table: str          # "input" (FC4) or "holding" (FC3/6/16)
    offset: int         # address, or offset from the axis base 100*axis when per_axis
    type: str           # u16 | i32 | u32
    unit: str           # wire unit
    scale_si: float     # SI value of one count (1.0 for raw)
    per_axis: bool
    doc: str

    @property
    def count(self) -> int:
        return 1 if self.type == "u16" else 2

    def address(self, axis: int | None = None) -> int:
        if not self.per_axis:
            return self.offset
        if axis is None or not 1 <= axis <= N_AXES:
            raise ValueError(f"{self.name}: axis must be 1..{N_AXES}")
        return 100 * axis + self.offset


REGISTERS: tuple[Reg, ...] = (
    Reg("protocol_version", "input", 0, "u16", "-", 1.0, False, "protocol version (1)"),
    Reg("n_axes", "input", 1, "u16", "-", 1.0, False, "number of axes (3)"),
    Reg("heartbeat", "input", 2, "u16", "-", 1.0, False, "+1 per controller tick, wraps"),
    Reg("time_ms", "input", 3, "u32", "ms", 1e-3, False, "controller time since start"),
    Reg("global_status", "input", 5, "u16", "bits", 1.0, False, "GlobalStatusBit"),
    Reg("remote", "holding", 0, "u16", "-", 1.0, False, "1 = remote control enabled (required for axis writes)"),
    Reg("watchdog_ms", "holding", 1, "u16", "ms", 1e-3, False, "watchdog timeout, 0 = off"),
    Reg("watchdog_kick", "holding", 2, "u16", "-", 1.0, False, "any write kicks the watchdog"),
    Reg("control", "holding", 0, "u16", "bits", 1.0, True, "ControlBit"),
    Reg("mode", "holding", 1, "u16", "-", 1.0, True, "Mode: 0 off, 1 position, 2 rate"),
    Reg("position_demand", "holding", 2, "i32", "udeg", SCALE_POSITION, True, "applied on NEW_SETPOINT rising edge"),
    Reg("rate_demand", "holding", 4, "i32", "1e-4 deg/s", SCALE_RATE, True, "applied on NEW_SETPOINT rising edge"),
    Reg("rate_limit", "holding", 6, "i32", "1e-4 deg/s", SCALE_RATE, True, "profile rate limit"),
    Reg("accel_limit", "holding", 8, "i32", "1e-3 deg/s^2", SCALE_ACCEL, True, "profile acceleration limit"),
    Reg("window", "holding", 10, "i32", "udeg", SCALE_POSITION, True, "in-position window"),
    Reg("dwell_ms", "holding", 12, "u16", "ms", 1e-3, True, "time in window before TARGET_REACHED"),
    Reg("sequence", "holding", 13, "u16", "-", 1.0, True, "command sequence number, echoed when applied"),
    Reg("status", "input", 0, "u16", "bits", 1.0, True, "StatusBit"),
    Reg("mode_display", "input", 1, "u16", "-", 1.0, True, "Mode in effect"),
    Reg("position", "input", 2, "i32", "udeg", SCALE_POSITION, True, "actual position, wrapped to [-180, 180) deg"),
    Reg("rate", "input", 4, "i32", "1e-4 deg/s", SCALE_RATE, True, "actual rate"),
    Reg("acceleration", "input", 6, "i32", "1e-3 deg/s^2", SCALE_ACCEL, True, "actual acceleration"),
    Reg("following_error", "input", 8, "i32", "udeg", SCALE_POSITION, True, "demand - actual"),
    Reg("fault_code", "input", 10, "u16", "-", 1.0, True, "FaultCode"),
    Reg("applied_sequence", "input", 11, "u16", "-", 1.0, True, "last applied sequence number"),
    Reg("sample_time_ms", "input", 12, "u32", "ms", 1e-3, True, "time of this snapshot (same clock as IR 3-4)"),
)
REG = {(r.table, r.name): r for r in REGISTERS}


# ------------------------------------------------------------------------------ codecs

def encode_32(value: int, signed: bool = True, word_order: str = "big") -> list[int]:
    """A 32-bit integer as two registers (big word order: high word first)."""
    hi, lo = struct.unpack(">HH", struct.pack(">i" if signed else ">I", int(value)))
    return [hi, lo] if word_order == "big" else [lo, hi]


def decode_32(regs: list[int], signed: bool = True, word_order: str = "big") -> int:
    """Inverse of :func:`encode_32`."""
    hi, lo = (regs[0], regs[1]) if word_order == "big" else (regs[1], regs[0])
    return struct.unpack(">i" if signed else ">I", struct.pack(">HH", hi & 0xFFFF, lo & 0xFFFF))[0]


def to_counts(value_si: float, scale_si: float, signed: bool = True) -> int:
    """SI value -> integer counts, rounded; raises OverflowError outside the 32-bit range."""
    c = int(round(value_si / scale_si))
    lo, hi = (-(1 << 31), (1 << 31) - 1) if signed else (0, (1 << 32) - 1)
    if not lo <= c <= hi:
        raise OverflowError(f"{value_si!r} is outside the register range at {scale_si!r} per count")
    return c


def from_counts(counts: int, scale_si: float) -> float:
    """Integer counts -> SI value."""
    return counts * scale_si


def wrap_angle(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi) rad (positions are reported wrapped, as on a continuous axis)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def _encode_block(values: dict[str, int], table: str, word_order: str) -> list[int]:
    out = [0] * AXIS_BLOCK
    for r in REGISTERS:
        if r.table != table or not r.per_axis:
            continue
        v = int(values[r.name])
        if r.type == "u16":
            out[r.offset] = v & 0xFFFF
        else:
            out[r.offset:r.offset + 2] = encode_32(v, r.type == "i32", word_order)
    return out


def _decode_block(regs: list[int], table: str, word_order: str) -> dict[str, int]:
    if len(regs) < AXIS_BLOCK:
        raise ValueError(f"an axis block is {AXIS_BLOCK} registers, got {len(regs)}")
    out = {}
    for r in REGISTERS:
        if r.table != table or not r.per_axis:
            continue
        out[r.name] = regs[r.offset] if r.type == "u16" else decode_32(
            regs[r.offset:r.offset + 2], r.type == "i32", word_order)
    return out


@dataclass
class AxisInputs:
    """Decoded input block of one axis (SI units)."""

    status: int
    mode: int
    position: float           # rad
    rate: float               # rad/s
    acceleration: float       # rad/s^2
    following_error: float    # rad
    fault_code: int
    applied_sequence: int
    sample_time: float        # s

    def encode(self, word_order: str = "big") -> list[int]:
        return _encode_block({
            "status": self.status, "mode_display": self.mode,
            "position": to_counts(wrap_angle(self.position), SCALE_POSITION),
            "rate": to_counts(self.rate, SCALE_RATE), "acceleration": to_counts(self.acceleration, SCALE_ACCEL),
            "following_error": to_counts(self.following_error, SCALE_POSITION),
            "fault_code": self.fault_code, "applied_sequence": self.applied_sequence,
            "sample_time_ms": int(round(self.sample_time * 1e3)) % (1 << 32)}, "input", word_order)

    @classmethod
    def decode(cls, regs: list[int], word_order: str = "big") -> AxisInputs:
        d = _decode_block(regs, "input", word_order)
        return cls(status=d["status"], mode=d["mode_display"], position=d["position"] * SCALE_POSITION,
                   rate=d["rate"] * SCALE_RATE, acceleration=d["acceleration"] * SCALE_ACCEL,
                   following_error=d["following_error"] * SCALE_POSITION, fault_code=d["fault_code"],
                   applied_sequence=d["applied_sequence"], sample_time=d["sample_time_ms"] * 1e-3)


@dataclass
class AxisHolding:
    """Decoded holding block of one axis (SI units)."""

    control: int = 0
    mode: int = 0
    position_demand: float = 0.0    # rad
    rate_demand: float = 0.0        # rad/s
    rate_limit: float = 0.0         # rad/s
    accel_limit: float = 0.0        # rad/s^2
    window: float = 0.0             # rad
    dwell: float = 0.0              # s
    sequence: int = 0

    def counts(self) -> dict[str, int]:
        return {"control": self.control, "mode": self.mode,
                "position_demand": to_counts(self.position_demand, SCALE_POSITION),
                "rate_demand": to_counts(self.rate_demand, SCALE_RATE),
                "rate_limit": to_counts(self.rate_limit, SCALE_RATE),
                "accel_limit": to_counts(self.accel_limit, SCALE_ACCEL),
                "window": to_counts(self.window, SCALE_POSITION), "dwell_ms": int(round(self.dwell * 1e3)),
                "sequence": self.sequence & 0xFFFF}

    def encode(self, word_order: str = "big") -> list[int]:
        return _encode_block(self.counts(), "holding", word_order)

    @classmethod
    def decode(cls, regs: list[int], word_order: str = "big") -> AxisHolding:
        d = _decode_block(regs, "holding", word_order)
        return cls(control=d["control"], mode=d["mode"], position_demand=d["position_demand"] * SCALE_POSITION,
                   rate_demand=d["rate_demand"] * SCALE_RATE, rate_limit=d["rate_limit"] * SCALE_RATE,
                   accel_limit=d["accel_limit"] * SCALE_ACCEL, window=d["window"] * SCALE_POSITION,
                   dwell=d["dwell_ms"] * 1e-3, sequence=d["sequence"])


def holding_field_names() -> list[str]:
    return [f.name for f in fields(AxisHolding)]
