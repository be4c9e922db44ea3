"""``rigctl sim up``: run the emulated hardware (one physics world) on real ptys and TCP ports.

Prints every endpoint, optionally writes a wired rig config pointing at them
(``--wire-config OUT.yaml``, from the template configs/sim-wire.yaml), prints ``ready`` and
serves until SIGINT/SIGTERM. Pty endpoints are symlinks in ``--link-dir`` (default: a temporary
directory removed on exit); a simulated disconnect re-points the same symlink to a new pty.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import yaml

from ..config.config import PROJECT_ROOT, load_config, resolve_config_path
from ..run.stop_signals import stop_on_signals
from ..errors import InputError

TEMPLATE = PROJECT_ROOT / "configs" / "sim-wire.yaml"


def cmd_sim_up(args: argparse.Namespace) -> int:
    from ..sim.hardware import start_hardware
    from ..sim.wire_config import write_wire_config

    cfg_path = resolve_config_path(args.config)
    cfg = load_config(cfg_path)
    if not 0.01 <= args.speed <= 1000:
        raise InputError(f"--speed {args.speed:g} is outside 0.01..1000")
    with stop_on_signals() as stop:
        with start_hardware(cfg, args.speed, link_dir=args.link_dir, acl_tcp_port=args.acl_port,
                            modbus_tcp_port=args.modbus_port, imu_baudrate=args.imu_baudrate,
                            pulse_period_s=args.pulse_period, imu_protocol=args.imu) as hw:
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
            while not stop.wait(1.0):
                if hw.lag_s > max(5.0, 50 * hw.tick_s * hw.speed):
                    print(f"warning: the emulator is {hw.lag_s:.1f} s of rig time behind the clock; "
                          "lower --speed", flush=True)
    print("stopped", flush=True)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="emulated hardware on real wires (rigctl sim up)")
    ssub = p.add_subparsers(dest="sim_command", metavar="SIMCOMMAND")
    ssub.required = True
    up = ssub.add_parser("up", help="start the emulated table/IMU/GNSS servers and print their endpoints")
    up.add_argument("--config", help="rig config whose emulator sections set the physics (default configs/sim.yaml)")
    up.add_argument("--speed", type=float, default=1.0, help="rig time per wall time (1 = real time; up to 1000)")
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
    up.add_argument("--pulse-period", type=float, default=None, help="mark pulse every N s of rig time")
    up.set_defaults(func=cmd_sim_up)
