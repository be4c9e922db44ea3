"""Running a procedure: the run directory, the recording, signals, safe state, checkpoints,
resuming a cut-off run, exit codes.

A run directory holds ``recording.h5``, ``run.log.jsonl`` (JSON lines), ``config.yaml`` (a
snapshot of the rig config) and ``checkpoint.json`` (rewritten atomically after every step).
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import _thread
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..recording import checkpoint as ckpt_mod
from ..recording import shield
from . import console as console_mod
from .console import ConsoleStream
from ..config.config import RigConfig, load_config
from ..engine.device_check import check_devices
from ..devices import DeviceFault, imu_identity
from ..engine.engine import Engine, Interrupted, Rig, RunError, rewarm_due
from ..errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, InputError, RigctlError, RunFailure
from ..engine.estimate import estimate
from ..engine.procedure import Procedure, Step, load_procedure
from ..progress import Progress, make_progress
from ..recording.recorder import LAYOUT, Recorder, Segment, library_versions, utc_now
from ..recording.recording_reader import check_layout, check_path
from ..engine.rig import open_rig
from .runlog import RunLog
from .solve import run_solvers, solver_names
from ..engine.states import StateMachine
from ..config.suspenders import SuspenderSet, SuspenderSettings
from ..units import format_duration

RECORDING, RUN_LOG, CONFIG_SNAPSHOT = "recording.h5", "run.log.jsonl", "config.yaml"


@dataclass
class RunResult:
    exit_code: int
    run_dir: Path
    recording: Path
    status: str
    message: str = ""
    #: the analysis of a complete run (the checkpoint's ``analysis``): "" (no solvers, or the
    #: run did not complete), ``done``, ``failed`` or ``interrupted``
    analysis: str = ""


@dataclass
class RunOptions:
    """How a run is driven (the daemon and tests set these; ``rigctl run`` uses the defaults)."""

    #: None: the rig config's ``suspenders:`` section (``RigConfig.suspenders``)
    suspenders: SuspenderSettings | None = None
    states: StateMachine | None = None
    rig_opener: Callable[[RigConfig], Any] = open_rig
    on_engine: Callable[[Engine | None], None] | None = None  # called with the engine, then None
    max_pause_s: float | None = None
    sample_poll_s: float = 0.5
    progress: Progress | None = None  # default: a bar on a terminal, plain lines otherwise
    #: open each configured port and ask each device who it is before creating anything
    #: (rigctl.engine.device_check); a failure is a DeviceError and no run directory is made
    check_devices: bool = True
    #: SIGINT / SIGTERM record of this run, for a caller that owns the process's signal handlers
    #: and does not let the run install its own (``install_signals=False``: the daemon, which
    #: calls ``signals.received`` from its handlers); None: the run's own
    signals: RunSignals | None = None


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


def check_run_dir(run_dir: str | Path, runs_root: str | Path) -> Path:
    """The resolved run directory, which must be a direct child of ``runs_root``."""
    root = Path(runs_root).resolve()
    d = Path(run_dir).resolve()
    if d.parent != root:
        raise InputError(f"{run_dir} is not a run directory inside {root}",
                         hint="pass --runs DIR, the directory the run was created in")
    if not d.is_dir():
        raise InputError(f"{d}: no such run directory")
    return d


class _DiskSafeLog:
    """A RunLog whose file writes may fail (disk full) without stopping the run: the message
    still reaches the console."""

    def __init__(self, log: RunLog) -> None:
        self._log = log

    def __call__(self, kind: str, message: str, **fields: Any) -> None:
        try:
            self._log(kind, message, **fields)
        except OSError as exc:
            print(f"{kind}: {message} [run log not written: {exc.strerror}]",
                  file=self._log.console, flush=True)

    def close(self) -> None:
        try:
            self._log.close()
        except OSError:
            pass

    @property
    def console(self) -> Any:
        return self._log.console


def _clock_zero_unix(rig: Rig, cfg: RigConfig) -> float:
    """Unix time at which the rig clock read zero (NaN for a virtual clock), s."""
    if cfg.clock == "virtual":
        return math.nan
    speed = cfg.speed if cfg.clock == "scaled" else 1.0
    return time.time() - rig.clock.now() / speed


#: what to do with a recording a resume cannot read or append to
RESUME_HINT = ("a damaged or hand-edited recording cannot be resumed: restore it from a copy, or start "
               "the procedure again")


def _open_cut_off(recording: Path) -> h5py.File:
    """A cut-off recording, for reading. A crash leaves HDF5's write flags set, which SWMR
    readers accept when the SWMR flag is set too; a crash of a resume between its plain 'r+'
    open and the switch to SWMR leaves the write flag alone, which every reader refuses: then
    the flags are cleared first (the resume clears them anyway before reopening).

    A file that cannot be one (a directory, unreadable, empty, not HDF5, cut off short of the
    end its superblock records -- which a SWMR reader would hang on -- or refused by HDF5) is
    an InputError naming it and what to do (:data:`RESUME_HINT`), before anything is touched."""
    try:
        check_path(recording)
        try:
            return h5py.File(recording, "r", libver="latest", swmr=True)
        except OSError:
            if ckpt_mod.status_flags(recording) != 1:
                raise
        ckpt_mod.clear_status_flags(recording)
        return h5py.File(recording, "r", libver="latest")
    except InputError as exc:
        raise InputError(exc.message, recording, hint=RESUME_HINT) from None
    except (OSError, ValueError, RuntimeError) as exc:
        raise InputError(f"cannot be read as HDF5 ({exc})", recording, hint=RESUME_HINT) from None


#: what a resume reads of the recording and appends to: groups of the layout (every dataset;
#: the layout's other groups too where the file has them: :meth:`Recorder.reopen` trims and
#: appends to each), datasets
RESUME_NEED = ("imu", "table", "segments", "events", "run/status")


def _check_resumable(f: h5py.File, recording: Path) -> None:
    """InputError (the file, what is missing or wrong, what to do) unless the cut-off recording
    has what a resume reads and appends to: :data:`RESUME_NEED`, every dataset of the layout's
    groups it has, and /meta; each dataset of the layout's row shape and dtype kind
    (:func:`rigctl.recording.recording_reader.check_layout`); /run/status not empty. Lengths
    may differ within a group (a crash mid-flush): :func:`_rows` and the reopen trim them."""
    try:
        rows = check_layout(f, recording, (*RESUME_NEED, *(g for g in LAYOUT if g in f)),
                            groups=("meta",))
        if rows["run"]["run/status"] < 1:
            raise InputError("/run/status is empty", recording)
    except InputError as exc:
        raise InputError(exc.message, recording, hint=RESUME_HINT) from None


def _rows(f: h5py.File, group: str, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Datasets ``names`` of ``group``, each cut to the rows all the group's datasets have (as
    :meth:`Recorder.reopen` trims them: a crash mid-flush can leave them uneven)."""
    n = min(f[group][d].shape[0] for d in LAYOUT[group])
    return {k: f[group][k][:n] for k in names}


