"""NovAtel #MARK1TIMEA / #MARKTIMEA ASCII logs and the MARKCONTROL command.

ASCII log form::

    #MARK1TIMEA,<port>,<seq>,<idle%>,<time status>,<week>,<seconds>,<rx status>,<reserved>,<sw>;
        <week>,<seconds>,<offset>,<offset std>,<utc offset>,<clock status>*<crc32 hex>

Body units: week (GPS week), seconds (s of week, receiver clock, at the leading edge of the
mark pulse, 10 ns resolution), offset (s; GPS system time = GPS reference time - offset),
offset std (s), utc offset (s; UTC = GPS + utc offset). MARKTIME (ID 231) is the deprecated
twin of MARK1TIME (ID 1130) with the same body.

CRC-32: NovAtel's table algorithm with the reflected polynomial 0xEDB88320, CRC initialised to
0, no final XOR, over the characters strictly between ``#`` and ``*``. That equals
``zlib.crc32(data, 0xFFFFFFFF) ^ 0xFFFFFFFF`` (zlib pre- and post-inverts; starting from the
inverted value and inverting the result cancels both), so zlib's C table implementation is used.
"""
from __future__ import annotations

import logging
import re
import zlib
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone

from rigctl.errors import DeviceError

from .lost_lines import LostLines

log = logging.getLogger(__name__)

SECONDS_PER_WEEK = 604_800
GPS_EPOCH = datetime(1980, 1, 6, tzinfo=timezone.utc)
MARK_LOGS = ("MARK1TIMEA", "MARK2TIMEA", "MARK3TIMEA", "MARK4TIMEA", "MARKTIMEA")
CLOCK_STATUS = ("VALID", "CONVERGING", "ITERATING", "INVALID", "ERROR")
#: EVENTINCONTROL/MARKCONTROL timeguard range in ms (SPAN-SE manual: default 4, min 4, max 3 599 999).
TIMEGUARD_MIN_MS, TIMEGUARD_MAX_MS, TIMEGUARD_DEFAULT_MS = 4, 3_599_999, 4


class NovatelError(DeviceError, ValueError):
    """A malformed or mis-checksummed NovAtel sentence or command."""


def crc32(data: bytes) -> int:
    """NovAtel CRC-32 of ``data`` (poly 0xEDB88320 reflected, init 0, no final XOR)."""
    return zlib.crc32(data, 0xFFFFFFFF) ^ 0xFFFFFFFF


def gps_to_datetime(week: int, seconds: float, utc_offset_s: float = 0.0) -> datetime:
    """GPS week + seconds of week (+ GPS->UTC offset in s, e.g. -18) -> aware UTC datetime.

    t_utc = GPS epoch (1980-01-06) + week * 604800 s + seconds + utc_offset. Resolution of the
    datetime is 1 us; keep (week, seconds) for anything finer.
    """
    return GPS_EPOCH + timedelta(weeks=int(week), seconds=float(seconds) + float(utc_offset_s))


def gps_total_seconds(week: int, seconds: float) -> float:
    """Seconds since the GPS epoch, week * 604800 + seconds (float64: ~0.1 us resolution today)."""
    return int(week) * SECONDS_PER_WEEK + float(seconds)


def normalize_week_seconds(week: int, seconds: float) -> tuple[int, float]:
    """Carry seconds outside [0, 604800) into the week number."""
    w, s = divmod(float(seconds), SECONDS_PER_WEEK)
    return int(week) + int(w), s


@dataclass(frozen=True)
class MarkTime:
    """One MARKxTIME log. Times in s, week in GPS weeks."""

    week: int
    seconds: float
    offset: float = 0.0
    offset_std: float = 0.0
    utc_offset: float = -18.0
    clock_status: str = "VALID"
    log_name: str = "MARK1TIMEA"
    port: str = "COM1"
    sequence: int = 0
    idle_pct: float = 0.0
    time_status: str = "FINESTEERING"
    header_week: int = 0
    header_seconds: float = 0.0
    rx_status: int = 0
    reserved: int = 0
    sw_build: int = 0

    @property
    def gps_seconds(self) -> float:
        """Seconds of week corrected to GPS system time: seconds - offset (s)."""
        return self.seconds - self.offset

    def to_datetime_utc(self) -> datetime:
        """UTC datetime of the mark (GPS system time + utc offset)."""
        return gps_to_datetime(self.week, self.gps_seconds, self.utc_offset)


