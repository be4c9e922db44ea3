"""A ROS bag, rosbag2 or MCAP file given to a command that needs a rigctl recording says what
it is and the import that makes one of it: `rigctl allan run.bag` said 'not an HDF5 file (give
a rigctl recording (.h5), or convert a CSV log with rigctl import)'. The bags are written with
rosbags here; a results database (SQLite, the same first bytes as a .db3) is not taken for one."""
from __future__ import annotations

import contextlib
import io
import sqlite3
from pathlib import Path

import pytest

from rigctl import cli

pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402


def _string_bags(tmp: Path) -> tuple[Path, Path]:
    s1, s2 = get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_HUMBLE)
    msg1 = s1.types["std_msgs/msg/String"](data="x")
    msg2 = s2.types["std_msgs/msg/String"](data="x")
    with Writer1(tmp / "run.bag") as w:
        c = w.add_connection("/s", "std_msgs/msg/String", typestore=s1)
        w.write(c, 1, s1.serialize_ros1(msg1, "std_msgs/msg/String"))
    with Writer2(tmp / "run2", version=8) as w:
        c = w.add_connection("/s", "std_msgs/msg/String", typestore=s2)
        w.write(c, 1, s2.serialize_cdr(msg2, "std_msgs/msg/String"))
    return tmp / "run.bag", tmp / "run2"


def _rigctl(*argv: str) -> tuple[int, str]:
    """The command in this process (as its console script calls it): exit code, stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(list(argv))
    return code, err.getvalue()


def test_a_bag_given_for_a_recording_names_the_import(tmp_path: Path) -> None:
    bag, bag2 = _string_bags(tmp_path)
    for verb, path, kind in (("allan", bag, "a ROS 1 bag"), ("calibrate", bag2, "a rosbag2"),
                             ("report", next(bag2.glob("*.db3")), "a rosbag2")):
        code, err = _rigctl(verb, str(path), "--db", "none") if verb != "report" else _rigctl(verb, str(path))
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
        assert lines[0].startswith(f"rigctl {verb}: error: {path}: {kind}, not a rigctl recording"), lines
        assert f"rigctl import {path} -o {path.stem}.h5" in lines[0], lines
    db = tmp_path / "results.sqlite"
    sqlite3.connect(db).execute("create table t (x)").connection.commit()
    code, err = _rigctl("allan", str(db))
    assert code == 2 and "not an HDF5 file" in err and "rosbag" not in err, err
