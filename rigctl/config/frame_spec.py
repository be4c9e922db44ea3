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
        - {name: gx, type: i, scale: 1.0e-7, unit: rad/s}
        - ...
        - {name: temperature, type: h, scale: 0.01, unit: degC}
      length: {field: length, counts: frame}           # or a number; optional
      checksum: {type: crc16-ccitt, init: 0xFFFF}      # none | xor8 | sum8 | crc16-ccitt | crc32

Field types are Python struct codes: b B h H i I q Q (integers), e f d (floats), ``Nx`` (N pad
bytes). A field may carry ``value:`` (an integer every frame holds, e.g. a message ID: it also
serves to find frames). Roles are by name: ``ax|ay|az`` (unit m/s^2, g or mg), ``gx|gy|gz``
(rad/s, deg/s, mrad/s) -- the axes' one spelling (:mod:`rigctl.sensor_axes`; the older names
``accel_x`` ... ``gyro_z`` are read as these, and the decoded fields carry the one spelling), ``temperature`` (degC), ``time`` (s, ms, us, ns; unwrapped at its
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
from dataclasses import MISSING, dataclass

from typing import Any, ClassVar

from .. import schema as S
from ..settings import Settings, entry, items, number, parse, setting, text
from ..sensor_axes import AXES, SENSOR, canonical
from ..yamlio import LocDict

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
INERTIAL = AXES
NAME = re.compile(r"^[a-z_][a-z0-9_]{0,31}$")


def role(name: str) -> str | None:
    """'accel' or 'gyro' for an axis (ax ... gz, or an older spelling such as gyro_x), the name
    itself for temperature, time and counter, else None (decoded and ignored)."""
    axis = canonical(name)
    if axis is not None:
        return SENSOR[axis]
    return name if name in ("temperature", "time", "counter") else None


def field_name(name: str) -> str:
    """The name a field is decoded under: an axis in its one spelling, anything else as given."""
    return canonical(name) or name


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


def _hexbytes(m: LocDict, key: str, default: bytes | None = None) -> bytes:
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


def _int_range(code: str, size: int) -> tuple[int, int]:
    bits = 8 * size
    return (0, (1 << bits) - 1) if code.isupper() else (-(1 << (bits - 1)), (1 << (bits - 1)) - 1)


@dataclass(frozen=True, kw_only=True)
class ColumnSettings(Settings):
    """A ``fields`` entry of a csv frame: one decimal column (``name``, ``scale``, ``unit``)."""

    EXTRA_KEYS: ClassVar[tuple[str, ...]] = ("type", "value")  # refused below, with the reason
    name: str = text()
    scale: float = number(1.0)
    #: required for a role's field (ax ... gz, temperature, time), one of UNITS[role]
    unit: str | None = text(None)

    def check(self, d: LocDict) -> None:
        if "type" in d:
            raise S.error(d, "type", "a csv column has no 'type' (every column is a decimal number)",
                          "remove 'type'")
        self._check_named(d, is_float=False)
        if "value" in d:
            raise S.error(d, "value", "'value' fixes an integer field of a binary frame",
                          "remove 'value', or give the field an integer type")

    def _check_named(self, d: LocDict, is_float: bool) -> None:
        name, r = self.name, role(self.name)
        if not NAME.match(name):
            raise S.error(d, "name", f"field name {name!r} is not a plain lower-case name",
                          "e.g. gx, ay, temperature, counter, time, status")
        if self.scale == 0:
            raise S.error(d, "scale", "'scale' is 0: every value would read as 0", "give the LSB weight, e.g. 1.0e-7")
        if r in UNITS:
            if self.unit is None:
                raise S.error(d, None, f"field {name!r} has no 'unit'",
                              f"add unit: one of {', '.join(UNITS[r])} (the unit of raw x scale)")
            if self.unit not in UNITS[r]:
                raise S.error(d, "unit", f"'unit' = {self.unit!r} is not allowed",
                              S.did_you_mean(self.unit, UNITS[r], "choose one of"))
        if r == "counter" and (is_float or self.scale != 1.0):
            raise S.error(d, "type" if is_float else "scale",
                          "the counter must be an unscaled integer field", "use type B, H, I or Q and no scale")

    def field(self, offset: int) -> Field:
        """The column at ``offset`` (its index)."""
        return Field(field_name(self.name), "", 0, offset, self.scale, self.unit or "")


@dataclass(frozen=True, kw_only=True)
class BinaryFieldSettings(ColumnSettings):
    """A ``fields`` entry of a binary frame: a struct ``type`` (or ``Nx`` pad bytes) and
    optionally the ``value`` every frame holds."""

    EXTRA_KEYS: ClassVar[tuple[str, ...]] = ()
    type: str = text()
    value: int | None = number(None, integer=True)

    @property
    def pad(self) -> int:
        """Pad bytes (0: not a pad)."""
        m = re.fullmatch(r"(\d{0,3})x", self.type)
        return int(m.group(1) or 1) if m else 0

    @property
    def size(self) -> int:
        return self.pad or struct.calcsize("<" + self.type)

    def check(self, d: LocDict) -> None:
        if re.fullmatch(r"(\d{0,3})x", self.type):
            if self.pad == 0:
                raise S.error(d, "type", "'type' 0x pads nothing", "remove the entry or give e.g. 2x")
            return
        if len(self.type) != 1 or self.type not in INT_CODES + FLOAT_CODES:
            raise S.error(d, "type", f"'type' = {self.type!r} is not a struct code",
                          "use one of b B h H i I q Q (integers), e f d (floats) or Nx (N pad bytes)")
        is_float = self.type in FLOAT_CODES
        self._check_named(d, is_float)
        if self.value is not None:
            if is_float:
                raise S.error(d, "value", "'value' fixes an integer field of a binary frame",
                              "remove 'value', or give the field an integer type")
            lo, hi = _int_range(self.type, self.size)
            if not lo <= self.value <= hi:
                raise S.error(d, "value", f"'value' {self.value} does not fit type {self.type} ({lo}..{hi})")

    def field(self, offset: int) -> Field:
        """The field at byte ``offset``."""
        if self.pad:
            return Field(self.name, "x", self.pad, offset, 1.0, "")
        return Field(field_name(self.name), self.type, self.size, offset, self.scale, self.unit or "", self.value)


@dataclass(frozen=True, kw_only=True)
class ChecksumSettings(Settings):
    """``checksum:`` of a binary frame (a type, or a mapping with ``init`` and ``from``)."""

    type: str = text(choices=CHECKSUMS)
    init: int | None = number(None, minimum=0, maximum=0xFFFF, integer=True)
    #: first byte covered (None: the first byte after the sync bytes)
    start: int | None = number(None, key="from", minimum=0, integer=True)

    def check(self, d: LocDict) -> None:
        if self.init is not None and self.type != "crc16-ccitt":
            raise S.error(d, "init", f"'init' applies to crc16-ccitt, not {self.type}", "remove 'init'")


def _checksum(m: LocDict, key: str, default: Any = None) -> ChecksumSettings:
    c = m[key]
    if isinstance(c, str):
        c = LocDict({"type": c})
        c.file, c.line = m.file, m.line_of(key)
    return parse(ChecksumSettings, S.require_mapping(c, f"'{key}'", m, key), f"'{key}'")


@dataclass(frozen=True, kw_only=True)
class LengthSettings(Settings):
    """``length: {field, counts}``: the field that holds the frame length (sync to checksum:
    ``frame``; the bytes of the field list: ``fields``)."""

    field: str = text()
    counts: str = text("frame", choices=("frame", "fields"))


def _length(m: LocDict, key: str, default: Any = None) -> int | LengthSettings:
    v = m[key]
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return S.get_number(m, key, integer=True, minimum=1)
    return parse(LengthSettings, S.require_mapping(v, f"'{key}'", m, key), f"'{key}'")


FIELD_HINT = "e.g. {name: gx, type: i, scale: 1.0e-7, unit: rad/s}"


@dataclass(frozen=True, kw_only=True)
class BinaryFrameSettings(Settings):
    """``frame:`` with ``format: binary`` (the module docstring)."""

    format: str = text("binary", choices=("binary", "csv"))
    sync: bytes = setting(read=_hexbytes)
    endian: str = text("little", choices=("little", "big"))
    fields: tuple[BinaryFieldSettings, ...] = items(BinaryFieldSettings, "'fields'", MISSING, min_length=1,
                                                         hint=FIELD_HINT)
    #: None: not declared; a number: the whole frame's bytes; or the field holding it
    length: int | LengthSettings | None = setting(None, read=_length)
    checksum: ChecksumSettings | None = setting(None, read=_checksum)


@dataclass(frozen=True, kw_only=True)
class CsvFrameSettings(Settings):
    """``frame:`` with ``format: csv`` (the module docstring)."""

    format: str = text("binary", choices=("binary", "csv"))
    prefix: str = text("")
    fields: tuple[ColumnSettings, ...] = items(ColumnSettings, "'fields'", MISSING, min_length=1,
                                               hint="e.g. {name: gx, scale: 1.0e-7, unit: rad/s}")
    checksum: str = text("none", choices=("none", "nmea"))

    def check(self, d: LocDict) -> None:
        if "," in self.prefix:
            raise S.error(d, "prefix", "'prefix' is one column and cannot hold a comma")
        if self.checksum == "nmea" and not self.prefix.startswith("$"):
            raise S.error(d, "checksum", "an NMEA checksum covers the bytes after '$'",
                          "start the prefix with '$' (e.g. prefix: $IMU) or use checksum: none")


def _check_names(m: LocDict, cols: tuple[ColumnSettings, ...]) -> None:
    """Each name once; the six inertial fields and a time or a counter."""
    seen: dict[str, str] = {}  # name decoded under -> the name as given
    for i, c in enumerate(cols):
        if isinstance(c, BinaryFieldSettings) and c.pad:
            continue
        name = field_name(c.name)
        if name in seen:
            again = "" if seen[name] == c.name else f" ({seen[name]!r} and {c.name!r} name the same axis)"
            raise S.error(entry(m, "fields", i), "name", f"field {name!r} appears twice{again}",
                          "give each field its own name")
        seen[name] = c.name
    missing = [n for n in INERTIAL if n not in seen]
    if missing:
        raise S.error(m, "fields", f"the frame has no {', '.join(missing)}",
                      f"add a field for each of {', '.join(INERTIAL)}")
    if "time" not in seen and "counter" not in seen:
        raise S.error(m, "fields", "the frame has neither 'time' nor 'counter'",
                      "add a counter (type H or I) or a time field: the run needs each sample's time")


def parse_frame_spec(section: LocDict, key: str = "frame") -> FrameSpec:
    """The ``frame:`` mapping of ``section`` as a :class:`FrameSpec` (read by
    :func:`rigctl.settings.parse` as :class:`BinaryFrameSettings` or :class:`CsvFrameSettings`,
    then the rules across fields); InputError with file, line and what to fix."""
    if key not in section:
        raise S.error(section, None, f"'imu' (frame) is missing '{key}'",
                      "describe the frame: sync, endian, fields, checksum (docs/hardware.md)")
    m = S.require_mapping(section[key], f"'{key}'", section, key)
    fmt = S.get_str(m, "format", "binary", choices=("binary", "csv"))
    if fmt == "csv":
        c = parse(CsvFrameSettings, m, f"'{key}' (csv)")
        _check_names(m, c.fields)
        return FrameSpec("csv", tuple(f.field(i) for i, f in enumerate(c.fields)), checksum=c.checksum,
                         prefix=c.prefix)
    b = parse(BinaryFrameSettings, m, f"'{key}' (binary)")
    fields, offset = [], len(b.sync)
    for f in b.fields:
        fields.append(f.field(offset))
        offset += f.size
    _check_names(m, b.fields)
    ck, init, start = "none", None, len(b.sync)
    if b.checksum is not None:
        ck = b.checksum.type
        init = b.checksum.init if b.checksum.init is not None else (0xFFFF if ck == "crc16-ccitt" else None)
        if b.checksum.start is not None:
            start = b.checksum.start
            if start > offset - 1:
                raise S.error(m["checksum"], "from", f"'from' = {start} is above its maximum {offset - 1}")
    total = offset + CHECKSUM_BYTES[ck]
    fields = _with_length(m, b.length, fields, total)
    return FrameSpec("binary", tuple(fields), sync=b.sync, endian=b.endian, checksum=ck, checksum_init=init,
                     checksum_from=start, length=total)


def _with_length(m: LocDict, length: int | LengthSettings | None, fields: list[Field], total: int) -> list[Field]:
    """The fields, the length field holding the frame's length (checked against the fields)."""
    if length is None:
        return fields
    if isinstance(length, int):
        if length != total:
            raise S.error(m, "length", f"'length' is {length} bytes but the fields, sync and checksum make {total}",
                          "fix the field types or the length")
        return fields
    lm, name = m["length"], length.field
    f = next((x for x in fields if x.name == name), None)
    if f is None:
        raise S.error(lm, "field", f"'length' names field {name!r}, which the frame does not have",
                      S.did_you_mean(name, [x.name for x in fields], "fields"))
    if f.code not in INT_CODES or f.scale != 1.0:
        raise S.error(lm, "field", f"the length field {name!r} must be an unscaled integer",
                      "give it type B or H")
    want = total if length.counts == "frame" else sum(x.size for x in fields)
    lo, hi = _int_range(f.code, f.size)
    if not lo <= want <= hi:
        raise S.error(lm, "field", f"the frame length {want} does not fit the length field's type {f.code}")
    if f.value is not None and f.value != want:
        raise S.error(lm, "field", f"field {name!r} has value {f.value} but the frame is {want} bytes",
                      "remove 'value' (the length is checked anyway)")
    return [Field(x.name, x.code, x.size, x.offset, x.scale, x.unit, want) if x is f else x for x in fields]


__all__ = ["CHECKSUMS", "BinaryFrameSettings", "CsvFrameSettings", "Field", "FrameSpec", "INERTIAL", "UNITS",
           "parse_frame_spec", "role"]
