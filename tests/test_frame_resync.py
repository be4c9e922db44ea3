"""Resynchronisation of the IMU stream decoders after one corrupted byte: the Xsens MTData2
decoder, VectorNav's binary output and the declarative frame (CRC-16 and an 8-bit sum), one
harness for all.

A stream of good frames has one byte of one frame (the host) XORed with a value, at every
position of that frame (sync/preamble, bus id, message id, length -- a length longer than the
frame, the extended-length marker 0xFF --, payload, checksum), and is fed to the decoder whole,
byte by byte and in random pieces. The expectation is the analysis of a byte-wise parser written
here: after a frame fails its check or claims an impossible length, the parser rescans from the
byte after its preamble, so the corrupted frame is the only one lost -- every other frame comes
out, in order, and the decoder counts exactly one frame lost -- however the bytes arrive.

Data are data: a payload can hold the bytes of a frame header. The hard cases are frames whose
payload carries a false frame whose check passes (``false_into_next``: a false frame that starts
in the host and ends in the next, good frame; ``false_inside``: a short false frame within the
host). With the host corrupted, a parser that takes the first frame that checks would take the
false one and lose the next good frame (``false_into_next``), or count the host twice
(``false_inside``): this is how a 1e-4 byte-error run over a pty (tests/test_hil_faults.py)
counted one frame lost more than the emulator hit. The false frames are crafted with the
checksums written here (sum, binascii.crc_hqx), not with the decoders' code.
"""
from __future__ import annotations

import binascii
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
import pytest

from rigctl.config.frame_spec import parse_frame_spec
from rigctl.drivers import frame_decl
from rigctl.drivers import vectornav as V
from rigctl.drivers import xsens as X
from rigctl.drivers.vectornav_imu import LAYOUT as VN_LAYOUT
from rigctl.drivers.xsens_decode import MTData2Stream
from rigctl.sim.frame_server import EXAMPLE, EXAMPLE_CSV
from rigctl.yamlio import LocDict

N_FRAMES = 5      # frames 0..4; the host is frame 1: one good frame before it, three after
HOST = 1
ID0 = 1000        # identity (counter / time stamp) of frame 0


@dataclass(frozen=True)
class Proto:
    """One frame format, as the test sees it (all checks are written here)."""

    name: str
    good_rows: Callable[[], np.ndarray]       # (N_FRAMES, L) uint8, frame i carrying identity ID0 + i
    reseal: Callable[[np.ndarray], None]      # recompute one frame's checksum in place
    passes: Callable[[bytes], bool]           # does a frame of these bytes pass its check
    parts: dict[str, list[int]]               # named byte positions of a frame
    false_header: Callable[[int], bytes]      # header of a false frame of n bytes
    false_spans: dict[str, tuple[int, int, list[int]]]   # variant -> (offset in host, length, free bytes)
    decode: Callable[[list[bytes]], tuple[list[int], int, int]]   # chunks -> (identities, lost counted, messages)


# ----------------------------------------------------------------------------------- Xsens
XS_ITEMS = [X.XDI.PACKET_COUNTER, X.XDI.SAMPLE_TIME_FINE, X.XDI.ACCELERATION, X.XDI.RATE_OF_TURN,
            X.XDI.TEMPERATURE, X.XDI.STATUS_WORD]      # the driver's output (xsens_imu.output_items)


def _xs_rows() -> np.ndarray:
    rng = np.random.default_rng(5)
    n = N_FRAMES
    f = {"packet_counter": ID0 + np.arange(n), "sample_time_fine": 50_000 + 5 * np.arange(n),
         "acceleration": rng.normal(0, 9.8, (n, 3)), "rate_of_turn": rng.normal(0, 1, (n, 3)),
         "temperature": rng.normal(30, 1, n), "status_word": np.zeros(n, np.int64)}
    return X.encode_mtdata2(XS_ITEMS, f).copy()


def _xs_reseal(row: np.ndarray) -> None:
    row[-1] = (-int(row[1:-1].sum())) & 0xFF          # BID + MID + LEN + DATA + CS = 0 mod 256


