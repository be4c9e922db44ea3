"""The declarative frame description of an IMU (the ``frame:`` mapping of an ``imu`` section with
``driver: frame``), validated with file and line like every other config key.

Binary frames (``format: binary``, the default)::

    frame:
      sync: "AA 55"                 # 1-4 bytes, hex
      endian: little                # little | big: every field and the checksum
      fields:                       # in frame order, after the sync bytes
        - {name: length, type: B}                      # a length field (see 'length')
        - {name: counter, type: H}                     # sample counter (wraps at its type's range)
        - {name: time, type: I, scale: 1.0e-6, unit: s}
        - {name: gyro_x, type: i, scale: 1.0e-7, unit: rad/s}
        - ...
        - {name: temperature, type: h, scale: 0.01, unit: degC}
      length: {field: length, counts: frame}           # or a number; optional
      checksum: {type: crc16-ccitt, init: 0xFFFF}      # none | xor8 | sum8 | crc16-ccitt | crc32

Field types are Python struct codes: b B h H i I q Q (integers), e f d (floats), ``Nx`` (N pad
bytes). A field may carry ``value:`` (an integer every frame holds, e.g. a message ID: it also
serves to find frames). Roles are by name: ``accel_x|y|z`` (unit m/s^2, g or mg), ``gyro_x|y|z``
(rad/s, deg/s, mrad/s), ``temperature`` (degC), ``time`` (s, ms, us, ns; unwrapped at its
integer type's range), ``counter`` (wraps at its type's range); other names are decoded and
ignored. A frame needs the six inertial fields and a ``time`` or ``counter``. ``length``: the
whole frame's length in bytes (checked against the fields), or ``{field, counts: frame |
fields}``: the named field holds the frame length (sync to checksum), or the bytes of the field
list only. ``checksum``: computed over ``from`` .. the byte before the checksum (default: from
the first byte after the sync bytes) and stored after the last field, in the frame's
endianness; ``crc16-ccitt`` is polynomial 0x1021, MSB first, ``init`` (default 0xFFFF: CRC-16/
CCITT-FALSE; 0: CRC-16/XMODEM, the VectorNav CRC); ``crc32`` is the IEEE CRC-32 of zlib.

ASCII lines (``format: csv``): ``fields`` are the comma-separated columns (types are not given;
every column is a decimal number), after an optional ``prefix`` column (e.g. ``$IMU``);
``checksum: nmea`` (``*HH`` after the last column: XOR of the bytes between ``$`` and ``*``) or
``none``; lines end with ``\\n`` (a ``\\r`` before it is allowed).
"""
from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass

from .. import schema as S
from ..yamlio import InputError, LocDict, LocList

INT_CODES = "bBhHiIqQ"
FLOAT_CODES = "efd"
CHECKSUMS = ("none", "xor8", "sum8", "crc16-ccitt", "crc32")
CHECKSUM_BYTES = {"none": 0, "xor8": 1, "sum8": 1, "crc16-ccitt": 2, "crc32": 4}
G0 = 9.80665
#: role -> {unit: factor to SI}
UNITS: dict[str, dict[str, float]] = {
    "accel": {"m/s^2": 1.0, "m/s2": 1.0, "g": G0, "mg": G0 * 1e-3},
    "gyro": {"rad/s": 1.0, "mrad/s": 1e-3, "deg/s": math.pi / 180.0},
    "temperature": {"degC": 1.0},
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9},
}
INERTIAL = ("accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
NAME = re.compile(r"^[a-z_][a-z0-9_]{0,31}$")


def role(name: str) -> str | None:
    if name.startswith("accel_"):
        return "accel"
    if name.startswith("gyro_"):
        return "gyro"
    return name if name in ("temperature", "time", "counter") else None


@dataclass(frozen=True)
class Field:
    name: str
    code: str            # struct code ("" for csv columns, "x" for padding)
    size: int            # bytes (binary)
    offset: int          # byte offset in the frame (binary) or column index (csv)
    scale: float         # raw * scale * unit factor = SI value
    unit: str
    value: int | None = None

    @property
    def factor(self) -> float:
        r = role(self.name)
        return self.scale * (UNITS[r][self.unit] if r in UNITS else 1.0)

    @property
    def wrap(self) -> int | None:
        """Range of an integer field (its counter / time wraps there), None for floats."""
        return 1 << (8 * self.size) if self.code and self.code in INT_CODES else None


@dataclass(frozen=True)
class FrameSpec:
    format: str                       # binary | csv
    fields: tuple[Field, ...]
    sync: bytes = b""
    endian: str = "little"
    checksum: str = "none"
    checksum_init: int | None = None
    checksum_from: int = 0
    length: int = 0                   # binary: whole frame, bytes
    prefix: str = ""                  # csv: first column

    @property
    def names(self) -> list[str]:
        return [f.name for f in self.fields if f.code != "x"]

    def field(self, name: str) -> Field | None:
        return next((f for f in self.fields if f.name == name), None)

    @property
    def checksum_offset(self) -> int:
        return self.length - CHECKSUM_BYTES[self.checksum]


def _hexbytes(m: LocDict, key: str) -> bytes:
    v = m[key]
    if isinstance(v, int) and not isinstance(v, bool):
        v = [v]
    if isinstance(v, list):
        if not all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 255 for x in v):
            raise S.error(m, key, f"'{key}' must list bytes 0-255", f'e.g. {key}: "AA 55" or [0xAA, 0x55]')
        out = bytes(v)
    elif isinstance(v, str):
        try:
            out = bytes.fromhex(v.replace("0x", "").replace(",", " "))
        except ValueError:
            raise S.error(m, key, f"'{key}' = {v!r} is not hex bytes", f'e.g. {key}: "AA 55"') from None
    else:
        raise S.error(m, key, f"'{key}' must be hex bytes", f'e.g. {key}: "AA 55"')
    if not 1 <= len(out) <= 4:
        raise S.error(m, key, f"'{key}' has {len(out)} bytes; a frame starts with 1-4 sync bytes",
                      f'e.g. {key}: "AA 55"')
    return out


