"""ROS bags and MCAP files to IMU arrays: the reading half of ``rigctl import FILE.bag``.

Inputs (recognised by their first bytes, not their names):

* a ROS 1 bag (``#ROSBAG V2.0``), read by ``rosbags.rosbag1``;
* a rosbag2 directory (``metadata.yaml`` beside sqlite3 ``.db3`` or ``.mcap`` storage files), or
  one ``.db3`` storage file, read by ``rosbags.rosbag2``;
* a bare MCAP file (``\\x89MCAP0``), read by the ``mcap`` package's own reader. It reads any MCAP
  profile (``ros2`` with CDR messages, ``ros1`` as written by ``mcap convert``), and when the
  file has no summary -- a recording cut off by a crash -- it streams the file from the start
  and keeps every message before the cut, where rosbags' MCAP reader refuses the whole file.

Messages of type ``sensor_msgs/msg/Imu`` (ROS 1: ``sensor_msgs/Imu``) are decoded with
rosbags' deserialisers (CDR for ROS 2, ROS 1 serialisation for ROS 1), from the message
definition the file embeds. ``linear_acceleration`` is the specific force (m/s^2),
``angular_velocity`` the angular rate (rad/s) (REP 103); orientation and every covariance are
ignored. Decoding is vectorised: the message has a fixed layout given the length of
``header.frame_id``, so the fields of a block of equal-length messages are read at their offsets
with numpy; the first and the last message of every such group are also decoded by rosbags and
must agree bit for bit, else the group is decoded message by message by rosbags (benchmarks
compare the speeds).

Time: ``header.stamp`` (default) or the bag's receive time (``time_source="receive"``). The
messages are sorted by it; exact repeats (same time, same values) are dropped and counted, a time
shared by different values is refused. Missing samples are found on a sample grid that follows
the clock (:func:`grid_counter`: period T from the median interval, refined to the mean interval
with the gaps counted (least-squares slope of time on sample number); phase from the circular mean of the stamps per 64 samples, so stamp
jitter up to half an interval and a slow drift between the stamping clock and the sensor's do
not create false gaps). The sample counter is the grid slot, so a gap of k missing samples shows
as a counter jump of k + 1 -- the way rigctl recordings record dropped samples
(docs/data-format.md, ``/imu/counter``); the rate is 1/T. The receive time is kept for the
receive-minus-stamp latency (median, min, max), which shows whether the stamps come from the
recorder's clock.

Errors are :class:`rigctl.errors.InputError` (one line: file, what is wrong, what to do).
"""
from __future__ import annotations

import importlib.util
import math
import struct
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..errors import InputError
from ..units import format_rate
from ..recording.foreign import MCAP_MAGIC, ROSBAG1_MAGIC, SQLITE_MAGIC, bag_kind  # noqa: F401 - bag_kind: the import command asks here

#: the message type, in rosbags' normalised (ROS 2) spelling; ROS 1's sensor_msgs/Imu maps to it
IMU_TYPE = "sensor_msgs/msg/Imu"
#: messages decoded per block (bounded memory: the raw bytes of one block at a time)
BLOCK = 1 << 16
#: offsets after the header's frame_id (same for ROS 1 and CDR; doubles, 8-byte aligned in CDR):
#: orientation (4) + covariance (9), angular_velocity (3) + covariance (9), linear_acceleration (3)
#: + covariance (9)
_GYR_OFF, _ACC_OFF, _TAIL = 13 * 8, 25 * 8, 37 * 8

Progress = Callable[[int, int], Any]


@dataclass
class TopicInfo:
    """One topic of a bag: name, message type (normalised), message count (None if unknown)."""

    topic: str
    msgtype: str
    count: int | None


@dataclass
class BagImu:
    """The IMU samples of one topic, ready for a recording (SI, sorted by time).

    ``time_s`` is the chosen time (header stamp) relative to the first sample, s; ``counter`` the
    sample counter whose gaps are the missing samples; ``stamp_zero_ns`` the first sample's
    absolute time, ns (Unix time when the stamps are wall-clock time).
    """

    source_format: str
    topic: str
    msgtype: str
    frame_id: str
    time_source: str
    time_s: np.ndarray
    counter: np.ndarray
    specific_force: np.ndarray
    angular_rate: np.ndarray
    rate_hz: float
    interval_ns: float
    median_interval_ns: float
    stamp_zero_ns: int
    n_messages: int
    gaps: int
    missing_samples: int
    largest_gap_s: float
    duplicates_dropped: int
    reordered: int
    receive_minus_stamp_s: dict[str, float]
    topics: list[TopicInfo]
    truncated: str = ""
    notes: list[str] = field(default_factory=list)


