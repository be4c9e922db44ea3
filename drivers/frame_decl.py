"""Declarative frames (rigctl.config.frame_spec): vectorised decoder and encoder of a described frame.

Binary: a :class:`~rigctl.drivers.frame_engine.FixedFrameStream` whose fixed bytes are the sync
bytes and every field with a ``value`` (a length field included), whose check is the described
checksum over the block of frames (position tables, :func:`frame_engine.affine_tables`), and
whose decode is one structured-dtype view of the rows (field -> float64 x scale x unit factor:
SI). CSV lines: split per line (a text protocol is slow anyway; its rates are low).

``decode`` output: {field name: (n,) float64 in SI (counter / time raw integers as int64 for
integer fields before scaling: ``counter`` int64; ``time`` float64 s)}, plus ``offset``.
"""
from __future__ import annotations

import functools
import zlib

import numpy as np

from rigctl.config.frame_spec import CHECKSUM_BYTES, FrameSpec

from .frame_engine import FixedFrameStream, FrameCounters, affine_tables, xor_reduce_lookup
from .lost_lines import LostLines


def crc16_ccitt(data: bytes, init: int = 0xFFFF) -> int:
    """CRC-16 polynomial 0x1021, MSB first, initial value ``init``, no final XOR."""
    crc = init
    for x in data:
        crc ^= x << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def checksum_function(spec: FrameSpec):
    """The scalar checksum of the covered bytes (for tables and reference)."""
    if spec.checksum == "xor8":
        return lambda d: np.bitwise_xor.reduce(np.frombuffer(d, np.uint8)) if d else 0
    if spec.checksum == "sum8":
        return lambda d: sum(d) & 0xFF
    if spec.checksum == "crc16-ccitt":
        init = spec.checksum_init if spec.checksum_init is not None else 0xFFFF
        return lambda d: crc16_ccitt(d, init)
    if spec.checksum == "crc32":
        return lambda d: zlib.crc32(d) & 0xFFFFFFFF
    return None


