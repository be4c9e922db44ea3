"""Before a run starts: open each configured port and ask each device who it is.

``rigctl validate --devices`` prints the report; ``rigctl run`` (and the daemon, for each job)
checks before it creates anything, so a run that cannot start leaves no run directory. Per
device the answer is ``ok`` with what the device said (the ACL controller's ``*IDN?``, the Xsens
DeviceID, a VectorNav's model / serial number / firmware, one valid frame of a declarative-frame
IMU, a Modbus unit's input block, the NovAtel receiver's ``<OK`` to MARKCONTROL, a GPIO
chip's label, a modem line's level), or one line saying what is wrong and what to do
(:func:`rigctl.drivers.serial_link.explain_link_error`): ``/dev/ttyUSB0: no such device; is the
adapter plugged in? ls /dev/serial/by-id``, permission denied -> the dialout group, a refused
TCP port -> is ``rigctl sim up`` / the device server running?

Nothing moves: the probe sends only identity requests (ACL ``*IDN?``; Xsens GoToConfig, ReqDID,
GoToMeasurement; VectorNav binary output off and register reads 1, 3, 4 -- the binary output
stays off until a run configures it; Modbus reads; NovAtel MARKCONTROL with the configured settings) and closes every
port again. The devices are asked in parallel, so the check takes the longest single answer.
"""
from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

from ..clock import make_clock
from ..config.config import RigConfig
from ..drivers.serial_link import explain_link_error
from ..errors import DeviceError
from .rig import build_chamber, build_imu, build_pulses, build_table


@dataclass(frozen=True)
class DeviceCheck:
    """The answer of one device: ``role`` (table, imu, pulses), ``where`` (port, URL, address),
    ``ok``, and ``text``: what the device said (ok) or what is wrong and what to do."""

    role: str
    where: str
    ok: bool
    text: str

    def line(self) -> str:
        return f"{self.role}: {self.where}: ok ({self.text})" if self.ok else f"{self.role}: {self.text}"


@dataclass(frozen=True)
class DeviceReport:
    checks: list[DeviceCheck]

    @property
    def problems(self) -> list[DeviceCheck]:
        return [c for c in self.checks if not c.ok]

    def raise_for_problems(self) -> None:
        """DeviceError (one line per device that failed) unless every device answered."""
        if self.problems:
            raise DeviceError([c.line() for c in self.problems])


def _where(cfg: RigConfig, role: str) -> tuple[str, str]:
    """(where, kind of port) of a wired device section; kind: serial, tcp or gpio."""
    if role == "chamber":
        return cfg.chamber.settings.where()
    dev = {"table": cfg.table, "imu": cfg.imu, "pulses": cfg.pulses}[role]
    s = dev.settings
    if dev.driver == "modbus" and s.transport == "tcp":
        return s.where(), "tcp"
    return s.where(), "gpio" if dev.driver == "gpio" else "serial"


def _probe(role: str, where: str, kind: str, build: Callable[[], Any]) -> DeviceCheck:
    dev = None
    try:
        dev = build()
        return DeviceCheck(role, where, True, str(dev.identify()))
    except Exception as exc:  # noqa: BLE001 - every failure becomes one line saying what to do
        return DeviceCheck(role, where, False, explain_link_error(where, exc, kind))
    finally:
        if dev is not None and hasattr(dev, "close"):
            try:
                dev.close()
            except Exception:  # noqa: BLE001,S110 - closing a port that never opened
                pass


def check_devices(cfg: RigConfig) -> DeviceReport:
    """Ask every device of ``cfg`` who it is (see the module docstring)."""
    if cfg.is_simulated:
        return DeviceReport([DeviceCheck(role, "in-process emulator", True, "emulated")
                             for role in ("table", "imu")])
    clock = make_clock("real" if cfg.clock == "virtual" else cfg.clock, cfg.speed)
    jobs = [("table", lambda: build_table(cfg, clock)), ("imu", lambda: build_imu(cfg, clock))]
    if cfg.pulses.driver not in ("none", "sim", "vectornav"):     # vectornav: its SYNC_IN, read with the IMU
        jobs.append(("pulses", lambda: build_pulses(cfg, clock)))
    if cfg.chamber.driver in ("watlow", "scpi"):
        jobs.append(("chamber", lambda: build_chamber(cfg, clock)))
    with ThreadPoolExecutor(max_workers=len(jobs), thread_name_prefix="rigctl-devcheck") as pool:
        futures = [pool.submit(_probe, role, *_where(cfg, role), build) for role, build in jobs]
        return DeviceReport([f.result() for f in futures])