def _field(item, fields: LocList, i: int, binary: bool, endian: str, offset: int, seen: set[str]) -> Field:
    if not isinstance(item, dict):
        raise InputError(f"'fields' entry {i + 1} must be a mapping such as {{name: gyro_x, type: i, "
                         "scale: 1.0e-7, unit: rad/s}", fields.file, fields.line_of(i))
    f = item if isinstance(item, LocDict) else LocDict(item)
    S.check_keys(f, ("name", "type", "scale", "unit", "value"), f"'fields' entry {i + 1}",
                 required=("name", "type") if binary else ("name",))
    name = S.get_str(f, "name")
    code = S.get_str(f, "type", "") if binary else ""
    size = 0
    if binary:
        pad = re.fullmatch(r"(\d{0,3})x", code)
        if pad:
            size = int(pad.group(1) or 1)
            if size == 0:
                raise S.error(f, "type", "'type' 0x pads nothing", "remove the entry or give e.g. 2x")
            return Field(name, "x", size, offset, 1.0, "")
        if len(code) != 1 or code not in INT_CODES + FLOAT_CODES:
            raise S.error(f, "type", f"'type' = {code!r} is not a struct code",
                          "use one of b B h H i I q Q (integers), e f d (floats) or Nx (N pad bytes)")
        size = struct.calcsize(("<" if endian == "little" else ">") + code)
    elif "type" in f:
        raise S.error(f, "type", "a csv column has no 'type' (every column is a decimal number)",
                      "remove 'type'")
    if not NAME.match(name):
        raise S.error(f, "name", f"field name {name!r} is not a plain lower-case name",
                      "e.g. gyro_x, accel_y, temperature, counter, time, status")
    if name in seen:
        raise S.error(f, "name", f"field {name!r} appears twice", "give each field its own name")
    seen.add(name)
    r = role(name)
    scale = S.get_number(f, "scale", 1.0)
    if scale == 0:
        raise S.error(f, "scale", "'scale' is 0: every value would read as 0", "give the LSB weight, e.g. 1.0e-7")
    if r in UNITS:
        if "unit" not in f:
            raise S.error(f, None, f"field {name!r} has no 'unit'",
                          f"add unit: one of {', '.join(UNITS[r])} (the unit of raw x scale)")
        unit = S.get_str(f, "unit", choices=list(UNITS[r]))
    else:
        unit = S.get_str(f, "unit", "")
    is_float = bool(code) and code in FLOAT_CODES
    if r == "counter" and (is_float or scale != 1.0):
        raise S.error(f, "type" if is_float else "scale",
                      "the counter must be an unscaled integer field", "use type B, H, I or Q and no scale")
    value = None
    if "value" in f:
        if not binary or is_float:
            raise S.error(f, "value", "'value' fixes an integer field of a binary frame",
                          "remove 'value', or give the field an integer type")
        value = S.get_number(f, "value", integer=True)
        lo, hi = _int_range(code, size)
        if not lo <= value <= hi:
            raise S.error(f, "value", f"'value' {value} does not fit type {code} ({lo}..{hi})")
    return Field(name, code, size, offset, scale, unit, value)


def _int_range(code: str, size: int) -> tuple[int, int]:
    bits = 8 * size
    return (0, (1 << bits) - 1) if code.isupper() else (-(1 << (bits - 1)), (1 << (bits - 1)) - 1)