def _xs_decode(chunks: list[bytes]) -> tuple[list[int], int, int]:
    st = MTData2Stream()
    ids: list[int] = []
    for c in chunks:
        ids += st.feed(c).counter.tolist()
    ids += st.flush().counter.tolist()
    c = st.counters
    return ids, c.bad_frames + c.truncated_frames, c.messages


# frame: FA FF 36 LEN | PC 4-8 | STF 9-15 | acc hdr 16-18 data 19-30 | gyro 31-33 data 34-45 |
#        temperature 46-52 | status 53-59 | CS 60
XSENS = Proto(
    name="xsens",
    good_rows=_xs_rows, reseal=_xs_reseal,
    passes=lambda f: len(f) >= 5 and sum(f[1:]) % 256 == 0,
    parts={"preamble": [0], "bus id": [1], "message id": [2], "length": [3], "payload": list(range(4, 60)),
           "checksum": [60]},
    # a false Error message (MID 0x42: no MTData2 structure to check, the 8-bit sum alone)
    false_header=lambda n: bytes([0xFA, 0xFF, 0x42, n - 5]),
    false_spans={"false_into_next": (21, 60, [19]),    # 21..81: ends 20 bytes into the next frame
                 "false_inside": (34, 20, [40])},      # 34..54, within the host's payload
    decode=_xs_decode,
)


# ------------------------------------------------------------------------------- VectorNav
def _vn_rows() -> np.ndarray:
    rng = np.random.default_rng(6)
    n = N_FRAMES
    f = {"time_startup_ns": (ID0 + np.arange(n)) * 1_250_000, "time_syncin_ns": rng.integers(0, 2**40, n),
         "syncin_count": np.arange(n), "uncomp_accel": rng.normal(0, 9.8, (n, 3)),
         "uncomp_gyro": rng.normal(0, 1, (n, 3)), "temperature": rng.normal(25, 1, n)}
    return V.encode(VN_LAYOUT, f).copy()


def _vn_reseal(row: np.ndarray) -> None:
    row[-2:] = np.frombuffer(binascii.crc_hqx(row[1:-2].tobytes(), 0).to_bytes(2, "big"), np.uint8)


