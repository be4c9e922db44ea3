"""VectorNav (VN-100 / VN-200 / VN-300) serial protocol: ASCII commands and binary output.

Taken from VectorNav's user manual (VN-100 UM001, sections 3.8 "Checksum / CRC", 4 "User
Configurable Binary Output Messages", 5.2.11 "Binary Output Register 1"):

ASCII commands: ``$VN<CMD>,<args>*<CK>\\r\\n`` where CK is the 8-bit XOR of every byte between
``$`` and ``*`` as two hex digits (``XX`` bypasses the check). Read register ``$VNRRG,<id>``,
write register ``$VNWRG,<id>,<values>``; the device answers with the same header and the
register's contents, or ``$VNERR,<code>``. Registers used here: 1 model number (text), 3 serial
number (u32), 4 firmware version (text), 6 async ASCII output type (0 = off), 75 binary output 1
(AsyncMode, RateDivisor of the 800 Hz ImuRate, OutputGroup in hex, one GroupField per active
group in hex).

Binary output message: sync byte 0xFA; the group byte (bit g-1 = group g active; bit 7 would
extend to groups 8-14, unused); one u16 little-endian field word per active group (bit i =
field i; bit 15 would extend, unused); the payload (the active fields in group order, then bit
order, each little endian); a CRC-16 (the manual's CRC16-CCITT: polynomial 0x1021, initial value
0, no final XOR -- the CRC-16/XMODEM parameters) over everything after the sync byte, sent
big-endian, so the CRC over group byte .. CRC is 0 for a good frame. Field sizes per group are
the manual's ``groupLen`` table.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigctl.errors import DeviceError

from .frame_engine import FixedFrameStream, affine_tables, xor_reduce_lookup

SYNC = 0xFA
IMU_RATE_HZ = 800          # the VN-100's ImuRate: binary output rate = IMU_RATE_HZ / RateDivisor

#: field sizes in bytes, per group (1-based) and field bit, from the manual's groupLen table
GROUP_LEN: dict[int, tuple[int, ...]] = {
    1: (8, 8, 8, 12, 16, 12, 24, 12, 12, 24, 20, 28, 2, 4, 8, 0),
    2: (8, 8, 8, 2, 8, 8, 8, 4, 4, 1, 1, 0, 0, 0, 0, 0),
    3: (2, 12, 12, 12, 4, 4, 16, 12, 12, 12, 12, 2, 40, 0, 0, 0),
    4: (8, 8, 2, 1, 1, 24, 24, 12, 12, 12, 4, 4, 2, 28, 2, 12),
    5: (2, 12, 16, 36, 12, 12, 12, 12, 12, 12, 28, 24, 0, 0, 0, 0),
    6: (2, 24, 24, 12, 12, 12, 12, 12, 12, 4, 4, 68, 64, 0, 0, 0),
    7: (8, 8, 2, 1, 1, 24, 24, 12, 12, 12, 4, 4, 2, 28, 2, 12),
}

#: (group, bit) -> (name, numpy dtype of one component, components) for the fields this driver
#: decodes (units: ns for times, m/s^2, rad/s, degC, deg for Ypr, kPa)
FIELDS: dict[tuple[int, int], tuple[str, str, int]] = {
    (1, 0): ("time_startup_ns", "<u8", 1), (1, 2): ("time_syncin_ns", "<u8", 1),
    (1, 3): ("ypr_deg", "<f4", 3), (1, 4): ("quaternion", "<f4", 4), (1, 5): ("angular_rate", "<f4", 3),
    (1, 8): ("accel", "<f4", 3), (1, 12): ("ins_status", "<u2", 1), (1, 13): ("syncin_count", "<u4", 1),
    (2, 0): ("time_startup_ns", "<u8", 1), (2, 4): ("time_syncin_ns", "<u8", 1),
    (2, 7): ("syncin_count", "<u4", 1),
    (3, 0): ("imu_status", "<u2", 1), (3, 1): ("uncomp_mag", "<f4", 3), (3, 2): ("uncomp_accel", "<f4", 3),
    (3, 3): ("uncomp_gyro", "<f4", 3), (3, 4): ("temperature", "<f4", 1), (3, 5): ("pressure_kpa", "<f4", 1),
    (3, 9): ("accel", "<f4", 3), (3, 10): ("angular_rate", "<f4", 3),
    (5, 1): ("ypr_deg", "<f4", 3), (5, 2): ("quaternion", "<f4", 4),
}

#: error codes of $VNERR (manual, section 3.7)
ERRORS = {1: "hard fault", 2: "serial buffer overflow", 3: "invalid checksum", 4: "invalid command",
          5: "not enough parameters", 6: "too many parameters", 7: "invalid parameter",
          8: "invalid register", 9: "unauthorized access", 10: "watchdog reset",
          11: "output buffer overflow", 12: "insufficient baud rate", 255: "error buffer overflow"}


class VectorNavError(DeviceError, ValueError):
    """A malformed message or a configuration the protocol cannot express."""


# ------------------------------------------------------------------------------------- ASCII
def checksum8(body: str | bytes) -> int:
    """The 8-bit XOR checksum of the bytes between ``$`` and ``*``."""
    data = body.encode("ascii") if isinstance(body, str) else body
    c = 0
    for x in data:
        c ^= x
    return c


def command(body: str) -> bytes:
    """``$<body>*<CK>\\r\\n`` (body without ``$``, e.g. ``VNRRG,03``)."""
    return f"${body}*{checksum8(body):02X}\r\n".encode("ascii")


def parse_line(line: bytes | str) -> tuple[str, list[str]]:
    """(header, fields) of one ASCII message (``$VNRRG,03,0100001234*5C``); VectorNavError on a
    bad frame or checksum (``XX`` accepted)."""
    s = line.decode("ascii", "replace") if isinstance(line, bytes) else line
    s = s.strip()
    if not s.startswith("$") or "*" not in s:
        raise VectorNavError(f"not a VectorNav ASCII message: {s[:40]!r}")
    body, ck = s[1:].rsplit("*", 1)
    if ck.upper() != "XX":
        try:
            want = int(ck[:2], 16)
        except ValueError:
            raise VectorNavError(f"bad checksum field {ck!r} in {s[:40]!r}") from None
        if want != checksum8(body):
            raise VectorNavError(f"checksum mismatch in {s[:40]!r}: {ck} != {checksum8(body):02X}")
    parts = body.split(",")
    return parts[0], parts[1:]


def read_register(reg: int) -> bytes:
    return command(f"VNRRG,{reg:02d}")


def write_register(reg: int, *values: object) -> bytes:
    return command(",".join([f"VNWRG,{reg:02d}", *[str(v) for v in values]]))


# ------------------------------------------------------------------------------------- CRC
def crc16(data: bytes | bytearray) -> int:
    """The manual's CRC16-CCITT (section 3.8.3; init 0, polynomial 0x1021), as its C code."""
    crc = 0
    for x in data:
        crc = ((crc >> 8) | (crc << 8)) & 0xFFFF
        crc ^= x
        crc ^= (crc & 0xFF) >> 4
        crc ^= (crc << 12) & 0xFFFF
        crc ^= ((crc & 0xFF) << 5) & 0xFFFF
    return crc


