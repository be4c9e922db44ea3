"""Command-line interface: ``rigctl run | validate | ...``.

Exit codes: 0 done, 1 failure at run time, 2 invalid input, 130 interrupted.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Any

from . import __version__
from .run.console import guarded_std_streams
from .errors import (EXIT_FAILED, EXIT_INTERRUPTED, EXIT_INVALID, EXIT_OK, InputError, Interrupted, RigctlError,
                     RunFailure)
from .units import format_bytes, format_duration

if TYPE_CHECKING:
    from .config.config import RigConfig
    from .engine.procedure import Procedure

# The config, the engine and the rig (numpy, h5py, the emulator) are imported by `run` and
# `validate` only, in the functions below: `rigctl status`, `rigctl --help` and the analysis
# commands do not pay for them (rigctl status: 0.71 -> 0.2 s of CPU).

#: Sub-command -> the module that adds it through ``register(subparsers)``. Only the module of
#: the command being run is imported (the solvers pull in scipy, about 1 s, which a client verb
#: such as ``rigctl status --watch`` need not pay); ``rigctl --help`` imports none (:data:`SUMMARIES`).
COMMANDS: dict[str, str] = {
    "sync": "rigctl.commands.sync_cmd", "allan": "rigctl.commands.allan_cmd", "calibrate": "rigctl.commands.calibrate_cmd",
    "import": "rigctl.commands.import_cmd", "apply-cal": "rigctl.commands.applycal_cmd", "report": "rigctl.commands.report_cmd",
    "sim": "rigctl.commands.sim_cmd", "history": "rigctl.commands.history_cmd", "batch": "rigctl.commands.batch_cmd",
    "certificate": "rigctl.commands.certificate_cmd", "thermal": "rigctl.commands.thermal_cmd",
    **{verb: "rigctl.service.daemon" for verb in ("serve", "submit", "status", "queue", "pause", "resume",
                                          "abort", "logs")},
}
COMMAND_MODULES: tuple[str, ...] = tuple(dict.fromkeys(COMMANDS.values()))
#: Each command's line in ``rigctl --help``, in the order the modules add them. A module's
#: ``register(subparsers)`` adds its commands without a help text; the adder it is given
#: (:class:`_Summarised`) puts this line on each, so ``rigctl --help`` (and a missing or
#: unknown command) lists them without importing any module (~1.4 s of CPU for all of them).
SUMMARIES: dict[str, str] = {
    "sync": "tap-hammer time synchronisation of a recording",
    "allan": "Allan analysis of a recording's IMU channels",
    "calibrate": "calibrate a recording (uncertainty, closed loop)",
    "import": "convert a foreign IMU log (CSV, ROS bag, MCAP) into a rigctl recording",
    "apply-cal": "write a recording with calibrated IMU data",
    "report": "write report.html (plots embedded) for a run",
    "sim": "emulated hardware on real wires (rigctl sim up)",
    "history": "a unit's parameters across its calibrations, with drift",
    "batch": "calibrate / Allan-analyse many recordings on Dask",
    "certificate": "the run's calibration certificate (PDF)",
    "thermal": "bias and scale against temperature of a record held still in several poses (no table)",
    "serve": "run the daemon in the foreground (owns the rig, runs queued jobs)",
    "submit": "queue a procedure on the daemon",
    "status": "the daemon's state, job, step and active suspenders",
    "queue": "list the daemon's jobs, or edit the queue (remove, move, clear, stop, start, history)",
    "pause": "pause the running job",
    "abort": "abort the running job (table to safe state)",
    "logs": "the running (or last) job's log",
    "resume": "resume the paused job, or with RUN continue a cut-off run",
}


class _Summarised:
    """The sub-command adder a module's ``register`` gets: argparse's, with each command's
    :data:`SUMMARIES` line as its help."""

    def __init__(self, sub: Any) -> None:
        self._sub = sub

    def add_parser(self, name: str, **kw: Any) -> argparse.ArgumentParser:
        return self._sub.add_parser(name, help=SUMMARIES[name], **kw)


def _load(args: argparse.Namespace):
    from .config.config import load_config, resolve_config_path
    from .engine.procedure import load_procedure, parse_overrides
    cfg_path = resolve_config_path(args.config)
    cfg = load_config(cfg_path)
    proc = load_procedure(args.procedure, parse_overrides(args.param), cfg.limits)
    return cfg_path, cfg, proc


def check_out_dir(out: Path) -> None:
    """``rigctl run --out DIR``: a directory the run folder can be made in (or one that can be
    created: its nearest existing parent a writable directory), else one line naming the option,
    the path and why, exit 2 -- before the rig is opened; nothing is created here."""
    from .recording.recording_reader import unwritable_reason

    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file, not a directory",
                         hint="give the directory the run folders go in (default: runs)")
    base = next((p for p in (out, *out.absolute().parents) if p.exists()), None)
    if base is not None and not base.is_dir():
        raise InputError(f"--out {out}: cannot be created: {base} is a file, not a directory",
                         hint="give the directory the run folders go in (default: runs)")
    why = unwritable_reason(base) if base is not None else None
    if why:
        raise InputError(f"--out {out}: cannot write in {base} ({why})",
                         hint="give a writable directory for the run folders")


def taps_without_pulses(proc: Procedure, cfg: RigConfig, cfg_path: Path) -> str | None:
    """The warning for a procedure with a ``taps`` step on a config without a pulse input (the
    default emulator's): the taps are recorded but ``rigctl sync`` finds no pulses to match."""
    taps = [n for n, s in enumerate(proc.steps, 1) if s.kind == "taps"]
    if not taps or cfg.pulses.driver != "none":
        return None
    return (f"warning: {proc.path}: step {taps[0]} (taps) needs a pulse input, and config {cfg_path} has none "
            "(pulses: driver: none), so rigctl sync will find no pulses; configure one (docs/hardware.md) "
            "or, on the emulator, give --config configs/sim-taps.yaml (a tap hammer and a GNSS mark input)")


def cmd_run(args: argparse.Namespace) -> int:
    from .engine.procedure import parse_overrides
    from .engine.rig import describe
    from .run.runner import RUN_LOG, resume_command, run_procedure  # the solvers (scipy): only for a run, not for client verbs
    cfg_path, cfg, proc = _load(args)
    check_out_dir(Path(args.out))
    print(f"rigctl {__version__}: config {cfg_path}: {describe(cfg)}", flush=True)
    warn = taps_without_pulses(proc, cfg, cfg_path)
    if warn:
        print(warn, file=sys.stderr, flush=True)
    result = run_procedure(proc, cfg, Path(args.out), overrides=parse_overrides(args.param))
    if result.exit_code == EXIT_OK:
        return EXIT_OK
    where = f"{result.run_dir / RUN_LOG}"
    if result.exit_code == EXIT_INTERRUPTED and result.status == "complete":  # during the analysis:
        raise Interrupted(result.message)                                       # it says it all
    if result.exit_code == EXIT_INTERRUPTED:
        raise Interrupted(f"{result.message}; recording {result.recording} closed as {result.status} "
                          f"({resume_command(result.run_dir)} continues it)")
    if result.exit_code == EXIT_INVALID:  # e.g. a driver setting the device refused when the rig opened
        raise InputError(f"{result.message} (recording {result.status}; details in {where})")
    raise RunFailure(f"{result.message} (recording {result.status}; details in {where})")


def print_device_report(cfg_path: Path, cfg: RigConfig) -> None:
    """``validate --devices``: one line per device; DeviceError when one did not answer."""
    from .engine.device_check import check_devices
    report = check_devices(cfg)
    for c in report.checks:
        if c.ok:
            print(c.line())
    report.raise_for_problems()
    print(f"devices of {cfg_path}: all answered")


def cmd_validate(args: argparse.Namespace) -> int:
    from .engine.estimate import data_volume_bytes, estimate
    from .engine.rig import describe
    cfg_path, cfg, proc = _load(args)
    if args.devices:
        print_device_report(cfg_path, cfg)
    print(f"procedure {proc.name} ({proc.path}) against config {cfg_path}: {describe(cfg)}")
    if proc.parameters:
        print("parameters: " + ", ".join(f"{k}={v}" for k, v in proc.parameters.items()))
    plan = estimate(proc.steps, cfg)
    elapsed = 0.0
    width = max([70, *(len(e.step.describe()) for e in plan)])  # one column for every step (rates are longer)
    for n, e in enumerate(plan, 1):
        elapsed += e.total_s
        extra = f"sample {format_duration(e.step.sample_s)}" if e.step.is_motion else "after the run"
        print(f"{n:4d}  {e.step.describe():<{width}s} {extra:<18s} ~{format_duration(e.total_s):>12s}"
              f"  (t+{format_duration(elapsed)})")
    total = sum(e.total_s for e in plan)
    counts: dict[str, int] = {}
    for s in proc.steps:
        counts[s.kind] = counts.get(s.kind, 0) + 1
    print("steps: " + ", ".join(f"{v} {k}" for k, v in counts.items()))
    print(f"total duration: about {format_duration(total)} ({total:.0f} s)")
    print(f"expected data volume: about {format_bytes(data_volume_bytes(total, cfg))} "
          f"(IMU at {cfg.imu_rate_hz:g} Hz)")
    warn = taps_without_pulses(proc, cfg, cfg_path)
    if warn:
        print(warn, file=sys.stderr, flush=True)
    print("valid")
    return 0


def _modules_for(argv: list[str] | None) -> tuple[str, ...]:
    """The command modules ``argv`` needs: the chosen command's only, else (help, typo) all."""
    words = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in words if not a.startswith("-")), None)
    if first in COMMANDS and not any(a in ("-h", "--help") for a in words[:words.index(first)]):
        return (COMMANDS[first],)
    return () if first in ("run", "validate") else COMMAND_MODULES


