"""``rigctl serve``: the daemon that owns the rig and runs queued jobs one at a time, and the
client verbs ``submit``, ``status [--watch]``, ``queue``, ``pause``, ``resume [RUN]``,
``abort``, ``logs`` (see docs/daemon.md).

The daemon keeps its job list in ``<runs>/.rigctl-daemon/jobs.json`` (rewritten atomically). On
start, a job it was running when it died (crash, power loss) is resumed first from its run's
checkpoint (:func:`rigctl.run.runner.resume_run`), then the queue continues.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import signal
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from . import control
from ..recording.checkpoint import try_lock, write_atomic
from ..run.console import detach_all
from ..clock import utc_now
from ..run.runlog import RunLog
from .daemon_text import reply_text
from ..errors import EXIT_INTERRUPTED, EXIT_INVALID, EXIT_OK, InputError, Interrupted, RigctlError, RunFailure
from ..run.stop_signals import stop_on_signals
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the runner pulls in the solvers (scipy, ~1 s): client verbs must not pay it
    from ..progress import Progress
    from ..run.runner import RunOptions, RunSignals
# Nor the config, procedures, progress, live feed or notifier (numpy, YAML, h5py): the daemon
# imports them where it uses them, so `rigctl status` and the other client verbs start in ~0.2 s
# of CPU instead of ~0.7 s.
from ..engine.states import StateMachine


@dataclass
class Job:
    id: int
    kind: str                   # run | resume
    procedure: str = ""         # absolute path (run)
    params: dict[str, Any] | None = None
    run_dir: str = ""           # set when it starts (run) or given (resume)
    state: str = "queued"       # queued | running | complete | interrupted | failed | crashed | removed
    message: str = ""
    submitted_utc: str = ""
    started_utc: str = ""
    ended_utc: str = ""
    #: the analysis of the job's complete recording (its procedure's solve steps): "" (none ran),
    #: done, failed (the job is failed) or interrupted (the job is interrupted; ``rigctl resume
    #: RUN`` runs the analysis only)
    analysis: str = ""


class Daemon:
    """Owns the rig config, the job queue, the state machine and the control socket."""

    def __init__(self, runs_dir: Path, config_path: Path, socket_path: Path,
                 console: Any = None, options: RunOptions | None = None) -> None:
        self.runs_dir = Path(runs_dir).resolve()
        self.runs_dir.mkdir(parents=True, exist_ok=True)
        self.config_path = Path(config_path).resolve()
        from ..config.config import load_config
        self.cfg = load_config(self.config_path)
        self._lock_fd = self._lock_runs_dir()  # before the job list is read or the log written
        try:
            self._init(socket_path, console, options)
        except BaseException:
            self._unlock_runs_dir()
            raise

    def _init(self, socket_path: Path, console: Any, options: RunOptions | None) -> None:
        self.socket_path = Path(socket_path)
        from ..config.notify import Notifier
        from ..progress import NullProgress
        from ..run.runner import RunOptions
        from .livefeed import LiveFeed
        self.base_options = options or RunOptions()
        self.states = StateMachine()
        self.log = RunLog(self.runs_dir / ".rigctl-daemon" / "daemon.log.jsonl"
                          if self._state_dir() else None, console)
        self.jobs: list[Job] = []
        self.queue: deque[int] = deque()
        self.cv = threading.Condition()
        self.engine: Any = None  # the running job's rigctl.engine.engine.Engine
        self.current: Job | None = None
        self.job_signals: RunSignals | None = None  # the running job's SIGINT / SIGTERM record
        self.progress: Progress = NullProgress()
        self.stopping: str | None = None
        self.queue_running = True   # False after queue_stop: the running job ends, no new one starts
        self.live = LiveFeed()
        self._load_jobs()
        self.server = control.ControlServer(self.socket_path, self.handle, self.log)
        self.worker = threading.Thread(target=self._work, name="rigctl-worker", daemon=True)
        self.web: Any = None  # a rigctl.service.web.WebServer when serving HTTP (start_http)
        self.notifier = Notifier(self.cfg.notifications, self.cfg.name, self.log)
        self._paused_since: float | None = None   # wall time (monotonic) the current pause began
        self._pause_noticed = False
        self.states.listeners.append(self._on_state)
        self.states.listeners.append(
            lambda old, new, why: self.log("state", f"daemon {old} -> {new}" + (f": {why}" if why else "")))

    # -- persistence -------------------------------------------------------------------------
    def _lock_runs_dir(self) -> int:
        """An exclusive lock on ``<runs>/.rigctl-daemon/daemon.lock`` for the daemon's life (the
        kernel drops it when the process dies, kill -9 too): a second daemon on the same runs
        directory (another socket, another session's $XDG_RUNTIME_DIR) would otherwise read the
        first's running job as cut off and resume it into the same recording."""
        fd, holder = try_lock(self._state_dir() / "daemon.lock")
        if fd is None:
            raise RunFailure(f"{self.runs_dir}: another rigctl serve{f' (pid {holder})' if holder else ''} "
                             "already runs jobs in this runs directory (rigctl status shows it); stop it "
                             "first, or give this one another --runs DIR")
        return fd

    def _unlock_runs_dir(self) -> None:
        fd, self._lock_fd = getattr(self, "_lock_fd", None), None
        if fd is not None:
            os.close(fd)  # releases the flock

    def _state_dir(self) -> Path:
        d = self.runs_dir / ".rigctl-daemon"
        d.mkdir(mode=0o700, exist_ok=True)
        return d

    def _save_jobs(self) -> None:
        write_atomic(self._state_dir() / "jobs.json",
                     json.dumps([asdict(j) for j in self.jobs], indent=1).encode())

    def _load_jobs(self) -> None:
        path = self._state_dir() / "jobs.json"
        if not path.exists():
            return
        try:
            raw = json.loads(path.read_text())
            self.jobs = [Job(**j) for j in raw]
        except (ValueError, TypeError) as exc:
            self.log("warning", f"ignoring unreadable {path}: {exc}")
            return
        resume_first = []
        for j in list(self.jobs):  # a copy: the resume jobs created here must not be queued twice
            if j.state == "running":
                j.state, j.message = "crashed", "the daemon stopped while the job ran"
                if j.run_dir and (Path(j.run_dir) / "checkpoint.json").exists():
                    r = self._new_job("resume", run_dir=j.run_dir)
                    resume_first.append(r.id)
                    self.log("info", f"job {j.id} was cut off; job {r.id} resumes {j.run_dir}")
            elif j.state == "queued":
                self.queue.append(j.id)
        for jid in reversed(resume_first):
            self.queue.remove(jid) if jid in self.queue else None
            self.queue.appendleft(jid)
        self._save_jobs()

    def _new_job(self, kind: str, position: int | None = None, **kw: Any) -> Job:
        job = Job(id=max((j.id for j in self.jobs), default=0) + 1, kind=kind,
                  submitted_utc=utc_now(), **kw)
        self.jobs.append(job)
        if position is None or position >= len(self.queue):
            self.queue.append(job.id)
        else:
            self.queue.insert(position, job.id)
        return job

    def _duplicate_of(self, kind: str, procedure: str = "", params: dict | None = None,
                      run_dir: str = "") -> Job | None:
        """A queued or running job that would do the same work: the same procedure with the same
        parameters, or a resume of (or the job running in) the same run directory."""
        for j in self.jobs:
            if j.state not in ("queued", "running"):
                continue
            if kind == "run" and j.kind == "run" and j.procedure == procedure and (j.params or {}) == (params or {}):
                return j
            if kind == "resume" and run_dir and j.run_dir == run_dir:
                return j
        return None

    def job(self, jid: int) -> Job:
        return next(j for j in self.jobs if j.id == jid)

    # -- requests ------------------------------------------------------------------------------
    def handle(self, cmd: str, args: dict[str, Any]) -> dict[str, Any]:
        with self.cv:
            return getattr(self, f"_cmd_{cmd}")(args)

    def _cmd_ping(self, _args: dict) -> dict:
        return {"ok": True, "state": self.states.state}

    def _cmd_status(self, _args: dict) -> dict:
        eng = self.engine
        state, reason = self.states.state, self.states.reason
        sig = self.job_signals
        since = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(self.states.since))
        if self.current is not None and state == "idle" and sig is not None and sig.analysing:
            state, reason = "analysing", (f"job {self.current.id}: analysing its complete, closed recording "
                                          "(the procedure's solve steps)")
        elif self.current is not None and state == "idle":  # between taking the job and the first step
            state, reason = "starting", f"job {self.current.id}: opening the rig and checking its devices"
            # since the job was taken, not since the daemon went idle (maybe hours before)
            since = self.current.started_utc[:19] + "Z" if self.current.started_utc else since
        out: dict[str, Any] = {"ok": True, "state": state, "reason": reason, "since_utc": since,
                               "queued": len(self.queue), "queue_running": self.queue_running,
                               "job": asdict(self.current) if self.current else None}
        if eng is not None:
            out["suspenders"] = dict(eng.suspenders.active)
            out["step"] = eng.current_step.describe() if eng.current_step else None
            out["imu_samples"] = eng.rec.n_imu
            out["segments"] = eng.rec.n_segments
            out["progress"] = self.progress.status_text()
            out["remaining_s"] = round(self.progress.remaining_s(), 1)
            out["deferred_pause"] = eng.deferred_pause is not None
            out["step_fraction"] = round(self.progress.fraction(), 3)
        return out

    def _cmd_queue(self, _args: dict) -> dict:
        return {"ok": True, "jobs": [asdict(j) for j in self.jobs[-200:]], "queued": list(self.queue),
                "queue_running": self.queue_running}

    def _queued_job(self, jid: int) -> Job | None:
        return self.job(jid) if jid in self.queue else None

    def _cmd_queue_remove(self, args: dict) -> dict:
        job = self._queued_job(args["job"])
        if job is None:
            return {"ok": False, "error": f"job {args['job']} is not queued", "exit_code": EXIT_INVALID}
        self.queue.remove(job.id)
        job.state, job.message, job.ended_utc = "removed", "removed from the queue", utc_now()
        self._save_jobs()
        return {"ok": True, "queued": list(self.queue)}

    def _cmd_queue_move(self, args: dict) -> dict:
        job = self._queued_job(args["job"])
        if job is None:
            return {"ok": False, "error": f"job {args['job']} is not queued", "exit_code": EXIT_INVALID}
        self.queue.remove(job.id)
        self.queue.insert(min(args["position"], len(self.queue)), job.id)
        self._save_jobs()
        return {"ok": True, "queued": list(self.queue)}

    def _cmd_queue_clear(self, _args: dict) -> dict:
        removed = list(self.queue)
        for jid in removed:
            j = self.job(jid)
            j.state, j.message, j.ended_utc = "removed", "queue cleared", utc_now()
        self.queue.clear()
        self._save_jobs()
        return {"ok": True, "removed": removed}

    def _cmd_queue_stop(self, _args: dict) -> dict:
        """Start no new job: the running one (if any) goes on to its end."""
        self.queue_running = False
        self.log("info", "queue stopped: no new job starts until 'queue start'")
        return {"ok": True, "queue_running": False, "running_job": self.current.id if self.current else None}

    def _cmd_queue_start(self, _args: dict) -> dict:
        self.queue_running = True
        self.log("info", "queue started")
        self.cv.notify_all()
        return {"ok": True, "queue_running": True}

    def _cmd_history(self, args: dict) -> dict:
        done = [asdict(j) for j in reversed(self.jobs) if j.state not in ("queued", "running")]
        return {"ok": True, "jobs": done[:int(args.get("limit", 50))]}

    def _cmd_submit(self, args: dict) -> dict:
        path = Path(args["procedure"])
        if not path.is_absolute():
            return {"ok": False, "error": "procedure path must be absolute (the client resolves it)",
                    "exit_code": EXIT_INVALID}
        params = dict(args.get("params") or {})
        try:
            from ..engine.procedure import load_procedure
            load_procedure(path, params, self.cfg.limits)  # validate now: errors go to the client
        except InputError as exc:
            return {"ok": False, "error": str(exc), "exit_code": exc.exit_code}
        dup = self._duplicate_of("run", procedure=str(path), params=params)
        if dup is not None:
            return {"ok": False, "error": f"job {dup.id} ({dup.state}) already runs {path} with the same "
                    "parameters; remove it first or change a parameter", "exit_code": EXIT_INVALID}
        job = self._new_job("run", position=args.get("position"), procedure=str(path), params=params)
        self._save_jobs()
        self.cv.notify_all()
        return {"ok": True, "job": job.id, "position": list(self.queue).index(job.id) + 1}

    def _cmd_pause(self, args: dict) -> dict:
        if self.engine is None or self.states.state not in ("running", "pausing", "paused"):
            return {"ok": False, "error": f"nothing to pause (daemon is {self.states.state})"}
        if args.get("deferred"):
            self.engine.request_pause("paused by operator at the end of a step (rigctl pause --deferred)",
                                      deferred=True)
            return {"ok": True, "state": self.states.state, "deferred": True,
                    "note": "pauses at the end of the step in flight"}
        self.engine.request_pause("paused by operator (rigctl pause)")
        return {"ok": True, "state": self.states.state}

    def _cmd_resume(self, args: dict) -> dict:
        if "run" in args:
            try:
                from ..run.runner import check_run_dir
                d = check_run_dir(args["run"], self.runs_dir)
            except InputError as exc:
                return {"ok": False, "error": str(exc), "exit_code": exc.exit_code}
            dup = self._duplicate_of("resume", run_dir=str(d))
            if dup is not None:
                return {"ok": False, "error": f"job {dup.id} ({dup.state}) already works on {d}",
                        "exit_code": EXIT_INVALID}
            job = self._new_job("resume", run_dir=str(d))
            self._save_jobs()
            self.cv.notify_all()
            return {"ok": True, "job": job.id}
        if self.states.state == "faulted":
            self.states.to("idle", "reset by operator (rigctl resume)")
            self.cv.notify_all()
            return {"ok": True, "state": "idle"}
        if self.engine is None or self.engine.suspenders.operator is None:
            return {"ok": False, "error": f"not paused by an operator (daemon is {self.states.state})"}
        self.engine.request_resume()
        return {"ok": True, "state": self.states.state,
                "note": f"resumes once every suspender is clear for {self.engine.suspenders.s.hold_s:g} s"}

    def _cmd_abort(self, _args: dict) -> dict:
        if self.engine is None:
            return {"ok": False, "error": "no job is running"}
        self.engine.request_abort("abort requested (rigctl abort)")
        # as in bluesky-queueserver: an abort stops the queue, the next job does not start at once
        self.queue_running = False
        self.log("info", "queue stopped by the abort: 'rigctl queue start' runs the next job")
        return {"ok": True, "queue_running": False,
                "note": f"queue stopped ({len(self.queue)} queued); 'rigctl queue start' goes on"}

    def _cmd_logs(self, args: dict) -> dict:
        job = self.current or next((j for j in reversed(self.jobs) if j.run_dir), None)
        if job is None or not job.run_dir:
            return {"ok": True, "lines": []}
        path = Path(job.run_dir) / "run.log.jsonl"
        n = int(args.get("lines", 50))
        lines: deque[str] = deque(maxlen=n)
        if path.exists():
            with open(path, encoding="utf-8", errors="replace") as fh:
                lines.extend(line.rstrip("\n") for line in fh)
        return {"ok": True, "job": job.id, "lines": list(lines)}

    # -- notices -------------------------------------------------------------------------------
    def _on_state(self, old: str, new: str, why: str) -> None:
        if new in ("pausing", "paused"):
            if self._paused_since is None:
                self._paused_since, self._pause_noticed = time.monotonic(), False
        else:
            self._paused_since = None
        if new == "faulted":
            job = self.current
            self.notifier.notify("faulted", why, asdict(job) if job else None)

    def _watch(self) -> None:
        """Send the 'suspended' notice once a pause has lasted ``suspended_after_s`` (wall time)."""
        limit = self.cfg.notifications.suspended_after_s
        while self.stopping is None:
            since = self._paused_since
            if since is not None and not self._pause_noticed and time.monotonic() - since >= limit:
                self._pause_noticed = True
                with self.cv:
                    eng, job = self.engine, self.current
                    reasons = dict(eng.suspenders.active) if eng is not None else {}
                    info = asdict(job) if job else None
                text = "; ".join(f"{k}: {v}" for k, v in reasons.items()) or self.states.reason
                self.notifier.notify("suspended", f"suspended for more than {limit:g} s: {text}", info)
            time.sleep(min(0.5, limit / 4))

    # -- jobs ----------------------------------------------------------------------------------
    def _set_engine(self, engine: Any) -> None:
        with self.cv:
            self.engine = engine
            if engine is not None:
                self.live.reset()
                engine.live = self.live
            if engine is not None and self.current is not None and not self.current.run_dir:
                self.current.run_dir = str(Path(engine.rec.path).parent)
                self._save_jobs()

    def _work(self) -> None:
        """Run queued jobs one at a time until :attr:`stopping` is set (checked at least every
        0.2 s: a signal handler sets it without notifying)."""
        while True:
            with self.cv:
                while not self.cv.wait_for(lambda: self.stopping or (self.queue and self.queue_running
                                                                      and self.states.state == "idle"), 0.2):
                    pass
                if self.stopping:
                    return
                job = self.job(self.queue.popleft())
                job.state, job.started_utc, self.current = "running", utc_now(), job
                self._save_jobs()
            self.log("info", f"job {job.id}: {job.kind} {job.procedure or job.run_dir}")
            # plain progress lines once a minute on the daemon's console; `status` reads it too
            from ..engine.procedure import load_procedure
            from ..progress import Progress
            from ..run.runner import RunOptions, RunSignals, resume_run, run_procedure
            self.progress = Progress(self.log.console, tty=False, interval_s=60.0)
            self.job_signals = RunSignals()
            opts = RunOptions(suspenders=self.base_options.suspenders, states=self.states,
                              rig_opener=self.base_options.rig_opener, on_engine=self._set_engine,
                              max_pause_s=self.base_options.max_pause_s,
                              sample_poll_s=self.base_options.sample_poll_s, progress=self.progress,
                              signals=self.job_signals)
            analysis = ""
            try:
                if job.kind == "run":
                    proc = load_procedure(job.procedure, job.params or {}, self.cfg.limits)
                    res = run_procedure(proc, self.cfg, self.runs_dir, console=self.log.console,
                                        install_signals=False, options=opts, overrides=job.params or {})
                else:
                    res = resume_run(job.run_dir, self.runs_dir, console=self.log.console,
                                     install_signals=False, options=opts)
                state, message, run_dir, analysis = res.status, res.message, str(res.run_dir), res.analysis
                if state == "complete" and analysis in ("failed", "interrupted"):  # the recording is
                    state = analysis  # complete, the job is not: its results are missing
            except RigctlError as exc:
                state, message, run_dir = "failed", str(exc), job.run_dir
            except Exception as exc:  # noqa: BLE001 - a bug; the daemon survives a broken job
                state, message, run_dir = "failed", f"{type(exc).__name__}: {exc}", job.run_dir
                self.log("error", f"job {job.id}: {message}", traceback=traceback.format_exc())
                if self.states.state not in ("idle", "faulted"):
                    self.states.to("faulted", message)
            with self.cv:
                job.state, job.message, job.run_dir, job.ended_utc = state, message, run_dir, utc_now()
                job.analysis = analysis
                self.current, self.engine, self.job_signals = None, None, None
                self._save_jobs()
                self.cv.notify_all()
            self.log("info", f"job {job.id} {state}" + (f": {message}" if message else ""))
            self.notifier.notify(state, message, asdict(job))

    def start(self, worker: bool = True) -> None:
        """Serve the control socket (and notices); with ``worker`` run the jobs in a thread of
        their own (in-process use: the jobs' analyses cannot be interrupted by a signal there;
        ``rigctl serve`` runs them in the main thread instead, :meth:`serve`)."""
        self.server.start()
        if worker:
            self.worker.start()
        if self.cfg.notifications.enabled:
            self.notifier.start()
            threading.Thread(target=self._watch, name="rigctl-watch", daemon=True).start()
        self.log("info", f"rigctl daemon: socket {self.socket_path}, runs in {self.runs_dir}, "
                         f"config {self.config_path}")

    def start_http(self, host: str = "127.0.0.1", port: int = 0, token_file: Path | None = None,
                   open_read: bool = False, procedures_dir: Path | None = None) -> Any:
        """Serve the HTTP API and web page (rigctl.service.web); returns the running WebServer."""
        from .web import WebApi, WebServer, load_or_create_token

        token_path = Path(token_file) if token_file else self._state_dir() / "http-token"
        token = load_or_create_token(token_path)
        api = WebApi(self, token, open_read=open_read, procedures_dir=procedures_dir)
        self.web = WebServer(api, host, port, log=self.log)
        self.web.start()
        self.log("info", f"rigctl daemon: web page and API at {self.web.url} (token in {token_path}"
                         + ("; read-only views open without it" if open_read else "") + ")")
        if host not in ("127.0.0.1", "::1", "localhost"):
            self.log("warning", f"HTTP is bound to {host}: reachable from other machines, unencrypted; "
                                "put it behind a TLS proxy or an SSH tunnel")
        return self.web

    def stop(self, reason: str = "shutdown") -> None:
        """Abort the running job (the table goes to its safe state), stop serving."""
        with self.cv:
            self.stopping = reason
            if self.engine is not None:
                self.engine.request_abort(reason)
            self.cv.notify_all()
        self.worker.join(timeout=30)
        self._close(reason)

    def _close(self, reason: str) -> None:
        if self.web is not None:
            self.web.close()
        self.server.close()
        self.notifier.close()
        self.log("info", f"rigctl daemon stopped ({reason})")
        self._unlock_runs_dir()

    def serve(self) -> None:
        """``rigctl serve``: serve and run the queued jobs in this thread -- the main one, where
        Python runs signal handlers -- until SIGINT or SIGTERM, then close.

        A signal while a job runs its procedure aborts it (the table to its safe state, the
        recording closed as ``interrupted``); while it analyses its complete recording it stops
        the analysis (rigctl.run.runner: every result written whole or not at all, the
        checkpoint's analysis ``interrupted``; the job ends ``interrupted`` with ``analysis``
        ``interrupted``, and ``rigctl resume RUN`` runs the analysis only); between jobs the
        daemon stops at once. No new job starts after it."""
        def on_signal(signum: int, _frame: Any) -> None:  # minimal: a signal handler
            if self.stopping is None:
                self.stopping = f"daemon stopped by {signal.Signals(signum).name}"
            eng = self.engine
            if eng is not None and eng.abort_requested is None:
                eng.request_abort(self.stopping)
            sig = self.job_signals
            if sig is not None:
                sig.received(signum)  # during the job's analysis: stops it (raises in this thread)

        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            self.start(worker=False)
            self._work()
        finally:
            for s, h in old.items():
                signal.signal(s, h)
        self._close(self.stopping or "stopped")


