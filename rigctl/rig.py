"""Building a rig from its config. The framework owns set-up and teardown (as OpenHTF does):
``with open_rig(cfg) as rig:`` connects every device and always stops the table and closes
every link on the way out, whatever happened inside."""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from .clock import make_clock
from .config import RigConfig
from .engine import Rig
from .yamlio import InputError


def describe(cfg: RigConfig) -> str:
    """One line saying what the run talks to."""
    if cfg.is_simulated:
        return (f"emulated three-axis table and IMU ({cfg.imu_rate_hz:g} Hz), in-process, "
                f"{cfg.clock} time -- no hardware")
    return f"table over {cfg.table.driver}, IMU over {cfg.imu.driver}, pulses from {cfg.pulses.driver}"


@contextmanager
def open_rig(cfg: RigConfig) -> Iterator[tuple[Rig, dict[str, Any] | None]]:
    """Yield (rig, truth); truth is the emulator's true parameters (None for real hardware)."""
    clock = make_clock(cfg.clock, cfg.speed)
    if cfg.table.driver == "sim" and cfg.imu.driver == "sim":
        from .sim.world import NoPulses, SimImuDevice, SimTableDevice, SimWorld

        world = SimWorld(cfg, clock)
        rig = Rig(table=SimTableDevice(world), imu=SimImuDevice(world), pulses=NoPulses(),
                  clock=clock, description=describe(cfg))
        try:
            yield rig, world.truth()
        finally:
            rig.table.stop()
        return
    raise InputError(f"table driver {cfg.table.driver!r} with IMU driver {cfg.imu.driver!r} is not "
                     "available in this version", cfg.path,
                     hint="use configs/sim.yaml (the built-in emulator)")