def _struct_dtype(spec: FrameSpec) -> np.dtype:
    e = "<" if spec.endian == "little" else ">"
    names, formats, offsets = [], [], []
    for f in spec.fields:
        if f.code == "x":
            continue
        names.append(f.name)
        formats.append(e + f.code)
        offsets.append(f.offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": spec.length})


class Checker:
    """Vectorised checksum of a spec over (k, L) frame rows: ``computed(rows)`` and ``stored(rows)``."""

    def __init__(self, spec: FrameSpec) -> None:
        self.spec = spec
        self.a, self.b = spec.checksum_from, spec.checksum_offset
        self.nbytes = CHECKSUM_BYTES[spec.checksum]
        fn = checksum_function(spec)
        self.table, self.c0 = (None, 0)
        if spec.checksum in ("xor8", "crc16-ccitt", "crc32"):
            dt = {1: np.uint8, 2: np.uint16, 4: np.uint32}[self.nbytes]
            self.table, self.c0 = affine_tables(fn, self.b - self.a, dt)
        self.stored_dtype = np.dtype(("<" if spec.endian == "little" else ">") + f"u{self.nbytes}") \
            if self.nbytes else None

    def computed(self, rows: np.ndarray) -> np.ndarray:
        cols = rows[:, self.a:self.b]
        if self.spec.checksum == "sum8":
            return cols.sum(axis=1, dtype=np.uint8)
        return xor_reduce_lookup(self.table, cols) ^ self.table.dtype.type(self.c0)

    def stored(self, rows: np.ndarray) -> np.ndarray:
        raw = np.ascontiguousarray(rows[:, self.b:self.b + self.nbytes])
        return raw.view(self.stored_dtype)[:, 0]

    def __call__(self, rows: np.ndarray) -> np.ndarray:
        if self.nbytes == 0:
            return np.ones(rows.shape[0], dtype=bool)
        return self.computed(rows) == self.stored(rows)


@functools.lru_cache(maxsize=32)
def checker(spec: FrameSpec) -> Checker:
    """The (cached) checker of a spec: its tables cost 8 x length scalar checksums to build."""
    return Checker(spec)


def binary_decoder(spec: FrameSpec) -> FixedFrameStream:
    """Streaming vectorised decoder of a binary spec (see the module docstring)."""
    dtype = _struct_dtype(spec)
    e = "<" if spec.endian == "little" else ">"
    fixed = list(enumerate(spec.sync))
    for f in spec.fields:
        if f.value is not None:
            raw = np.array([f.value], dtype=e + f.code).view(np.uint8)
            fixed += [(f.offset + j, int(v)) for j, v in enumerate(raw)]
    check = checker(spec)
    fields = [f for f in spec.fields if f.code != "x"]

    def decode(rows: np.ndarray) -> dict[str, np.ndarray]:
        rec = np.ascontiguousarray(rows).view(dtype)[:, 0] if rows.shape[0] else np.zeros(0, dtype)
        out: dict[str, np.ndarray] = {}
        for f in fields:
            v = rec[f.name]
            if f.name == "counter" or (f.name == "time" and f.code in "bBhHiIqQ"):
                out[f.name] = v.astype(np.int64)
            else:
                out[f.name] = v.astype(np.float64) * f.factor
        return out

    return FixedFrameStream(spec.length, fixed, check, decode)


def encode_binary(spec: FrameSpec, values: dict[str, np.ndarray]) -> np.ndarray:
    """(n, L) uint8 frames of ``values`` (SI for scaled fields; raw integers for ``counter``
    and an integer ``time`` field; fields not given are 0), with sync, fixed values and checksum."""
    n = len(next(iter(values.values())))
    dtype = _struct_dtype(spec)
    rec = np.zeros(n, dtype=dtype)
    for f in spec.fields:
        if f.code == "x":
            continue
        if f.value is not None:
            rec[f.name] = f.value
            continue
        if f.name not in values:
            continue
        v = np.asarray(values[f.name])
        if f.name == "counter" or (f.name == "time" and f.code in "bBhHiIqQ"):
            rec[f.name] = (v.astype(np.int64) % f.wrap).astype(rec.dtype[f.name])
        elif f.code in "bBhHiIqQ":
            info = np.iinfo(rec.dtype[f.name])
            rec[f.name] = np.clip(np.rint(v / f.factor), info.min, info.max).astype(rec.dtype[f.name])
        else:
            rec[f.name] = v / f.factor
    rows = rec.view(np.uint8).reshape(n, spec.length).copy()
    rows[:, :len(spec.sync)] = np.frombuffer(spec.sync, np.uint8)
    check = checker(spec)
    if check.nbytes:
        c = check.computed(rows).astype(check.stored_dtype)
        rows[:, check.b:check.b + check.nbytes] = c.view(np.uint8).reshape(n, check.nbytes)
    return rows


# --------------------------------------------------------------------------------- CSV lines
def nmea_checksum(body: bytes) -> int:
    c = 0
    for x in body:
        c ^= x
    return c


class CsvStream:
    """Streaming decoder of CSV lines: ``feed(bytes) -> dict`` as the binary decoder's; counts
    lines that fail (wrong column count, not a number, checksum) as bad frames, by the bytes
    between good lines (:class:`rigctl.drivers.lost_lines.LostLines`: a damaged sentence leaves
    all its bytes, whatever the error made of them, a line end or a ``$``, and bytes after a
    whole sentence's checksum, a hit line end, are no line), counted as they come. With an
    NMEA checksum a line is also cut before each ``$`` (:meth:`_pieces`)."""

    def __init__(self, spec: FrameSpec) -> None:
        self.spec = spec
        self.counters = FrameCounters()
        self._buf = b""
        self._synced = False
        self._abs = 0
        self._lost = LostLines()  # lines lost between good lines (by their bytes)
        self.cols = [f for f in spec.fields]

    def _line(self, line: bytes) -> list[float] | None:
        s = self.spec
        if s.checksum == "nmea":
            if b"*" not in line or not line.startswith(b"$"):
                return None
            body, ck = line[1:].split(b"*", 1)
            try:            # the sentence ends with the two hex digits (bytes after them: a hit line end)
                if len(ck) < 2 or int(ck[:2], 16) != nmea_checksum(body):
                    return None
            except ValueError:
                return None
            line = b"$" + body
        parts = line.decode("ascii", "replace").split(",")
        if s.prefix:
            if parts[0] != s.prefix:
                return None
            parts = parts[1:]
        if len(parts) != len(self.cols):
            return None
        try:
            return [float(p) for p in parts]
        except ValueError:
            return None

    def _pieces(self, raw: bytes) -> list[bytes]:
        """A line cut before every ``$`` after its first byte: NMEA sentences start with ``$``,
        so a line end lost to a byte error merges two lines, and the second is still whole."""
        if self.spec.checksum != "nmea" or raw.find(b"$", 1) < 0:
            return [raw]
        out, i = [], 0
        while (j := raw.find(b"$", i + 1)) >= 0:
            out.append(raw[i:j])
            i = j
        return out + [raw[i:]]

    def feed(self, data: bytes, final: bool = False) -> dict[str, np.ndarray]:
        buf = self._buf + bytes(data)
        lines = buf.split(b"\n")
        self._buf = b"" if final else lines.pop()
        rows, offsets, pos = [], [], self._abs
        for raw in lines:
            start = pos
            pos += len(raw) + 1
            if not raw.rstrip(b"\r"):
                continue
            pieces = self._pieces(raw)
            for k, piece in enumerate(pieces):
                size = len(piece) + (k == len(pieces) - 1)          # the line end with the last
                vals = self._line(piece.rstrip(b"\r"))
                if vals is None:
                    if self._synced:
                        self.counters.garbage_bytes += size
                        self.counters.bad_frames += self._lost.garbage(size)
                    else:
                        self.counters.presync_bytes += size
                else:
                    self._synced = True
                    self._lost.good(size)
                    rows.append(vals)
                    offsets.append(start)
                start += len(piece)
        if final:
            self._lost.end()
        self._abs = pos
        arr = np.asarray(rows, dtype=np.float64).reshape(len(rows), len(self.cols))
        out: dict[str, np.ndarray] = {"offset": np.asarray(offsets, dtype=np.int64)}
        for j, f in enumerate(self.cols):
            if f.name == "counter":
                out[f.name] = arr[:, j].astype(np.int64)
            else:
                out[f.name] = arr[:, j] * f.factor
        self.counters.frames += len(rows)
        return out

    def flush(self) -> dict[str, np.ndarray]:
        return self.feed(b"", final=True)


def encode_csv(spec: FrameSpec, values: dict[str, np.ndarray]) -> bytes:
    """CSV lines of ``values`` (SI; ``counter`` raw), 7 significant digits."""
    n = len(next(iter(values.values())))
    cols = []
    for f in spec.fields:
        v = np.asarray(values.get(f.name, np.zeros(n)))
        if f.name == "counter":
            cols.append([str(int(x)) for x in v])
        else:
            cols.append([f"{x:.7g}" for x in v / f.factor])
    out = []
    for i in range(n):
        body = ",".join(([spec.prefix] if spec.prefix else []) + [c[i] for c in cols])
        if spec.checksum == "nmea":
            body = f"{body}*{nmea_checksum(body[1:].encode()):02X}"
        out.append(body + "\r\n")
    return "".join(out).encode("ascii")


def decoder(spec: FrameSpec):
    return binary_decoder(spec) if spec.format == "binary" else CsvStream(spec)


def encode(spec: FrameSpec, values: dict[str, np.ndarray]) -> bytes:
    return encode_binary(spec, values).tobytes() if spec.format == "binary" else encode_csv(spec, values)


__all__ = ["Checker", "CsvStream", "binary_decoder", "checksum_function", "crc16_ccitt", "decoder",
           "encode", "encode_binary", "encode_csv"]
