"""NovAtel MARK1TIMEA / MARKCONTROL codec and the emulated receiver on a pty."""
from __future__ import annotations

import time
from datetime import datetime, timezone

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
