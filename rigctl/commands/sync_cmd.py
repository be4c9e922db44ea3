"""`rigctl sync RECORDING.h5`: tap-hammer time synchronisation of a recording.

Detects the taps in /imu/specific_force, matches them to the pulses in /pulses/*, fits the IMU
clock and writes /results/sync (the pipeline: :mod:`rigctl.analysis.sync`). See docs/sync.md.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..recording.recording_reader import check_results_writable
from ..analysis.sync import SyncOptions, result_arrays, summary_lines, sync_recording, tap_axis


def register(subparsers: Any) -> None:
    """Add the ``sync`` subcommand (``func=run``)."""
    p = subparsers.add_parser("sync", description=__doc__)
    p.add_argument("recording", type=Path, help="recording .h5 (opened r+; /results/sync written)")
    p.add_argument("--axis", type=str, default="az",
                   help="tap axis: ax, ay or az, the accelerometer axis the hammer strikes along "
                        "(default az; the older x, y, z are read too)")
    p.add_argument("--plot-dir", type=Path, default=None, help="write PNG plots here")
    p.add_argument("--response", choices=["auto", "none", "learn", "second-order"],
                   default="auto", help="sensor response for sub-sample timing (default auto)")
    p.add_argument("--natural-freq-hz", type=float, default=30.0)
    p.add_argument("--damping", type=float, default=0.7)
    p.add_argument("--wander", choices=["none", "quadratic"], default="none")
    p.add_argument("--timescale", choices=["run", "gps"], default="run",
                   help="pulse times from /pulses/time (run) or gps_week/gps_seconds (gps)")
    p.add_argument("--tolerance-s", type=float, default=0.05, help="matching gate (s)")
    p.add_argument("--range-m-s2", type=float, default=None,
                   help="accelerometer saturation level (default: repeated extreme values)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """CLI entry: 0 ok; errors are raised (rigctl.errors: 2 invalid input, 1 failure)."""
    path: Path = args.recording
    check_results_writable(path, "rigctl sync", "sync")
    args.axis = tap_axis(args.axis)
    opts = SyncOptions(response=args.response, natural_freq_hz=args.natural_freq_hz,
                       damping=args.damping,
                       wander=None if args.wander == "none" else args.wander,
                       tolerance_s=args.tolerance_s, saturation_m_s2=args.range_m_s2)
    given = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "func"}
    done = sync_recording(path, opts, axis=args.axis, timescale=args.timescale, options=given)
    s = done.result.summary
    print(f"sync {path}: timing {s['timing']}, axis {args.axis}")
    for line in summary_lines(s):
        print(f"  {line}")
    print(f"  wrote /results/sync to {path}")
    if args.plot_dir is not None:
        try:
            from ..report import report_plots
            arrays = {k: a for k, (a, _) in result_arrays(done.result, done.counter,
                                                          done.pulse_time_s).items()}
            args.plot_dir.mkdir(parents=True, exist_ok=True)
            for p in (report_plots.draw_sync_hist(arrays, s, args.plot_dir),
                      report_plots.draw_sync_residual(arrays, args.plot_dir)):
                print(f"  plot {p}")
        except ImportError:
            print("  plots skipped: matplotlib is not installed (pip install rigctl[report])",
                  file=sys.stderr)
    return 0