_HEX8 = re.compile(rb"^[0-9A-Fa-f]{8}$")


def format_mark(m: MarkTime) -> bytes:
    """Format a MARKxTIMEA sentence with its CRC, terminated by CR LF."""
    if m.log_name not in MARK_LOGS:
        raise NovatelError(f"not a mark log: {m.log_name}")
    body = (f"{m.log_name},{m.port},{m.sequence},{m.idle_pct:.1f},{m.time_status},{m.header_week},"
            f"{m.header_seconds:.3f},{m.rx_status:08x},{m.reserved:04x},{m.sw_build};"
            f"{m.week},{m.seconds:.9f},{m.offset:.9f},{m.offset_std:.9f},{m.utc_offset:.9f},"
            f"{m.clock_status}").encode("ascii")
    return b"#" + body + b"*" + f"{crc32(body):08x}".encode() + b"\r\n"


def check_sentence(line: bytes) -> bytes:
    """Verify ``#...*crc`` and return the part between ``#`` and ``*``; raises NovatelError."""
    line = line.strip()
    if not line.startswith(b"#"):
        raise NovatelError("missing '#' sync character")
    star = line.rfind(b"*")
    if star < 0 or not _HEX8.match(line[star + 1:]):
        raise NovatelError("missing or malformed '*crc32' trailer")
    body = line[1:star]
    want = int(line[star + 1:], 16)
    got = crc32(body)
    if got != want:
        raise NovatelError(f"CRC mismatch: sentence says {want:08x}, computed {got:08x}")
    return body


def parse_mark(line: bytes) -> MarkTime:
    """Parse and CRC-check one MARKxTIMEA sentence; raises NovatelError on any defect."""
    body = check_sentence(line)
    try:
        text = body.decode("ascii")
        head, data = text.split(";", 1)
        h = head.split(",")
        d = data.split(",")
        if h[0] not in MARK_LOGS:
            raise NovatelError(f"not a mark log: {h[0]}")
        if len(h) != 10 or len(d) != 6:
            raise NovatelError(f"{h[0]}: expected 10 header and 6 body fields, got {len(h)} and {len(d)}")
        if d[5] not in CLOCK_STATUS:
            raise NovatelError(f"unknown clock status {d[5]!r}")
        return MarkTime(week=int(d[0]), seconds=float(d[1]), offset=float(d[2]), offset_std=float(d[3]),
                        utc_offset=float(d[4]), clock_status=d[5], log_name=h[0], port=h[1],
                        sequence=int(h[2]), idle_pct=float(h[3]), time_status=h[4], header_week=int(h[5]),
                        header_seconds=float(h[6]), rx_status=int(h[7], 16), reserved=int(h[8], 16),
                        sw_build=int(h[9]))
    except NovatelError:
        raise
    except (ValueError, UnicodeDecodeError) as exc:
        raise NovatelError(f"malformed mark log: {exc}") from exc


@dataclass
class MarkReaderCounters:
    """Diagnostics of a :class:`MarkLogReader`: ``bad_crc`` counts the logs lost to byte errors
    (a CRC mismatch or broken framing), ``malformed`` logs with a good CRC that do not parse,
    ``garbage_bytes`` the bytes between logs that belong to no whole log."""

    marks: int = 0
    bad_crc: int = 0
    malformed: int = 0
    other_lines: int = 0
    overlong: int = 0
    garbage_bytes: int = 0


#: a log from its ``#`` up to the first ``#``, ``*``, CR or LF (``*`` then ends a whole log)
_HEAD = re.compile(rb"#[^#*\r\n]*")
#: text outside logs, up to the next ``#`` or LF
_TEXT = re.compile(rb"[^#\n]*")
_HEXDIGITS = frozenset(b"0123456789ABCDEFabcdef")