# -- CLI -------------------------------------------------------------------------------------------
def cmd_serve(args: argparse.Namespace) -> int:
    if args.http:  # before the daemon takes its runs directory and socket
        missing = [m for m in ("starlette", "uvicorn") if importlib.util.find_spec(m) is None]
        if missing:
            raise InputError(f"--http {args.http}: the web page and HTTP API need {' and '.join(missing)}, "
                             "which is not installed", hint="install the web extra: pip install -e '.[web]'")
    from ..config.config import resolve_config_path
    cfg_path = resolve_config_path(args.config)
    d = Daemon(Path(args.runs), cfg_path, Path(args.socket) if args.socket else control.default_socket_path())
    if args.http:
        from .web import parse_hostport
        try:
            host, port = parse_hostport(args.http)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        procs = Path(args.procedures) if args.procedures else _default_procedures()
        try:
            d.start_http(host, port, args.http_token_file, args.http_open_read, procs)
        except OSError as exc:
            d.server.close()
            d._unlock_runs_dir()
            raise RunFailure(f"--http {args.http}: {exc.strerror or exc}") from None
    # a hang-up (the terminal or SSH session closed) detaches the console; the daemon goes on
    signal.signal(signal.SIGHUP, lambda *_: detach_all("hang-up (SIGHUP)", notify=False))
    d.serve()  # until SIGINT or SIGTERM
    return 0


