"""NovAtel MARK1TIMEA / MARKCONTROL codec and the emulated receiver on a pty."""
from __future__ import annotations

import binascii
import time
from datetime import datetime, timezone

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from rigctl.drivers import novatel as N
from rigctl.sim.gnss_server import GnssServer

SPAN_SE_EXAMPLE = (b"#MARK1TIMEA,COM1,0,98.0,FINESTEERING,1521,336487.000,00000000,0000,149;"
                   b"1521,336487.000000025,0.000000000,0.000000000,-14.999999992,VALID*7597ecee")


def crc32_table_reference(data: bytes) -> int:
    """NovAtel's documented table algorithm, written out independently of zlib."""
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0xEDB88320 if c & 1 else c >> 1
        table.append(c)
    crc = 0
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def test_crc_matches_published_example_and_table_algorithm():
    body = SPAN_SE_EXAMPLE[1:SPAN_SE_EXAMPLE.index(b"*")]
    assert N.crc32(body) == 0x7597ECEE
    assert crc32_table_reference(body) == 0x7597ECEE


@settings(max_examples=50, deadline=None, derandomize=True, database=None)
@given(st.binary(max_size=200))
def test_crc_equals_table_algorithm_on_random_data(data):
    assert N.crc32(data) == crc32_table_reference(data)


def test_parse_published_example():
    m = N.parse_mark(SPAN_SE_EXAMPLE)
    assert (m.log_name, m.week, m.clock_status, m.time_status, m.sw_build) == ("MARK1TIMEA", 1521, "VALID",
                                                                                 "FINESTEERING", 149)
    assert m.seconds == pytest.approx(336487.000000025, abs=1e-10)
    assert m.utc_offset == pytest.approx(-14.999999992, abs=1e-12)


def test_format_parse_round_trip_and_marktime():
    for name in ("MARK1TIMEA", "MARKTIMEA"):
        m = N.MarkTime(week=2300, seconds=123456.123456789, offset=3e-9, offset_std=2e-9, utc_offset=-18.0,
                       log_name=name, header_week=2300, header_seconds=123456.2)
        line = N.format_mark(m)
        assert line.endswith(b"\r\n")
        assert N.parse_mark(line) == m


def test_bad_crc_rejected_and_counted():
    good = N.format_mark(N.MarkTime(week=2300, seconds=10.5))
    bad = good.replace(b"10.5", b"10.6")
    with pytest.raises(N.NovatelError, match="CRC"):
        N.parse_mark(bad)
    r = N.MarkLogReader()
    got = r.feed(good[:20]) + r.feed(good[20:] + bad + b"<OK\r\n#MARK1TIMEA,garbage*00000000\r\n")
    assert len(got) == 1 and got[0].seconds == 10.5
    assert (r.counters.marks, r.counters.bad_crc, r.counters.other_lines) == (1, 2, 1)
    assert r.responses == ["<OK"]


def test_malformed_with_valid_crc_rejected():
    body = b"MARK1TIMEA,COM1,0,98.0,FINESTEERING,1521,1.0,00000000,0000,149;1521,1.0,0,0,-18,MAYBE"
    line = b"#" + body + b"*" + f"{N.crc32(body):08x}".encode()
    with pytest.raises(N.NovatelError, match="clock status"):
        N.parse_mark(line)


def test_gps_week_seconds_to_time():
    # the second GPS week-number rollover (week 2048) began 2019-04-07 00:00:00 GPS time
    assert N.gps_to_datetime(2048, 0.0) == datetime(2019, 4, 7, tzinfo=timezone.utc)
    assert N.gps_to_datetime(2048, 0.0, -18.0) == datetime(2019, 4, 6, 23, 59, 42, tzinfo=timezone.utc)
    assert N.gps_to_datetime(1024, 86400.5) == datetime(1999, 8, 23, 0, 0, 0, 500000, tzinfo=timezone.utc)
    assert N.normalize_week_seconds(2300, 604800.25) == (2301, 0.25)
    assert N.gps_total_seconds(1, 2.0) == 604802.0