def parse_frame_spec(section: LocDict, key: str = "frame") -> FrameSpec:
    """The ``frame:`` mapping of ``section`` as a :class:`FrameSpec`; InputError with file, line
    and what to fix."""
    if key not in section:
        raise S.error(section, None, f"'imu' (frame) is missing '{key}'",
                      "describe the frame: sync, endian, fields, checksum (docs/hardware.md)")
    m = S.require_mapping(section[key], f"'{key}'", section, key)
    fmt = S.get_str(m, "format", "binary", choices=("binary", "csv"))
    binary = fmt == "binary"
    allowed = ("format", "sync", "endian", "fields", "length", "checksum") if binary else \
        ("format", "prefix", "fields", "checksum")
    S.check_keys(m, allowed, f"'{key}' ({fmt})", required=("sync", "fields") if binary else ("fields",))
    endian = S.get_str(m, "endian", "little", choices=("little", "big")) if binary else "little"
    sync = _hexbytes(m, "sync") if binary else b""
    items = S.get_list(m, "fields", min_length=1)
    if not isinstance(items, LocList):
        items = LocList(items)
        items.file, items.line = m.file, m.line_of("fields")
    seen: set[str] = set()
    fields, offset = [], len(sync)
    for i, item in enumerate(items):
        f = _field(item, items, i, binary, endian, offset if binary else i, seen)
        fields.append(f)
        offset += f.size
    missing = [n for n in INERTIAL if n not in seen]
    if missing:
        raise S.error(m, "fields", f"the frame has no {', '.join(missing)}",
                      "add a field for each of accel_x, accel_y, accel_z, gyro_x, gyro_y, gyro_z")
    if "time" not in seen and "counter" not in seen:
        raise S.error(m, "fields", "the frame has neither 'time' nor 'counter'",
                      "add a counter (type H or I) or a time field: the run needs each sample's time")
    if not binary:
        ck = S.get_str(m, "checksum", "none", choices=("none", "nmea"))
        prefix = S.get_str(m, "prefix", "")
        if "," in prefix:
            raise S.error(m, "prefix", "'prefix' is one column and cannot hold a comma")
        if ck == "nmea" and not prefix.startswith("$"):
            raise S.error(m, "checksum", "an NMEA checksum covers the bytes after '$'",
                          "start the prefix with '$' (e.g. prefix: $IMU) or use checksum: none")
        return FrameSpec("csv", tuple(fields), checksum=ck, prefix=prefix)
    ck, init, start = "none", None, len(sync)
    if "checksum" in m:
        c = m["checksum"]
        if isinstance(c, str):
            c = LocDict({"type": c})
            c.file, c.line = m.file, m.line_of("checksum")
        c = S.require_mapping(c, "'checksum'", m, "checksum")
        S.check_keys(c, ("type", "init", "from"), "'checksum'", required=("type",))
        ck = S.get_str(c, "type", choices=CHECKSUMS)
        if "init" in c:
            if ck != "crc16-ccitt":
                raise S.error(c, "init", f"'init' applies to crc16-ccitt, not {ck}", "remove 'init'")
            init = S.get_number(c, "init", minimum=0, maximum=0xFFFF, integer=True)
        elif ck == "crc16-ccitt":
            init = 0xFFFF
        start = S.get_number(c, "from", len(sync), minimum=0, maximum=offset - 1, integer=True)
    total = offset + CHECKSUM_BYTES[ck]
    fields = _length(m, fields, total, len(sync), endian)
    return FrameSpec("binary", tuple(fields), sync=sync, endian=endian, checksum=ck, checksum_init=init,
                     checksum_from=start, length=total)


def _length(m: LocDict, fields: list[Field], total: int, nsync: int, endian: str) -> list[Field]:
    if "length" not in m:
        return fields
    v = m["length"]
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        n = S.get_number(m, "length", integer=True, minimum=1)
        if n != total:
            raise S.error(m, "length", f"'length' is {n} bytes but the fields, sync and checksum make {total}",
                          "fix the field types or the length")
        return fields
    lm = S.require_mapping(v, "'length'", m, "length")
    S.check_keys(lm, ("field", "counts"), "'length'", required=("field",))
    name = S.get_str(lm, "field")
    counts = S.get_str(lm, "counts", "frame", choices=("frame", "fields"))
    f = next((x for x in fields if x.name == name), None)
    if f is None:
        raise S.error(lm, "field", f"'length' names field {name!r}, which the frame does not have",
                      S.did_you_mean(name, [x.name for x in fields], "fields"))
    if f.code not in INT_CODES or f.scale != 1.0:
        raise S.error(lm, "field", f"the length field {name!r} must be an unscaled integer",
                      "give it type B or H")
    want = total if counts == "frame" else sum(x.size for x in fields)
    lo, hi = _int_range(f.code, f.size)
    if not lo <= want <= hi:
        raise S.error(lm, "field", f"the frame length {want} does not fit the length field's type {f.code}")
    if f.value is not None and f.value != want:
        raise S.error(lm, "field", f"field {name!r} has value {f.value} but the frame is {want} bytes",
                      "remove 'value' (the length is checked anyway)")
    return [Field(x.name, x.code, x.size, x.offset, x.scale, x.unit, want) if x is f else x for x in fields]


__all__ = ["CHECKSUMS", "Field", "FrameSpec", "INERTIAL", "UNITS", "parse_frame_spec", "role"]