def _default_procedures() -> Path:
    """./procedures when it exists, else the project's procedures directory."""
    from ..config.config import PROJECT_ROOT
    here = Path.cwd() / "procedures"
    return here if here.is_dir() else PROJECT_ROOT / "procedures"


def _client(args: argparse.Namespace, cmd: str, payload: dict[str, Any] | None = None) -> dict[str, Any]:
    path = Path(args.socket) if args.socket else control.default_socket_path()
    return control.request(path, cmd, payload)


def _print_reply(reply: dict[str, Any], cmd: str = "", args: argparse.Namespace | None = None) -> int:
    """Print a daemon's answer: aligned text (rigctl.service.daemon_text), or with ``--json`` the reply
    as one JSON document. A refusal raises the error its ``exit_code`` names (2: the request or
    the procedure is invalid, else 1), so the CLI exits as ``rigctl run`` would."""
    as_json = bool(getattr(args, "json", False))
    if as_json:
        print(json.dumps(reply, indent=1, default=str))
    if not reply.get("ok"):
        text = str(reply.get("error", "unknown error"))
        raise InputError(text) if reply.get("exit_code") == EXIT_INVALID else RunFailure(text)
    if not as_json:
        text = reply_text(cmd, reply)
        if text:
            print(text)
    return 0


