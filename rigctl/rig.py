"""Building a rig from its config. The framework owns set-up and teardown (as OpenHTF does):
``with open_rig(cfg) as rig:`` connects every device and always stops the table and closes
every link on the way out, whatever happened inside.

Two kinds of rig:

* in-process emulator (``driver: sim`` for table and IMU): one :class:`rigctl.sim.world.SimWorld`
  on the config's clock (virtual, real or scaled);
* wired (table ``acl`` | ``modbus``, IMU ``xsens``, pulses ``novatel`` | ``gpio`` | ``modem`` |
  ``none``): real drivers on real links (hardware, or ``rigctl sim up``). The run clock is the
  host's (``clock: real``), or real time x ``speed`` (``clock: scaled``) to match an emulator
  started with the same ``--speed``. Recorded times come from the devices, mapped onto the run
  clock by an offset each driver fixes while connecting: table controller time (offset from the
  shortest-round-trip probe), IMU SampleTimeFine (minimum-latency offset), GNSS mark time (GPS
  time minus an anchor from the log headers), GPIO/modem kernel or host timestamps. See
  docs/hardware.md, "Time base".

Set-up order: table (connect, interlocks closed, limits set), IMU (configure, stream), pulses.
Teardown (reverse): table stop (controlled stop on every axis) first, then every link closed and
every reader thread joined -- also when a connect fails half-way.
"""
from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

from .clock import make_clock
from .config import RigConfig
from .devices import Clock, LinkLost, NoPulses
from .engine import Rig
from .yamlio import InputError

log = logging.getLogger(__name__)


def describe(cfg: RigConfig) -> str:
    """One line saying what the run talks to."""
    if cfg.is_simulated:
        return (f"emulated three-axis table and IMU ({cfg.imu_rate_hz:g} Hz), in-process, "
                f"{cfg.clock} time -- no hardware")
    t = cfg.table.settings
    where = t.get("port") or f"{t.get('host')}:{t.get('tcp_port')}"
    clock = f"{cfg.clock} clock" + (f" x{cfg.speed:g}" if cfg.clock == "scaled" else "")
    return (f"table over {cfg.table.driver} ({where}), IMU over {cfg.imu.driver} "
            f"({cfg.imu.settings.get('port')}, {cfg.imu_rate_hz:g} Hz), pulses from {cfg.pulses.driver}; "
            f"{clock}")


def build_table(cfg: RigConfig, clock: Clock):
    s = cfg.table.settings
    if cfg.table.driver == "acl":
        from .drivers.acl_table import AclTable
        return AclTable(s["port"], cfg.limits, clock, baudrate=s["baudrate"], timeout_s=s["timeout_s"],
                        close_interlocks=s["close_interlocks"],
                        open_interlocks_on_stop=s["open_interlocks_on_stop"])
    if cfg.table.driver == "modbus":
        from .drivers.modbus_table import ModbusTable
        kw = {k: v for k, v in s.items() if k in ("transport", "host", "tcp_port", "port", "baudrate", "parity",
                                                    "unit_id", "word_order", "timeout_s", "retries",
                                                    "watchdog_ms", "window_deg", "dwell_s")}
        return ModbusTable(cfg.limits, clock, **kw)
    raise InputError(f"table driver {cfg.table.driver!r} is not a wired driver", cfg.path)


def build_imu(cfg: RigConfig, clock: Clock):
    s = cfg.imu.settings
    from .drivers.xsens_imu import XsensImu
    return XsensImu(s["port"], cfg.imu_rate_hz, clock, baudrate=s["baudrate"], timeout_s=s["timeout_s"],
                    sample_time_fine_wrap=s["sample_time_fine_wrap"], align_wait_s=s["align_wait_s"],
                    link_timeout_s=s["link_timeout_s"])


def build_pulses(cfg: RigConfig, clock: Clock):
    s, d = cfg.pulses.settings, cfg.pulses.driver
    if d == "novatel":
        from .drivers.novatel_marks import NovatelMarks
        return NovatelMarks(s["port"], clock, baudrate=s["baudrate"], timeout_s=s["timeout_s"],
                            signal=s["signal"], polarity=s["polarity"], timebias_ns=s["timebias_ns"],
                            timeguard_ms=s["timeguard_ms"], log_name=s["log"])
    if d == "gpio":
        from .drivers.gpio_pulses import GpioPulses
        return GpioPulses(s["chip"], s["line"], clock, edge=s["edge"], event_clock=s["event_clock"],
                          debounce_us=s["debounce_us"], bias=s["bias"])
    if d == "modem":
        from .drivers.modem_pulses import ModemPulses
        return ModemPulses(s["port"], clock, baudrate=s["baudrate"], line=s["line"], edge=s["edge"],
                           mode=s["mode"], poll_interval_s=s["poll_interval_s"])
    return NoPulses()


@contextmanager
def _wired_rig(cfg: RigConfig) -> Iterator[Rig]:
    clock = make_clock(cfg.clock, cfg.speed)
    with ExitStack() as stack:
        devices = []
        for build in (build_table, build_imu, build_pulses):
            dev = build(cfg, clock)
            if hasattr(dev, "close"):
                stack.callback(dev.close)
            if hasattr(dev, "connect"):
                dev.connect()
            devices.append(dev)
        table, imu, pulses = devices
        from .chamber import build_chamber
        chamber = build_chamber(cfg, clock)
        if chamber is not None:
            stack.callback(chamber.close)
            chamber.connect()
        rig = Rig(table=table, imu=imu, pulses=pulses, clock=clock, description=describe(cfg),
                  chamber=chamber, chamber_band=cfg.chamber.settings.get("band_c", (-70.0, 180.0)))
        try:
            yield rig
        finally:
            try:
                table.stop()
            except (LinkLost, OSError, RuntimeError, ValueError) as exc:
                log.error("could not stop the table on the way out: %s", exc)
            if chamber is not None:
                try:
                    chamber.stop()
                except (LinkLost, OSError, RuntimeError, ValueError) as exc:
                    log.error("could not put the chamber at its safe set point on the way out: %s", exc)


@contextmanager
def open_rig(cfg: RigConfig) -> Iterator[tuple[Rig, dict[str, Any] | None]]:
    """Yield (rig, truth); truth is the emulator's true parameters (None for a wired rig)."""
    if cfg.is_simulated:
        # import the emulator (scipy.signal, ~1 s) BEFORE the run clock starts, so that second
        # is not spent with data accruing and nothing on disk
        from .sim.world import SimChamberDevice, SimImuDevice, SimTableDevice, SimWorld
        clock = make_clock(cfg.clock, cfg.speed)

        world = SimWorld(cfg, clock)
        chamber = SimChamberDevice(world, cfg.chamber.settings["safe_c"]) \
            if cfg.chamber.driver == "sim" else None
        rig = Rig(table=SimTableDevice(world), imu=SimImuDevice(world), pulses=world.pulses(),
                  clock=clock, description=describe(cfg), operator=world.operator, chamber=chamber,
                  chamber_band=cfg.chamber.settings.get("band_c", (-70.0, 180.0)))
        try:
            yield rig, world.truth()
        finally:
            rig.table.stop()
            if chamber is not None:
                chamber.stop()
        return
    with _wired_rig(cfg) as rig:
        yield rig, None