def topics_text(topics: list[TopicInfo]) -> str:
    """``/imu (sensor_msgs/msg/Imu, 2000 messages), /tf (...)`` or ``none``."""
    if not topics:
        return "none"
    return ", ".join(f"{t.topic} ({t.msgtype}, "
                     f"{'?' if t.count is None else t.count} messages)" for t in topics)


def choose_topic(path: Path, topics: list[TopicInfo], topic: str | None) -> TopicInfo:
    """The Imu topic to read: ``topic`` if given (it must exist and be an Imu topic), else
    the only Imu topic; else InputError listing the topics and types present."""
    present = f"topics present: {topics_text(topics)}"
    imu = [t for t in topics if t.msgtype == IMU_TYPE]
    if topic is not None:
        match = [t for t in topics if t.topic == topic]
        if not match:
            raise InputError(f"no topic {topic}; {present}", path, hint="choose one with --topic")
        if match[0].msgtype != IMU_TYPE:
            raise InputError(f"topic {topic} is {match[0].msgtype}, not {IMU_TYPE}; {present}", path,
                             hint="choose a sensor_msgs/Imu topic with --topic")
        chosen = match[0]
    elif len(imu) == 1:
        chosen = imu[0]
    elif not imu:
        raise InputError(f"no {IMU_TYPE} topic; {present}", path,
                         hint="record the IMU's sensor_msgs/Imu topic")
    else:
        raise InputError(f"{len(imu)} {IMU_TYPE} topics ({', '.join(t.topic for t in imu)}); "
                         "choose one with --topic", path)
    if chosen.count == 0:
        raise InputError(f"topic {chosen.topic} has no messages; {present}", path,
                         hint="choose a topic with messages")
    return chosen


# ---------------------------------------------------------------------------- decoding

