"""``rigctl report RUN``: the run's report.html (self-contained) and its PNGs.

RUN is a run directory (``runs/<timestamp>-<procedure>``) or a recording .h5. The page and the
PNGs go into the run directory, or ``--out DIR``. Exit codes: 0 written, 1 failure,
2 invalid input (no such run, not a recording, matplotlib missing).
"""
from __future__ import annotations

import argparse
import sys
from typing import Any

from ..report.report_build import build_report


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl report``; errors are raised (rigctl.errors)."""
    def log(kind: str, message: str, **_: Any) -> None:
        print(f"{kind}: {message}", file=sys.stderr)

    path = build_report(args.run, args.out, log=log)
    print(f"report written: {path}")
    return 0


def register(subparsers: Any) -> None:
    """Add the ``report`` subcommand (``func=run``)."""
    p = subparsers.add_parser("report", description=__doc__.splitlines()[0])
    p.add_argument("run", help="run directory or recording .h5")
    p.add_argument("--out", default=None,
                   help="directory for report.html and the PNGs (default: the run directory)")
    p.set_defaults(func=run)