def test_markcontrol_parse_format_and_limits():
    mc = N.parse_markcontrol("markcontrol mark1 enable positive 50 100")
    assert mc == N.MarkControl("MARK1", True, "POSITIVE", 50, 100)
    assert N.parse_markcontrol(N.format_markcontrol(mc)) == mc
    assert N.parse_markcontrol("MARKCONTROL MARK2 DISABLE") == N.MarkControl("MARK2", False)
    assert N.MarkControl().timeguard_ms == 4
    for bad in ("MARKCONTROL MARK9", "MARKCONTROL MARK1 ENABLE NEGATIVE 0 3", "MARKCONTROL MARK1 MAYBE",
                "MARKCONTROL MARK1 ENABLE NEGATIVE x 5", "LOG MARK1TIMEA"):
        with pytest.raises(N.NovatelError):
            N.parse_markcontrol(bad)


class ManualClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def read_marks(port, reader: N.MarkLogReader, n: int, timeout: float = 3.0) -> list[N.MarkTime]:
    out, t_end = [], time.monotonic() + timeout
    while len(out) < n and time.monotonic() < t_end:
        out += reader.feed(port.read(4096))
    return out


def command(port, reader, line: bytes) -> str:
    port.write(line + b"\r\n")
    t_end = time.monotonic() + 3
    while not reader.responses and time.monotonic() < t_end:
        reader.feed(port.read(256))
    return reader.responses.pop(0)


def test_gnss_server_marks_with_timeguard_and_timebias():
    clock = ManualClock()
    srv = GnssServer(clock=clock, gps_week0=2300, gps_seconds0=604_790.0, log_delay_s=0.03)
    port = serial.serial_for_url(srv.path, baudrate=115200, timeout=0.05)
    reader = N.MarkLogReader()
    try:
        assert command(port, reader, b"LOG COM1 MARK1TIMEA ONNEW") == "<OK"
        assert command(port, reader, b"MARKCONTROL MARK1 ENABLE NEGATIVE 50 100") == "<OK"
        assert command(port, reader, b"MARKCONTROL MARK1 ENABLE NEGATIVE 0 1").startswith("<ERROR")
        assert command(port, reader, b"LOG BESTPOSA ONTIME 1").startswith("<ERROR")
        assert [srv.pulse(t) for t in (1.0, 1.05, 1.0999, 1.2, 12.5)] == [True, False, False, True, True]
        assert srv.suppressed == 2
        clock.t = 1.1                                # only the first log is due (1.0 + 0.03)
        marks = read_marks(port, reader, 1)
        clock.t = 20.0
        marks += read_marks(port, reader, 2)
    finally:
        port.close()
        srv.close()
    assert [m.week for m in marks] == [2300, 2300, 2301]
    expect = [604_791.0 + 50e-9, 604_791.2 + 50e-9, 604_802.5 + 50e-9 - 604_800]
    for m, e in zip(marks, expect):
        assert m.seconds == pytest.approx(e, abs=1e-8)
        assert m.log_name == "MARK1TIMEA" and m.clock_status == "VALID" and m.utc_offset == -18.0
    assert marks[0].header_seconds == pytest.approx(604_791.03, abs=1e-3)
    assert reader.counters.bad_crc == 0


def test_gnss_server_disabled_and_unlogged():
    clock = ManualClock()
    srv = GnssServer(clock=clock, autolog=True)
    port = serial.serial_for_url(srv.path, baudrate=115200, timeout=0.05)
    reader = N.MarkLogReader()
    try:
        assert command(port, reader, b"MARKCONTROL MARK1 DISABLE") == "<OK"
        assert srv.pulse(1.0) is False and srv.ignored == 1
        assert command(port, reader, b"MARKCONTROL MARK1 ENABLE") == "<OK"
        assert command(port, reader, b"UNLOGALL") == "<OK"
        assert srv.pulse(2.0) is True
        clock.t = 5.0
        time.sleep(0.1)
        assert read_marks(port, reader, 1, timeout=0.3) == []
        assert command(port, reader, b"LOG MARKTIMEA ONNEW") == "<OK"
        srv.pulse(6.0)
        clock.t = 7.0
        marks = read_marks(port, reader, 1)
    finally:
        port.close()
        srv.close()
    assert len(marks) == 1 and marks[0].log_name == "MARKTIMEA"