def decode_imu_block(raws: list[bytes], encoding: str, deserialize: Callable[[bytes], Any]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Header stamps (ns, int64), linear_acceleration and angular_velocity ((k, 3) float64)
    and the first frame_id of serialised Imu messages (``encoding`` ``cdr`` or ``ros1``).

    Vectorised per group of equal-length messages (see the module docstring), checked against
    ``deserialize`` (rosbags) on the group's first and last message; rosbags per message where
    the fixed layout does not apply (big-endian CDR, another definition) or disagrees."""
    k = len(raws)
    stamp = np.empty(k, np.int64)
    acc = np.empty((k, 3))
    gyr = np.empty((k, 3))
    sizes = np.fromiter(map(len, raws), np.int64, k)
    for size in np.unique(sizes):
        idx = np.flatnonzero(sizes == size)
        got = _fixed_layout([raws[i] for i in idx], int(size), encoding, deserialize)
        if got is None:
            got = _one_by_one([raws[i] for i in idx], deserialize)
        stamp[idx], acc[idx], gyr[idx] = got
    frame = deserialize(raws[0]).header.frame_id if k else ""
    return stamp, acc, gyr, str(frame)


def _fields(msg: Any) -> tuple[int, tuple[float, float, float], tuple[float, float, float]]:
    st, a, w = msg.header.stamp, msg.linear_acceleration, msg.angular_velocity
    return int(st.sec) * 1_000_000_000 + int(st.nanosec), (a.x, a.y, a.z), (w.x, w.y, w.z)


def _one_by_one(raws: list[bytes], deserialize: Callable[[bytes], Any]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rows = [_fields(deserialize(r)) for r in raws]
    return (np.array([r[0] for r in rows], np.int64), np.array([r[1] for r in rows], float),
            np.array([r[2] for r in rows], float))


def _fixed_layout(raws: list[bytes], size: int, encoding: str, deserialize: Callable[[bytes], Any]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Fields read at fixed offsets; None when the layout does not apply or disagrees."""
    if size < 16:
        return None
    # both serialisations put sec at byte 4, nanosec at 8 and frame_id's length at 12
    # (ROS 1: seq first; CDR: the 4-byte encapsulation header first)
    flen = int.from_bytes(raws[0][12:16], "little")
    if encoding == "cdr":
        base = 4 + (12 + flen + 7) // 8 * 8  # frame_id (with its NUL) padded to 8 bytes
    elif encoding == "ros1":
        base = 16 + flen
    else:
        return None
    if base + _TAIL != size:
        return None
    buf = np.frombuffer(b"".join(raws), np.uint8).reshape(len(raws), size)
    if encoding == "cdr" and not (np.all(buf[:, 0] == 0) and np.all(buf[:, 1] == 1)):
        return None  # not little-endian CDR
    sec = np.ascontiguousarray(buf[:, 4:8]).view("<i4" if encoding == "cdr" else "<u4")[:, 0]
    nsec = np.ascontiguousarray(buf[:, 8:12]).view("<u4")[:, 0]
    stamp = sec.astype(np.int64) * 1_000_000_000 + nsec.astype(np.int64)
    gyr = np.ascontiguousarray(buf[:, base + _GYR_OFF:base + _GYR_OFF + 24]).view("<f8").astype(float)
    acc = np.ascontiguousarray(buf[:, base + _ACC_OFF:base + _ACC_OFF + 24]).view("<f8").astype(float)
    for j in {0, len(raws) - 1}:  # the library's decoding of the same bytes must agree exactly
        s, a, w = _fields(deserialize(raws[j]))
        if (s != stamp[j] or np.array(a, float).tobytes() != acc[j].tobytes()
                or np.array(w, float).tobytes() != gyr[j].tobytes()):
            return None
    return stamp, acc, gyr


class _Collector:
    """Buffers one topic's raw messages and decodes them a block at a time."""

    def __init__(self, encoding: str, deserialize: Callable[[bytes], Any]):
        self.encoding, self.deserialize = encoding, deserialize
        self.raws: list[bytes] = []
        self.recv: list[int] = []
        self.parts: list[tuple[np.ndarray, ...]] = []
        self.frame_id: str | None = None
        self.n = 0

    def add(self, receive_ns: int, raw: bytes) -> None:
        self.raws.append(bytes(raw))
        self.recv.append(int(receive_ns))
        self.n += 1
        if len(self.raws) >= BLOCK:
            self._decode()

    def _decode(self) -> None:
        if not self.raws:
            return
        stamp, acc, gyr, frame = decode_imu_block(self.raws, self.encoding, self.deserialize)
        if self.frame_id is None:
            self.frame_id = frame
        self.parts.append((stamp, np.array(self.recv, np.int64), acc, gyr))
        self.raws, self.recv = [], []

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        self._decode()
        if not self.parts:
            return (np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3)))
        return tuple(np.concatenate(c) for c in zip(*self.parts))  # type: ignore[return-value]


# ---------------------------------------------------------------------------- readers

@contextmanager
def _reading(path: Path, what: str, hint: str) -> Iterator[None]:
    """Any failure inside the bag libraries' parsers (a damaged file can fail anywhere in them:
    struct, zstd, lz4, sqlite errors) becomes one InputError line naming the file."""
    try:
        yield
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - see the docstring; the type is named in the message
        raise InputError(f"{what} ({type(exc).__name__}: {exc})", path, hint=hint) from None


class _Raw(NamedTuple):
    """What a reader found: format, topics, the chosen topic, its arrays (stamp ns, receive ns,
    acc, gyr, in file order), its frame_id, and why the file was cut short ('' if it was not)."""

    source_format: str
    topics: list[TopicInfo]
    chosen: TopicInfo
    arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    frame_id: str
    truncated: str


@contextmanager
def _rosbags_reader(path: Path) -> Iterator[Any]:
    from rosbags.highlevel import AnyReader

    with _reading(path, "not a readable ROS bag", "give a rosbag1 file, a rosbag2 directory or an MCAP file"):
        reader = AnyReader([path])
        reader.open()
    try:
        yield reader
    finally:
        reader.close()


def _rosbag1_records(buf: bytes | memoryview, pos: int = 0) -> Iterator[tuple[dict[str, bytes], memoryview, int]]:
    """The records of a rosbag1 byte stream from ``pos``: (header fields, data, end offset), up
    to the first one the bytes do not hold whole (a file cut off there)."""
    view = memoryview(buf)
    n = len(view)
    while pos + 4 <= n:
        (hlen,) = struct.unpack_from("<I", view, pos)
        if pos + 8 + hlen > n:
            return
        fields: dict[str, bytes] = {}
        i, hend = pos + 4, pos + 4 + hlen
        while i + 4 <= hend:
            (flen,) = struct.unpack_from("<I", view, i)
            name, _, value = bytes(view[i + 4:i + 4 + flen]).partition(b"=")
            fields[name.decode("latin-1")] = value
            i += 4 + flen
        (dlen,) = struct.unpack_from("<I", view, hend)
        if hend + 4 + dlen > n:
            return
        yield fields, view[hend + 4:hend + 4 + dlen], hend + 4 + dlen
        pos = hend + 4 + dlen