def imu_meta(rig: Rig, cfg: RigConfig) -> dict[str, str]:
    """/meta attrs naming the unit under test: ``imu_device_id`` (what the connected IMU reports,
    "" when it cannot), ``imu_identity_json`` (its whole ``identity``), ``imu_serial`` (the rig
    config's ``imu.serial``, "" when not given)."""
    ident = imu_identity(rig.imu)
    return {"imu_device_id": ident["device_id"], "imu_identity_json": json.dumps(ident, sort_keys=True, default=str),
            "imu_serial": cfg.imu_serial}


def check_same_imu(rig: Rig, recording: Path, recorded_id: str) -> None:
    """Refuse (InputError) to continue ``recording`` on an IMU whose device ID differs from the
    one it was started with (both known)."""
    now_id = imu_identity(rig.imu)["device_id"]
    if recorded_id and now_id and now_id != recorded_id:
        raise InputError(f"{recording}: the run was recorded with IMU {recorded_id} but the connected IMU "
                         f"is {now_id}: resuming would mix two units in one recording",
                         hint=f"reconnect IMU {recorded_id} and resume again, or start a new run for IMU {now_id}")


def _with_settings(options: RunOptions | None, cfg: RigConfig) -> RunOptions:
    """``options`` with the suspender settings resolved: given ones win, else the config's."""
    opts = options or RunOptions()
    return opts if opts.suspenders is not None else replace(opts, suspenders=cfg.suspenders)


def _checkpoint_for(proc: Procedure, overrides: dict[str, Any]) -> ckpt_mod.Checkpoint:
    return ckpt_mod.Checkpoint(procedure_path=str(Path(proc.path).resolve()), overrides=overrides,
                               source_sha256={str(Path(p).resolve()): ckpt_mod.sha256_text(t)
                                              for p, t in proc.sources.items()},
                               solvers=solver_names(proc))


class AnalysisInterrupted(BaseException):
    """SIGINT or SIGTERM (its name is the message) while the solvers analyse a complete recording:
    raised by the signal handler where the analysis is, or once the results write in progress is
    whole (rigctl.recording.shield). A BaseException, so that no solver's ``except Exception``
    takes it for a failure of its own."""


#: wall time after which a signal that should have stopped the analysis, while the analysis
#: still runs, is delivered to the main thread again (RunSignals), s
REDELIVER_S = 1.0


