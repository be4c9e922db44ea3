"""`rigctl import` of ROS bags and MCAP files, written here with those libraries' own writers.

The same samples (a rest, a turn, a rest; 3 samples missing; two frame_id spellings so the
messages have two lengths) go into a rosbag1 (rosbags.rosbag1.Writer), a rosbag2 with sqlite3
storage and one with mcap storage (rosbags.rosbag2.Writer), a bare MCAP file
(mcap_ros2.writer.Writer, profile ros2) and a ROS 1 profile MCAP (mcap.writer.Writer with
rosbags' ROS 1 serialiser, as `mcap convert` writes). Each bag also holds a std_msgs/String
topic. Expected values come from the samples themselves (plain numpy): time = header stamp
minus the first, counter jumping by 4 over the 3 missing samples, rate 200 Hz.
"""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from rigctl.analysis import bag_import as B
from rigctl.cli import main

rosbags = pytest.importorskip("rosbags")
from mcap.writer import Writer as McapWriter  # noqa: E402
from mcap_ros2.writer import Writer as McapRos2Writer  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

IMU = "sensor_msgs/msg/Imu"
RATE = 200.0
T0_NS = 1_700_000_000_123_456_789
N_ALL = 4000
MISSING = slice(2500, 2503)  # three samples never published


def _samples() -> dict[str, np.ndarray]:
    """Stamps (ns), receive times (ns), specific force and rate: 8 s at rest, a 90 deg turn
    about z in 2 s while tilted, 10 s at rest; white noise."""
    rng = np.random.default_rng(5)
    k = np.arange(N_ALL)
    stamp = T0_NS + k * 5_000_000
    acc = np.array([0.0, 0.0, 9.80665]) + 0.02 * rng.standard_normal((N_ALL, 3))
    gyr = 2e-3 * rng.standard_normal((N_ALL, 3))
    turn = (k >= 1600) & (k < 2000)
    gyr[turn, 2] += np.pi / 2 / 2.0
    acc[k >= 1800, 0] += 3.0  # a different pose after the turn
    keep = np.ones(N_ALL, bool)
    keep[MISSING] = False
    recv = stamp + 1_000_000 + (k % 7) * 100_000  # received 1.0-1.6 ms later
    frames = np.where(k % 2 == 0, "imu_link", "imu")
    return {"stamp": stamp[keep], "recv": recv[keep], "acc": acc[keep], "gyr": gyr[keep],
            "frame": frames[keep]}


