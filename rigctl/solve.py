"""Solvers a procedure's ``solve`` step names, run on the recording once it is closed."""
from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path

from .procedure import Procedure

#: solver name -> "module:function", called as fn(recording_path, log) -> None.
#: The three calibration solvers share one hook: the first computes the whole calibration
#: (published fits and the closed loop) and prints it, the others see it done and return.
SOLVER_HOOKS: dict[str, str] = {
    "accel24": "rigctl.calibrate_cmd:solve_hook",
    "gyro-rate": "rigctl.calibrate_cmd:solve_hook",
    "closed-loop": "rigctl.calibrate_cmd:solve_hook",
    "allan": "rigctl.allan_cmd:solve_recording",
    "report": "rigctl.report_build:solve_report",
}


def run_solvers(proc: Procedure, recording: Path, log: Callable[..., None]) -> None:
    for step in proc.steps:
        for name in step.solvers:
            hook = SOLVER_HOOKS.get(name)
            if hook is None:
                log("warning", f"solver {name!r}: not available in this version of rigctl; "
                               f"run it later on {recording}")
                continue
            mod, fn = hook.split(":")
            getattr(importlib.import_module(mod), fn)(recording, log)
