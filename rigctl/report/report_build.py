"""Build the run report: load the run (:mod:`rigctl.report.report`), draw the plots
(:mod:`rigctl.report.report_plots`) and write ``report.html`` (:mod:`rigctl.report.report_html`).
:func:`solve_report` is the hook a procedure's ``solve: [report]`` step calls."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..errors import InputError
from ..recording.checkpoint import write_atomic
from ..recording.recording_reader import unwritable_reason
from . import report_html, report_plots
from .report import REPORT_HTML, ReportDependencyError, load_run, require_matplotlib, resolve_run


def build_report(run: str | Path, out_dir: str | Path | None = None,
                 log: Callable[..., None] | None = None) -> Path:
    """Write report.html and its PNGs for a run directory or recording; returns the HTML path.

    ``out_dir`` defaults to the run directory (the folder of the recording).
    """
    require_matplotlib()
    rec, run_dir = resolve_run(run)
    data = load_run(rec, run_dir)
    out = Path(out_dir) if out_dir is not None else run_dir
    out.mkdir(parents=True, exist_ok=True)
    why = unwritable_reason(out)
    if why:
        raise InputError(f"cannot write the report here ({why})", out,
                         hint="give --out DIR, a writable directory")
    plots = report_plots.make_plots(data, out, log)
    html = report_html.render(data, plots)
    target = out / REPORT_HTML
    write_atomic(target, html.encode("utf-8"))  # whole or not at all, also when interrupted
    return target


def solve_report(recording_path: str | Path, log: Callable[..., None]) -> None:
    """SOLVER_HOOKS entry ``report``: write report.html beside the recording."""
    try:
        path = build_report(recording_path, log=log)
    except ReportDependencyError as exc:
        log("warning", f"report skipped: {exc}")
        return
    log("info", f"report: {path}")