def _log_line(seq: int, seconds: float) -> bytes:
    """A MARK1TIMEA line written here by hand (not with format_mark): NovAtel CRC-32 (reflected
    0xEDB88320, init 0, no final XOR) = zlib's CRC with its pre- and post-inversion undone."""
    body = (f"MARK1TIMEA,COM1,{seq},98.0,FINESTEERING,2300,{seconds + 0.03:.3f},00000000,0000,149;"
            f"2300,{seconds:.9f},0.000000000,0.000000000,-18.000000000,VALID").encode()
    crc = binascii.crc32(body, 0xFFFFFFFF) ^ 0xFFFFFFFF
    return b"#" + body + b"*" + f"{crc:08x}".encode() + b"\r\n"


def _feed(pieces: list[bytes]) -> tuple[list[int], N.MarkLogReader]:
    r = N.MarkLogReader()
    return [m.sequence for p in pieces for m in r.feed(p)], r


def test_one_corrupted_byte_costs_its_log_only():
    """Logs 0..5 (sequence 8..13, so lengths differ by a byte), one byte of log 2 set to '#', '*',
    CR, LF, a digit or a letter, at every position of its line. Expected here from the bytes: log 2
    is lost (and counted once) when the byte is in '#' .. its last CRC digit (a CRC-32 catches every
    one-byte error), else (its CR LF) nothing is lost; every other log is decoded -- also log 3,
    which merged with log 2 when its line end was hit (before, both were lost and counted once).
    Fed whole, byte by byte and in random pieces."""
    assert binascii.crc32(SPAN_SE_EXAMPLE[1:-9], 0xFFFFFFFF) ^ 0xFFFFFFFF == 0x7597ECEE
    lines = [_log_line(8 + i, 604_700.0 + 0.37 * i) for i in range(6)]
    assert len({len(x) for x in lines}) == 2
    head, target, tail = b"".join(lines[:2]), lines[2], b"".join(lines[3:])
    rng = np.random.default_rng(7)
    cases = 0
    for i in range(len(target)):
        for v in b"#*\r\n7Z":
            if target[i] == v:
                continue
            hit = bytearray(target)
            hit[i] = v
            stream = head + bytes(hit) + tail
            lost = i < len(target) - 2                          # before its CR LF
            want = [8 + k for k in range(6) if not (lost and k == 2)]
            cuts = np.r_[0, np.sort(rng.choice(np.arange(1, len(stream)), 12, replace=False)), len(stream)]
            for pieces in ([stream], [stream[k:k + 1] for k in range(len(stream))],
                           [stream[a:b] for a, b in zip(cuts[:-1], cuts[1:])]):
                got, r = _feed(pieces)
                assert (got, r.counters.bad_crc, r.counters.malformed) == (want, int(lost), 0), (i, chr(v))
            cases += 1
    assert cases > 5 * len(target)


