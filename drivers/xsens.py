"""Xsens MT low-level binary protocol: framing, configuration messages, MTData2 encoding.

Frame layout (all multi-byte fields big-endian)::

    PRE(0xFA) BID(0xFF) MID LEN [EXTLEN(u16) if LEN == 0xFF] DATA[n] CS

The checksum makes ``(BID + MID + LEN [+ EXTLEN bytes] + sum(DATA) + CS) mod 256 == 0``;
the preamble is excluded. An MTData2 payload is a sequence of items
``XDI(u16) | size(u8) | data[size]``; the low two XDI bits select the precision
(0 float32, 1 FP12.20, 2 FP16.32, 3 float64) and bits 2-3 the coordinate system.

This module is pure (no I/O). The vectorised decoder lives in
:mod:`rigctl.drivers.xsens_decode`; it re-exports nothing from here to keep the import graph flat.

Units on the wire follow Xsens: acceleration m/s^2, rate of turn rad/s, temperature degC,
DeltaV m/s, DeltaQ unit quaternion increment, SampleTimeFine in 1e-4 s ticks (10 kHz).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from rigctl.errors import DeviceError, InputError

PREAMBLE = 0xFA
BID_MASTER = 0xFF
MAX_STD_LEN = 254
MAX_EXT_LEN = 2048
#: Largest frame we ever accept: PRE BID MID 0xFF EXTLEN(2) DATA CS.
MAX_FRAME_BYTES = 7 + MAX_EXT_LEN
#: Bits on the wire per byte for 8N1 framing (start + 8 data + stop).
BITS_PER_BYTE_8N1 = 10
#: SampleTimeFine tick rate, Hz.
SAMPLE_TIME_FINE_HZ = 10_000
#: Default SampleTimeFine modulus (u32 counter). MTi-10/100 wrap after one day (864_000_000);
#: pass that to the decoder when talking to such a device.
SAMPLE_TIME_FINE_WRAP = 1 << 32


class MID(IntEnum):
    """Message identifiers used here (acknowledgement = MID + 1)."""

    REQ_DID = 0x00
    DEVICE_ID = 0x01
    GO_TO_MEASUREMENT = 0x10
    GO_TO_MEASUREMENT_ACK = 0x11
    GO_TO_CONFIG = 0x30
    GO_TO_CONFIG_ACK = 0x31
    MTDATA = 0x32
    MTDATA2 = 0x36
    WAKE_UP = 0x3E
    WAKE_UP_ACK = 0x3F
    RESET = 0x40
    RESET_ACK = 0x41
    ERROR = 0x42
    SET_OUTPUT_CONFIGURATION = 0xC0
    SET_OUTPUT_CONFIGURATION_ACK = 0xC1


class ErrorCode(IntEnum):
    """Payload byte of an Error (0x42) message."""

    INVALID_PERIOD = 0x03
    INVALID_MESSAGE = 0x04
    TIMER_OVERFLOW = 0x1E
    INVALID_BAUDRATE = 0x20
    INVALID_PARAMETER = 0x21
    DEVICE_ERROR = 0x28


class XDI(IntEnum):
    """MTData2 data identifiers (base type, precision/coordinate bits cleared)."""

    TEMPERATURE = 0x0810
    PACKET_COUNTER = 0x1020
    SAMPLE_TIME_FINE = 0x1060
    DELTA_V = 0x4010
    ACCELERATION = 0x4020
    RATE_OF_TURN = 0x8020
    DELTA_Q = 0x8030
    STATUS_WORD = 0xE020


class Precision(IntEnum):
    """Low two XDI bits."""

    FLOAT32 = 0
    FP1220 = 1
    FP1632 = 2
    FLOAT64 = 3


PRECISION_BYTES = {Precision.FLOAT32: 4, Precision.FP1220: 4, Precision.FP1632: 6, Precision.FLOAT64: 8}
#: Number of values per XDI for the real-valued types; None = integer type with a fixed size.
XDI_COMPONENTS: dict[int, int] = {
    XDI.TEMPERATURE: 1, XDI.DELTA_V: 3, XDI.ACCELERATION: 3, XDI.RATE_OF_TURN: 3, XDI.DELTA_Q: 4,
}
XDI_INT_SIZE: dict[int, int] = {XDI.PACKET_COUNTER: 2, XDI.SAMPLE_TIME_FINE: 4, XDI.STATUS_WORD: 4}
#: Field names used by the encoder/decoder for each XDI.
XDI_FIELD: dict[int, str] = {
    XDI.TEMPERATURE: "temperature", XDI.PACKET_COUNTER: "packet_counter",
    XDI.SAMPLE_TIME_FINE: "sample_time_fine", XDI.DELTA_V: "delta_v",
    XDI.ACCELERATION: "acceleration", XDI.RATE_OF_TURN: "rate_of_turn", XDI.DELTA_Q: "delta_q",
    XDI.STATUS_WORD: "status_word",
}


def split_xdi(xdi: int) -> tuple[int, int, int]:
    """Split an XDI into (base type = xdi & 0xFFF0, precision = xdi & 3, coordinate bits = xdi & 0xC)."""
    return xdi & 0xFFF0, xdi & 0x3, xdi & 0xC


def item_size(xdi: int) -> int | None:
    """Data size in bytes of a known XDI (with its precision bits), or None if unknown."""
    base, prec, _ = split_xdi(xdi)
    if base in XDI_INT_SIZE:
        return XDI_INT_SIZE[base] if (xdi & 0xF) == 0 else None
    if base in XDI_COMPONENTS:
        return XDI_COMPONENTS[base] * PRECISION_BYTES[Precision(prec)]
    return None


class XsensError(DeviceError, ValueError):
    """A malformed Xsens message (a device answering wrongly: exit code 1)."""


class RateDoesNotFitError(InputError, ValueError):
    """The configured MTData2 output does not fit the serial line's bandwidth (a setting of the
    rig config: exit code 2)."""


# ---------------------------------------------------------------------------------- framing

def checksum(body: bytes) -> int:
    """Checksum byte for ``body`` = BID..last data byte: ``(-sum(body)) & 0xFF``."""
    return (-sum(body)) & 0xFF


def build_message(mid: int, data: bytes = b"", bid: int = BID_MASTER) -> bytes:
    """Build one framed message; uses the extended length form for more than 254 data bytes."""
    n = len(data)
    if n > MAX_EXT_LEN:
        raise XsensError(f"payload of {n} bytes exceeds the {MAX_EXT_LEN}-byte maximum")
    if n <= MAX_STD_LEN:
        body = bytes((bid, mid, n)) + data
    else:
        body = bytes((bid, mid, 0xFF, n >> 8, n & 0xFF)) + data
    return bytes((PREAMBLE,)) + body + bytes((checksum(body),))


@dataclass(frozen=True)
class Message:
    """One decoded message."""

    mid: int
    data: bytes
    bid: int = BID_MASTER


def parse_message(frame: bytes) -> Message:
    """Parse exactly one complete frame; raises :class:`XsensError` on any defect."""
    if len(frame) < 5 or frame[0] != PREAMBLE:
        raise XsensError("not an Xsens frame (missing preamble or too short)")
    ln = frame[3]
    hdr = 4
    if ln == 0xFF:
        if len(frame) < 7:
            raise XsensError("truncated extended-length header")
        ln = (frame[4] << 8) | frame[5]
        hdr = 6
    if len(frame) != hdr + ln + 1:
        raise XsensError(f"frame length {len(frame)} does not match LEN {ln}")
    if sum(frame[1:]) & 0xFF:
        raise XsensError("checksum mismatch")
    return Message(mid=frame[2], data=bytes(frame[hdr:hdr + ln]), bid=frame[1])


def split_messages(buf: bytes) -> tuple[list[Message], int, int]:
    """Scalar resynchronising splitter for control traffic (acks, errors).

    Returns (messages, bytes_consumed, bad_frames). Incomplete data at the end is not consumed.
    For high-rate MTData2 streams use :class:`rigctl.drivers.xsens_decode.MTData2Stream`.
    """
    out: list[Message] = []
    i, n, bad = 0, len(buf), 0
    while True:
        j = buf.find(b"\xfa\xff", i)
        if j < 0:
            return out, (n - 1 if n and buf[-1] == PREAMBLE else n), bad
        if j + 4 > n:
            return out, j, bad
        ln, hdr = buf[j + 3], 4
        if ln == 0xFF:
            if j + 6 > n:
                return out, j, bad
            ln, hdr = (buf[j + 4] << 8) | buf[j + 5], 6
        end = j + hdr + ln + 1
        if ln > MAX_EXT_LEN:
            bad, i = bad + 1, j + 1
            continue
        if end > n:
            return out, j, bad
        if sum(buf[j + 1:end]) & 0xFF:
            bad, i = bad + 1, j + 1
            continue
        out.append(Message(mid=buf[j + 2], data=bytes(buf[j + hdr:end - 1]), bid=buf[j + 1]))
        i = end


# ----------------------------------------------------------------------- configuration msgs

def go_to_config() -> bytes:
    """GoToConfig request (``FA FF 30 00 D1``)."""
    return build_message(MID.GO_TO_CONFIG)


def go_to_measurement() -> bytes:
    """GoToMeasurement request (``FA FF 10 00 F1``)."""
    return build_message(MID.GO_TO_MEASUREMENT)


def req_did() -> bytes:
    """ReqDID request (``FA FF 00 00 01``); the device answers DeviceID (0x01)."""
    return build_message(MID.REQ_DID)


#: DeviceID payload sizes: 4 bytes (MTi-1/10/100, MTi-G), 8 bytes on newer devices.
DEVICE_ID_SIZES = (4, 8)


def encode_device_id(device_id: int) -> bytes:
    """DeviceID payload of ``device_id``: u32 big-endian, or u64 when it does not fit 32 bits."""
    if not 0 <= device_id < 1 << 64:
        raise XsensError(f"device ID {device_id} does not fit 64 bits")
    return struct.pack(">I" if device_id < 1 << 32 else ">Q", device_id)


def decode_device_id(data: bytes) -> str:
    """The DeviceID payload as Xsens prints it: upper-case hex, two digits per byte
    (``03780001``; 16 digits for an 8-byte ID). Raises XsensError on another size."""
    if len(data) not in DEVICE_ID_SIZES:
        raise XsensError(f"DeviceID payload of {len(data)} bytes (expected 4 or 8)")
    return data.hex().upper()


def ack_for(mid: int, data: bytes = b"") -> bytes:
    """Acknowledgement of request ``mid`` (MID + 1)."""
    return build_message(mid + 1, data)


def error_message(code: int) -> bytes:
    """Error (0x42) message with one code byte."""
    return build_message(MID.ERROR, bytes((code,)))


#: Output-configuration frequency meaning "every packet / maximum rate".
FREQ_MAX = 0xFFFF


@dataclass(frozen=True)
class OutputItem:
    """One SetOutputConfiguration entry: an XDI (with precision bits) and its rate in Hz."""

    xdi: int
    freq_hz: int = FREQ_MAX


def encode_output_configuration(items: list[OutputItem]) -> bytes:
    """Payload of SetOutputConfiguration: N x (XDI u16, freq u16), big-endian."""
    return b"".join(struct.pack(">HH", it.xdi, it.freq_hz) for it in items)


def decode_output_configuration(data: bytes) -> list[OutputItem]:
    """Inverse of :func:`encode_output_configuration`; raises XsensError on a ragged payload."""
    if len(data) % 4:
        raise XsensError(f"output configuration payload of {len(data)} bytes is not a multiple of 4")
    return [OutputItem(x, f) for x, f in struct.iter_unpack(">HH", data)]


def set_output_configuration(items: list[OutputItem]) -> bytes:
    """SetOutputConfiguration (0xC0) request message."""
    return build_message(MID.SET_OUTPUT_CONFIGURATION, encode_output_configuration(items))


def resolve_output_rate(items: list[OutputItem], max_rate_hz: int) -> int:
    """Packet rate in Hz implied by a configuration: the highest explicit item rate.

    Items at FREQ_MAX (or 0) ride in every packet; if every item is FREQ_MAX the device's
    maximum rate ``max_rate_hz`` applies.
    """
    rates = [it.freq_hz for it in items if it.freq_hz not in (0, FREQ_MAX)]
    return max(rates) if rates else max_rate_hz


# ------------------------------------------------------------------------- bandwidth check

def mtdata2_frame_bytes(xdis: list[int]) -> int:
    """Bytes on the wire of one MTData2 frame carrying ``xdis`` (header + items + checksum)."""
    payload = 0
    for x in xdis:
        size = item_size(x)
        if size is None:
            raise XsensError(f"unknown data ID 0x{x:04X}")
        payload += 3 + size
    return payload + (5 if payload <= MAX_STD_LEN else 7)


def check_rate_fits(xdis: list[int], rate_hz: float, baudrate: int,
                    bits_per_byte: int = BITS_PER_BYTE_8N1) -> float:
    """Check that MTData2 frames of ``xdis`` at ``rate_hz`` fit a serial line of ``baudrate``.

    Required bit rate = frame_bytes * bits_per_byte * rate_hz (bit/s). Returns the line load
    (fraction of the baud rate, <= 1) or raises :class:`RateDoesNotFitError` with the numbers.
    """
    nbytes = mtdata2_frame_bytes(xdis)
    need = nbytes * bits_per_byte * rate_hz
    if need > baudrate:
        raise RateDoesNotFitError(
            f"MTData2 output at {rate_hz:g} Hz needs {nbytes} bytes/frame x {bits_per_byte} bit/byte "
            f"x {rate_hz:g} Hz = {need:,.0f} bit/s, more than the {baudrate:,} baud line carries; "
            f"lower the rate (max {baudrate / (nbytes * bits_per_byte):.0f} Hz), drop fields or raise the baud rate")
    return need / baudrate


# ----------------------------------------------------------------------- MTData2 encoding

def _encode_real(values: np.ndarray, prec: int) -> np.ndarray:
    """Encode real values (N, k) at a precision as big-endian bytes (N, k*size)."""
    v = np.asarray(values, dtype=np.float64)
    n, k = v.shape
    if prec == Precision.FLOAT32:
        return v.astype(">f4").view(np.uint8).reshape(n, 4 * k)
    if prec == Precision.FLOAT64:
        return v.astype(">f8").view(np.uint8).reshape(n, 8 * k)
    if prec == Precision.FP1220:
        return np.round(v * (1 << 20)).astype(">i4").view(np.uint8).reshape(n, 4 * k)
    fixed = np.round(v * 2.0**32).astype(np.int64)          # FP16.32: u32 fraction then i16 int
    out = np.empty((n, k, 6), dtype=np.uint8)
    out[..., :4] = (fixed & 0xFFFFFFFF).astype(">u4").view(np.uint8).reshape(n, k, 4)
    out[..., 4:] = (fixed >> 32).astype(">i2").view(np.uint8).reshape(n, k, 2)
    return out.reshape(n, 6 * k)


def encode_mtdata2(xdis: list[int], fields: dict[str, np.ndarray]) -> np.ndarray:
    """Encode N MTData2 frames with one fixed layout; returns a (N, frame_bytes) uint8 array.

    ``fields`` maps the names of :data:`XDI_FIELD` to arrays: packet_counter (N,) taken mod 2^16,
    sample_time_fine (N,) ticks taken mod 2^32, status_word (N,), acceleration/rate_of_turn/
    delta_v (N,3), delta_q (N,4), temperature (N,). ``frames.tobytes()`` is the wire stream.
    """
    n = None
    for v in fields.values():
        n = len(v)
        break
    if n is None:
        raise XsensError("no fields to encode")
    length = mtdata2_frame_bytes(xdis)
    payload = length - (5 if length - 5 <= MAX_STD_LEN else 7)
    out = np.empty((n, length), dtype=np.uint8)
    if length - 5 <= MAX_STD_LEN:
        out[:, :4] = (PREAMBLE, BID_MASTER, MID.MTDATA2, payload)
        pos = 4
    else:
        out[:, :6] = (PREAMBLE, BID_MASTER, MID.MTDATA2, 0xFF, payload >> 8, payload & 0xFF)
        pos = 6
    for x in xdis:
        base, prec, _ = split_xdi(x)
        size = item_size(x)
        assert size is not None
        out[:, pos:pos + 3] = (x >> 8, x & 0xFF, size)
        pos += 3
        name = XDI_FIELD[base]
        if name not in fields:
            raise XsensError(f"field {name!r} needed for data ID 0x{x:04X} is missing")
        val = np.asarray(fields[name])
        if base in XDI_INT_SIZE:
            mod = 1 << (8 * size)
            ints = np.asarray(val, dtype=np.int64) % mod
            dt = ">u2" if size == 2 else ">u4"
            out[:, pos:pos + size] = ints.astype(dt).view(np.uint8).reshape(n, size)
        else:
            out[:, pos:pos + size] = _encode_real(val.reshape(n, -1), prec)
        pos += size
    # checksum: CS = -sum(BID..last data) mod 256
    s = out[:, 1:-1].sum(axis=1, dtype=np.uint64)
    out[:, -1] = ((-s.astype(np.int64)) & 0xFF).astype(np.uint8)
    return out