def _unraisable(info: Any) -> None:
    """sys.unraisablehook: an :class:`AnalysisInterrupted` that Python dropped (raised by the
    signal handler inside a finalizer or weakref callback) is delivered again by
    :class:`RunSignals`, silently; anything else as Python's own hook prints it."""
    if not isinstance(info.exc_value, AnalysisInterrupted):
        sys.__unraisablehook__(info)


@dataclass
class RunSignals:
    """What SIGINT / SIGTERM did during a run: ``names`` of those received; while ``analysing``,
    the handler stops the analysis (:class:`AnalysisInterrupted`). :meth:`received` is called
    from a signal handler, so in the main thread: the thread the run must run in for its
    analysis to be interruptible.

    Python prints and drops an exception that a signal handler raises while the main thread
    runs a finalizer or a weakref callback ("Exception ignored in: <function
    WeakValueDictionary.__init__.<locals>.remove ...>": seen in 1 of 6 SIGINTs to ``rigctl serve``
    during allan, at load 18, whose analysis then ran to its end and the job said ``complete``).
    So until the analysis has taken the interruption (``pending`` cleared by :func:`_analyse`),
    a thread delivers the signal to the main thread again every :data:`REDELIVER_S`."""

    names: list[str] = field(default_factory=list)
    analysing: bool = False
    #: an interruption of the analysis is on its way (set by the handler, cleared by _analyse)
    pending: bool = False
    _again: bool = False  # the next call is a re-delivery

    def received(self, signum: int) -> None:  # minimal: called from a signal handler
        self.names.append(signal.Signals(signum).name)
        if not self.analysing or (self.pending and not self._again):
            return  # a second signal while the first is handled changes nothing
        if self._again and isinstance(sys.exc_info()[1], AnalysisInterrupted):
            # a re-delivery that lands while the interruption is being handled (between its
            # raise and _analyse clearing ``pending``): taken already, not raised again
            self._again = False
            return
        self._again = False
        if not self.pending:
            self.pending = True
            sys.unraisablehook = _unraisable  # a dropped interruption: no traceback on the console
            threading.Thread(target=self._redeliver, args=(signum,), name="rigctl-interrupt", daemon=True).start()
        shield.interrupt(AnalysisInterrupted(self.names[0]))

    def _redeliver(self, signum: int) -> None:
        while True:
            time.sleep(REDELIVER_S)
            if not (self.analysing and self.pending):
                return
            self._again = True
            _thread.interrupt_main(signum)  # the main thread runs the handler again


@contextmanager
def _signal_handlers(install: bool, handler: Callable[[int, Any], None]) -> Iterator[None]:
    """``handler`` for SIGINT and SIGTERM while the block runs (``install``), the previous ones after."""
    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)} if install else {}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def resume_command(run_dir: Path) -> str:
    """The command that takes up the run ``run_dir`` again (an interrupted run continues; a
    complete run whose analysis did not finish redoes the analysis): ``rigctl resume RUN`` (with
    ``--runs`` unless RUN is in ``runs/`` of the working directory, its default)."""
    cmd = f"rigctl resume {run_dir}"
    return cmd if run_dir.parent.resolve() == Path("runs").resolve() else f"{cmd} --runs {run_dir.parent}"


def _analyse(run_dir: Path, recording: Path, ckpt: ckpt_mod.Checkpoint, log: Any,
             signals: RunSignals) -> tuple[int, str]:
    """Run the checkpoint's solvers on the complete, closed ``recording``: (exit code, message).

    The checkpoint's ``analysis`` says ``running`` while they run, then ``done``, ``failed`` or
    ``interrupted``. A signal (one already received too) stops them: every result is either
    written whole or not at all (rigctl.recording.shield), the recording stays as it was closed,
    and the message names the command that redoes the analysis (:func:`resume_command`)."""
    def save(state: str) -> None:
        ckpt.analysis = state
        try:
            ckpt_mod.save(run_dir, ckpt)
        except OSError as exc:
            log("warning", f"checkpoint not written: {exc}")

    if not ckpt.solvers:
        return EXIT_OK, ""
    code, message = EXIT_OK, ""
    try:
        signals.analysing = True
        if signals.names:  # received as the run ended: no analysis starts
            raise AnalysisInterrupted(signals.names[0])
        save("running")
        log("info", f"analysis: {', '.join(dict.fromkeys(ckpt.solvers))} on {recording} (the recording "
                    "is complete and closed; an interruption now stops the analysis only)")
        run_solvers(ckpt.solvers, recording, log)
        signals.analysing = False
        save("done")
    except AnalysisInterrupted as exc:
        signals.analysing = signals.pending = False
        code = EXIT_INTERRUPTED
        message = (f"analysis interrupted by {exc}: the recording {recording} is complete and closed, "
                   f"no result is half-written ({resume_command(run_dir)} redoes the analysis)")
        save("interrupted")
        log("error", message, echo=False)  # the caller prints it (one line on stderr)
    except Exception as exc:  # noqa: BLE001 - the recording is complete; the solver failed
        signals.analysing = False
        code, message = EXIT_FAILED, f"solver failed: {type(exc).__name__}: {exc}"
        save("failed")
        log("error", f"{message} (traceback in {run_dir / RUN_LOG}); the recording is complete: "
                     f"{resume_command(run_dir)} runs the analysis again", traceback=traceback.format_exc())
    return code, message


