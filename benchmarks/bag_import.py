"""Read throughput of `rigctl import` for ROS bags and MCAP (rigctl.analysis.bag_import).

Writes N sensor_msgs/Imu messages (default 200,000: 1000 s at 200 Hz) as a rosbag1, a rosbag2
with mcap storage and a bare MCAP file, then measures messages read per second by
``bag_import.read_imu`` (iteration + vectorised decoding + time base) and, for comparison, the
same iteration with rosbags' deserialiser called per message (what the vectorised path replaces).
For scale: a 12-hour capture at 200 Hz is 8.6 million messages. Last line: one JSON object.

Usage: python benchmarks/bag_import.py [n_messages]
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.writer import Writer as McapWriter
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from rigctl.analysis import bag_import as B

IMU = "sensor_msgs/msg/Imu"


def _messages(store, n: int, ros1: bool) -> list[bytes]:
    T = store.types
    V, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, 3))
    z9 = np.zeros(9)
    out = []
    for i in range(n):
        hdr = {"stamp": T["builtin_interfaces/msg/Time"](sec=i // 200, nanosec=(i % 200) * 5_000_000),
               "frame_id": "imu_link"}
        if ros1:
            hdr["seq"] = i
        m = T[IMU](header=T["std_msgs/msg/Header"](**hdr), orientation=Q, orientation_covariance=z9,
                   angular_velocity=V(*a[i]), angular_velocity_covariance=z9,
                   linear_acceleration=V(*a[i]), linear_acceleration_covariance=z9)
        out.append(bytes(store.serialize_ros1(m, IMU) if ros1 else store.serialize_cdr(m, IMU)))
    return out


def _per_message(path: Path) -> float:
    """Messages per second: rosbags' iteration with its deserialiser on every message."""
    t0 = time.perf_counter()
    n = 0
    with AnyReader([path]) as r:
        for c, _, raw in r.messages():
            m = r.deserialize(raw, c.msgtype)
            _ = (m.header.stamp.sec, m.linear_acceleration.x, m.angular_velocity.x)
            n += 1
    return n / (time.perf_counter() - t0)


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200_000
    figures: dict[str, float] = {"messages": n}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        s1, s2 = get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_HUMBLE)
        raw1, raw2 = _messages(s1, n, True), _messages(s2, n, False)
        with Writer1(d / "b.bag") as w:
            c = w.add_connection("/imu", IMU, typestore=s1)
            for i, r in enumerate(raw1):
                w.write(c, i * 5_000_000 + 1, r)
        with Writer2(d / "b2", version=9, storage_plugin=StoragePlugin.MCAP) as w:
            c = w.add_connection("/imu", IMU, typestore=s2)
            for i, r in enumerate(raw2):
                w.write(c, i * 5_000_000 + 1, r)
        with open(d / "b.mcap", "wb") as fh:
            w = McapWriter(fh)
            w.start(profile="ros2", library="benchmark")
            sid = w.register_schema(IMU, "ros2msg", s2.generate_msgdef(IMU, ros_version=2)[0].encode())
            cid = w.register_channel("/imu", "cdr", sid)
            for i, r in enumerate(raw2):
                w.add_message(cid, log_time=i * 5_000_000 + 1, publish_time=i * 5_000_000 + 1, data=r)
            w.finish()
        for name, path in (("rosbag1", d / "b.bag"), ("rosbag2_mcap", d / "b2"), ("mcap", d / "b.mcap")):
            t0 = time.perf_counter()
            b = B.read_imu(path)
            dt = time.perf_counter() - t0
            assert b.n_messages == n and b.gaps == 0
            figures[f"{name}_read_imu_msgs_per_s"] = round(n / dt)
            print(f"{name}: read_imu {n / dt:,.0f} messages/s ({dt:.2f} s; 12 h at 200 Hz: "
                  f"{8.64e6 / (n / dt):.0f} s)")
            if name != "mcap":
                r = _per_message(path)
                figures[f"{name}_rosbags_per_message_msgs_per_s"] = round(r)
                print(f"{name}: rosbags deserialise per message {r:,.0f} messages/s")
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
