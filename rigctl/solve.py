"""Solvers a procedure's ``solve`` step names, run on the recording once it is closed."""
from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path

from .analysis import sync
from .procedure import Procedure
from .report_build import solve_report

Hook = Callable[[Path, Callable[..., None]], None]

#: solver name -> hook, called as hook(recording_path, log) -> None. The three calibration
#: solvers share one hook: the first computes the whole calibration (published fits and the
#: closed loop) and prints it, the others see it done and return. A "module:function" string is
#: imported when the step runs.
SOLVER_HOOKS: dict[str, Hook | str] = {
    "accel24": "rigctl.analysis.calibration:solve_hook",
    "gyro-rate": "rigctl.analysis.calibration:solve_hook",
    "closed-loop": "rigctl.analysis.calibration:solve_hook",
    "allan": "rigctl.analysis.allan:solve_recording",
    "sync": sync.solve_recording,
    "report": solve_report,
}


def _resolve(hook: Hook | str) -> Hook:
    if callable(hook):
        return hook
    mod, fn = hook.split(":")
    return getattr(importlib.import_module(mod), fn)


def run_solvers(proc: Procedure, recording: Path, log: Callable[..., None]) -> None:
    for step in proc.steps:
        for name in step.solvers:
            hook = SOLVER_HOOKS.get(name)
            if hook is None:
                log("warning", f"solver {name!r}: not available in this version of rigctl; "
                               f"run it later on {recording}")
                continue
            _resolve(hook)(recording, log)