def test_byte_errors_cost_the_damaged_logs_only():
    """3000 logs with byte errors at 1e-3 (half random bytes, half '#', '*', CR, LF, '7', 'Z'), so
    also several in one log and in neighbouring logs: every intact log (no changed byte in '#' ..
    its last CRC digit) is decoded and bad_crc == the damaged logs, fed whole and in 2000 random
    pieces. Expected here from the clean and the damaged bytes (423 damaged logs; the old reader
    missed 8 intact logs and counted 367 bad CRC + 54 malformed + 42 'other lines')."""
    rng = np.random.default_rng(0)
    lines = [_log_line(i, 600_000.0 + 0.731 * i) for i in range(3000)]
    clean = np.frombuffer(b"".join(lines), np.uint8)
    noisy = clean.copy()
    pos = np.flatnonzero(rng.random(clean.size) < 1e-3)
    new = np.where(rng.random(pos.size) < 0.5, rng.integers(0, 256, pos.size),
                   rng.choice(np.frombuffer(b"#*\r\n7Z", np.uint8), pos.size))
    noisy[pos] = new
    pos = np.flatnonzero(clean != noisy)
    starts = np.cumsum([0] + [len(x) for x in lines[:-1]])
    line = np.searchsorted(starts, pos, side="right") - 1
    in_log = pos - starts[line] < np.array([len(x) for x in lines])[line] - 2      # before CR LF
    lost = set(line[in_log].tolist())
    assert len(lost) > 300 and (~in_log).sum() > 3
    assert np.isin(noisy[pos], np.frombuffer(b"#\r\n", np.uint8)).sum() > 50
    cuts = np.r_[0, np.sort(rng.choice(np.arange(1, noisy.size), 2000, replace=False)), noisy.size]
    for pieces in ([noisy.tobytes()], [noisy[a:b].tobytes() for a, b in zip(cuts[:-1], cuts[1:])]):
        got, r = _feed(pieces)
        assert got == sorted(set(range(3000)) - lost)
        assert (r.counters.bad_crc, r.counters.malformed) == (len(lost), 0)


def test_overlong_counted_the_same_whatever_the_chunking():
    """Lines and logs longer than max_line (1024 bytes) before their end -- a 3000-byte line, a
    2000-byte log body, a 1025-byte line, 1500 bytes and a 1500-byte log head running straight
    into the next log's '#' -- are each counted overlong once and cost no intact log; a
    1024-byte line is not overlong. Fed whole, byte by byte and in 40 random cuttings: the same
    logs, counters and responses (before, a long stretch was counted overlong only where a read
    ended inside it: 0 fed whole or in 4000-byte reads, 3 in 1000-byte reads, 5 in 7-500-byte
    reads, 6 byte by byte). Expected here from the bytes: every
    gap between whole logs (their CR LF, the junk) costs round(bytes / the last log's length)."""
    rng = np.random.default_rng(3)
    alphabet = np.frombuffer(b"ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789,.;", np.uint8)

    def junk(k: int) -> bytes:
        return rng.choice(alphabet, k).tobytes()

    logs = [_log_line(i, 604_000.0 + 0.5 * i) for i in range(8)]
    # (log, what follows it up to the next log, overlong stretches in it, response lines in it)
    parts = [(logs[0], junk(3000) + b"\r\n", 1, b""),
             (logs[1], b"#" + junk(2000) + b"*12345678\r\n", 1, b""),
             (logs[2], junk(1024) + b"\n", 0, b""),
             (logs[3], junk(1025) + b"\n", 1, b""),
             (logs[4], b"<OK\r\n" + junk(1500), 1, b"<OK\r\n"),
             (logs[5], b"#" + junk(1500), 1, b""),
             (logs[6], b"", 0, b""),
             (logs[7], b"", 0, b"")]
    stream = b"".join(log + after for log, after, _, _ in parts)
    want_lost = sum(round((2 + len(after) - len(resp)) / len(log)) for log, after, _, resp in parts[:-1])
    want = (list(range(8)), N.MarkReaderCounters(
        marks=8, bad_crc=want_lost, malformed=0, other_lines=1, overlong=sum(p[2] for p in parts),
        garbage_bytes=sum(2 + len(after) - len(resp) for _, after, _, resp in parts)), ["<OK"])
    assert want[1].overlong == 5 and want_lost > 50
    cuttings = [[stream], [stream[k:k + 1] for k in range(len(stream))]]
    for _ in range(40):
        cuts = np.r_[0, np.sort(rng.choice(np.arange(1, len(stream)), rng.integers(2, 200),
                                           replace=False)), len(stream)]
        cuttings.append([stream[a:b] for a, b in zip(cuts[:-1], cuts[1:])])
    for pieces in cuttings:
        got, r = _feed(pieces)
        assert (got, r.counters, r.responses) == want, len(pieces)