def _rosbag1_chunk(fields: dict[str, bytes], data: memoryview) -> bytes:
    kind = fields.get("compression", b"none").decode("latin-1")
    if kind == "none":
        return bytes(data)
    if kind == "bz2":
        import bz2
        return bz2.decompress(data)
    if kind == "lz4":
        import lz4.frame  # rosbags' own dependency for lz4 bags
        return lz4.frame.decompress(data)
    raise ValueError(f"chunk compression {kind!r} is not one of none, bz2, lz4")


def _read_rosbag1_unindexed(path: Path, topic: str | None, progress: Progress | None, why: str) -> "_Raw":
    """A ROS 1 bag without a usable index -- ``rosbag record`` killed, a full disk, an incomplete
    copy: its chunks read from the start as far as they go (what ``rosbag reindex`` would
    recover), every message of the complete chunks kept; the connection records inside the chunks
    carry each topic's type and message definition."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    from rosbags.typesys.msg import normalize_msgtype

    data = path.read_bytes()
    conns: dict[int, tuple[str, str, str]] = {}   # id -> topic, type, message definition
    seen: dict[str, TopicInfo] = {}
    cols: dict[str, _Collector] = {}
    n = chunks = 0
    end = len(ROSBAG1_MAGIC)
    for fields, payload, end in _rosbag1_records(data, len(ROSBAG1_MAGIC)):
        if fields.get("op") != b"\x05":
            continue  # the bag header, index records, chunk infos
        chunks += 1
        for rec, body, _ in _rosbag1_records(_rosbag1_chunk(fields, payload)):
            op = rec.get("op")
            if op == b"\x07":
                (cid,) = struct.unpack("<I", rec["conn"])
                info = dict(f.partition(b"=")[::2] for f in _ros1_fields(body))
                conns[cid] = (rec.get("topic", b"").decode(), normalize_msgtype(info.get(b"type", b"").decode()),
                              info.get(b"message_definition", b"").decode())
            elif op == b"\x02":
                (cid,) = struct.unpack("<I", rec["conn"])
                tname, mtype, msgdef = conns.get(cid, ("", "", ""))
                t = seen.setdefault(tname, TopicInfo(tname, mtype, 0))
                t.count = (t.count or 0) + 1
                if mtype == IMU_TYPE and (topic is None or topic == tname):
                    if tname not in cols:
                        store = get_typestore(Stores.EMPTY)
                        store.register(get_types_from_msg(msgdef, IMU_TYPE))
                        cols[tname] = _Collector("ros1", lambda raw, st=store: st.deserialize_ros1(raw, IMU_TYPE))
                    sec, nsec = struct.unpack("<II", rec["time"])
                    cols[tname].add(sec * 1_000_000_000 + nsec, body)
                n += 1
                if progress is not None and n % BLOCK == 0:
                    progress(n, 0)
    if n == 0:
        raise InputError(f"not a readable ROS bag ({why}), and no complete chunk of messages in it", path,
                         hint="give a rosbag1 file, a rosbag2 directory or an MCAP file")
    topics = sorted(seen.values(), key=lambda t: t.topic)
    chosen = choose_topic(path, topics, topic)
    col = cols[chosen.topic]
    left = len(data) - end
    truncated = (f"the bag has no usable index ({why}): read from the start as far as it goes, "
                 f"{n} messages in {chunks} complete chunks"
                 + (f"; the last {left} bytes, a chunk cut short, dropped" if left > 0 else ""))
    return _Raw("rosbag1", topics, chosen, col.arrays(), col.frame_id or "", truncated)


def _ros1_fields(body: memoryview) -> Iterator[bytes]:
    """The length-prefixed fields of a rosbag1 connection header (name=value)."""
    i = 0
    while i + 4 <= len(body):
        (flen,) = struct.unpack_from("<I", body, i)
        yield bytes(body[i + 4:i + 4 + flen])
        i += 4 + flen


def _read_rosbags(path: Path, kind: str, topic: str | None, progress: Progress | None
                  ) -> "_Raw":
    if kind == "rosbag1" and path.name.endswith(".bag.active"):
        return _read_rosbag1_unindexed(path, topic, progress, "a *.bag.active file: rosbag record did not finish it")
    if kind == "rosbag1":
        try:
            with _rosbags_reader(path):
                pass
        except InputError as exc:
            return _read_rosbag1_unindexed(path, topic, progress, str(exc.message).removeprefix(
                "not a readable ROS bag (").removesuffix(")"))
    with _rosbags_reader(path) as reader:
        conns = reader.connections
        topics: dict[str, TopicInfo] = {}
        for c in conns:
            t = topics.setdefault(c.topic, TopicInfo(c.topic, c.msgtype, 0))
            t.count = (t.count or 0) + int(c.msgcount)
        if kind == "rosbag1":
            fmt = "rosbag1"
        else:
            storage = "mcap" if any(p.suffix == ".mcap" for p in _storage_files(path)) else "sqlite3"
            fmt = f"rosbag2 ({storage} storage)"
        listed = sorted(topics.values(), key=lambda t: t.topic)
        chosen = choose_topic(path, listed, topic)
        sel = [c for c in conns if c.topic == chosen.topic]
        encoding = "ros1" if kind == "rosbag1" else "cdr"
        col = _Collector(encoding, lambda raw: reader.deserialize(raw, chosen.msgtype))
        total = int(chosen.count or 0)
        with _reading(path, f"cannot read topic {chosen.topic}", "the bag may be damaged; re-record it"):
            for i, (_, t_ns, raw) in enumerate(reader.messages(connections=sel)):
                col.add(t_ns, raw)
                if progress is not None and i and i % BLOCK == 0:
                    progress(i, total)
            arrays = col.arrays()
    return _Raw(fmt, listed, chosen, arrays, col.frame_id or "", "")


def _storage_files(path: Path) -> list[Path]:
    return [path] if path.is_file() else sorted(p for p in path.iterdir() if p.is_file())


def _mcap_decoder(schema: Any, encoding: str) -> Callable[[bytes], Any]:
    """rosbags' deserialiser for an MCAP channel, built from the schema the file embeds."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    text = schema.data.decode("utf-8")
    if schema.encoding in ("ros2msg", "ros1msg"):
        store.register(get_types_from_msg(text, IMU_TYPE))
    elif schema.encoding == "ros2idl":
        store.register(get_types_from_idl(text))
    else:
        raise ValueError(f"schema encoding {schema.encoding!r} is not a ROS message definition")
    if encoding == "cdr":
        return lambda raw: store.deserialize_cdr(raw, IMU_TYPE)
    return lambda raw: store.deserialize_ros1(raw, IMU_TYPE)