def build_parser(argv: list[str] | None = None, everything: bool = True) -> argparse.ArgumentParser:
    """The parser; with ``everything=False`` only the modules ``argv`` needs are imported."""
    p = argparse.ArgumentParser(prog="rigctl", description="Test automation for inertial sensor labs: "
                                "turntable procedures, HDF5 recording, calibration and noise analysis.")
    p.add_argument("--version", action="version", version=f"rigctl {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("procedure", help="procedure YAML file, e.g. procedures/24pos.yaml")
        sp.add_argument("--config", help="rig config YAML (default: configs/sim.yaml, the emulator)")
        sp.add_argument("-p", "--param", action="append", metavar="NAME=VALUE",
                        help="override a procedure parameter (repeatable), e.g. -p warmup='5 min'")

    r = sub.add_parser("run", help="run a procedure and record it")
    common(r)
    r.add_argument("--out", default="runs", help="directory the run folder is created in (default: runs)")
    r.set_defaults(func=cmd_run)
    v = sub.add_parser("validate", help="check a procedure and print its steps, duration and data volume")
    common(v)
    v.add_argument("--devices", action="store_true",
                   help="also open each configured port and ask each device who it is (ok, or what to do)")
    v.set_defaults(func=cmd_validate)
    modules = COMMAND_MODULES if everything else _modules_for(argv)
    if modules == COMMAND_MODULES and not everything:  # help, no command or an unknown one: the list
        for name, line in SUMMARIES.items():
            sub.add_parser(name, help=line)
        return p
    for mod in modules:
        importlib.import_module(mod).register(_Summarised(sub))
    return p


def _command_name(argv: list[str] | None) -> str:
    words = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in words if not a.startswith("-")), "")
    return f"rigctl {first}" if first in (*COMMANDS, "run", "validate") else "rigctl"


