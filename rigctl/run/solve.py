"""Solvers a procedure's ``solve`` step names, run on the recording once it is closed.

Each hook imports its pipeline (rigctl.analysis, the report) when the step runs, not when the
CLI starts: commands that never solve (status, submit, ...) do not load scipy or matplotlib
(tests/test_cli_virtual.py checks this).
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..engine.procedure import Procedure

Log = Callable[..., None]
Hook = Callable[[Path, Log], None]


def _calibration(recording: Path, log: Log) -> None:
    """accel24, gyro-rate and closed-loop share one hook: the first computes the whole
    calibration (published fits and the closed loop) and prints it, the others see it done."""
    from ..analysis import calibration
    calibration.solve_hook(recording, log)


def _allan(recording: Path, log: Log) -> None:
    from ..analysis import allan
    allan.solve_recording(recording, log)


def _sync(recording: Path, log: Log) -> None:
    from ..analysis import sync
    sync.solve_recording(recording, log)


def _report(recording: Path, log: Log) -> None:
    from ..report.report_build import solve_report
    solve_report(recording, log)


#: solver name -> hook(recording_path, log) -> None: one for each name a procedure's solve step
#: accepts (rigctl.engine.procedure.SOLVERS; tests/test_procedure.py checks they agree)
SOLVER_HOOKS: dict[str, Hook] = {
    "accel24": _calibration, "gyro-rate": _calibration, "closed-loop": _calibration,
    "allan": _allan, "sync": _sync, "report": _report,
}


def solver_names(proc: Procedure) -> list[str]:
    """The solvers ``proc``'s solve steps name, in order."""
    return [name for step in proc.steps for name in step.solvers]


def run_solvers(names: list[str], recording: Path, log: Log) -> None:
    for name in names:
        SOLVER_HOOKS[name](recording, log)