def _mcap_type(schema: Any) -> str:
    from rosbags.typesys.msg import normalize_msgtype

    return normalize_msgtype(schema.name) if schema is not None and schema.name else "(no schema)"


_MCAP_ENCODINGS = {"cdr": "cdr", "ros1": "ros1"}


def _read_mcap(path: Path, topic: str | None, progress: Progress | None
               ) -> "_Raw":
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader, make_reader

    summary = None
    with open(path, "rb") as fh:
        try:
            fmt = f"mcap ({NonSeekingReader(fh).get_header().profile or 'no'} profile)"
        except (McapError, ValueError, AssertionError) as exc:
            raise InputError(f"not a readable MCAP file ({type(exc).__name__}: {exc})", path,
                             hint="give an MCAP file written by ros2 bag or an MCAP writer") from None
        fh.seek(0)
        try:
            summary = make_reader(fh).get_summary()
        except (McapError, OSError, ValueError, AssertionError):
            summary = None  # no summary or footer: cut off; stream it below
    if summary is not None and summary.channels:
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        listed: dict[str, TopicInfo] = {}
        for cid, ch in summary.channels.items():
            t = listed.setdefault(ch.topic, TopicInfo(ch.topic, _mcap_type(summary.schemas.get(ch.schema_id)),
                                                      0 if counts else None))
            if counts:
                t.count = (t.count or 0) + int(counts.get(cid, 0))
        topics = sorted(listed.values(), key=lambda t: t.topic)
        chosen = choose_topic(path, topics, topic)
        col: _Collector | None = None
        with open(path, "rb") as fh, _reading(path, f"cannot read topic {chosen.topic}",
                                              "the file may be damaged"):
            for i, (schema, ch, msg) in enumerate(make_reader(fh).iter_messages(topics=[chosen.topic])):
                if col is None:
                    col = _mcap_collector(path, schema, ch)
                col.add(msg.log_time, msg.data)
                if progress is not None and i and i % BLOCK == 0:
                    progress(i, int(chosen.count or 0))
            arrays = col.arrays() if col is not None else None
        if col is None or arrays is None:
            raise InputError(f"topic {chosen.topic} has no messages; topics present: {topics_text(topics)}",
                             path, hint="choose a topic with messages")
        return _Raw(fmt, topics, chosen, arrays, col.frame_id or "", "")
    # no summary: one streaming pass, every Imu channel decoded, the others only counted
    cols: dict[str, _Collector] = {}
    seen: dict[str, TopicInfo] = {}
    truncated = ""
    with open(path, "rb") as fh, _reading(path, "cannot read the MCAP file", "the file may be damaged"):
        n = 0
        try:
            for schema, ch, msg in NonSeekingReader(fh).iter_messages(log_time_order=False):
                t = seen.setdefault(ch.topic, TopicInfo(ch.topic, _mcap_type(schema), 0))
                t.count = (t.count or 0) + 1
                if t.msgtype == IMU_TYPE and (topic is None or topic == ch.topic):
                    if ch.topic not in cols:
                        cols[ch.topic] = _mcap_collector(path, schema, ch)
                    cols[ch.topic].add(msg.log_time, msg.data)
                n += 1
                if progress is not None and n % BLOCK == 0:
                    progress(n, 0)
        except (McapError, struct.error, EOFError) as exc:
            # the file ends inside a record: mcap's stream reader raises EndOfFile where the cut
            # falls on a record's opcode, struct.error ("unpack requires a buffer of 8 bytes")
            # where it falls inside a record's length or fields -- the commoner case
            if n == 0:
                raise InputError(f"MCAP file without a summary and without a complete message "
                                 f"({type(exc).__name__}: {exc}): cut off before its first chunk ended?", path,
                                 hint="give an MCAP file written by ros2 bag or an MCAP writer") from None
            why = "a record cut short" if isinstance(exc, (struct.error, EOFError)) else type(exc).__name__
            truncated = (f"the file ends early ({why}): no summary, read as far as it "
                         f"goes ({n} messages)")
        topics = sorted(seen.values(), key=lambda t: t.topic)
        chosen = choose_topic(path, topics, topic)
        col = cols[chosen.topic]
        arrays = col.arrays()
    return _Raw(fmt, topics, chosen, arrays, col.frame_id or "", truncated)