def report_error(prog: str, exc: BaseException) -> int:
    """The one place that turns an exception into one line on stderr and an exit code
    (rigctl.errors): RigctlError -> its ``exit_code``; OSError (disk, permissions) -> 1;
    KeyboardInterrupt -> 130; anything else is a bug -> 1, with its traceback only when
    RIGCTL_DEBUG=1 (a run's own failures go to its run log, rigctl.run.runner)."""
    if isinstance(exc, KeyboardInterrupt):
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if isinstance(exc, RigctlError):
        word = {EXIT_INVALID: "error", EXIT_INTERRUPTED: "interrupted"}.get(exc.exit_code, "failed")
        for line in str(exc).splitlines() or [""]:  # several problems: one line each
            print(f"{prog}: {word}: {line}", file=sys.stderr)
        return exc.exit_code
    if isinstance(exc, OSError):
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"{prog}: failed: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_FAILED
    if os.environ.get("RIGCTL_DEBUG") == "1":
        traceback.print_exception(exc, file=sys.stderr)
    print(f"{prog}: internal error: {type(exc).__name__}: {exc} (a bug in rigctl: please report it "
          "with the output of the same command run with RIGCTL_DEBUG=1)", file=sys.stderr)
    return EXIT_FAILED


def main(argv: list[str] | None = None) -> int:
    """The entry point of every command: parse, run, map errors to exit codes (rigctl.errors).
    Standard output and error are console streams that survive their reader (rigctl.run.console)."""
    prog = _command_name(argv)
    with guarded_std_streams():
        try:
            parser = build_parser(argv, everything=False)
            args = parser.parse_args(argv)
            return int(args.func(args))
        except SystemExit as exc:  # argparse: --help, --version (0) and usage errors (2)
            return exc.code if isinstance(exc.code, int) else EXIT_INVALID
        except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - the one place errors become exit codes
            return report_error(prog, exc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
