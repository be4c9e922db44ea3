"""``rigctl allan RECORDING.h5``: Allan analysis of a recording's IMU channels.

Parses the arguments, calls the pipeline (:mod:`rigctl.analysis.allan`: streamed overlapping
Allan deviation, Stable32-style noise identification, EDF intervals, the joint IEEE 952 fit
and its self-check, stored under /results/allan), and prints it: a table per axis with the
self-check's warnings (:mod:`rigctl.analysis.allan_text`), ``--plot FILE`` (a log-log plot,
:func:`rigctl.report.report_plots.plot_allan_result`; needs matplotlib) and the exports.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from rigctl.analysis import noise_export, production
from rigctl.analysis.allan import (AXES, GAP_MODES, OUTLIER_MODES, choose_range,
                                   collector_paused_for_command, compute, default_axes,
                                   gap_message, store)
from rigctl.analysis.allan_drift import TEMPERATURE_MODES, WARMUP_MODES
from rigctl.analysis.allan_quiet import DEFAULT_EXCURSIONS, EXCURSION_MODES
from rigctl.analysis.allan_text import format_table
from rigctl.analysis.verdicts import format_verdicts
from rigctl.commands.cli_options import add_production_options, check_output_files
from rigctl.config.spec import load_spec
from rigctl.errors import InputError
from rigctl.recording.recording_reader import check_results_writable
from rigctl.sensor_axes import canonical
from rigctl.solvers import allan as A


def _parse_taus(text: str) -> A.TauSpec:
    if text in ("octave", "decade", "all"):
        return text
    try:
        n = int(text)
    except ValueError:
        raise InputError(f"--taus {text!r}: use octave, decade, all or a number") from None
    if n < 2:
        raise InputError("--taus N needs N >= 2")
    return n


def _parse_axes(text: str) -> list[str]:
    """--axes: canonical names (gx, ..., az); the old spellings (gyro_x, gyr_x, accel_x, acc_x)
    are read as their canonical axis (rigctl.sensor_axes.canonical)."""
    given = [a.strip() for a in text.split(",") if a.strip()]
    bad = [a for a in given if canonical(a) not in AXES]
    if not given or bad:
        raise InputError(f"--axes {text!r}: choose from {','.join(AXES)}")
    return list(dict.fromkeys(str(canonical(a)) for a in given))


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl allan``: 0 ok; errors are raised (rigctl.errors, mapped to exit
    codes by rigctl.cli.main). The cyclic garbage collector is paused for the whole command
    (:func:`rigctl.analysis.allan.collector_paused_for_command`: no collection walks the
    objects made beside the stream while the results are stored)."""
    with collector_paused_for_command():
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    axes = _parse_axes(args.axes) if args.axes is not None else default_axes(args.recording)
    taus = _parse_taus(str(args.taus))
    if args.plot:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            raise InputError("--plot needs matplotlib: pip install 'rigctl[report]'") from None
    if args.kalibr and set(axes) != set(AXES):
        if args.axes is None:  # the import found only these axes (/meta import_axes)
            raise InputError(f"--kalibr needs all six axes; this recording has {','.join(axes)} "
                             "only (the others were not filled in the imported log): Kalibr's "
                             "imu.yaml holds both sensors' noise", args.recording,
                             hint="analyse these axes without --kalibr and write the other "
                                  "sensor's values into imu.yaml yourself")
        raise InputError("--kalibr needs all six axes (--axes gx,gy,gz,ax,ay,az)")
    if not args.kalibr_inflate > 0:
        raise InputError(f"--kalibr-inflate {args.kalibr_inflate:g}: give a factor > 0 (1: none)")
    if not args.kalibr and (args.kalibr_inflate != 1.0 or args.kalibr_topic is not None):
        opt = "--kalibr-inflate" if args.kalibr_inflate != 1.0 else "--kalibr-topic"
        raise InputError(f"{opt} without --kalibr: no imu.yaml is written",
                         hint="add --kalibr imu.yaml")
    check_output_files(("--plot", args.plot), ("--kalibr", args.kalibr), ("--json", args.json),
                       ("--csv", args.csv))
    check_results_writable(Path(args.recording), "rigctl allan", "allan")
    spec = load_spec(args.spec, args.decision_rule) if args.spec else None  # invalid: exit 2 now
    production.check_database_option(args.db, "rigctl allan")
    rng, where, warn = choose_range(args.recording, axes, args.whole)
    print(f"analysing the {where} of {args.recording}", flush=True)
    if warn:
        print(f"warning: {warn}", file=sys.stderr, flush=True)
    # the results database's modules are imported (Python holding the GIL) on a thread
    # started once the first chunk is done, beside the compiled sums, not before the first
    # chunk, where the command's own start-up holds the GIL (docs/allan.md)
    result = compute(args.recording, axes, taus, args.exact, rng, progress_stream=sys.stderr,
                     outliers=args.outliers, gaps=args.gaps, warmup=args.warmup,
                     temperature=args.temperature, excursions=args.excursions,
                     when_streaming=lambda: production.preload_database(args.db))
    gap_line = gap_message(result.get("gaps") or {})
    if gap_line:
        print(gap_line, file=sys.stderr, flush=True)
    result["segment"] = where
    for a, r in result["axes"].items():
        print(format_table(a, r))
    result["verdicts"] = production.verdicts_for(spec, "allan", result)
    if result["verdicts"]:
        print(format_verdicts(result["verdicts"]))
    store(args.recording, result)
    print(f"results written to {args.recording}:/results/allan")
    db_line = production.to_database(args.recording, "allan", result, args.db)
    if db_line:
        print(db_line)
    if args.plot:
        from rigctl.report.report_plots import plot_allan_result  # matplotlib: only with --plot

        plot_allan_result(result, args.plot)
        print(f"plot written to {args.plot}")
    export(args, result)
    return 0


