"""Foreign log formats told by their first bytes: the ROS bags and MCAP files ``rigctl import``
reads (rigctl.analysis.bag_import), and what a command that needs a rigctl recording says when
it is given one of them instead."""
from __future__ import annotations

from pathlib import Path

ROSBAG1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"


def bag_kind(path: Path) -> str | None:
    """``rosbag1``, ``rosbag2`` (directory with metadata.yaml, or a sqlite3 .db3 file),
    ``mcap``, or None when the path is none of these (first bytes, not the file name)."""
    if path.is_dir():
        return "rosbag2" if (path / "metadata.yaml").is_file() else None
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return None
    if head.startswith(ROSBAG1_MAGIC):
        return "rosbag1"
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(SQLITE_MAGIC):
        return "rosbag2"
    return None


def import_hint(path: Path) -> str | None:
    """For a ROS bag, rosbag2 directory or MCAP file given where a recording is needed: the
    ``rigctl import`` command that makes one of it; None for anything else."""
    kind = bag_kind(path)
    if kind is None or (kind == "rosbag2" and path.is_file() and path.suffix.lower() != ".db3"):
        return None  # any SQLite file (a results.sqlite) starts as a .db3 does
    name = {"rosbag1": "a ROS 1 bag", "rosbag2": "a rosbag2", "mcap": "an MCAP file"}[kind]
    return (f"{name}, not a rigctl recording: import it first, rigctl import {path} -o "
            f"{path.stem or 'imported'}.h5 [--topic /imu] (docs/ros.md)")
