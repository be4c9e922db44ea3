"""The climatic chamber: its device protocol, its state record, and its config section.

A chamber is a small duck-typed device like the table and the IMU (rigctl.devices)::

    set_setpoint(value_c, ramp_c_per_min=None)  # new target; a ramp at that rate, or a step
    read() -> ChamberState                      # air, product (second input), set points, status
    stop()                                      # safe state: the configured safe set point

Drivers (built by :func:`rigctl.engine.rig.build_chamber`): :mod:`rigctl.drivers.watlow_chamber` (Watlow F4T over Modbus RTU or TCP) and
:mod:`rigctl.drivers.scpi_chamber` (an SCPI chamber through PyVISA, command set per model); the
in-process emulator's is :class:`rigctl.sim.world.SimChamberDevice`. Config (docs/thermal.md)::

    chamber:
      driver: sim | watlow | scpi | none
      safe_c: 25              # set point commanded on abort, crash clean-up and at the end
      band_c: [-45, 90]       # chamber or product temperature outside: the 'chamber' suspender
      # watlow: transport (rtu | tcp), port, baudrate, host, tcp_port, unit_id, timeout_s
      # scpi:   resource (a VISA resource string), model, commands, timeout_s
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Protocol, runtime_checkable

from .. import schema as S
from ..settings import Settings, mapping, number, parse, setting, text
from ..yamlio import LocDict

#: statuses a chamber reports
STATUSES = ("idle", "running", "off", "fault")



@dataclass(frozen=True)
class ChamberState:
    """One reading of the chamber. Temperatures degC (NaN when the chamber has no such input)."""

    time: float
    air_c: float
    product_c: float
    setpoint_c: float
    status: str
    fault: str = ""


@runtime_checkable
class Chamber(Protocol):
    def set_setpoint(self, value_c: float, ramp_c_per_min: float | None = None) -> None:
        """New target set point, degC; with ``ramp_c_per_min`` the controller ramps to it."""

    def read(self) -> ChamberState:
        """The chamber's state now."""

    def stop(self) -> None:
        """Safe state (the configured safe set point, as a step)."""


def _band(d: LocDict, key: str, default: tuple[float, float]) -> tuple[float, float]:
    band = S.number_list(d, key, list(default), length=2)
    return float(band[0]), float(band[1])


@dataclass(frozen=True, kw_only=True)
class ChamberSettings(Settings):
    """``chamber:`` (driver sim, and what every chamber driver's section holds): the safe set
    point, and the band outside which the 'chamber' suspender pauses a run."""

    EXTRA_KEYS: ClassVar[tuple[str, ...]] = ("sim",)
    safe_c: float = number(25.0, minimum=-100, maximum=200)
    band_c: tuple[float, float] = setting((-70.0, 180.0), read=_band)

    def check(self, d: LocDict) -> None:
        if not self.band_c[0] < self.safe_c < self.band_c[1]:
            raise S.error(d, "band_c", f"band_c [{self.band_c[0]:g}, {self.band_c[1]:g}] must contain safe_c "
                          f"{self.safe_c:g} degC")

    def keywords(self) -> dict[str, Any]:
        """The driver's keyword arguments: every field but ``band_c`` (the suspender's band,
        not the driver's)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "band_c"}


@dataclass(frozen=True, kw_only=True)
class WatlowSettings(ChamberSettings):
    """``chamber:`` driver ``watlow`` (rigctl.drivers.watlow_chamber.WatlowF4T): Modbus RTU (port,
    baudrate, parity) or TCP (host, tcp_port); ``registers`` overrides addresses of the map."""

    transport: str = text("rtu", choices=("rtu", "tcp"))
    port: str | None = text(None)
    baudrate: int = number(9600, minimum=300, integer=True)
    parity: str = text("N", choices=("N", "E", "O"))
    host: str = text("127.0.0.1")
    tcp_port: int = number(502, minimum=1, maximum=65535, integer=True)
    unit_id: int = number(1, minimum=0, maximum=247, integer=True)
    timeout_s: float = number(1.0, minimum=0.01, maximum=60)
    registers: dict[str, Any] | None = mapping(None)

    def check(self, d: LocDict) -> None:
        super().check(d)
        if self.transport == "rtu" and self.port is None:
            raise S.error(d, None, "'chamber' (watlow) is missing 'port'", "add a line 'port: ...'")

    def where(self) -> tuple[str, str]:
        """(where, kind of link): serial or tcp."""
        return (str(self.port), "serial") if self.transport == "rtu" else (f"{self.host}:{self.tcp_port}", "tcp")


@dataclass(frozen=True, kw_only=True)
class ScpiChamberSettings(ChamberSettings):
    """``chamber:`` driver ``scpi`` (rigctl.drivers.scpi_chamber.ScpiChamber, through PyVISA)."""

    resource: str = text()
    model: str = text("generic")
    commands: dict[str, str] | None = mapping(None)
    timeout_s: float = number(2.0, minimum=0.01, maximum=60)

    def where(self) -> tuple[str, str]:
        return self.resource, "tcp" if self.resource.upper().startswith("TCPIP") else "serial"


#: driver -> its settings (``none``: a chamber section that holds only the driver)
SETTINGS: dict[str, type[ChamberSettings]] = {"sim": ChamberSettings, "watlow": WatlowSettings,
                                              "scpi": ScpiChamberSettings}


def chamber_settings(driver: str, d: LocDict) -> ChamberSettings:
    """Validated settings of the ``chamber:`` section for ``driver`` (rigctl.settings.parse)."""
    if driver == "none":
        S.check_keys(d, ("driver",), "'chamber'")
        return ChamberSettings()
    return parse(SETTINGS[driver], d, f"'chamber' ({driver})", ("driver",))


def describe_trip(state: ChamberState, band: tuple[float, float]) -> str | None:
    """The 'chamber' suspender's reason for a reading, or None when it is fine."""
    if state.status == "fault":
        return f"chamber fault: {state.fault or 'the controller reports a fault'}"
    for name, v in (("air", state.air_c), ("product", state.product_c)):
        if math.isfinite(v) and not band[0] <= v <= band[1]:
            return (f"chamber {name} temperature {v:.1f} degC outside [{band[0]:g}, {band[1]:g}] degC")
    return None