def _mcap_collector(path: Path, schema: Any, channel: Any) -> _Collector:
    enc = _MCAP_ENCODINGS.get(channel.message_encoding)
    if enc is None or schema is None:
        raise InputError(f"topic {channel.topic}: message encoding {channel.message_encoding!r} "
                         "is not ROS (cdr or ros1)", path, hint="rigctl reads ROS 1 and ROS 2 Imu messages")
    try:
        return _Collector(enc, _mcap_decoder(schema, enc))
    except Exception as exc:  # noqa: BLE001 - any failure of the embedded definition is bad input
        raise InputError(f"topic {channel.topic}: the embedded message definition cannot be used "
                         f"({type(exc).__name__}: {exc})", path) from None


# ---------------------------------------------------------------------------- time and gaps

@dataclass
class TimeBase:
    """Sorted, de-duplicated sample times and the counter they imply (see the module doc)."""

    order: np.ndarray  # indices into the input, in time order, repeats removed
    time_ns: np.ndarray  # chosen time of those samples, ns
    counter: np.ndarray  # uint64, starts at 0; a jump of k + 1 means k samples missing
    interval_ns: float  # least-squares slope of time on counter (the median when counted_by "intervals"), ns
    median_interval_ns: float
    counted_by: str  # "grid" (grid_counter) or "intervals" (max(1, round(dt / median)))
    gaps: int
    missing: int
    largest_gap_ns: int
    duplicates: int
    reordered: int