_CRC_TABLES: dict[int, tuple[np.ndarray, int]] = {}


def crc16_rows(rows: np.ndarray) -> np.ndarray:
    """CRC-16 of every row of a (k, m) uint8 array (vectorised, position tables cached per m)."""
    m = rows.shape[1]
    if m not in _CRC_TABLES:
        _CRC_TABLES[m] = affine_tables(crc16, m, np.uint16)
    table, c0 = _CRC_TABLES[m]
    return xor_reduce_lookup(table, rows) ^ np.uint16(c0)


# ---------------------------------------------------------------------------- binary layout
@dataclass(frozen=True)
class Layout:
    """One binary output configuration: {group: field word}, groups 1-7, bits 0-14."""

    groups: tuple[tuple[int, int], ...]

    @classmethod
    def of(cls, groups: dict[int, int]) -> Layout:
        for g, word in groups.items():
            if g not in GROUP_LEN:
                raise VectorNavError(f"binary output group {g} does not exist (1-7)")
            if not 0 < word < 0x8000:
                raise VectorNavError(f"group {g}: field word 0x{word:04X} must select fields 0-14")
            for bit in range(15):
                if word >> bit & 1 and GROUP_LEN[g][bit] == 0:
                    raise VectorNavError(f"group {g} field bit {bit} is not defined")
        return cls(tuple(sorted(groups.items())))

    @property
    def group_byte(self) -> int:
        return sum(1 << (g - 1) for g, _ in self.groups)

    @property
    def header(self) -> bytes:
        out = bytearray([SYNC, self.group_byte])
        for _, word in self.groups:
            out += int(word).to_bytes(2, "little")
        return bytes(out)

    @property
    def items(self) -> list[tuple[int, int, int, int]]:
        """[(group, bit, offset in frame, size)] in payload order."""
        pos, out = len(self.header), []
        for g, word in self.groups:
            for bit in range(15):
                if word >> bit & 1:
                    size = GROUP_LEN[g][bit]
                    out.append((g, bit, pos, size))
                    pos += size
        return out

    @property
    def length(self) -> int:
        """Whole frame, sync to CRC, bytes."""
        return len(self.header) + sum(s for *_, s in self.items) + 2

    def register_values(self, async_mode: int, rate_divisor: int) -> list[str]:
        """Values of Binary Output Register 1 (75) for this layout."""
        return [str(async_mode), str(rate_divisor), f"{self.group_byte:02X}",
                *[f"{w:04X}" for _, w in self.groups]]

    @classmethod
    def from_register(cls, values: list[str]) -> tuple[int, int, Layout]:
        """(async_mode, rate_divisor, layout) from register 75's values (hex group / fields)."""
        try:
            mode, div, gbyte = int(values[0]), int(values[1]), int(values[2], 16)
            words = [int(v, 16) for v in values[3:]]
        except (IndexError, ValueError):
            raise VectorNavError(f"bad binary output register values {values}") from None
        groups = [g for g in range(1, 8) if gbyte >> (g - 1) & 1]
        if gbyte & 0x80 or len(groups) != len(words):
            raise VectorNavError(f"{len(groups)} active groups but {len(words)} field words")
        return mode, div, cls.of(dict(zip(groups, words)))