def _imu(store, s, i: int):
    T = store.types
    hdr = {"stamp": T["builtin_interfaces/msg/Time"](sec=int(s["stamp"][i] // 10**9),
                                                      nanosec=int(s["stamp"][i] % 10**9)),
           "frame_id": str(s["frame"][i])}
    if "seq" in T["std_msgs/msg/Header"].__dataclass_fields__:
        hdr["seq"] = i
    v3 = T["geometry_msgs/msg/Vector3"]
    return T[IMU](header=T["std_msgs/msg/Header"](**hdr),
                  orientation=T["geometry_msgs/msg/Quaternion"](x=0.1, y=0.2, z=0.3, w=0.9),
                  orientation_covariance=np.full(9, -1.0),
                  angular_velocity=v3(*s["gyr"][i]), angular_velocity_covariance=np.full(9, 1e-6),
                  linear_acceleration=v3(*s["acc"][i]), linear_acceleration_covariance=np.full(9, 1e-4))


def _string(store, text: str):
    return store.types["std_msgs/msg/String"](data=text)


def _fill(w, store, serialize, s) -> None:
    """The Imu samples on /imu and a String every 500 samples on /status, with rosbags' writer."""
    ci = w.add_connection("/imu", IMU, typestore=store)
    cs = w.add_connection("/status", "std_msgs/msg/String", typestore=store)
    for i in range(len(s["stamp"])):
        w.write(ci, int(s["recv"][i]), serialize(_imu(store, s, i), IMU))
        if i % 500 == 0:
            w.write(cs, int(s["recv"][i]), serialize(_string(store, "ok"), "std_msgs/msg/String"))


def write_rosbag1(path: Path, s) -> Path:
    store = get_typestore(Stores.ROS1_NOETIC)
    with Writer1(path) as w:
        _fill(w, store, store.serialize_ros1, s)
    return path


def write_rosbag2(path: Path, s, storage) -> Path:
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Writer2(path, version=9, storage_plugin=storage) as w:
        _fill(w, store, store.serialize_cdr, s)
    return path


def write_mcap_ros2(path: Path, s, chunk_size: int = 1 << 20) -> Path:
    store = get_typestore(Stores.ROS2_HUMBLE)
    with open(path, "wb") as fh:
        w = McapRos2Writer(fh, chunk_size=chunk_size)
        imu = w.register_msgdef(IMU, store.generate_msgdef(IMU, ros_version=2)[0])
        txt = w.register_msgdef("std_msgs/msg/String", "string data\n")
        for i in range(len(s["stamp"])):
            a, g = s["acc"][i], s["gyr"][i]
            w.write_message("/imu", imu, {
                "header": {"stamp": {"sec": int(s["stamp"][i] // 10**9), "nanosec": int(s["stamp"][i] % 10**9)},
                           "frame_id": str(s["frame"][i])},
                "orientation": {"x": 0.1, "y": 0.2, "z": 0.3, "w": 0.9}, "orientation_covariance": [-1.0] * 9,
                "angular_velocity": {"x": g[0], "y": g[1], "z": g[2]}, "angular_velocity_covariance": [1e-6] * 9,
                "linear_acceleration": {"x": a[0], "y": a[1], "z": a[2]},
                "linear_acceleration_covariance": [1e-4] * 9}, log_time=int(s["recv"][i]))
            if i % 500 == 0:
                w.write_message("/status", txt, {"data": "ok"}, log_time=int(s["recv"][i]))
        w.finish()
    return path


def write_mcap_ros1(path: Path, s) -> Path:
    """A ROS 1 profile MCAP (ros1msg schemas, ros1 message encoding), as `mcap convert` makes."""
    store = get_typestore(Stores.ROS1_NOETIC)
    with open(path, "wb") as fh:
        w = McapWriter(fh)
        w.start(profile="ros1", library="test")
        sid = w.register_schema("sensor_msgs/Imu", "ros1msg",
                                store.generate_msgdef(IMU, ros_version=1)[0].encode())
        cid = w.register_channel("/imu", "ros1", sid)
        for i in range(len(s["stamp"])):
            w.add_message(cid, log_time=int(s["recv"][i]), publish_time=int(s["recv"][i]),
                          data=bytes(store.serialize_ros1(_imu(store, s, i), IMU)))
        w.finish()
    return path


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("bags")
    s = _samples()
    return {"rosbag1": write_rosbag1(d / "imu.bag", s),
            "rosbag2 (sqlite3 storage)": write_rosbag2(d / "imu_sqlite", s, StoragePlugin.SQLITE3),
            "rosbag2 (mcap storage)": write_rosbag2(d / "imu_mcap", s, StoragePlugin.MCAP),
            "mcap (ros2 profile)": write_mcap_ros2(d / "imu.mcap", s),
            "mcap (ros1 profile)": write_mcap_ros1(d / "imu_ros1.mcap", s)}


def _rigctl(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["import", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def _read(rec: Path) -> tuple[dict, dict, dict]:
    with h5py.File(rec, "r") as f:
        assert f["run/status"][0] == b"complete"
        imu = {k: f["imu"][k][()] for k in f["imu"]}
        imu["rate"] = f["imu"].attrs["sample_rate_hz"]
        seg = {k: f["segments"][k][()] for k in f["segments"]}
        meta = dict(f["meta"].attrs)
    return imu, seg, meta


def test_every_format_imports_to_the_same_recording(bags, tmp_path, capsys):
    s = _samples()
    recs = {}
    for name, path in bags.items():
        rec = tmp_path / f"{path.name}.h5"
        code, out, err = _rigctl(capsys, str(path), "-o", str(rec))
        assert code == 0, err
        assert "gaps: 1 (3 samples missing, largest 0.02 s)" in out
        assert "sample rate 200 Hz (mean interval, gaps counted: 5 ms; median interval 5 ms)" in out
        recs[name] = _read(rec)
    imu, seg, meta = recs["rosbag1"]
    # against the samples themselves
    assert np.array_equal(imu["time"], (s["stamp"] - s["stamp"][0]) / 1e9)
    assert np.array_equal(imu["specific_force"], s["acc"]) and np.array_equal(imu["angular_rate"], s["gyr"])
    counter = np.arange(N_ALL)[np.r_[0:MISSING.start, MISSING.stop:N_ALL]]
    assert np.array_equal(imu["counter"], counter.astype(np.uint64))
    assert imu["rate"] == pytest.approx(RATE, rel=1e-12) and np.all(np.isnan(imu["temperature"]))
    assert meta["import_topic"] == "/imu" and meta["import_msgtype"] == IMU
    assert meta["import_stamp_zero_ns"] == T0_NS and meta["import_gaps"] == 1
    assert meta["import_missing_samples"] == 3 and meta["import_time_source"] == "header.stamp"
    lat = json.loads(meta["import_receive_minus_stamp_s_json"])
    assert lat["min"] == pytest.approx(1e-3) and lat["max"] == pytest.approx(1.6e-3)
    # segments: rest, turn (capture), rest in the new pose
    kinds = [k.decode() for k in seg["kind"]]
    assert kinds.count("orientation") == 2, kinds
    # every format: the same arrays bit for bit, the same segments and meta but the source
    for name, (imu2, seg2, meta2) in recs.items():
        assert meta2["import_format"] == name
        for k in imu:
            assert imu2[k].dtype == imu[k].dtype and imu2[k].tobytes() == imu[k].tobytes(), (name, k)
        for k in seg:
            assert seg2[k].tobytes() == seg[k].tobytes(), (name, k)
        skip = {"import_source", "import_format", "started_utc", "ended_utc", "import_utc"}
        assert {k: str(v) for k, v in meta2.items() if k not in skip} == \
            {k: str(v) for k, v in meta.items() if k not in skip}, name


def test_topic_choice_and_one_line_errors(bags, tmp_path, capsys):
    d = tmp_path
    rec = d / "x.h5"
    bag = bags["rosbag2 (sqlite3 storage)"]
    cases = [
        ((str(d / "nope.bag"),), "input file not found"),
        ((str(d / "notabag.bag"),), "not a ROS bag or MCAP file"),
        ((str(d / "notmcap.mcap"),), "not a ROS bag or MCAP file"),
        ((str(bag), "--topic", "/status"), "topic /status is std_msgs/msg/String, not sensor_msgs/msg/Imu; "
                                           "topics present: /imu (sensor_msgs/msg/Imu, 3997 messages), "
                                           "/status (std_msgs/msg/String, 8 messages)"),
        ((str(bag), "--topic", "/imu0"), "no topic /imu0; topics present: /imu"),
        ((str(bag), "--columns", "acc_x=1"), "--columns applies to CSV files only"),
    ]
    (d / "notabag.bag").write_text("time,ax\n0,1\n")
    (d / "notmcap.mcap").write_bytes(b"\x89MCAP9\r\n" + bytes(100))
    # no Imu topic at all; an Imu topic without messages
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Writer2(d / "status_only", version=9) as w:
        c = w.add_connection("/status", "std_msgs/msg/String", typestore=store)
        w.write(c, 1, store.serialize_cdr(_string(store, "x"), "std_msgs/msg/String"))
    with Writer2(d / "empty_imu", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection("/imu", IMU, typestore=store)
    s_nan = _samples()
    s_nan["gyr"][7, 1] = np.nan
    write_mcap_ros2(d / "nan.mcap", s_nan)
    cases.append(((str(d / "nan.mcap"),), "1 messages with a non-finite linear_acceleration or angular_velocity "
                                          "(first at 0.035000 s, sample 7)"))
    cases += [((str(d / "status_only"),), "no sensor_msgs/msg/Imu topic; topics present: "
                                          "/status (std_msgs/msg/String, 1 messages)"),
              ((str(d / "empty_imu"),), "topic /imu has no messages")]
    # two Imu topics: --topic needed
    s = _samples()
    store1 = get_typestore(Stores.ROS1_NOETIC)
    with Writer1(d / "two.bag") as w:
        for t in ("/imu0", "/imu1"):
            c = w.add_connection(t, IMU, typestore=store1)
            w.write(c, 1, store1.serialize_ros1(_imu(store1, s, 0), IMU))
    cases.append(((str(d / "two.bag"),), "2 sensor_msgs/msg/Imu topics (/imu0, /imu1); choose one with --topic"))
    for args, text in cases:
        code, out, err = _rigctl(capsys, *args, "-o", str(rec))
        assert code == 2, (args, err)
        assert err.count("\n") == 1 and text in err and "Traceback" not in err, (args, err)
        assert not rec.exists()
    code, out, err = _rigctl(capsys, str(bag), "--topic", "/imu", "-o", str(rec))
    assert code == 0 and "topic /imu" in out


def test_cut_off_mcap_keeps_the_complete_chunks(tmp_path, capsys):
    """An MCAP without summary (the recorder was killed): the messages before the cut."""
    s = _samples()
    full = write_mcap_ros2(tmp_path / "full.mcap", s, chunk_size=16_000).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full[: len(full) // 2])
    rec = tmp_path / "cut.h5"
    code, out, err = _rigctl(capsys, str(cut), "-o", str(rec))
    assert code == 0, err
    assert "warning: the file ends early" in out
    imu, _, _ = _read(rec)
    n = len(imu["time"])
    assert 1000 < n < len(s["stamp"])
    assert np.array_equal(imu["specific_force"], s["acc"][:n]) and np.array_equal(imu["angular_rate"], s["gyr"][:n])


def test_time_base_sorts_drops_repeats_and_counts_gaps():
    rng = np.random.default_rng(1)
    k = np.r_[0:500, 502:900, 905:3000]  # two and five missing
    # host-clock stamps: 100.002 Hz sensor, 10 ms nominal, +-0.3 interval jitter on every stamp
    t = (k * 9_999_800 + rng.integers(-3_000_000, 3_000_000, k.size)).astype(np.int64)
    acc = rng.standard_normal((k.size, 3))
    gyr = rng.standard_normal((k.size, 3))
    perm = np.r_[0:10, 11, 10, 12:k.size]  # two messages swapped in the bag
    rep = np.r_[perm, 20]  # and one recorded twice
    tb = B.time_base(t[rep], acc[rep], gyr[rep])
    assert tb.reordered == 2 and tb.duplicates == 1
    assert np.array_equal(tb.time_ns, t) and np.array_equal(rep[tb.order], np.arange(k.size))
    assert np.array_equal(tb.counter, k.astype(np.uint64)) and tb.gaps == 2 and tb.missing == 7
    # least-squares slope: sd = jitter sd / sqrt(sum (c - mean c)^2), jitter sd = 6 ms / sqrt(12)
    sd = 6e6 / np.sqrt(12) / np.sqrt(np.sum((k - k.mean()) ** 2))
    assert tb.counted_by == "grid" and tb.interval_ns == pytest.approx(9_999_800, abs=4 * sd)
    # the sensor's clock drifts against the stamps by 200 ppm over the record: still no false gap
    drift = (t + 2e-4 * t * t / t[-1]).astype(np.int64)
    assert np.array_equal(B.time_base(drift, acc, gyr).counter, k.astype(np.uint64))
    bad = np.r_[0:k.size, 20]
    acc2 = acc[bad].copy()
    acc2[-1] += 1.0  # same time, other values
    with pytest.raises(ValueError, match="share their time"):
        B.time_base(t[bad], acc2, gyr[bad])


def test_vectorised_decoding_equals_rosbags_message_by_message():
    s = _samples()
    for stores, ser, enc in ((Stores.ROS2_HUMBLE, "serialize_cdr", "cdr"),
                             (Stores.ROS1_NOETIC, "serialize_ros1", "ros1")):
        store = get_typestore(stores)
        raws = [bytes(getattr(store, ser)(_imu(store, s, i), IMU)) for i in range(300)]
        assert len({len(r) for r in raws}) == 2  # the two frame_ids
        de = (store.deserialize_cdr if enc == "cdr" else store.deserialize_ros1)
        stamp, acc, gyr, frame = B.decode_imu_block(raws, enc, lambda r: de(r, IMU))
        assert frame == "imu_link"
        assert np.array_equal(stamp, s["stamp"][:300])
        assert acc.tobytes() == s["acc"][:300].tobytes() and gyr.tobytes() == s["gyr"][:300].tobytes()


@pytest.mark.parametrize("frac", [0.3, 0.5, 0.77, 0.999])
def test_mcap_cut_anywhere_keeps_what_was_read(tmp_path, capsys, frac):
    """Wherever the cut falls -- on a record's opcode (mcap's own stream reader: EndOfFile) or
    inside a record's length or fields (struct.error, the commoner case: a 1 h bare MCAP cut
    at half its length was refused with "cannot read the MCAP file (error: unpack requires a
    buffer of 8 bytes)") -- the import warns and keeps the messages read before the cut, a
    prefix of the samples (64 kB chunks, zstd; four cut points)."""
    from mcap.reader import NonSeekingReader

    s = _samples()
    full = write_mcap_ros2(tmp_path / "full.mcap", s, chunk_size=64_000).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full[: int(len(full) * frac)])
    # what mcap's own reader makes of the cut (read here, not by rigctl)
    n_lib = 0
    with open(cut, "rb") as fh:
        try:
            for _schema, ch, _msg in NonSeekingReader(fh).iter_messages(log_time_order=False):
                n_lib += ch.topic == "/imu"
            raised = None
        except Exception as exc:  # noqa: BLE001 - the type is what the test reports
            raised = type(exc).__name__
    assert raised is not None and n_lib > 0
    rec = tmp_path / "cut.h5"
    code, out, err = _rigctl(capsys, str(cut), "-o", str(rec))
    assert code == 0, (raised, err)
    assert "warning: the file ends early (" in out and "(error)" not in out
    imu, _, _ = _read(rec)
    n = len(imu["time"])
    assert n == n_lib
    assert np.array_equal(imu["specific_force"], s["acc"][:n]) and np.array_equal(imu["angular_rate"], s["gyr"][:n])


def test_a_binary_file_is_not_called_a_csv_file(tmp_path, capsys):
    """A PNG (matplotlib's, as an Allan plot) given to `rigctl import`: it was refused as "a CSV
    file" lacking --columns; it is binary data, neither a table nor a bag."""
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    png = tmp_path / "allan.png"
    fig, ax = plt.subplots()
    ax.plot([1, 2], [3, 4])
    fig.savefig(png)
    plt.close(fig)
    code, out, err = _rigctl(capsys, str(png), "-o", str(tmp_path / "x.h5"))
    assert code == 2 and err.count("\n") == 1 and str(png) in err
    assert "a binary file, not a text table" in err and "--columns" not in err, err
    # a text table without --columns is still asked for them
    csv = tmp_path / "log.csv"
    csv.write_text("time,ax\n0,1\n")
    code, out, err = _rigctl(capsys, str(csv), "-o", str(tmp_path / "y.h5"))
    assert code == 2 and "--columns is required" in err


def test_an_imported_bag_is_dated_by_its_own_stamps(bags, tmp_path, capsys):
    """/meta started_utc and ended_utc of an imported bag are the capture's (first and last
    stamp), not the import's: the report's "started (UTC)" and the results database's
    "recorded" time read them. A 2023 bag imported today said today. The import's own time is
    kept in import_utc. Stamps that are no wall-clock time (a sensor's time since boot) leave
    the import's times, and /meta capture_time says the capture's time is unknown."""
    import datetime as dt

    def iso(ns: int) -> str:  # written out here: ns since the epoch -> the recorder's ISO form
        t = dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc) + dt.timedelta(microseconds=ns // 1000)
        return t.strftime("%Y-%m-%dT%H:%M:%S.%fZ")

    s = _samples()
    rec = tmp_path / "dated.h5"
    code, out, err = _rigctl(capsys, str(bags["rosbag2 (sqlite3 storage)"]), "-o", str(rec))
    assert code == 0, err
    _, _, meta = _read(rec)
    assert meta["started_utc"] == iso(int(s["stamp"][0])) == "2023-11-14T22:13:20.123456Z"
    assert meta["ended_utc"] == iso(int(s["stamp"][-1]))
    today = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d")
    assert meta["import_utc"].startswith(today)
    # stamps since boot (5 s): the import's own times
    boot = {k: v for k, v in s.items()}
    boot["stamp"] = s["stamp"] - T0_NS + 5_000_000_000
    boot["recv"] = s["recv"] - T0_NS + 5_000_000_000
    rec2 = tmp_path / "boot.h5"
    code, out, err = _rigctl(capsys, str(write_mcap_ros2(tmp_path / "boot.mcap", boot)), "-o", str(rec2))
    assert code == 0, err
    _, _, meta2 = _read(rec2)
    assert meta2["started_utc"].startswith(today) and meta2["capture_time"].startswith("unknown")
    assert meta["capture_time"] == "the file's own time stamps (wall clock)"


def _rosbag1_index_pos(data: bytes) -> int:
    """index_pos from a rosbag1 file's bag header record (the first record after the 13-byte
    magic: u32 header length, fields 'u32 length, name=value', op 0x03), parsed here."""
    pos = 13
    (hlen,) = np.frombuffer(data[pos:pos + 4], "<u4")
    i = pos + 4
    while i < pos + 4 + hlen:
        (flen,) = np.frombuffer(data[i:i + 4], "<u4")
        name, _, value = data[i + 4:i + 4 + flen].partition(b"=")
        if name == b"index_pos":
            return int(np.frombuffer(value, "<u8")[0])
        i += 4 + flen
    raise AssertionError("no index_pos in the bag header")


@pytest.mark.parametrize("compression", [None, "bz2"])
def test_cut_off_rosbag1_keeps_the_complete_chunks(tmp_path, capsys, compression):
    """A ROS 1 bag whose index was never written (`rosbag record` killed, a full disk, an
    incomplete copy) -- rosbags refuses it ('Bag index looks damaged'), so the import read
    nothing and the capture was lost without ROS's `rosbag reindex`. Cut where its index
    begins: every message is there (all samples back, bit for bit); cut in the middle: a
    prefix of the samples, the complete chunks', with a warning (read under the name
    NAME.bag.active that a killed `rosbag record` leaves, too)."""
    s = _samples()
    store = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp_path / "full.bag"
    w = Writer1(bag)
    w.chunk_threshold = 24_000  # several chunks in this short bag (1 MiB by default)
    if compression:
        w.set_compression(Writer1.CompressionFormat.BZ2)
    with w:
        _fill(w, store, store.serialize_ros1, s)
    full = bag.read_bytes()
    index_pos = _rosbag1_index_pos(full)
    assert 0 < index_pos < len(full)
    for name, size in (("noindex", index_pos), ("half", len(full) // 2)):
        # the half-written one under the name `rosbag record` gives the file while it records
        cut = tmp_path / (f"{name}.bag" if name == "noindex" else f"{name}.bag.active")
        cut.write_bytes(full[:size])
        rec = tmp_path / f"{name}.h5"
        code, out, err = _rigctl(capsys, str(cut), "--topic", "/imu", "-o", str(rec))
        assert code == 0, err
        assert "warning: the bag has no usable index" in out, out
        imu, _, _ = _read(rec)
        n = len(imu["time"])
        if name == "noindex":
            assert n == len(s["stamp"]) and "dropped" not in out
            assert np.array_equal(imu["counter"], (s["stamp"] - s["stamp"][0]) // 5_000_000)
        else:
            assert 500 < n < len(s["stamp"]) and "a chunk cut short, dropped" in out
        assert np.array_equal(imu["specific_force"], s["acc"][:n]) and np.array_equal(imu["angular_rate"], s["gyr"][:n])
        assert np.array_equal(imu["time"], (s["stamp"][:n] - s["stamp"][0]) / 1e9)