def _run_client(fn: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    def wrapped(args: argparse.Namespace) -> int:
        try:
            return fn(args)
        except ConnectionError as exc:  # no daemon: a failure at run time (1)
            raise RunFailure(str(exc)) from None
    return wrapped


@_run_client
def cmd_submit(args: argparse.Namespace) -> int:
    from ..engine.procedure import parse_overrides
    params = parse_overrides(args.param)
    payload: dict[str, Any] = {"procedure": str(Path(args.procedure).resolve()), "params": params}
    if args.position is not None:
        if args.position < 1:
            raise InputError(f"--position {args.position}: positions start at 1")
        payload["position"] = args.position - 1
    return _print_reply(_client(args, "submit", payload), "submit", args)


QUEUE_ACTIONS = ("remove", "move", "clear", "stop", "start", "history")
_QUEUE_ARITY = {"remove": (1, 1), "move": (2, 2), "clear": (0, 0), "stop": (0, 0), "start": (0, 0),
                "history": (0, 1), None: (0, 0)}


@_run_client
def cmd_queue(args: argparse.Namespace) -> int:
    """``rigctl queue [ACTION ...]``: list, or one queue operation (positions count from 1)."""
    lo, hi = _QUEUE_ARITY[args.action]
    if not lo <= len(args.values) <= hi:
        raise InputError(f"queue {args.action or ''}: expected "
                         + {"remove": "JOB", "move": "JOB POSITION", "history": "[N]"}.get(args.action or "", "nothing")
                         + f", got {' '.join(map(str, args.values)) or 'nothing'}")
    if args.action in (None, "clear", "stop", "start"):
        cmd = "queue" if args.action is None else f"queue_{args.action}"
        return _print_reply(_client(args, cmd), cmd, args)
    if args.action == "remove":
        return _print_reply(_client(args, "queue_remove", {"job": args.values[0]}), "queue_remove", args)
    if args.action == "move":
        if args.values[1] < 1:
            raise InputError(f"queue move: position {args.values[1]}: positions start at 1")
        return _print_reply(_client(args, "queue_move", {"job": args.values[0], "position": args.values[1] - 1}),
                            "queue_move", args)
    return _print_reply(_client(args, "history", {"limit": args.values[0]} if args.values else {}), "history", args)


def watch_line(reply: dict[str, Any]) -> str:
    """One plain line of a status reply for ``status --watch``: UTC, state, progress, suspenders."""
    parts = [time.strftime("%H:%M:%SZ", time.gmtime()), str(reply.get("state"))]
    job = reply.get("job")
    if job:
        parts.append(f"job {job.get('id')} {Path(str(job.get('procedure') or job.get('run_dir') or '')).name}")
    if reply.get("progress"):
        parts.append(str(reply["progress"]))
    if reply.get("suspenders"):
        parts.append("suspended: " + "; ".join(f"{k}: {v}" for k, v in reply["suspenders"].items()))
    if reply.get("queued"):
        parts.append(f"{reply['queued']} queued")
    return " | ".join(parts)


@_run_client
def cmd_status(args: argparse.Namespace) -> int:
    """Print the daemon's status; with ``--watch`` one plain line per interval until Ctrl-C
    (SIGINT) or SIGTERM, then exit 0.

    The watch installs its own handlers (:func:`rigctl.run.stop_signals.stop_on_signals`) instead of
    relying on KeyboardInterrupt, which a process started with SIGINT ignored never gets."""
    if not args.watch:
        return _print_reply(_client(args, "status"), "status", args)
    with stop_on_signals() as stop:
        while not stop.is_set():
            reply = _client(args, "status")
            if not reply.get("ok"):
                return _print_reply(reply, "status", args)
            print(json.dumps(reply, default=str) if args.json else watch_line(reply), flush=True)
            stop.wait(args.interval)
    return 0


@_run_client
def cmd_simple(args: argparse.Namespace) -> int:
    payload = {"lines": args.lines} if args.command == "logs" else None
    if args.command == "pause" and args.deferred:
        payload = {"deferred": True}
    return _print_reply(_client(args, args.command, payload), args.command, args)


def resume_runs_dir(run: str, runs: str | None) -> str:
    """The runs directory of a local ``rigctl resume RUN``: ``--runs`` when given, else the
    folder holding RUN (a run directory is always a direct child of the ``--out`` it was made
    in), else ``runs`` (RUN is not a directory: the refusal names it)."""
    if runs is not None:
        return runs
    d = Path(run)
    return str(d.resolve().parent) if d.is_dir() else "runs"


def cmd_resume(args: argparse.Namespace) -> int:
    if args.run is None:
        return _run_client(lambda a: _print_reply(_client(a, "resume"), "resume", a))(args)
    path = Path(args.socket) if args.socket else control.default_socket_path()
    if control.ping(path):  # the daemon owns the rig: let it run the resume
        return _print_reply(control.request(path, "resume", {"run": str(Path(args.run).resolve())}), "resume", args)
    from ..run.runner import resume_run
    res = resume_run(args.run, resume_runs_dir(args.run, args.runs))
    if res.exit_code == EXIT_INTERRUPTED and res.status == "complete":  # during the analysis: the
        raise Interrupted(res.message)                                   # message says it all
    if res.exit_code != EXIT_OK:
        raise (Interrupted if res.exit_code == EXIT_INTERRUPTED else RunFailure)(
            f"{res.message} (recording {res.status}; details in {res.run_dir / 'run.log.jsonl'})")
    return EXIT_OK


def register(sub: Any) -> None:
    """Add serve, submit, status, queue, pause, resume, abort and logs to the rigctl CLI."""
    def sock(p: argparse.ArgumentParser, client: bool = True) -> None:
        p.add_argument("--socket", help="control socket (default: $RIGCTL_SOCKET, "
                       "$XDG_RUNTIME_DIR/rigctl/rigctl.sock or /tmp/rigctl-UID/rigctl.sock)")
        if client:
            p.add_argument("--json", action="store_true",
                           help="print the daemon's answer as one JSON document (status --watch: one per line)")

    p = sub.add_parser("serve")
    sock(p, client=False)
    p.add_argument("--config", help="rig config YAML (default: configs/sim.yaml)")
    p.add_argument("--runs", default="runs", help="directory for run folders (default: runs)")
    p.add_argument("--http", metavar="HOST:PORT", help="also serve the HTTP API and web page "
                   "(default: off; e.g. 127.0.0.1:8470; another address exposes it to the network)")
    p.add_argument("--http-token-file", help="token file for HTTP control (default: "
                   "RUNS/.rigctl-daemon/http-token, created with mode 0600)")
    p.add_argument("--http-open-read", action="store_true",
                   help="let read-only views (status, queue, runs, live plots) be opened without the token")
    p.add_argument("--procedures", help="directory of procedures the web page may queue "
                   "(default: ./procedures, else the project's)")
    p.set_defaults(func=cmd_serve)
    p = sub.add_parser("submit")
    sock(p)
    p.add_argument("procedure")
    p.add_argument("-p", "--param", action="append", metavar="NAME=VALUE")
    p.add_argument("--position", type=int, help="place in the queue (1 = next to run; default: last)")
    p.set_defaults(func=cmd_submit)
    p = sub.add_parser("status")
    sock(p)
    p.add_argument("--watch", action="store_true", help="repeat until interrupted")
    p.add_argument("--interval", type=float, default=1.0, help="seconds between updates with --watch")
    p.set_defaults(func=cmd_status)
    p = sub.add_parser("queue")
    sock(p)
    p.add_argument("action", nargs="?", choices=QUEUE_ACTIONS, help="remove JOB | move JOB POSITION | clear | "
                   "stop (after the current job) | start | history [N]; none: list")
    p.add_argument("values", nargs="*", type=int, help="JOB, POSITION (1 = next to run) or N")
    p.set_defaults(func=cmd_queue)
    for name in ("pause", "abort", "logs"):
        p = sub.add_parser(name)
        sock(p)
        if name == "logs":
            p.add_argument("-n", "--lines", type=int, default=50)
        if name == "pause":
            p.add_argument("--deferred", action="store_true",
                           help="pause at the end of the step in flight (nothing re-runs) instead of at once")
        p.set_defaults(func=cmd_simple)
    p = sub.add_parser("resume")
    sock(p)
    p.add_argument("run", nargs="?", help="a run directory cut off by a crash or power loss")
    p.add_argument("--runs", default=None,
                   help="the directory RUN must be in (default: the folder holding RUN, as "
                        "`rigctl run --out DIR` made it; runs when RUN is not a directory)")
    p.set_defaults(func=cmd_resume)