def encode(layout: Layout, fields: dict[str, np.ndarray]) -> np.ndarray:
    """(n, L) uint8 frames carrying ``fields`` (names of :data:`FIELDS`; a field of the layout
    that is not given is sent as zeros) with their CRC."""
    n = len(next(iter(fields.values())))
    out = np.zeros((n, layout.length), dtype=np.uint8)
    out[:, :len(layout.header)] = np.frombuffer(layout.header, np.uint8)
    for g, bit, off, size in layout.items:
        spec = FIELDS.get((g, bit))
        if spec is None or spec[0] not in fields:
            continue
        name, dt, k = spec
        vals = np.asarray(fields[name]).reshape(n, k).astype(dt)
        out[:, off:off + size] = vals.view(np.uint8).reshape(n, size)
    crc = crc16_rows(out[:, 1:-2])
    out[:, -2] = (crc >> 8).astype(np.uint8)
    out[:, -1] = (crc & 0xFF).astype(np.uint8)
    return out


def decoder(layout: Layout) -> FixedFrameStream:
    """A streaming vectorised decoder of ``layout``'s frames: ``feed(bytes)`` returns the
    :data:`FIELDS` of the layout as arrays (float64; times and counts int64)."""
    items = [(FIELDS[(g, b)], off, size) for g, b, off, size in layout.items if (g, b) in FIELDS]
    fixed = list(enumerate(layout.header))

    def check(rows: np.ndarray) -> np.ndarray:
        return crc16_rows(rows[:, 1:]) == 0

    def decode(rows: np.ndarray) -> dict[str, np.ndarray]:
        n = rows.shape[0]
        out: dict[str, np.ndarray] = {}
        for (name, dt, k), off, size in items:
            raw = np.ascontiguousarray(rows[:, off:off + size]).view(dt).reshape(n, k) if n else \
                np.empty((0, k), dt)
            v = raw.astype(np.int64) if dt[1] in "ui" else raw.astype(np.float64)
            out[name] = v[:, 0] if k == 1 else v
        return out

    return FixedFrameStream(layout.length, fixed, check, decode)


def decode_buffer(layout: Layout, data: bytes) -> tuple[dict[str, np.ndarray], FixedFrameStream]:
    """Decode a complete buffer (end of stream included)."""
    st = decoder(layout)
    return st.feed(data, final=True), st


__all__ = ["ERRORS", "FIELDS", "GROUP_LEN", "IMU_RATE_HZ", "Layout", "VectorNavError", "checksum8", "command",
           "crc16", "crc16_rows", "decode_buffer", "decoder", "encode", "parse_line", "read_register",
           "write_register"]
