"""``rigctl batch 'runs/*/recording.h5'``: calibrate / Allan-analyse many recordings on Dask.

Every recording the pattern(s) match is analysed as ``rigctl calibrate`` (and ``rigctl allan``
with ``--analyses calibrate,allan``) would, on Dask's local scheduler (``--workers N``
processes, default the CPU count) or on a running dask.distributed cluster (``--scheduler
tcp://HOST:PORT``). The results go into each recording as usual and into the results database
(``--db``; default results.sqlite in the folder that holds all the run directories); a failed recording is reported
and the rest go on. The summary (yield and parameter distributions per lot: the folder that holds
the run directories, or ``--lot``) is printed and written with a plot to ``--out`` (default
``batch-<UTC>`` in that same folder). Exit codes: 0 all analysed, 1 some failed, 2 invalid input.
"""
from __future__ import annotations

import argparse
import glob
import importlib.util
import json
import time
from pathlib import Path
from typing import Any

from ..analysis import batch as B
from ..analysis import production
from ..analysis.calibration import check_noise_choice
from ..config.spec import load_spec
from ..errors import InputError, RunFailure
from ..recording.recorder import utc_now
from ..report.report_plots import plot_batch_summary
from .cli_options import add_production_options


def expand(patterns: list[str]) -> list[str]:
    """Recordings matching the glob patterns (sorted, each once)."""
    out: dict[str, None] = {}
    for pat in patterns:
        for p in sorted(glob.glob(pat, recursive=True)):
            if Path(p).is_file():
                out[str(Path(p).resolve())] = None
    return list(out)


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl batch``."""
    missing = [m for m in ("dask", "distributed") if importlib.util.find_spec(m) is None]
    if missing:  # before anything is printed or analysed
        raise InputError(f"rigctl batch needs {' and '.join(missing)}, which is not installed",
                         hint="install the batch extra: pip install -e '.[batch]'")
    recs = expand(args.recordings)
    if not recs:
        raise InputError(f"no recording matches {' '.join(args.recordings)}",
                         hint="quote the pattern so the shell does not expand it: 'runs/*/recording.h5'")
    analyses = tuple(a.strip() for a in args.analyses.split(",") if a.strip())
    if not analyses or any(a not in B.ANALYSES for a in analyses):
        raise InputError(f"--analyses {args.analyses!r}: choose from {','.join(B.ANALYSES)}")
    spec = load_spec(args.spec, args.decision_rule) if args.spec else None  # invalid: exit 2 now
    if args.workers is not None and args.workers < 1:
        raise InputError("--workers must be at least 1")
    check_noise_choice(args.noise)
    production.check_database_option(args.db, "rigctl batch")  # before the analyses, not after
    home = B.database_home(recs)
    where = f"dask.distributed at {args.scheduler}" if args.scheduler else \
        f"Dask local scheduler, {args.workers or 'all'} worker processes"
    print(f"rigctl batch: {len(recs)} recordings ({', '.join(analyses)}) on {where}", flush=True)
    done = [0]

    def progress(r: dict[str, Any]) -> None:
        done[0] += 1
        state = "ok" if r["ok"] else f"FAILED: {r['error']}"
        print(f"  [{done[0]}/{len(recs)}] {r['recording']}: {state}", flush=True)

    t0 = time.perf_counter()
    try:
        results = B.run_batch(recs, analyses, str(Path(args.spec).resolve()) if args.spec else None,
                              args.decision_rule, args.workers, args.scheduler, args.noise, progress)
    except OSError as exc:
        raise RunFailure(f"cannot reach the scheduler ({exc})") from exc
    wall = time.perf_counter() - t0
    lots = {r: (args.lot or B.lot_of(r)) for r in recs}
    db_line = B.store_in_database(results, lots, args.db, home)
    summary = B.summarise(results, lots, with_spec=spec is not None)
    out = Path(args.out) if args.out else home / f"batch-{utc_now()[:19].replace(':', '')}"
    out.mkdir(parents=True, exist_ok=True)
    text = B.summary_text(summary)
    (out / "summary.txt").write_text(text + "\n", encoding="utf-8")
    (out / "summary.json").write_text(json.dumps({"recordings": recs, "wall_s": wall, "summary": summary},
                                                 indent=1, default=str), encoding="utf-8")
    png = plot_batch_summary(results, lots, out, spec)
    print(text)
    print(f"{sum(r['ok'] for r in results)} of {len(recs)} analysed in {wall:.1f} s; summary: {out}"
          + (f", plot {png.name}" if png else ""))
    if db_line:
        print(db_line)
    return 0 if all(r["ok"] for r in results) else 1


def register(subparsers: Any) -> None:
    """Add the ``batch`` sub-command."""
    p = subparsers.add_parser("batch", description=__doc__.split("\n\n")[0])
    p.add_argument("recordings", nargs="+", help="glob pattern(s), quoted: 'runs/*/recording.h5'")
    p.add_argument("--analyses", default="calibrate", help="calibrate, allan or calibrate,allan (default calibrate)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, help="local worker processes (default: the CPU count)")
    g.add_argument("--scheduler", metavar="ADDRESS", help="a dask.distributed scheduler, e.g. tcp://127.0.0.1:8786")
    p.add_argument("--noise", default="auto", help="calibration noise model, as rigctl calibrate --noise")
    p.add_argument("--lot", help="one lot name for all (default: the folder holding the run directories)")
    p.add_argument("--out", help="summary folder (default batch-<UTC> beside the database)")
    add_production_options(p)
    p.set_defaults(func=run)