def time_base(time_ns: np.ndarray, acc: np.ndarray, gyr: np.ndarray) -> TimeBase:
    """Sort by ``time_ns``, drop exact repeats, estimate the interval (median of the
    differences) and build the counter: c_0 = 0, c_i = c_(i-1) + max(1, round(dt_i / T)).

    Raises ValueError for fewer than two distinct times or a time shared by different values."""
    reordered = int(np.count_nonzero(np.diff(time_ns) < 0))
    order = np.argsort(time_ns, kind="stable")
    ts = time_ns[order]
    same = np.flatnonzero(np.diff(ts) == 0)
    if same.size:
        a, b = order[same], order[same + 1]
        differ = np.any(acc[a] != acc[b], axis=1) | np.any(gyr[a] != gyr[b], axis=1)
        if np.any(differ):
            j = int(same[np.argmax(differ)])
            raise ValueError(f"{int(np.count_nonzero(differ))} samples share their time with a "
                             f"different sample (first at {(ts[j] - ts[0]) * 1e-9:.6f} s from the start)")
        keep = np.ones(ts.size, bool)
        keep[same + 1] = False
        order, ts = order[keep], ts[keep]
    if ts.size < 2:
        raise ValueError(f"only {ts.size} distinct sample time(s)")
    dt = np.diff(ts)
    median = float(np.median(dt))
    rel = (ts - ts[0]).astype(np.float64)
    counter, interval, how = None, median, "grid"
    for _ in range(2):  # the second pass with the mean interval the first pass's counter gives
        counter = grid_counter(rel, interval)
        if counter is None or counter[-1] == 0:
            counter = None
            break
        cc = counter - counter.mean()
        interval = float(cc @ (rel - rel.mean()) / (cc @ cc))  # least-squares slope of t on c
    if counter is None:  # stamps too irregular for a grid: count from consecutive intervals
        interval, how = median, "intervals"
        counter = np.concatenate(([0], np.cumsum(np.maximum(1, np.rint(dt / median))))).astype(np.int64)
    steps = np.diff(counter)
    gap = steps > 1
    return TimeBase(order=order, time_ns=ts, counter=counter.astype(np.uint64), interval_ns=interval,
                    median_interval_ns=median, counted_by=how,
                    gaps=int(np.count_nonzero(gap)), missing=int(np.sum(steps[gap] - 1)),
                    largest_gap_ns=int(dt[gap].max()) if np.any(gap) else 0,
                    duplicates=int(same.size), reordered=reordered)


