"""Building a rig from its config. The framework owns set-up and teardown (as OpenHTF does):
``with open_rig(cfg) as rig:`` connects every device and always stops the table and closes
every link on the way out, whatever happened inside.

Two kinds of rig:

* in-process emulator (``driver: sim`` for table and IMU): one :class:`rigctl.sim.world.SimWorld`
  on the config's clock (virtual, real or scaled);
* wired (table ``acl`` | ``modbus``, IMU ``xsens`` | ``vectornav`` | ``frame``, pulses ``novatel`` | ``gpio`` | ``modem`` |
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
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from typing import Any

from ..clock import make_clock
from ..config.config import RigConfig
from ..devices import Clock, LinkLost, NoPulses
from .engine import Rig, slow_rig_message, slow_rig_speed
from ..errors import DeviceError, InputError

log = logging.getLogger(__name__)


def describe(cfg: RigConfig) -> str:
    """One line saying what the run talks to."""
    if cfg.is_simulated:
        return (f"emulated three-axis table and IMU ({cfg.imu_rate_hz:g} Hz), in-process, "
                f"{cfg.clock} time -- no hardware")
    clock = f"{cfg.clock} clock" + (f" x{cfg.speed:g}" if cfg.clock == "scaled" else "")
    return (f"table over {cfg.table.driver} ({cfg.table.settings.where()}), IMU over {cfg.imu.driver} "
            f"({cfg.imu.settings.where()}, {cfg.imu_rate_hz:g} Hz), pulses from {cfg.pulses.driver}; "
            f"{clock}")


def build_table(cfg: RigConfig, clock: Clock):
    """The table's driver, its settings passed as named in rigctl.config.linkconfig."""
    s = cfg.table.settings
    if cfg.table.driver == "acl":
        from ..drivers.acl_table import AclTable
        return AclTable(s.port, cfg.limits, clock, **s.keywords())
    if cfg.table.driver == "modbus":
        from ..drivers.modbus_table import ModbusTable
        return ModbusTable(cfg.limits, clock, **s.keywords())
    raise InputError(f"table driver {cfg.table.driver!r} is not a wired driver", cfg.path)


def build_imu(cfg: RigConfig, clock: Clock):
    s = cfg.imu.settings
    if cfg.imu.driver == "vectornav":
        from ..drivers.vectornav_imu import VectorNavImu
        return VectorNavImu(s.port, cfg.imu_rate_hz, clock, **s.keywords())
    if cfg.imu.driver == "frame":
        from ..drivers.frame_imu import FrameImu
        from ..config.frame_spec import parse_frame_spec
        return FrameImu(s.port, parse_frame_spec(cfg.imu.options), cfg.imu_rate_hz, clock, **s.keywords())
    from ..drivers.xsens_imu import XsensImu
    return XsensImu(s.port, cfg.imu_rate_hz, clock, **s.keywords())


def build_pulses(cfg: RigConfig, clock: Clock, imu=None):
    """The pulse source; ``imu``: the IMU built for ``cfg`` (``vectornav``: its SYNC_IN)."""
    s, d = cfg.pulses.settings, cfg.pulses.driver
    if d == "vectornav":
        return (imu if imu is not None else build_imu(cfg, clock)).syncin_pulses()
    if d == "novatel":
        from ..drivers.novatel_marks import NovatelMarks
        return NovatelMarks(s.port, clock, **s.keywords())
    if d == "gpio":
        from ..drivers.gpio_pulses import GpioPulses
        return GpioPulses(s.chip, s.line, clock, **s.keywords())
    if d == "modem":
        from ..drivers.modem_pulses import ModemPulses
        return ModemPulses(s.port, clock, **s.keywords())
    return NoPulses()


def build_chamber(cfg: RigConfig, clock: Clock):
    """The wired chamber driver of a config (None for ``driver: none`` or ``sim``)."""
    c = cfg.chamber
    s = c.settings
    if c.driver == "watlow":
        from ..drivers.watlow_chamber import WatlowF4T
        return WatlowF4T(clock, **s.keywords())
    if c.driver == "scpi":
        from ..drivers.scpi_chamber import ScpiChamber
        return ScpiChamber(s.resource, clock, **{k: v for k, v in s.keywords().items() if k != "resource"})
    return None


def _table_mark(table: Any) -> tuple[float, float] | None:
    """(wall time, the table's time) now; None when the table cannot be read."""
    try:
        return time.monotonic(), float(table.read().time)
    except (LinkLost, OSError, RuntimeError, ValueError):
        return None


def _raise_if_slow(cfg: RigConfig, clock: Clock, devices: list[Any], mark: tuple[float, float] | None,
                   exc: LinkLost) -> None:
    """A device that did not come up (the IMU's 'no stream') on a clock faster than real time:
    when the table's time ran slower than the clock meanwhile, the cause is an emulator this
    machine cannot compute that fast, not the link -- raise DeviceError saying so and what to do
    (:func:`rigctl.engine.engine.slow_rig_message`)."""
    speed = float(getattr(clock, "speed", 1.0))
    if mark is None or not devices or speed <= 1.0:
        return
    now = _table_mark(devices[0])
    if now is None:
        return
    achieved = slow_rig_speed(speed, now[0] - mark[0], now[1] - mark[1])
    if achieved is not None:
        raise DeviceError(f"{slow_rig_message(speed, achieved)} ({exc})") from exc


@contextmanager
def _wired_rig(cfg: RigConfig) -> Iterator[Rig]:
    clock = make_clock(cfg.clock, cfg.speed)
    with ExitStack() as stack:
        devices: list[Any] = []
        pace: tuple[float, float] | None = None    # (wall, table time) once the table answers
        for build in (build_table, build_imu, build_pulses):
            dev = build(cfg, clock, devices[1]) if build is build_pulses else build(cfg, clock)
            if hasattr(dev, "close"):
                stack.callback(dev.close)
            if hasattr(dev, "connect"):
                try:
                    dev.connect()
                except LinkLost as exc:
                    _raise_if_slow(cfg, clock, devices, pace, exc)
                    raise
            devices.append(dev)
            if build is build_table:
                pace = _table_mark(dev)
        table, imu, pulses = devices
        chamber = build_chamber(cfg, clock)
        if chamber is not None:
            stack.callback(chamber.close)
            chamber.connect()
        rig = Rig(table=table, imu=imu, pulses=pulses, clock=clock, description=describe(cfg),
                  chamber=chamber, chamber_band=cfg.chamber.settings.band_c)
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
        # import the emulator (numba, scipy.linalg: ~0.5 s) BEFORE the run clock starts, so that time
        # is not spent with data accruing and nothing on disk
        from ..sim.world import SimChamberDevice, SimImuDevice, SimTableDevice, SimWorld
        clock = make_clock(cfg.clock, cfg.speed)

        world = SimWorld(cfg, clock)
        chamber = SimChamberDevice(world, cfg.chamber.settings.safe_c) \
            if cfg.chamber.driver == "sim" else None
        rig = Rig(table=SimTableDevice(world), imu=SimImuDevice(world), pulses=world.pulses(),
                  clock=clock, description=describe(cfg), operator=world.operator, chamber=chamber,
                  chamber_band=cfg.chamber.settings.band_c)
        if hasattr(clock, "restart"):  # rig time starts now, not while the world was built
            clock.restart()            # (at 500x, 1 s of set-up is 500 s of samples to make)
        try:
            yield rig, world.truth()
        finally:
            rig.table.stop()
            if chamber is not None:
                chamber.stop()
        return
    with _wired_rig(cfg) as rig:
        yield rig, None