def _analysis_outcome(ckpt: ckpt_mod.Checkpoint) -> str:
    """The analysis' end as :attr:`RunResult.analysis` gives it: "" when none ran."""
    return ckpt.analysis if ckpt.solvers and ckpt.status == "complete" else ""


class _LogHandler(logging.Handler):
    """Records of the ``rigctl`` loggers (drivers, rig set-up) during a run: into the run log,
    with their traceback if any; on the console only the message line, never a traceback."""

    def __init__(self, log: Callable[..., None]) -> None:
        super().__init__(logging.WARNING)
        self._log = log

    def emit(self, record: logging.LogRecord) -> None:
        fields: dict[str, Any] = {"logger": record.name}
        if record.exc_info:
            fields["traceback"] = "".join(traceback.format_exception(*record.exc_info))
        try:
            self._log("error" if record.levelno >= logging.ERROR else "warning",
                      f"{record.name}: {record.getMessage()}", **fields)
        except Exception:  # noqa: BLE001 - logging must never break the run
            self.handleError(record)


@contextmanager
def _run_context(log: Callable[..., None], install_signals: bool, console_streams: list[ConsoleStream],
                 hangups: list[str]) -> Iterator[None]:
    """For the length of a run: console loss noted in the run log (the run goes on), the
    ``rigctl`` loggers routed to the run log, and (``install_signals``) SIGHUP detaching the
    console instead of ending the process."""
    def lost(name: str, reason: str) -> None:
        log("warning", f"console ({name}) lost: {reason}; the run goes on, its messages go to the "
                       "run log only", echo=False)

    def on_hangup(_signum: int, _frame: Any) -> None:  # minimal: a signal handler
        hangups.append(f"hang-up (SIGHUP) at {utc_now()}")
        for st in console_streams:
            st.detach("hang-up (SIGHUP)", notify=False)
        console_mod.detach_all("hang-up (SIGHUP)", notify=False)

    handler = _LogHandler(log)
    logger = logging.getLogger("rigctl")
    logger.addHandler(handler)
    old_hup = None
    if install_signals and hasattr(signal, "SIGHUP"):
        old_hup = signal.signal(signal.SIGHUP, on_hangup)
    try:
        with console_mod.on_lost(lost):
            yield
    finally:
        if old_hup is not None:
            signal.signal(signal.SIGHUP, old_hup)
        logger.removeHandler(handler)


def _drive(proc: Procedure, cfg: RigConfig, run_dir: Path, log: RunLog, ckpt: ckpt_mod.Checkpoint,
           make_recorder: Callable[[Rig, Any], tuple[Recorder, int]], opts: RunOptions,
           install_signals: bool, progress: Progress, resuming: bool = False,
           rewarm: str | None = None) -> RunResult:
    """Open the rig, run ``proc`` from the step ``make_recorder`` says, and always end safe: the
    table stopped, the recording closed with a final status, the checkpoint saying the same.
    Whatever fails (a device, the disk, a bug) is one line on the console and its traceback in
    the run log; opening the rig or creating the recording may fail too (status ``failed``).
    ``rewarm``: the IMU restarted before the cut-off and owes its warm-up (rewarm_due)."""
    log = _DiskSafeLog(log)  # type: ignore[assignment]
    # SIGINT / SIGTERM: from before the rig opens until the analysis of the closed recording ends.
    # During the run the handler only asks the engine to abort (at its next poll; before the
    # engine exists, as soon as it does); a second signal while the run winds down changes
    # nothing: the table is put in its safe state and the recording closed either way. During
    # the analysis of a complete run it stops the analysis (_analyse).
    signals = opts.signals if opts.signals is not None else RunSignals()
    signalled = signals.names
    engines: list[Engine] = []

    def on_signal(signum: int, _frame: Any) -> None:  # minimal: a signal handler
        signals.received(signum)
        for e in engines:
            if e.abort_requested is None and status_box[0] is None:
                e.request_abort(signalled[0])

    status_box: list[str | None] = [None]  # set once the run's outcome is known (no more aborts)
    with _signal_handlers(install_signals, on_signal):
        return _drive_signalled(proc, cfg, run_dir, log, ckpt, make_recorder, opts, progress, resuming,
                                install_signals, signals, engines, status_box, rewarm)


