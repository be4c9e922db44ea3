"""``rigctl apply-cal RECORDING.h5 -o OUT.h5``: write calibrated IMU data.

The calibration's sensor model (``rigctl calibrate``: /results/calibration of the recording, or a
JSON file with ``--calibration``), SI units:

    accelerometer  A = b_a + M_a a + k2 o (a o a)        (o: element-wise)
    gyro           W = b_g + M_g w + G a

is inverted per sample (the accelerometer by Newton's method: :mod:`rigctl.solvers.sensor_model`;
the pipeline: :mod:`rigctl.analysis.apply_cal`).

The output is a complete copy of the recording (docs/data-format.md) with /imu/specific_force and
/imu/angular_rate replaced, /results emptied (results of the raw data do not describe the
corrected data) and the provenance in /meta attrs ``calibration_applied_json`` (the model, its
source and the input file). It is built as OUT.h5.part and renamed when complete; nothing else
is written. The input is never modified and OUT may not be the input.

A thermal calibration (/results/thermal when there is no /results/calibration, or a JSON with
``"mode": "thermal"``) is applied at each sample's temperature (/imu/temperature):
:func:`rigctl.analysis.thermal.thermal_corrector`, docs/thermal.md.

Exit codes: 0 written, 2 invalid input, 1 failure.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis.apply_cal import apply_calibration, load_model
from ..analysis.log_import import check_output
from ..errors import InputError, RunFailure


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl apply-cal``: 0 ok, 2 invalid input, 1 failure."""
    src, out = Path(args.recording), Path(args.output)
    if out.exists() and out.resolve() == src.resolve():
        raise InputError("-o names the input recording; apply-cal never modifies its input", out,
                         hint="choose another output file")
    check_output(src, out, args.force)  # exists, a directory, no such directory: one piece with import
    if args.calibration and args.from_results:
        raise InputError("give either --calibration JSON or --from-results, not both")
    info, origin = load_model(src, args.calibration)
    try:
        n = apply_calibration(src, out, info, origin)
    except (OSError, ValueError, np.linalg.LinAlgError) as exc:
        raise RunFailure(f"{src}: {exc}") from exc
    note = "" if info.get("trustworthy", True) is not False else " (WARNING: that calibration is NOT TRUSTWORTHY)"
    print(f"applied calibration from {origin} to {n} samples{note}")
    print(f"recording: {out}")
    return 0


def register(subparsers: Any) -> None:
    """Add the ``apply-cal`` sub-command."""
    p = subparsers.add_parser("apply-cal", description=__doc__.split("\n\n")[0])
    p.add_argument("recording", help="rigctl HDF5 recording (read only)")
    p.add_argument("-o", "--output", required=True, help="corrected recording to write (.h5)")
    p.add_argument("--calibration", help="calibration JSON written by rigctl calibrate")
    p.add_argument("--from-results", action="store_true",
                   help="use the recording's /results/calibration (the default)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)
