"""``rigctl certificate RUN --spec SPEC.yaml``: the run's calibration certificate as a PDF.

RUN is a run directory or a recording that ``rigctl calibrate`` analysed. Writes
certificate.html and certificate.pdf (headless Chromium) into the run directory or ``--out``.
Exit codes: 0 written, 1 failure (Chromium could not print), 2 invalid input.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..errors import RunFailure
from ..report.certificate import write_certificate
from ..report.report import resolve_run
from ..solvers.conformity import RULES
from ..config.spec import load_spec


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl certificate``."""
    rec, run_dir = resolve_run(args.run)
    spec = load_spec(args.spec, args.decision_rule) if args.spec else None
    try:
        pdf, d = write_certificate(rec, Path(args.out) if args.out else run_dir, spec)
    except (RuntimeError, OSError, TimeoutError) as exc:
        raise RunFailure(f"{rec}: {exc}") from exc
    v = d["verdicts"]
    print(f"certificate of unit {d['unit_id']} ({len(d['measured'])} results"
          + (f", overall {v['overall']} against {v['spec']}" if v else ", no spec: no verdicts") + f"): {pdf}")
    return 0


def register(subparsers: Any) -> None:
    """Add the ``certificate`` sub-command."""
    p = subparsers.add_parser("certificate", description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="run directory or recording .h5 (calibrated)")
    p.add_argument("--spec", metavar="SPEC.yaml", help="acceptance limits: verdicts on the certificate")
    p.add_argument("--decision-rule", choices=RULES, default=None, help="guarded or simple (default: the spec's)")
    p.add_argument("--out", help="output directory (default: the run directory)")
    p.set_defaults(func=run)