@dataclass
class MarkLogReader:
    """Stream parser: ``feed(bytes) -> list[MarkTime]``; keeps partial logs across feeds.

    A log runs from its ``#`` to the 8 hex digits after its ``*`` (bytes after them up to the
    line end are a hit line end, not a log), and a log is also cut before each ``#``: a byte
    error that destroys a line end (or makes a ``#``) costs only the damaged log, never the
    intact one after it. Logs lost to byte errors are counted (``counters.bad_crc``) by the
    bytes since the last whole log, ``round(g / r)`` with ``r`` the last whole log's length +
    CR LF, so a damaged log cut in pieces counts once; a whole-framed ``#...*crc`` with a wrong
    CRC counts at least ``floor(start / r) + 1`` (its own log). Counting is eager (no flush) and
    the same whatever the read chunking. Logs with a good CRC that do not parse are counted
    ``malformed``; lines starting with ``<`` (command replies such as ``<OK``) are collected in
    ``responses``. Bad logs are logged and dropped. A log whose ``#`` .. first ``#``, ``*``, CR
    or LF, or a line outside logs up to its LF or ``#``, longer than ``max_line`` bytes is
    ``overlong``: counted once and dropped up to the next ``#`` or LF (as garbage bytes), decided
    on its first ``max_line + 1`` bytes, so also the same whatever the read chunking.
    """

    max_line: int = 1024
    counters: MarkReaderCounters = field(default_factory=MarkReaderCounters)
    responses: list[str] = field(default_factory=list)
    _buf: bytes = b""
    #: logs lost between whole logs (before the first whole log a formatted mark's length)
    _lost: LostLines = field(default_factory=lambda: LostLines(
        nominal=len(format_mark(MarkTime(week=0, seconds=0.0)))))
    _skip: bool = False  # in an overlong log or line: bytes up to the next '#' or LF dropped

    def _garbage(self, size: int, whole: bool = False) -> None:
        """``size`` bytes that belong to no good log; ``whole``: a whole-framed bad log."""
        self.counters.garbage_bytes += size
        more = self._lost.garbage(size, whole)
        if more:
            log.warning("NovAtel log lost to a byte error (CRC mismatch or broken framing)")
            self.counters.bad_crc += more

    def _whole(self, sentence: bytes) -> MarkTime | None:
        """A whole-framed ``#...*crc`` log: its mark, or None (counted)."""
        try:
            m = parse_mark(sentence)
        except NovatelError as exc:
            if "CRC" in str(exc):
                self._garbage(len(sentence), whole=True)
            else:
                log.warning("rejected NovAtel sentence: %s", exc)
                self.counters.malformed += 1
                self._lost.good(len(sentence) + 2)
            return None
        self.counters.marks += 1
        self._lost.good(len(sentence) + 2)
        return m

    def _text(self, text: bytes) -> None:
        """Bytes outside logs: command replies (lines starting with ``<``), line ends, garbage."""
        parts = text.split(b"\n")
        for k, part in enumerate(parts):
            size = len(part) + (k < len(parts) - 1)                    # its LF with it
            line = part.strip()
            if line.startswith(b"<"):
                self.counters.other_lines += 1
                self.responses.append(line.decode("ascii", "replace"))
            elif size:
                self._garbage(size)

    def _overlong(self, pos: int) -> int:
        """The ``max_line + 1`` bytes from ``pos`` hold no end of their log or line: counted
        ``overlong`` once and dropped, with the rest of it up to the next ``#`` or LF
        (:attr:`_skip`). Returns the position after them."""
        self.counters.overlong += 1
        self._garbage(self.max_line + 1)
        self._skip = True
        return pos + self.max_line + 1

    def feed(self, data: bytes) -> list[MarkTime]:
        buf = self._buf + bytes(data)
        n, pos = len(buf), 0
        out: list[MarkTime] = []
        while pos < n:
            if self._skip:                                      # the rest of an overlong one
                e = _TEXT.match(buf, pos).end()
                stop = e + (e < n and buf[e] == 0x0A)
                if stop > pos:
                    self._garbage(stop - pos)
                self._skip, pos = e == n, stop
                continue
            if buf[pos] != 0x23:                                # text: a line, up to its LF or '#'
                e = _TEXT.match(buf, pos).end()
                if e - pos > self.max_line:
                    pos = self._overlong(pos)
                    continue
                if e == n:                                      # wait for its end
                    break
                stop = e + (buf[e] == 0x0A)
                self._text(buf[pos:stop])
                pos = stop
                continue
            e = _HEAD.match(buf, pos).end()
            if e - pos > self.max_line:
                pos = self._overlong(pos)
                continue
            if e == n or (buf[e] == 0x2A and e + 9 > n and all(b in _HEXDIGITS for b in buf[e + 1:])):
                break                                           # wait for the rest of the log
            if buf[e] == 0x2A and all(b in _HEXDIGITS for b in buf[e + 1:e + 9]):
                m = self._whole(buf[pos:e + 9])
                if m is not None:
                    out.append(m)
                pos = e + 9
            else:                                               # cut by '#', CR, LF or a bad CRC
                stop = e + (buf[e] == 0x2A)
                self._garbage(stop - pos)
                pos = stop
        self._buf = buf[pos:]
        return out