def grid_counter(t: np.ndarray, interval: float, window: int = 64) -> np.ndarray | None:
    """Sample numbers of the times ``t`` (s or ns, from 0) on a grid of period ``interval``
    that follows the clock slowly: per window of ``window`` samples the grid's phase is the
    circular mean phi_w = T/(2 pi) arg sum_j exp(2 pi i t_j / T) (missing samples do not move
    it, jitter averages out), unwrapped across windows (drift between the stamps' clock and the
    sensor's), interpolated to each sample; c_i = round((t_i - phi_i) / T) - c_0. None when two
    samples fall in one slot (jitter beyond half an interval)."""
    n = t.size
    nw = -(-n // window)
    z = np.zeros(nw * window, complex)
    z[:n] = np.exp(2j * np.pi * (t / interval))
    phase = np.unwrap(np.angle(z.reshape(nw, window).sum(axis=1))) * interval / (2 * np.pi)
    starts = np.arange(nw) * window
    centres = starts + (np.minimum(window, n - starts) - 1) / 2.0
    c = np.rint((t - np.interp(np.arange(n), centres, phase)) / interval).astype(np.int64)
    c -= c[0]
    return None if np.any(np.diff(c) <= 0) else c


def read_imu(path: str | Path, topic: str | None = None, time_source: str = "header",
             progress: Progress | None = None) -> BagImu:
    """Read one Imu topic of a ROS bag / rosbag2 directory / MCAP file (see the module doc).

    ``progress(done, total)`` is called every few ten thousand messages (total 0 if unknown).
    """
    path = Path(path)
    if not path.exists():
        raise InputError("input file not found", path)
    missing = [m for m in ("rosbags", "mcap") if importlib.util.find_spec(m) is None]
    if missing:
        raise InputError(f"reading ROS bags and MCAP files needs {' and '.join(missing)}", path,
                         hint="pip install 'rigctl[ros]'")
    if time_source not in ("header", "receive"):
        raise InputError(f"--time-source {time_source!r}: use header or receive")
    kind = bag_kind(path)
    if kind is None:
        raise InputError("not a ROS bag or MCAP file (neither a rosbag1 file, a rosbag2 directory "
                         "with metadata.yaml, nor an MCAP file)", path,
                         hint="give a .bag, a rosbag2 directory or a .mcap file; CSV needs --columns")
    active = kind == "rosbag1" and path.name.endswith(".bag.active")  # rosbag record's file while it ran
    if kind != "mcap" and path.is_file() and not active and path.suffix != {"rosbag1": ".bag"}.get(kind, ".db3"):
        want = {"rosbag1": ".bag"}.get(kind, ".db3")
        raise InputError(f"a {'ROS 1 bag' if kind == 'rosbag1' else 'rosbag2 sqlite3 file'} must be "
                         f"named *{want} to be read", path, hint=f"rename or link it to *{want}")
    raw = _read_mcap(path, topic, progress) if kind == "mcap" else _read_rosbags(path, kind, topic, progress)
    chosen, topics = raw.chosen, raw.topics
    stamp, recv, acc, gyr = raw.arrays
    if stamp.size == 0:
        raise InputError(f"topic {chosen.topic} has no messages; topics present: {topics_text(topics)}",
                         path, hint="choose a topic with messages")
    chosen_t = stamp if time_source == "header" else recv
    what = "header.stamp" if time_source == "header" else "bag receive time"
    try:
        tb = time_base(chosen_t, acc, gyr)
    except ValueError as exc:
        other = "receive" if time_source == "header" else "header"
        raise InputError(f"topic {chosen.topic}: {what} is not a usable sample time: {exc}", path,
                         hint=f"try --time-source {other}") from None
    o = tb.order
    bad = ~(np.isfinite(acc[o]).all(axis=1) & np.isfinite(gyr[o]).all(axis=1))
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(f"topic {chosen.topic}: {int(bad.sum())} messages with a non-finite "
                         f"linear_acceleration or angular_velocity (first at {(tb.time_ns[k] - tb.time_ns[0]) / 1e9:.6f} s, "
                         f"sample {k})", path, hint="remove them from the bag (e.g. filter the topic) and import again")
    lat = (recv[o] - stamp[o]) / 1e9
    notes = []
    if tb.counted_by == "intervals":
        notes.append(f"{what} jitters by more than half a sample interval: the gaps are counted from "
                     "consecutive intervals (max(1, round(dt / median))) and may be miscounted")
    if raw.truncated:
        notes.append(raw.truncated)
    return BagImu(source_format=raw.source_format, topic=chosen.topic, msgtype=chosen.msgtype,
                  frame_id=raw.frame_id, time_source=what,
                  time_s=(tb.time_ns - tb.time_ns[0]).astype(np.float64) / 1e9,
                  counter=tb.counter, specific_force=acc[o], angular_rate=gyr[o],
                  rate_hz=1e9 / tb.interval_ns, interval_ns=tb.interval_ns,
                  median_interval_ns=tb.median_interval_ns,
                  stamp_zero_ns=int(tb.time_ns[0]), n_messages=int(stamp.size), gaps=tb.gaps,
                  missing_samples=tb.missing, largest_gap_s=tb.largest_gap_ns / 1e9,
                  duplicates_dropped=tb.duplicates, reordered=tb.reordered,
                  receive_minus_stamp_s={"median": float(np.median(lat)), "min": float(lat.min()),
                                         "max": float(lat.max())},
                  topics=topics, truncated=raw.truncated, notes=notes)


def describe(b: BagImu) -> list[str]:
    """The lines ``rigctl import`` prints about a bag import (rate, gaps, clock)."""
    dur = float(b.time_s[-1]) if b.time_s.size else 0.0
    lines = [f"{b.source_format}: topic {b.topic} ({b.msgtype}, frame_id '{b.frame_id}'), "
             f"{b.n_messages} messages over {dur:.3f} s, time = {b.time_source}",
             f"sample rate {format_rate(b.rate_hz)} (mean interval, gaps counted: "
             f"{b.interval_ns / 1e6:.8g} ms; median interval {b.median_interval_ns / 1e6:.8g} ms)"]
    if b.gaps:
        lines.append(f"gaps: {b.gaps} ({b.missing_samples} samples missing, largest "
                     f"{b.largest_gap_s:.6g} s); recorded as /imu/counter jumps")
    else:
        lines.append("gaps: none")
    extra = []
    if b.duplicates_dropped:
        extra.append(f"{b.duplicates_dropped} repeated messages dropped")
    if b.reordered:
        extra.append(f"{b.reordered} messages out of order in the bag (sorted by time)")
    if extra:
        lines.append("; ".join(extra))
    r = b.receive_minus_stamp_s
    if math.isfinite(r["median"]):
        lines.append(f"bag receive time - header.stamp: median {r['median']:.6g} s "
                     f"(min {r['min']:.6g}, max {r['max']:.6g})")
    lines.extend(f"warning: {n}" for n in b.notes)
    return lines