def _vn_decode(chunks: list[bytes]) -> tuple[list[int], int, int]:
    st = V.decoder(VN_LAYOUT)
    ids: list[int] = []
    for c in chunks:
        ids += (st.feed(c)["time_startup_ns"] // 1_250_000).tolist()
    ids += (st.flush()["time_startup_ns"] // 1_250_000).tolist()
    return ids, st.counters.bad_frames + st.counters.truncated_frames, 0


VN_HDR = len(VN_LAYOUT.header)
VN_LEN = VN_LAYOUT.length
VECTORNAV = Proto(
    name="vectornav",
    good_rows=_vn_rows, reseal=_vn_reseal,
    passes=lambda f: binascii.crc_hqx(f[1:], 0) == 0,       # CRC-16/XMODEM over group .. CRC
    parts={"sync": [0], "group byte": [1], "field words": list(range(2, VN_HDR)),
           "payload": list(range(VN_HDR, VN_LEN - 2)), "checksum": [VN_LEN - 2, VN_LEN - 1]},
    false_header=lambda n: VN_LAYOUT.header,
    false_spans={"false_into_next": (VN_HDR + 22, VN_LEN, [VN_HDR + 18, VN_HDR + 19])},
    decode=_vn_decode,
)


# ------------------------------------------------------------------------ declarative frame
def _frame_spec(checksum):
    return parse_frame_spec(LocDict({"frame": LocDict({**EXAMPLE, "checksum": checksum})}))


def _fd_rows(spec) -> np.ndarray:
    rng = np.random.default_rng(7)
    n = N_FRAMES
    v = {"counter": ID0 + np.arange(n), "time": (ID0 + np.arange(n)) * 10_000}
    for ax in "xyz":
        v[f"g{ax}"], v[f"a{ax}"] = rng.normal(0, 1, n), rng.normal(0, 9.8, n)
    v["temperature"] = rng.normal(25, 1, n)
    return frame_decl.encode_binary(spec, v).copy()


def _fd_decode(spec) -> Callable[[list[bytes]], tuple[list[int], int, int]]:
    def decode(chunks: list[bytes]) -> tuple[list[int], int, int]:
        st = frame_decl.binary_decoder(spec)
        ids: list[int] = []
        for c in chunks:
            ids += st.feed(c)["counter"].tolist()
        ids += st.flush()["counter"].tolist()
        return ids, st.counters.bad_frames + st.counters.truncated_frames, 0
    return decode


# EXAMPLE: AA 55 | length 2 | counter 3-4 | time 5-8 | gyro 9-20 | accel 21-32 | temperature 33-34 |
#          status 35 | checksum (over 2 .. before it, little endian)
FD_PARTS = {"sync": [0, 1], "length": [2], "payload": list(range(3, 36))}


def _fd_proto(name: str, checksum, nck: int, reseal, passes) -> Proto:
    spec = _frame_spec(checksum)
    length = spec.length
    return Proto(
        name=name, good_rows=lambda: _fd_rows(spec), reseal=reseal, passes=passes,
        parts={**FD_PARTS, "checksum": list(range(length - nck, length))},
        false_header=lambda n: bytes([0xAA, 0x55, length]),
        false_spans={"false_into_next": (21, length, [10, 11][:nck])},
        decode=_fd_decode(spec),
    )


def _crc_ccitt_reseal(row: np.ndarray) -> None:
    row[-2:] = np.frombuffer(binascii.crc_hqx(row[2:-2].tobytes(), 0xFFFF).to_bytes(2, "little"), np.uint8)


def _sum8_reseal(row: np.ndarray) -> None:
    row[-1] = int(row[2:-1].sum()) & 0xFF


FRAME_CRC = _fd_proto("frame-crc16", {"type": "crc16-ccitt", "init": 0xFFFF}, 2, _crc_ccitt_reseal,
                      lambda f: binascii.crc_hqx(f[2:-2], 0xFFFF) == int.from_bytes(f[-2:], "little"))
FRAME_SUM8 = _fd_proto("frame-sum8", "sum8", 1, _sum8_reseal, lambda f: sum(f[2:-1]) & 0xFF == f[-1])

PROTOS = {p.name: p for p in (XSENS, VECTORNAV, FRAME_CRC, FRAME_SUM8)}
CASES = [(p, v) for p in PROTOS for v in ("plain", *PROTOS[p].false_spans)]


# ------------------------------------------------------------------------------- the stream
@cache
def stream_rows(proto: str, variant: str) -> np.ndarray:
    """The good frames; for a false_* variant the host's payload carries a false frame (its
    header at the variant's offset, free payload bytes set so that its check passes, the host
    resealed), checked here with the independent checks."""
    p = PROTOS[proto]
    rows = p.good_rows()
    for r in rows:
        assert p.passes(r.tobytes())                      # the encoders' frames are good
    if variant == "plain":
        return rows
    off, n, free = p.false_spans[variant]
    host = rows[HOST]
    host[off:off + len(p.false_header(n))] = np.frombuffer(p.false_header(n), np.uint8)
    for v in range(256 ** len(free)):
        host[free] = np.frombuffer(v.to_bytes(len(free), "big"), np.uint8)
        p.reseal(host)
        flat = rows.tobytes()
        start = HOST * rows.shape[1] + off
        if p.passes(flat[start:start + n]):
            break
    else:
        raise AssertionError(f"{proto}: no value of the free bytes makes the false frame pass")
    assert p.passes(host.tobytes())
    return rows


def _feeds(data: bytes, seed: int, names: tuple[str, ...]) -> dict[str, list[bytes]]:
    """The stream whole, byte by byte, or cut at 6 random places."""
    out = {}
    for name in names:
        if name == "whole":
            out[name] = [data]
        elif name == "bytes":
            out[name] = [data[i:i + 1] for i in range(len(data))]
        else:
            rng = np.random.default_rng(seed)
            cuts = np.r_[0, np.sort(rng.choice(np.arange(1, len(data)), 6, replace=False)), len(data)]
            out[name] = [data[a:b] for a, b in zip(cuts[:-1], cuts[1:])]
    return out


def _cases(p: Proto, variant: str, host: np.ndarray) -> list[tuple[int, int, tuple[str, ...]]]:
    """(position, XOR value, feeds): every value at a length byte (a shorter length, one longer
    than the frame, the extended-length marker 0xFF), else 0x01 and the value that makes the
    first sync byte; byte by byte (the slow feed) at the header bytes, the checksum, the false
    frame's header and a few payload bytes, with a few chosen values at a length byte."""
    header = [i for k, v in p.parts.items() if k not in ("payload", "checksum") for i in v]
    length = p.parts.get("length", [])
    off = p.false_spans[variant][0] if variant in p.false_spans else None
    payload = p.parts["payload"]
    slow = set(header) | set(p.parts["checksum"]) | {payload[0], payload[len(payload) // 2], payload[-1]}
    if off is not None:
        slow |= {off, off + 1, off + 3}
    out = []
    for pos in range(len(host)):
        b = int(host[pos])
        if pos in length:
            probe = _length_probe(p, b)
            out += [(pos, x, ("whole", "bytes", "random") if x in probe else ("whole",)) for x in range(1, 256)]
            continue
        for x in sorted({0x01, b ^ p.false_header(10)[0]} - {0}):
            out.append((pos, x, ("whole", "bytes", "random") if pos in slow else ("whole", "random")))
    return out


def _length_probe(p: Proto, byte: int) -> set[int]:
    """XOR values of a length byte fed in every way: to 0xFF (extended length), the longest
    standard length, one more and one less, 20 more, and lengths that end the host where its
    false frame starts."""
    targets = {0xFF, 0xFE, byte + 1, byte - 1, byte + 20, 5}
    for off, _, _ in p.false_spans.values():
        targets |= {off - 5, off - 4, off - 3}
    return {t ^ byte for t in targets if 0 <= t <= 255 and t != byte}


def _ambiguous(p: Proto, variant: str, pos: int) -> bool:
    """The one case a parser cannot get right: the host's preamble, bus id or length is hit,
    so nothing says where the host ended, and its payload holds a whole false frame that passes
    its check (``false_inside``): the false frame is taken (a message), and the host counts as
    two lost frames (the bytes before and after it). No good frame is lost."""
    return variant == "false_inside" and pos in p.parts["preamble"] + p.parts["bus id"] + p.parts["length"]


@pytest.mark.parametrize("proto,variant", CASES)
def test_one_corrupted_byte_costs_its_frame_only(proto: str, variant: str) -> None:
    p = PROTOS[proto]
    rows = stream_rows(proto, variant)
    want = [ID0 + i for i in range(N_FRAMES) if i != HOST]
    for pos, x, names in _cases(p, variant, rows[HOST]):
        bad = rows.copy()
        bad[HOST, pos] ^= x
        for name, chunks in _feeds(bad.tobytes(), pos * 256 + x, names).items():
            ids, lost, messages = p.decode(chunks)
            where = f"{p.name} ({variant}): byte {pos} ^ 0x{x:02X}, fed {name}"
            assert ids == want, f"{where}: decoded {ids}, good frames {want}"
            counted = (2, 1) if _ambiguous(p, variant, pos) else (1, 0)
            assert (lost, messages) == counted, f"{where}: {lost} frames counted lost, {messages} messages"


@pytest.mark.parametrize("proto,variant", [c for c in CASES if c[1] != "plain"])
def test_a_false_frame_in_a_good_frame_costs_nothing(proto: str, variant: str) -> None:
    """No corruption: the host carries a false frame that passes its check; every frame comes
    out, whatever the read boundaries (every single cut, byte by byte)."""
    p = PROTOS[proto]
    data = stream_rows(proto, variant).tobytes()
    want = [ID0 + i for i in range(N_FRAMES)]
    feeds = [[data[:k], data[k:]] for k in range(1, len(data))] + [[data[i:i + 1] for i in range(len(data))]]
    for chunks in feeds:
        ids, lost, messages = p.decode(chunks)
        assert (ids, lost, messages) == (want, 0, 0), f"{proto} cut at {len(chunks[0])}: {ids} lost {lost}"


def test_a_length_hit_to_an_item_boundary_costs_its_frame_only() -> None:
    """Xsens: the host's length byte hit to 49, the end of its Temperature item, and its data
    such that the shortened frame (FA FF 36 31 .. Temperature, the StatusWord header's 0xE0 as
    checksum) adds up: a valid MTData2 frame of a layout the stream never had, followed by the
    rest of the host, not by a frame. It is the head of the corrupted host, so the host is one
    lost frame and one counter gap, and no partial sample of it comes out."""
    rows = stream_rows("xsens", "plain").copy()
    host = rows[HOST]
    short = 49
    host[40] = (int(host[40]) - (sum(host[1:4 + short + 1].tolist()) - int(host[3]) + short)) % 256
    _xs_reseal(host)
    assert sum(host[1:].tolist()) % 256 == 0                       # the host is a good frame
    bad = rows.copy()
    bad[HOST, 3] = short
    assert sum(bad[HOST, 1:short + 5].tolist()) % 256 == 0         # and its head now one too
    want = [ID0 + i for i in range(N_FRAMES) if i != HOST]
    data = bad.tobytes()
    feeds = [[data[:k], data[k:]] for k in range(1, len(data))] + [[data[i:i + 1] for i in range(len(data))]]
    for chunks in feeds:
        st = MTData2Stream()
        ids = [v for c in chunks for v in st.feed(c).counter.tolist()] + st.flush().counter.tolist()
        c = st.counters
        assert (ids, c.bad_frames + c.truncated_frames, c.dropped_samples, c.messages) == (want, 1, 1, 0), \
            f"cut at {len(chunks[0])}: {ids}, {c}"


def test_csv_one_corrupted_byte_costs_its_line_only() -> None:
    """The declarative CSV lines (NMEA checksum; EXAMPLE_CSV): one byte of line 1 XORed at every
    position, to 0x01-different, a line end, a '$', a carriage return, a comma, a '*': the
    damaged sentence ('$' .. the two checksum digits) is the only one lost and counted, and a hit
    '\\r' or '\\n' after it costs nothing (the sentence is whole; with the '\\n' gone the next line
    is cut off at its '$'), fed whole and in random pieces (byte by byte at the sentence's ends)."""
    spec = parse_frame_spec(LocDict({"frame": LocDict(EXAMPLE_CSV)}))
    v = {"counter": ID0 + np.arange(N_FRAMES)}
    rng = np.random.default_rng(9)
    for ax in "xyz":
        v[f"g{ax}"], v[f"a{ax}"] = rng.normal(0, 1, N_FRAMES), rng.normal(0, 9.8, N_FRAMES)
    v["temperature"] = rng.normal(25, 1, N_FRAMES)
    lines = frame_decl.encode_csv(spec, v).split(b"\r\n")[:-1]
    lines = [ln + b"\r\n" for ln in lines]
    assert all(ln.startswith(b"$IMU,") for ln in lines)
    head = b"".join(lines[:HOST])
    host = lines[HOST]
    for pos in range(len(host)):
        for x in sorted({0x01, host[pos] ^ 0x0A, host[pos] ^ ord("$"), host[pos] ^ 0x0D, host[pos] ^ ord(","),
                         host[pos] ^ ord("*")} - {0}):
            bad = bytearray(host)
            bad[pos] ^= x
            data = head + bytes(bad) + b"".join(lines[HOST + 1:])
            whole = pos >= len(host) - 2                   # the line end: the sentence is intact
            want = [ID0 + i for i in range(N_FRAMES) if whole or i != HOST]
            slow = pos < 2 or pos >= len(host) - 5             # '$I', the checksum, '\r\n': byte by byte too
            names = ("whole", "bytes", "random") if slow else ("whole", "random")
            for name, chunks in _feeds(data, pos * 256 + x, names).items():
                st = frame_decl.CsvStream(spec)
                ids = [c for ch in chunks for c in st.feed(ch)["counter"].tolist()] + st.flush()["counter"].tolist()
                assert (ids, st.counters.bad_frames) == (want, 0 if whole else 1), \
                    f"byte {pos} ^ 0x{x:02X} fed {name}: {ids}, {st.counters}"