# ------------------------------------------------------------------------- MARKCONTROL

@dataclass(frozen=True)
class MarkControl:
    """``MARKCONTROL signal [switch [polarity [timebias [timeguard]]]]``.

    timebias_ns shifts reported mark times later by that many ns; timeguard_ms is the dead time
    after an accepted mark during which further pulses are ignored.
    """

    signal: str = "MARK1"
    enable: bool = True
    polarity: str = "NEGATIVE"
    timebias_ns: int = 0
    timeguard_ms: int = TIMEGUARD_DEFAULT_MS

    def __post_init__(self) -> None:
        if self.signal not in ("MARK1", "MARK2", "MARK3", "MARK4"):
            raise NovatelError(f"MARKCONTROL: unknown signal {self.signal!r}")
        if self.polarity not in ("NEGATIVE", "POSITIVE"):
            raise NovatelError(f"MARKCONTROL: polarity must be NEGATIVE or POSITIVE, got {self.polarity!r}")
        if not TIMEGUARD_MIN_MS <= self.timeguard_ms <= TIMEGUARD_MAX_MS:
            raise NovatelError(f"MARKCONTROL: timeguard {self.timeguard_ms} ms outside "
                               f"[{TIMEGUARD_MIN_MS}, {TIMEGUARD_MAX_MS}] ms")


def format_markcontrol(mc: MarkControl) -> bytes:
    """The MARKCONTROL command line (CR LF terminated)."""
    return (f"MARKCONTROL {mc.signal} {'ENABLE' if mc.enable else 'DISABLE'} {mc.polarity} "
            f"{mc.timebias_ns} {mc.timeguard_ms}\r\n").encode("ascii")


def parse_markcontrol(line: str | bytes) -> MarkControl:
    """Parse a MARKCONTROL command (case-insensitive, optional trailing fields take defaults)."""
    if isinstance(line, bytes):
        line = line.decode("ascii", "replace")
    tok = line.replace(",", " ").split()
    if not tok or tok[0].upper() != "MARKCONTROL":
        raise NovatelError("not a MARKCONTROL command")
    if len(tok) < 2 or len(tok) > 6:
        raise NovatelError("MARKCONTROL takes 1 to 5 parameters")
    args = [t.upper() for t in tok[1:]]
    sw = args[1] if len(args) > 1 else "ENABLE"
    if sw not in ("ENABLE", "DISABLE"):
        raise NovatelError(f"MARKCONTROL: switch must be ENABLE or DISABLE, got {sw!r}")
    try:
        bias = int(args[3]) if len(args) > 3 else 0
        guard = int(args[4]) if len(args) > 4 else TIMEGUARD_DEFAULT_MS
    except ValueError as exc:
        raise NovatelError(f"MARKCONTROL: {exc}") from exc
    return MarkControl(signal=args[0], enable=sw == "ENABLE",
                       polarity=args[2] if len(args) > 2 else "NEGATIVE", timebias_ns=bias, timeguard_ms=guard)
