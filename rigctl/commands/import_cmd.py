"""``rigctl import FILE.csv|FILE.bag|ROSBAG2_DIR|FILE.mcap -o OUT.h5``: a foreign IMU log as a
rigctl recording.

Data from other tools (hand-held multi-position sessions, loggers, other calibration tools)
enter the same pipeline as rig recordings: ``rigctl calibrate``, ``rigctl allan`` and
``rigctl apply-cal`` read the file this writes (docs/data-format.md, status ``complete``).

* ``--columns``: column map ``ax=AccX,ay=AccY,az=AccZ,gx=GyrX,gy=GyrY,gz=GyrZ`` (CSV
  header names, or 0-based column numbers for files without a header), optional ``time=``,
  ``temp=`` (degC) and ``section=`` (a column naming each row's section, e.g. imucal's
  ``part``); or the path of a YAML/JSON file holding that mapping.
* ``--units``: ``acc=g|mg|m/s^2|counts:SCALE UNIT`` and ``gyr=deg/s|rad/s|deg/h|counts:SCALE
  UNIT`` (e.g. ``acc=counts:1/2048 g,gyr=counts:1/16.4 deg/s``), ``time=s|ms|us|ns|min|h|d``; angle
  and velocity units (``gyr=rad|deg|mrad|urad``, ``acc=m/s|mm/s``) mark increments per sample
  (divided by the interval), or with ``--integrated`` running integrals (differenced first: an
  integrated angle, or a clock's phase in s for a Stable32 phase file). Samples
  are converted to SI (m/s^2, rad/s) with these nominal scales; a calibration then reports
  the residual scale errors as ratios to them.
* ``--rate HZ``: nominal sample rate. Without a time column, t = k / rate.
* ROS bags (rosbag1 ``.bag``, a rosbag2 directory with sqlite3 or mcap storage, a bare ``.mcap``
  file; recognised by their first bytes): ``--topic`` names a ``sensor_msgs/Imu`` topic (optional
  when there is exactly one); ``--time-source header|receive`` (default ``header``: the time
  column is header.stamp). Units are SI already, the rate is estimated from the stamps (median
  interval), gaps become /imu/counter jumps. Reading: :mod:`rigctl.analysis.bag_import`.
* segments (kind ``orientation`` with NaN table angles: no table, orientation unknown):
  from ``--segments JSON`` (``{"label": {"start": i, "end": j}, ...}`` as imucal's session
  lists, or ``[{"label", "start", "end", "kind"}, ...]``; sample indices, end exclusive),
  from the ``section=`` column (a run of equal values is a section), or detected
  automatically as static intervals (:func:`rigctl.solvers.multipos.detect_static_intervals`,
  threshold from the first ``--t-init`` seconds, which must be at rest). Sections whose label
  contains ``rot`` or that are not at rest are kind ``capture`` (motion between poses).

The work: :mod:`rigctl.analysis.log_import`. Exit codes: 0 written, 2 invalid input (the message names the file, the line and what to do),
1 failure while writing.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any

from ..analysis.log_import import ImportOptions, import_file, is_bag
from ..errors import InputError, RunFailure
from ..progress import WorkProgress


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl import``: 0 ok, 2 invalid input, 1 failure."""
    opts = ImportOptions(**{f.name: getattr(args, f.name) for f in fields(ImportOptions)})
    src = Path(opts.file)
    shown = (WorkProgress(f"import {src.name}", 1, unit="messages", stream=sys.stderr)
             if src.exists() and is_bag(src) else None)

    def progress(done: int, total: int) -> None:
        if shown is not None:
            shown.total = float(max(total, done, 1))
            shown.update(done)

    try:
        done = import_file(opts, progress)
    except InputError:
        raise
    except OSError as exc:
        raise RunFailure(f"{args.output}: {exc}") from exc
    if shown is not None:
        shown.done = float(done.messages)
        shown.finish()
    kinds: dict[str, int] = {}
    for s in done.sections:
        kinds[s["kind"]] = kinds.get(s["kind"], 0) + 1
    for line in done.lines:
        print(line)
    print("segments: " + ", ".join(f"{v} {k}" for k, v in kinds.items()))
    print(f"recording: {done.out}")
    return 0


def register(subparsers: Any) -> None:
    """Add the ``import`` sub-command."""
    p = subparsers.add_parser("import", description=__doc__.split("\n\n")[0])
    p.add_argument("file", help="CSV file (or .csv.gz), ROS 1 bag, rosbag2 directory (sqlite3 or mcap storage) or MCAP file")
    p.add_argument("-o", "--output", required=True, help="recording to write (.h5)")
    p.add_argument("--columns",
                   help="CSV: ax=COL,...,gz=COL[,time=COL][,temp=COL][,section=COL] (acc_x, gyr_x, ... also read) or a YAML/JSON file")
    p.add_argument("--units", help="CSV: e.g. acc=g,gyr=deg/s or acc=counts:1/2048 g,gyr=counts:1/16.4 deg/s")
    p.add_argument("--rate", type=float, help="CSV: nominal sample rate, Hz (bags: estimated from the stamps)")
    p.add_argument("--integrated", action="store_true",
                   help="CSV: the angle/velocity columns (--units gyr=rad|deg, acc=m/s) are running "
                        "integrals (an angle, a clock's phase), differenced into rates; without it "
                        "such columns are increments per sample")
    p.add_argument("--skip-rows", type=int, default=0, help="CSV: lines before the header (metadata)")
    p.add_argument("--topic", help="bag/MCAP: the sensor_msgs/Imu topic (optional when there is only one)")
    p.add_argument("--time-source", choices=("header", "receive"), default="header",
                   help="bag/MCAP: sample time from header.stamp (default) or the bag's receive time")
    p.add_argument("--segments", help="sections JSON (imucal session list or list of {label,start,end})")
    p.add_argument("--t-init", type=float, default=5.0,
                   help="seconds of initial rest for automatic static detection (default 5)")
    p.add_argument("--gravity", type=float, help="local gravity, m/s^2 (default: normal gravity at "
                   "--latitude-deg, else 9.80665)")
    p.add_argument("--latitude-deg", type=float, help="site latitude, deg")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)