def _drive_signalled(proc: Procedure, cfg: RigConfig, run_dir: Path, log: Any, ckpt: ckpt_mod.Checkpoint,
                     make_recorder: Callable[[Rig, Any], tuple[Recorder, int]], opts: RunOptions,
                     progress: Progress, resuming: bool, install_signals: bool, signals: RunSignals,
                     engines: list[Engine], status_box: list[str | None],
                     rewarm: str | None = None) -> RunResult:
    signalled = signals.names
    recording = run_dir / RECORDING
    states = opts.states or StateMachine()
    status, code, message = "failed", EXIT_FAILED, ""
    rec: Recorder | None = None
    sim_time = math.nan
    wall0 = time.monotonic()
    hangups: list[str] = []
    streams = [progress.stream] if isinstance(progress.stream, ConsoleStream) else []

    def note_hangups() -> None:
        while hangups:
            log("warning", f"{hangups.pop(0)}: console detached; the run goes on (see "
                           "docs/troubleshooting.md: nohup, systemd-run, tmux)", echo=False)

    def guarded(what: str, fn: Callable[[], Any]) -> bool:
        """Run one clean-up step; a failure is logged (traceback in the run log), never raised."""
        try:
            fn()
            return True
        except Exception as exc:  # noqa: BLE001 - every clean-up step must get its turn
            log("error", f"{what}: {type(exc).__name__}: {exc}", traceback=traceback.format_exc())
            return False

    with _run_context(log, install_signals, streams, hangups):
        try:
            with opts.rig_opener(cfg) as (rig, truth):
                rec, start = make_recorder(rig, truth)
                suspenders = SuspenderSet(opts.suspenders, run_dir)
                engine = Engine(rig, rec, log=log, suspenders=suspenders, states=states,
                                sample_poll_s=opts.sample_poll_s, max_pause_s=opts.max_pause_s,
                                open_interlocks=bool(cfg.table.options.get("open_interlocks_on_stop", False)),
                                progress=progress, imu_rate_hz=cfg.imu_rate_hz)
                if rewarm is not None:
                    engine.rewarm = rewarm
                    log("warning", f"resuming after a device restart that no warm-up followed ({rewarm}): "
                                   "the warm-up runs again before the next measurement")

                def on_transition(old: str, new: str, reason: str) -> None:
                    log("state", f"{old} -> {new}" + (f": {reason}" if reason else ""), state=new)
                    if rec is not None and not rec.closed:
                        rec.add_event(rig.clock.now(), "state", f"{old} -> {new}: {reason}")

                states.listeners.append(on_transition)

                def on_step(step: Step, seg: Segment) -> None:
                    note_hangups()
                    ckpt.last_step, ckpt.n_imu, ckpt.n_segments = step.index, rec.n_imu, rec.n_segments
                    ckpt.t_file = seg.t_end + rec.time_offset
                    try:
                        ckpt_mod.save(run_dir, ckpt)
                    except OSError as exc:  # resume falls back on the recording's complete segments
                        log("warning", f"checkpoint not written: {exc}")

                engines.append(engine)
                if signalled:  # a signal came while the rig opened: stop at the first poll
                    engine.request_abort(signalled[0])
                if opts.on_engine:
                    opts.on_engine(engine)
                try:
                    plan = estimate(proc.steps, cfg)
                    progress.start([e for e in plan if e.step.index >= start], proc.name,
                                   done_before=sum(e.step.index < start and getattr(e.step, "is_motion", True)
                                                   for e in plan))
                    # resuming: the cut-off left the table as it was; stop it before any motion
                    engine.run(proc.steps, start, on_step=on_step,
                               stop_first=f"session {ckpt.sessions}" if resuming else None)
                    status, code = "complete", EXIT_OK
                except Interrupted as exc:
                    status, code, message = "interrupted", EXIT_INTERRUPTED, f"interrupted by {exc}"
                    states.to("aborting", message)
                    log("error", f"{message}: table stopped, recording closed as interrupted")
                except RunError as exc:
                    status, code, message = "failed", EXIT_FAILED, str(exc)
                    states.to("aborting", message)
                    log("error", message)
                except DeviceFault as exc:  # a device that needs an operator, e.g. another IMU on the port
                    status, code, message = "failed", EXIT_FAILED, str(exc)
                    if states.state != "idle":
                        states.to("faulted", message)
                    log("error", message)
                except RigctlError as exc:  # a driver's own error (a setting the device refuses, a
                    # garbled reply): its one line and exit code (rigctl.errors), no traceback
                    status, code, message = "failed", exc.exit_code, str(exc)
                    if states.state != "idle":
                        guarded("state change", lambda: states.to("faulted", message))
                    log("error", message)
                except Exception as exc:  # noqa: BLE001 - reported with its traceback in the run log
                    status, code, message = "failed", EXIT_FAILED, f"{type(exc).__name__}: {exc}"
                    tb = traceback.format_exc()
                    if states.state != "idle":
                        guarded("state change", lambda: states.to("faulted", message))
                    log("error", f"unexpected error: {message} (traceback in {run_dir / RUN_LOG})",
                        traceback=tb)
                finally:
                    status_box[0] = status
                    if not guarded("putting the table in its safe state", engine.safe_state):
                        if status == "complete":
                            status, code, message = "failed", EXIT_FAILED, "the table could not be stopped"
                    guarded("progress display", lambda: progress.finish(status))
                    if states.state in ("running", "aborting"):
                        guarded("state change", lambda: states.to("idle", f"run {status}"))
                    if on_transition in states.listeners:
                        states.listeners.remove(on_transition)
                    if opts.on_engine:
                        guarded("daemon hook", lambda: opts.on_engine(None))
                    if not rec.closed:
                        if message:
                            guarded("event", lambda: rec.add_event(rig.clock.now(), status, message))
                        if not guarded("closing the recording", lambda: rec.close(status)):
                            if status == "complete":
                                status, code, message = "failed", EXIT_FAILED, "the recording could not be closed"
                sim_time = rig.clock.now()
        except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - opening the rig, creating
            # the recording, or closing the rig after the run, failed
            if resuming and isinstance(exc, InputError):  # refused before anything was changed
                raise                                     # (resume on another IMU)
            interrupted = isinstance(exc, KeyboardInterrupt)
            # rigctl's own errors (e.g. a driver setting the device refuses when the rig opens):
            # their one line and exit code; a traceback in the run log only for anything else (a bug)
            known = isinstance(exc, RigctlError)
            what = "interrupted (SIGINT)" if interrupted else str(exc) if known else f"{type(exc).__name__}: {exc}"
            tb = None if interrupted or known else traceback.format_exc()
            if rec is None:  # nothing ran: no recording
                status = "interrupted" if interrupted else "failed"
                code = EXIT_INTERRUPTED if interrupted else exc.exit_code if known else EXIT_FAILED
                message = f"the run did not start: {what}"
                log("error", message, traceback=tb)
            else:  # the run's own outcome is recorded; the devices' teardown failed after it
                code = EXIT_FAILED if code == EXIT_OK else code
                message = f"{message}; then closing the devices failed: {what}" if message else \
                    f"closing the devices failed: {what}"
                log("error", message, traceback=tb)
                if not rec.closed:
                    guarded("closing the recording", lambda: rec.close(status))
        if rec is not None or not resuming:  # a resume that never started keeps its checkpoint
            ckpt.status = status
            try:
                ckpt_mod.save(run_dir, ckpt)
            except OSError as exc:
                log("error", f"checkpoint not written: {exc}")
        note_hangups()
        wall = time.monotonic() - wall0
        if rec is not None:
            log("info", f"run {status}: {rec.n_segments} segments, {rec.n_imu} IMU samples, "
                        f"{format_duration(sim_time)} of rig time in {wall:.1f} s wall, opening the rig and "
                        "closing the recording included")
        if status == "complete":
            a_code, a_message = _analyse(run_dir, recording, ckpt, log, signals)
            if a_code != EXIT_OK:
                code, message = a_code, a_message
        if rec is not None:
            log("info", f"recording: {recording}")
        log.close()
    return RunResult(code, run_dir, recording, status, message, analysis=_analysis_outcome(ckpt))


