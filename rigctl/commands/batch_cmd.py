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
import json
import os
import time
from pathlib import Path
from typing import Any

from ..analysis import batch as B
from ..analysis import production
from .cli_options import add_production_options
from ..display_units import format_value
from ..recording.recorder import utc_now
from ..config.spec import load_spec
from ..errors import InputError, RunFailure


def expand(patterns: list[str]) -> list[str]:
    """Recordings matching the glob patterns (sorted, each once)."""
    out: dict[str, None] = {}
    for pat in patterns:
        for p in sorted(glob.glob(pat, recursive=True)):
            if Path(p).is_file():
                out[str(Path(p).resolve())] = None
    return list(out)


def summary_text(summary: dict[str, Any]) -> str:
    """The lot summary as a table."""
    lines = []
    for lot, s in summary.items():
        v = s["verdicts"]
        y = "n/a (no spec)" if s["yield"] is None else f"{100 * s['yield']:.0f} %"
        lines.append(f"lot {lot}: {s['recordings']} recordings, {s['analysed']} analysed, {len(s['failed'])} failed; "
                     f"yield {y} (PASS {v['PASS']}, FAIL {v['FAIL']}, INDETERMINATE {v['INDETERMINATE']})")
        lines.append(f"  {'parameter':<32} {'unit':<14} {'n':>3} {'mean':>12} {'sd':>10} {'min':>12} {'max':>12}")
        for name, p in s["parameters"].items():
            ref = p["median_u"]  # digits from the units' typical uncertainty
            f = [format_value(p[k], ref)[0] for k in ("mean", "min", "max")]
            sd = format_value(p["sd"], ref)[0] if p["sd"] == p["sd"] else "n/a"
            lines.append(f"  {name:<32} {p['unit']:<14} {p['n']:>3} {f[0]:>12} {sd:>10} {f[1]:>12} {f[2]:>12}")
        for fl in s["failed"]:
            lines.append(f"  FAILED {fl['recording']}: {fl['error']}")
    return "\n".join(lines)


def plot_summary(results: list[dict[str, Any]], lots: dict[str, str], out: Path, spec: Any) -> Path | None:
    """Each specified (or the first 12) parameter across units, per lot: value with its 95 %
    interval, and the spec's limits."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    series: dict[str, list[tuple[str, int, float, float, float, Any]]] = {}
    for i, r in enumerate(x for x in results if x["ok"]):
        for kind, payload in r["results"].items():
            for m in production.measured(kind, payload):
                d = m.display
                lo, hi = m.interval
                series.setdefault(d.base, []).append((lots[r["recording"]], i, d.value(m.value),
                                                      d.value(lo), d.value(hi), d))
    names = [n for n in series if spec is None or spec.limit_for(n) is not None][:12] if series else []
    if not names:
        return None
    ncol = 3
    nrow = -(-len(names) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(11, 2.6 * nrow), squeeze=False)
    for ax, name in zip(axes.flat, names):
        pts = series[name]
        d = pts[0][5]
        for lot in sorted({p[0] for p in pts}):
            sel = [p for p in pts if p[0] == lot]
            x = [p[1] for p in sel]
            y = [p[2] for p in sel]
            err = [[p[2] - p[3] for p in sel], [p[4] - p[2] for p in sel]]
            ax.errorbar(x, y, yerr=err, fmt="o", ms=3, lw=0.8, label=f"lot {lot}")
        lim = spec.limit_for(name) if spec is not None else None
        if lim is not None:
            for v in lim.si(d):
                if v is not None:
                    ax.axhline(d.value(v), color="tab:red", lw=0.8, ls="--")
        ax.set_title(name, fontsize=8)
        ax.set_ylabel(f"[{d.unit}]", fontsize=8)
        ax.set_xlabel("recording", fontsize=7)
        ax.tick_params(labelsize=7)
        ax.grid(True, lw=0.3)
    for ax in list(axes.flat)[len(names):]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=6)
    fig.suptitle("Parameters across units (95 % intervals; dashed: spec limits)", fontsize=10)
    fig.tight_layout()
    path = out / "batch.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def run(args: argparse.Namespace) -> int:
    """Entry point of ``rigctl batch``."""
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
    db_line = ""
    from ..recording import results_db as db  # optional dependency: rigctl[db]

    home = Path(os.path.commonpath([str(db.default_path(r).parent) for r in recs]))
    if args.db != "none":
        target = args.db or str(home / db.DEFAULT_NAME)
        engine = db.open_db(target)
        try:
            for r in results:
                for kind, payload in r["results"].items():
                    db_line = production.to_database(r["recording"], kind, payload, target,
                                                     lot=lots[r["recording"]], engine=engine)
        finally:
            engine.dispose()
    summary = B.summarise(results, lots)
    out = Path(args.out) if args.out else home / f"batch-{utc_now()[:19].replace(':', '')}"
    out.mkdir(parents=True, exist_ok=True)
    text = summary_text(summary)
    (out / "summary.txt").write_text(text + "\n", encoding="utf-8")
    (out / "summary.json").write_text(json.dumps({"recordings": recs, "wall_s": wall, "summary": summary},
                                                 indent=1, default=str), encoding="utf-8")
    png = plot_summary(results, lots, out, spec)
    print(text)
    print(f"{sum(r['ok'] for r in results)} of {len(recs)} analysed in {wall:.1f} s; summary: {out}"
          + (f", plot {png.name}" if png else ""))
    if db_line:
        print(db_line)
    return 0 if all(r["ok"] for r in results) else 1


def register(subparsers: Any) -> None:
    """Add the ``batch`` sub-command."""
    p = subparsers.add_parser("batch", help="calibrate / Allan-analyse many recordings on Dask",
                              description=__doc__.split("\n\n")[0])
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
