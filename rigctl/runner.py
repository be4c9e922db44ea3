"""Running a procedure: the run directory, the recording, signals, safe state, exit codes."""
from __future__ import annotations

import json
import math
import re
import signal
import time
import traceback
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from .config import RigConfig
from .engine import Engine, Interrupted, RunError
from .estimate import estimate
from .procedure import Procedure
from .recorder import Recorder, library_versions
from .rig import open_rig
from .runlog import RunLog
from .solve import run_solvers
from .units import format_duration

EXIT_OK, EXIT_FAILED, EXIT_INVALID, EXIT_INTERRUPTED = 0, 1, 2, 130



@dataclass
class RunResult:
    exit_code: int
    run_dir: Path
    recording: Path
    status: str
    message: str = ""


def make_run_dir(parent: Path, procedure_name: str) -> Path:
    """``parent/<UTC timestamp>-<procedure name>/``, created; never outside ``parent``."""
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", procedure_name).strip(".-") or "run"
    parent.mkdir(parents=True, exist_ok=True)
    for n in range(1000):
        d = parent / (f"{stamp}-{safe}" + (f"-{n}" if n else ""))
        try:
            d.mkdir()
            return d
        except FileExistsError:
            continue
    raise RunError(f"could not create a run directory in {parent}")


def run_procedure(proc: Procedure, cfg: RigConfig, out_parent: Path,
                  console: Any = None, install_signals: bool = True) -> RunResult:
    """Execute ``proc`` on the rig of ``cfg``; the recording and log go to a new run directory."""
    run_dir = make_run_dir(out_parent, proc.name)
    recording = run_dir / "recording.h5"
    log = RunLog(run_dir / "run.log.jsonl", console)
    plan = estimate(proc.steps, cfg)
    total = sum(e.total_s for e in plan)
    log("info", f"procedure {proc.name}: {sum(s.is_motion for s in proc.steps)} steps, "
                f"about {format_duration(total)} of rig time", procedure=proc.path)
    status, code, message = "failed", EXIT_FAILED, ""
    engine: Engine | None = None
    old_handlers: dict[int, Any] = {}
    wall0 = time.monotonic()
    with open_rig(cfg) as (rig, truth):
        meta = {"procedure_name": proc.name, "procedure_path": proc.path, "procedure_text": proc.text,
                "parameters_json": json.dumps(proc.parameters, default=str),
                "config_path": cfg.path, "config_yaml": cfg.text,
                "versions_json": json.dumps(library_versions()), "rig": rig.description,
                "latitude_deg": math.degrees(cfg.latitude),
                "height_m": cfg.height_m, "gravity_m_s2": cfg.gravity}
        rec = Recorder(recording, meta, truth, imu_rate_hz=cfg.imu_rate_hz,
                       flush_interval_s=cfg.flush_interval_s)
        engine = Engine(rig, rec, log=log)

        def on_signal(signum: int, _frame: Any) -> None:
            engine.request_abort(signal.Signals(signum).name)

        if install_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                old_handlers[sig] = signal.signal(sig, on_signal)
        try:
            engine.run(proc.steps)
            status, code = "complete", EXIT_OK
        except Interrupted as exc:
            status, code, message = "interrupted", EXIT_INTERRUPTED, f"interrupted by {exc}"
            log("error", f"{message}: table stopped, recording closed as interrupted")
        except RunError as exc:
            status, code, message = "failed", EXIT_FAILED, str(exc)
            log("error", message)
        except Exception as exc:  # noqa: BLE001 - reported with its traceback in the run log
            status, code, message = "failed", EXIT_FAILED, f"{type(exc).__name__}: {exc}"
            log("error", f"unexpected error: {message} (traceback in {run_dir / 'run.log.jsonl'})",
                traceback=traceback.format_exc())
        finally:
            engine.safe_state()
            for sig, h in old_handlers.items():
                signal.signal(sig, h)
            if not rec.closed:
                if message:
                    rec.add_event(rig.clock.now(), status, message)
                rec.close(status)
        sim_time = rig.clock.now()
    wall = time.monotonic() - wall0
    log("info", f"run {status}: {rec.n_segments} segments, {rec.n_imu} IMU samples, "
                f"{format_duration(sim_time)} of rig time in {wall:.1f} s wall")
    if status == "complete":
        run_solvers(proc, recording, log)
    log("info", f"recording: {recording}")
    log.close()
    return RunResult(code, run_dir, recording, status, message)
