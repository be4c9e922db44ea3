"""An IMU's samples as a ROS 2 bag: a rosbag2 (mcap storage) of ``sensor_msgs/msg/Imu``, written
with the rosbags package's own writer as a robot's recorder writes it -- what a ROS user hands
``rigctl import``. Used by the tests and benchmarks that import bags; needs ``rigctl[ros]``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

IMU = "sensor_msgs/msg/Imu"


def write_imu_bag(path: str | Path, stamps_ns: np.ndarray, angular_rate: np.ndarray,
                  specific_force: np.ndarray, *, topic: str = "/imu", frame_id: str = "imu",
                  receive_delay_ns: int = 0) -> None:
    """One message per sample on ``topic``: header stamp ``stamps_ns[i]`` (ns since the epoch),
    ``angular_velocity`` = ``angular_rate[i]`` (rad/s), ``linear_acceleration`` =
    ``specific_force[i]`` (m/s^2), the identity orientation and zero covariances, received
    (the bag's log time) ``receive_delay_ns`` after its stamp. ``path``: the bag's folder, which
    must not exist yet."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    w_all = np.asarray(angular_rate, dtype=float).reshape(len(stamps), 3)
    f_all = np.asarray(specific_force, dtype=float).reshape(len(stamps), 3)
    store = get_typestore(Stores.ROS2_HUMBLE)
    T = store.types
    vec, header, time = (T["geometry_msgs/msg/Vector3"], T["std_msgs/msg/Header"],
                         T["builtin_interfaces/msg/Time"])
    quat = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    z9 = np.zeros(9)
    with Writer(Path(path), version=9, storage_plugin=StoragePlugin.MCAP) as bag:
        conn = bag.add_connection(topic, IMU, typestore=store)
        for ns, w, f in zip(stamps.tolist(), w_all.tolist(), f_all.tolist()):
            hdr = header(stamp=time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame_id)
            msg = T[IMU](header=hdr, orientation=quat, orientation_covariance=z9,
                         angular_velocity=vec(*w), angular_velocity_covariance=z9,
                         linear_acceleration=vec(*f), linear_acceleration_covariance=z9)
            bag.write(conn, ns + receive_delay_ns, store.serialize_cdr(msg, IMU))