#: the lock file a process running or resuming a run holds in its directory
RUN_LOCK = ".rigctl-run.lock"


@contextmanager
def hold_run_dir(run_dir: Path) -> Iterator[None]:
    """Hold the run directory's lock (:data:`RUN_LOCK`) while a run or a resume writes it: a
    second `rigctl resume` of the same run -- in another terminal, or while the run itself still
    goes on -- would otherwise write a second session into the same recording beside the first
    (times going back, steps twice). RunFailure naming the holder's pid when another has it."""
    fd, holder = ckpt_mod.try_lock(run_dir / RUN_LOCK)
    if fd is None:
        raise RunFailure(f"{run_dir}: another rigctl process{f' (pid {holder})' if holder else ''} is running "
                         "or resuming this run; wait for it to end (rigctl resume continues a run only "
                         "once nothing writes it)")
    try:
        yield
    finally:
        os.close(fd)


def run_procedure(proc: Procedure, cfg: RigConfig, out_parent: Path,
                  console: Any = None, install_signals: bool = True,
                  options: RunOptions | None = None,
                  overrides: dict[str, Any] | None = None) -> RunResult:
    """Execute ``proc`` on the rig of ``cfg``; the recording and log go to a new run directory.
    ``overrides`` (the ``-p`` values) are kept in the checkpoint for ``rigctl resume``."""
    opts = _with_settings(options, cfg)
    if opts.check_devices:  # before anything is created: a run that cannot start leaves nothing
        check_devices(cfg).raise_for_problems()
    run_dir = make_run_dir(out_parent, proc.name)
    with hold_run_dir(run_dir):  # a `rigctl resume` of it while it runs is refused
        return _run_new(proc, cfg, run_dir, console, opts, install_signals, overrides)


