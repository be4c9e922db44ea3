"""Command-line options shared by the commands that produce or read production results."""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

from ..errors import InputError
from ..recording.recording_reader import unwritable_reason
from ..solvers.conformity import RULES
from ..units import format_duration


def add_production_options(p: argparse.ArgumentParser) -> None:
    """--spec, --decision-rule and --db (calibrate, allan, batch)."""
    p.add_argument("--spec", metavar="SPEC.yaml", help="acceptance limits: a verdict per parameter and "
                   "overall, stored with the results (configs/spec-example.yaml)")
    p.add_argument("--decision-rule", choices=RULES, default=None,
                   help="guarded (JCGM 106 guard band = U: PASS / FAIL / INDETERMINATE) or simple "
                        "(shared risk, the risk stated per parameter); default: the spec's")
    p.add_argument("--db", metavar="URL|FILE", default=None,
                   help="results database: a SQLite file or a URL (postgresql+psycopg://...); default "
                        "results.sqlite beside the run directories; 'none' to skip")


def check_output_files(*options: tuple[str, str | None]) -> None:
    """Refuse, before the analysis (minutes on a long capture), an output file option
    ((option, path) pairs; None: not given) whose directory does not exist or cannot be
    written, or that is a directory: one line, exit 2, instead of a failure after the work is
    done."""
    for opt, name in options:
        if not name:
            continue
        out = Path(name)
        if out.is_dir():
            raise InputError(f"{opt}: is a directory", out, hint=f"give a file name, e.g. {out / 'x'}")
        if not out.resolve().parent.is_dir():
            raise InputError(f"{opt}: output directory does not exist", out.parent,
                             hint="create it, or give a file in an existing directory")
        why = unwritable_reason(out.resolve().parent)
        if why:
            raise InputError(f"{opt}: cannot write in this directory ({why})", out.parent,
                             hint="give a file in a writable directory")


def stage_printer(command: str, recording: str) -> Callable[[str], None]:
    """For an analysis that runs long between its outputs: each stage as it starts, with the
    time since the command began, one line on stderr ('thermal tag.h5, 41.9 s: gyro: ...')."""
    t0 = time.monotonic()
    name = Path(recording).name

    def say(line: str) -> None:
        print(f"{command} {name}, {format_duration(time.monotonic() - t0)}: {line}", file=sys.stderr, flush=True)
    return say
