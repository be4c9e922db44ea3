"""``rigctl sim up``: run the emulated hardware (one physics world) on real ptys and TCP ports.

Prints every endpoint, optionally writes a wired rig config pointing at them
(``--wire-config OUT.yaml``, from the template configs/sim-wire.yaml), prints ``ready`` and
serves until SIGINT/SIGTERM. Pty endpoints are symlinks in ``--link-dir`` (default: a temporary
directory removed on exit); a simulated disconnect re-points the same symlink to a new pty.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

import yaml

from ..config.config import PROJECT_ROOT, load_config, resolve_config_path
from ..run.stop_signals import stop_on_signals
from ..clock import suggested_speed
from ..errors import InputError

TEMPLATE = PROJECT_ROOT / "configs" / "sim-wire.yaml"


def cmd_sim_up(args: argparse.Namespace) -> int:
    speed = parse_speed(args.speed)  # before the emulator is imported (a few seconds)
    limit = None if args.compute_limit is None else parse_compute_limit(args.compute_limit)
    from ..sim.hardware import start_hardware
    from ..sim.wire_config import write_wire_config

    cfg_path = resolve_config_path(args.config)
    cfg = load_config(cfg_path)
    args.speed = speed
    with stop_on_signals() as stop:
        with start_hardware(cfg, args.speed, link_dir=args.link_dir, acl_tcp_port=args.acl_port,
                            modbus_tcp_port=args.modbus_port, imu_baudrate=args.imu_baudrate,
                            pulse_period_s=args.pulse_period, imu_protocol=args.imu,
                            compute_limit=limit) as hw:
            print(f"rigctl sim up: physics of {cfg_path} at {args.speed:g}x real time", flush=True)
            for name, where in hw.endpoints.items():
                print(f"  {name:<18s} {where}", flush=True)
            if args.wire_config:
                template = Path(args.template) if args.template else TEMPLATE
                base = yaml.safe_load(template.read_text(encoding="utf-8"))
                physics = yaml.safe_load(cfg.text)
                for sec, keys in (("table", ("limits", "sim")), ("imu", ("rate_hz", "sim"))):
                    base.setdefault(sec, {}).update({k: v for k, v in (physics.get(sec) or {}).items()
                                                     if k in keys})
                base["site"] = physics.get("site", base.get("site"))
                out = write_wire_config(args.wire_config, base, hw, table=args.table, link=args.table_link,
                                        chamber=args.chamber)
                print(f"  wired rig config   {out}", flush=True)
            print("ready", flush=True)
            pace = PaceWatch(hw)
            while not stop.wait(1.0):
                line = pace.check()
                if line:
                    print(line, flush=True)
    print("stopped", flush=True)
    return 0


SPEED_RANGE = (0.01, 1000.0)


def parse_speed(text: str) -> float:
    """``--speed``: a number of times real time within :data:`SPEED_RANGE`; else one line (an
    InputError) saying what was asked, what the emulator takes and what to do."""
    lo, hi = SPEED_RANGE
    try:
        speed = float(text)
    except ValueError:
        speed = math.nan
    if not lo <= speed <= hi:  # also NaN and inf
        raise InputError(f"--speed {text!r}: the emulated rig's clock runs {lo:g} to {hi:g} times real time",
                         hint="give a number in that range, 1 = real time; above what this machine "
                              "computes, the clock runs slower and 'rigctl sim up' says how fast")
    return speed


def parse_compute_limit(text: str) -> float:
    """``--compute-limit``: a positive number of times real time; else one line (InputError)."""
    try:
        limit = float(text)
    except ValueError:
        limit = math.nan
    if not 0.0 < limit < math.inf:
        raise InputError(f"--compute-limit {text!r}: the most the emulated rig is computed at, in times real time",
                         hint="give a positive number, e.g. 50; without it the rig is computed as fast as this machine can")
    return limit


class PaceWatch:
    """Says how fast the emulated rig's time really runs when it runs slower than ``--speed``
    asks (this machine cannot compute the physics and the IMU stream that fast: the devices'
    time falls behind the clock), once, measured over PACE_WINDOW_WALL_S of wall time on the
    table controller's time; then how far behind it is, at most every REPEAT_S."""

    REPEAT_S = 60.0

    def __init__(self, hw: Any) -> None:
        self.hw, self.said = hw, -math.inf
        self.mark = (time.monotonic(), hw.table.time())

    def check(self) -> str:
        from ..engine.engine import PACE_WINDOW_WALL_S

        (w0, t0), wall, t = self.mark, time.monotonic(), self.hw.table.time()
        if wall - w0 < PACE_WINDOW_WALL_S or wall - self.said < self.REPEAT_S:
            return ""
        self.mark = (wall, t)
        speed, achieved = self.hw.speed, (t - t0) / (wall - w0)
        if achieved >= 0.9 * speed:
            return ""
        first, self.said = self.said == -math.inf, wall
        return (f"warning: --speed {speed:g} asked, but this machine computes the emulated rig at about "
                f"{achieved:.0f}x: its devices' time runs at that speed and is "
                f"{self.hw.lag_s:.0f} s of rig time behind the clock{', growing' if first else ''}; "
                f"use --speed {suggested_speed(achieved):g} or less")


def register(sub: Any) -> None:
    p = sub.add_parser("sim")
    ssub = p.add_subparsers(dest="sim_command", metavar="SIMCOMMAND")
    ssub.required = True
    up = ssub.add_parser("up", help="start the emulated table/IMU/GNSS servers and print their endpoints")
    up.add_argument("--config", help="rig config whose emulator sections set the physics (default configs/sim.yaml)")
    up.add_argument("--speed", default="1", help="rig time per wall time (1 = real time; 0.01 to 1000)")
    up.add_argument("--wire-config", metavar="OUT.yaml", help="write a wired rig config for these endpoints")
    up.add_argument("--chamber", choices=("watlow-rtu", "watlow-tcp", "scpi"),
                    help="put the emulated climatic chamber in the --wire-config, over this link")
    up.add_argument("--template", help="wired config template (default configs/sim-wire.yaml)")
    up.add_argument("--table", choices=("acl", "modbus"), help="table protocol in the written config")
    up.add_argument("--table-link", choices=("pty", "tcp", "rtu"), help="table link in the written config")
    up.add_argument("--link-dir", help="directory for the pty symlinks (default: a temporary directory)")
    up.add_argument("--acl-port", type=int, default=0, help="ACL TCP port (default: any free port)")
    up.add_argument("--modbus-port", type=int, default=0, help="Modbus TCP port (default: any free port)")
    up.add_argument("--imu", choices=("xsens", "vectornav", "frame"), default="xsens",
                    help="IMU protocol on the pty 'imu': Xsens MT, VectorNav binary, or the declarative frame "
                         "of docs/hardware.md (example 1)")
    up.add_argument("--imu-baudrate", type=int, default=921_600, help="nominal IMU baud rate (bandwidth check)")
    up.add_argument("--compute-limit", metavar="X", default=None,
                    help="compute the rig at no more than X times real time, as a machine too slow for --speed "
                         "would (to see what a run does then)")
    up.add_argument("--pulse-period", type=float, default=None, help="mark pulse every N s of rig time")
    up.set_defaults(func=cmd_sim_up)