def export(args: argparse.Namespace, result: dict[str, Any]) -> None:
    """--kalibr, --json, --csv (rigctl.analysis.noise_export.write_exports)."""
    for line in noise_export.write_exports(args.recording, result, args.kalibr, args.kalibr_inflate,
                                           args.kalibr_topic, args.json, args.csv):
        print(line)


def register(subparsers: Any) -> None:
    """Add the ``allan`` subcommand (sets ``func=run``)."""
    p = subparsers.add_parser("allan", description=__doc__.splitlines()[0])
    p.add_argument("recording", help="rigctl HDF5 recording (results are written into it)")
    p.add_argument("--axes", default=None,
                   help="comma-separated axes from gx,gy,gz,ax,ay,az (the older gyro_x, gyr_x, accel_x, "
                        "acc_x, ... are read as these; default: all, or those an import found in the file)")
    p.add_argument("--plot", metavar="FILE", help="write a log-log plot (needs matplotlib)")
    p.add_argument("--taus", default="95",
                   help="octave, decade, all, or N log-spaced taus (default 95)")
    p.add_argument("--whole", action="store_true",
                   help="analyse the whole recording (default: its longest capture segment, if any)")
    p.add_argument("--outliers", choices=OUTLIER_MODES, default="report",
                   help="spikes (samples > 10 robust sd from their neighbours): report them "
                        "(default) or also exclude them (replaced by the running median)")
    p.add_argument("--excursions", choices=EXCURSION_MODES, default=DEFAULT_EXCURSIONS,
                   help="short excursions of the level (30 s .. a quarter of the record, tested "
                        "before the fit), always reported: those inside a quiet stretch left out "
                        "of its fit (exclude, the default; their windows are gaps, handled as "
                        "--gaps says), or kept in it (report). The whole record's fit keeps them")
    p.add_argument("--warmup", choices=WARMUP_MODES, default="report",
                   help="a start transient (tested before the fit): report it, or cut it (exclude)")
    p.add_argument("--temperature", choices=TEMPERATURE_MODES, default="report",
                   help="a drift with /imu/temperature: report it, or subtract it (remove)")
    p.add_argument("--gaps", choices=GAP_MODES, default="skip",
                   help="dropped samples in the range: skip every Allan term that touches a gap "
                        "(default; Stable32's gap handling), refuse (say where), analyse the "
                        "longest gap-free stretch, or bridge them (biased)")
    p.add_argument("--exact", action="store_true",
                   help="fully overlapping sums for every tau (slower; default: fast mode)")
    p.add_argument("--kalibr", metavar="FILE", help="write Kalibr's imu.yaml (noise densities and random "
                   "walks, SI; the largest axis per sensor; docs/allan.md)")
    p.add_argument("--kalibr-inflate", type=float, default=1.0, metavar="X",
                   help="multiply the Kalibr values by X (default 1: as fitted); stated in the file")
    p.add_argument("--kalibr-topic", metavar="TOPIC",
                   help="rostopic in imu.yaml (default: the bag topic of an imported recording, else /imu0)")
    p.add_argument("--json", metavar="FILE", help="write the whole Allan result as JSON")
    p.add_argument("--csv", metavar="FILE", help="write the deviation table (tau, m, sigma, 68 %% and 95 %% bands, EDF, noise type; SI) as CSV")
    add_production_options(p)
    p.set_defaults(func=run)
