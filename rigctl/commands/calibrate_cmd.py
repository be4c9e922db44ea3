"""``rigctl calibrate RECORDING.h5``: calibration with uncertainty and the closed loop.

Parses the options and prints; the pipeline is :mod:`rigctl.analysis.calibration`.
Exit codes: 0 done, 2 invalid input, 1 failure.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis import production
from ..analysis.calibration import calibrate, check_noise_choice
from .cli_options import add_production_options, check_output_files, stage_printer
from ..errors import InputError, RunFailure
from ..recording.recording_reader import check_results_writable
from ..config.spec import load_spec


def run(args: argparse.Namespace) -> int:
    """``rigctl calibrate``: 0 done, 2 invalid input, 1 failure."""
    check_noise_choice(args.noise)  # before the analysis: its error line comes first
    check_output_files(("--json", args.json))
    check_results_writable(Path(args.recording), "rigctl calibrate", "calibration")
    spec = load_spec(args.spec, args.decision_rule) if args.spec else None
    production.check_database_option(args.db, "rigctl calibrate")
    try:
        payload, text, explain = calibrate(args.recording, args.noise, True, args.json, spec,
                                         args.thermal_degree, progress=stage_printer("calibrate", args.recording))
        db_line = production.to_database(args.recording, "calibration", payload, args.db)
        text += "\n" + db_line if db_line else ""
    except InputError:
        raise
    except (OSError, ValueError, np.linalg.LinAlgError) as exc:
        raise RunFailure(f"{args.recording}: {exc}") from exc
    print(text.rstrip())
    if args.explain and explain:
        print(explain)
    return 0


def register(subparsers: Any) -> None:
    """Add the ``calibrate`` sub-command."""
    p = subparsers.add_parser("calibrate", description=__doc__.split("\n\n")[0])
    p.add_argument("recording", help="rigctl HDF5 recording (results are stored in it)")
    p.add_argument("--explain", action="store_true", help="print the closed loop's chain of decisions")
    p.add_argument("--json", help="JSON output path (default: RECORDING.calibration.json beside it)")
    p.add_argument("--noise", default="auto", metavar="{auto,allan,self,FILE.h5}",
                   help="segment noise model: this recording's /results/allan (allan), the data (self), "
                        "allan if present else self (auto, default), or FILE.h5: the /results/allan of an "
                        "overnight capture of the same IMU (best: a 40-minute session cannot pin down the "
                        "slow terms)")
    p.add_argument("--thermal-degree", metavar="{N,B,S,M,auto}",
                   help="thermal calibration (a chamber run): polynomial degree in temperature of every "
                        "group (N), of bias, scale and misalignment (B,S,M), or chosen from the data (auto); "
                        "default 2,2,1 (docs/thermal.md)")
    add_production_options(p)
    p.set_defaults(func=run)