def _run_new(proc: Procedure, cfg: RigConfig, run_dir: Path, console: Any, opts: RunOptions,
             install_signals: bool, overrides: dict[str, Any] | None) -> RunResult:
    (run_dir / CONFIG_SNAPSHOT).write_text(cfg.text, encoding="utf-8")
    progress = opts.progress or make_progress(ConsoleStream.wrap(console if console is not None else sys.stdout))
    log = RunLog(run_dir / RUN_LOG, progress.console)
    plan = estimate(proc.steps, cfg)
    total = sum(e.total_s for e in plan)
    log("info", f"procedure {proc.name}: {sum(s.is_motion for s in proc.steps)} steps, "
                f"about {format_duration(total)} of rig time", procedure=proc.path, echo=False)
    ckpt = _checkpoint_for(proc, dict(overrides if overrides is not None else proc.parameters))
    versions = json.dumps(library_versions())  # before the rig (and its clock) starts: it is slow

    def make_recorder(rig: Rig, truth: Any) -> tuple[Recorder, int]:
        meta = {"procedure_name": proc.name, "procedure_path": proc.path, "procedure_text": proc.text,
                "parameters_json": json.dumps(proc.parameters, default=str),
                "config_path": cfg.path, "config_yaml": cfg.text,
                "versions_json": versions, "rig": rig.description,
                "latitude_deg": math.degrees(cfg.latitude),
                "height_m": cfg.height_m, "gravity_m_s2": cfg.gravity,
                "clock_zero_unix_s": _clock_zero_unix(rig, cfg), **imu_meta(rig, cfg)}
        ckpt_mod.save(run_dir, ckpt)
        rec = Recorder(run_dir / RECORDING, meta, truth, imu_rate_hz=cfg.imu_rate_hz,
                       flush_interval_s=cfg.flush_interval_s,
                       min_free_bytes=opts.suspenders.min_free_bytes // 4)
        return rec, 0

    return _drive(proc, cfg, run_dir, log, ckpt, make_recorder, opts, install_signals, progress)


def _analyse_again(run_dir: Path, ckpt: ckpt_mod.Checkpoint, console: Any, install_signals: bool,
                   opts: RunOptions) -> RunResult:
    """``rigctl resume`` of a complete run whose analysis did not end (interrupted, failed, or
    cut off by a crash): the analysis only, on the closed recording; the rig is not opened."""
    recording = run_dir / ckpt.recording
    progress = opts.progress or make_progress(ConsoleStream.wrap(console if console is not None else sys.stdout))
    log = _DiskSafeLog(RunLog(run_dir / RUN_LOG, progress.console))
    log("info", f"resuming {run_dir.name}: the run is complete, its analysis {ckpt.analysis}: "
                "running the analysis again")
    signals = opts.signals if opts.signals is not None else RunSignals()
    with _signal_handlers(install_signals, lambda signum, _frame: signals.received(signum)):
        code, message = _analyse(run_dir, recording, ckpt, log, signals)
        log.close()
    return RunResult(code, run_dir, recording, "complete", message, analysis=_analysis_outcome(ckpt))


def resume_run(run_dir: str | Path, runs_root: str | Path, console: Any = None,
               install_signals: bool = True, options: RunOptions | None = None) -> RunResult:
    """Continue a cut-off (crashed, interrupted or failed) run from the step after its last
    complete one, into the same run directory and recording.

    The procedure is loaded again from its original path and must be unchanged (its files'
    SHA-256 are in the checkpoint); the rig config comes from the run's snapshot. Rows recorded
    while the step in flight ran are written as an ``incomplete`` segment plus a ``resume`` event
    naming their range, so solvers never use them.

    A complete run whose analysis did not end (an interruption while the solvers ran) gets the
    analysis only."""
    d = check_run_dir(run_dir, runs_root)
    with hold_run_dir(d):  # before the checkpoint is read: one writer at a time
        return _resume(d, console, install_signals, options or RunOptions())


def _resume(d: Path, console: Any, install_signals: bool, opts: RunOptions) -> RunResult:
    ck = ckpt_mod.load(d)  # CheckpointError is an InputError
    if ck.status == "complete":
        if ck.analysis in ("running", "interrupted", "failed"):
            return _analyse_again(d, ck, console, install_signals, opts)
        raise InputError(f"{d}: the run is already complete; nothing to resume")
    cfg = load_config(d / ck.config_file)
    opts = _with_settings(opts, cfg)
    proc = load_procedure(ck.procedure_path, ck.overrides, cfg.limits)
    for path, text in proc.sources.items():
        if ck.source_sha256.get(str(Path(path).resolve())) != ckpt_mod.sha256_text(text):
            raise InputError(f"{path} changed since the run started (or is not the same file)",
                             hint="restore the procedure as it was, or start a new run")
    recording = d / ck.recording
    if not recording.exists():
        raise InputError(f"{d}: the run was cut off before its recording was created",
                         hint="start the procedure again")
    with _open_cut_off(recording) as f:
        _check_resumable(f, recording)
        seg = _rows(f, "segments", ("status", "step", "last_sample", "kind", "t_start"))
        ev = _rows(f, "events", ("time", "kind", "message"))
        file_status = f["run/status"][0].decode()
        recorded_id = f["meta"].attrs.get("imu_device_id", "")  # absent: recorded before rigctl knew
    recorded_id = recorded_id.decode() if isinstance(recorded_id, bytes) else str(recorded_id)
    if file_status == "complete":
        raise InputError(f"{recording}: the recording is already complete; nothing to resume")
    done = seg["status"] == b"complete"
    last_done = max([ck.last_step, *(int(x) for x in seg["step"][done])])
    # IMU rows of the step in flight start where the last complete step's samples ended
    in_flight_from = max([int(ck.n_imu), *(int(x) for x in seg["last_sample"][done])])
    todo = [s for s in proc.steps if s.is_motion and s.index > last_done]
    progress = opts.progress or make_progress(ConsoleStream.wrap(console if console is not None else sys.stdout))
    log = RunLog(d / RUN_LOG, progress.console)
    ck.sessions += 1
    log("info", f"resuming {d.name} (session {ck.sessions}): {len(todo)} steps left after step "
                f"{last_done + 1}; recording {recording}")
    by_index = {s.index: s for s in proc.steps}

    def make_recorder(rig: Rig, truth: Any) -> tuple[Recorder, int]:
        check_same_imu(rig, recording, recorded_id)  # before the recording or the table is touched
        rec = Recorder.reopen(recording, imu_rate_hz=cfg.imu_rate_hz,
                              flush_interval_s=cfg.flush_interval_s,
                              min_free_bytes=opts.suspenders.min_free_bytes // 4)
        lt = rec.last_times()
        first = min(in_flight_from, rec.n_imu)
        t_end = np.nanmax([*lt.values(), ck.t_file])
        nxt = todo[0] if todo else None
        if nxt is not None and rec.n_imu > first:
            nan3 = np.full(3, np.nan)
            rec.add_segment(Segment(kind=nxt.kind, label=nxt.label, step=nxt.index,
                                    first_sample=first, last_sample=rec.n_imu, t_start=ck.t_file,
                                    t_end=float(t_end), settle_time=math.nan,
                                    commanded_angle=nxt.angles,
                                    commanded_rate=np.nan_to_num(nxt.rates, nan=0.0),
                                    measured_angle=nan3, measured_rate=nan3, status="incomplete"),
                            file_time=True)
        what = (f"step {nxt.index + 1} ({nxt.label}) was in flight: IMU rows [{first}, {rec.n_imu}) "
                "marked incomplete" if nxt is not None else "no step was in flight")
        # the checkpoint counts this session before the file names it: a kill between the two
        # leaves the count one ahead of the file's resume events, never behind (behind, the next
        # session would take this one's number)
        ck.status = "running"
        ckpt_mod.save(d, ck)
        rec.add_event(float(t_end), "resume",
                      f"session {ck.sessions} after a cut-off at t={float(t_end):.3f} s; {what}; "
                      f"new session starts at t={rec.time_offset:.3f} s", file_time=True)
        log("info", f"{what}; new data start at t={rec.time_offset:.3f} s, IMU counter "
                    f"{rec.counter_offset}")
        start = min((by_index[s.index].index for s in todo), default=len(proc.steps))
        return rec, start

    try:
        return _drive(proc, cfg, d, log, ck, make_recorder, opts, install_signals, progress, resuming=True,
                      rewarm=rewarm_due(ev["time"], ev["kind"], ev["message"], seg["kind"], seg["status"],
                                        seg["t_start"]))
    except InputError as exc:  # e.g. another IMU: nothing was changed, say so in the run's log too
        log("error", f"resume refused: {exc}", echo=False)  # the caller reports it
        log.close()
        raise
