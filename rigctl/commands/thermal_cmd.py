"""``rigctl thermal RECORDING.h5``: bias and scale factor against temperature of a record held
still in two or more poses (no table): a unit in a fridge or a climatic chamber, turned between
soaks.

Each pose (the recording's segments, e.g. ``rigctl import ... section=COLUMN``, or ``--poses
FILE``) is cut into windows (``--window-s``, default 1800 s) after ``--settle-s`` seconds; per
sensor and axis the bias per K (and per K^2 ...) and, for the accelerometer, the scale factor per
K are fitted by generalised least squares with an offset per pose (the pose's gravity reference
is g along its mean specific force), the noise of the window means estimated from the record;
the closed loop tests thermal hysteresis and a temperature-rate term. Printed in field units
(mg/K, deg/h/K, ppm/K) with standard uncertainties and 95 % intervals; every chi-square with its
99 % band, outside it a finding. A chamber run is calibrated by ``rigctl calibrate``.

Pose file (YAML or JSON; seconds on the recording's time axis, /imu/time)::

    - {label: z up, from_s: 480, to_s: 92460}
    - {label: x up, from_s: 92880, to_s: 182100}

Exit codes: 0 done; 2 invalid input, one line: no temperature readings, one pose (--one-pose:
the apparent bias per K only), an IMU temperature span under 5 K, a bad pose file, a chamber
run (--static); 1 failure. Docs: docs/thermal.md, "Static records".

The work: :mod:`rigctl.analysis.thermal_static`.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis.thermal import MAX_FIT_DEGREE, STATIC_WINDOW_S
from ..analysis.thermal_static import format_text, static_fit, write_csv
from ..errors import InputError, RunFailure
from .cli_options import check_output_files, stage_printer


def run(args: argparse.Namespace) -> int:
    """``rigctl thermal``: 0 done, 2 invalid input, 1 failure."""
    check_output_files(("--json", args.json), ("--csv", args.csv))  # before the fit
    try:
        result = static_fit(args.recording, settle_s=args.settle_s, window_s=args.window_s,
                            bias_degree=args.bias_degree, loop=not args.no_loop, poses_file=args.poses,
                            one_pose=args.one_pose, force_static=args.static, progress=stage_printer("thermal", args.recording))
    except InputError:
        raise
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise RunFailure(f"{args.recording}: the thermal fit failed: {exc}") from exc
    print(format_text(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
        print(f"JSON written to {args.json}")
    if args.csv:
        print(f"CSV written to {write_csv(result, args.csv)}")
    return 0


def register(subparsers: Any) -> None:
    """Add the ``thermal`` sub-command."""
    p = subparsers.add_parser("thermal", description=__doc__.split("\n\n")[0],
                              epilog="\n\n".join(__doc__.split("\n\n")[1:5]).replace("::", ":"),
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", help="rigctl HDF5 recording with an IMU temperature column (read only)")
    p.add_argument("--static", action="store_true",
                   help="fit a chamber run (/chamber readings) as a static record too (default: refused, "
                        "rigctl calibrate does its thermal calibration)")
    p.add_argument("--poses", metavar="FILE",
                   help="the poses' time ranges (YAML/JSON list of {label, from_s, to_s}, seconds on the "
                        "recording's time axis) instead of the recording's segments")
    p.add_argument("--settle-s", type=float, default=0.0, metavar="S",
                   help="leave out the first S seconds of every pose, while the temperature falls or rises "
                        "fast after the unit went in (default 0; e.g. 3600)")
    p.add_argument("--window-s", type=float, default=STATIC_WINDOW_S, metavar="S",
                   help=f"window length (default {STATIC_WINDOW_S:g} s)")
    p.add_argument("--bias-degree", type=int, default=2, metavar="N",
                   help=f"polynomial degree in temperature of bias and scale, 1 .. {MAX_FIT_DEGREE} (default 2: "
                        "per K and per K^2)")
    p.add_argument("--no-loop", action="store_true",
                   help="do not test thermal hysteresis and a temperature-rate term (the closed loop)")
    p.add_argument("--one-pose", action="store_true",
                   help="accept a record in one pose: the apparent bias per K only (default: refused)")
    p.add_argument("--json", metavar="FILE", help="write the whole result as JSON (field units and SI)")
    p.add_argument("--csv", metavar="FILE", help="write every coefficient as CSV (field units and SI)")
    p.set_defaults(func=run)
