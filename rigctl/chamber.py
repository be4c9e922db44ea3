"""The climatic chamber: its device protocol, its state record, and its config section.

A chamber is a small duck-typed device like the table and the IMU (rigctl.devices)::

    set_setpoint(value_c, ramp_c_per_min=None)  # new target; a ramp at that rate, or a step
    read() -> ChamberState                      # air, product (second input), set points, status
    stop()                                      # safe state: the configured safe set point

Drivers (built by :func:`rigctl.rig.build_chamber`): :mod:`rigctl.drivers.watlow_chamber` (Watlow F4T over Modbus RTU or TCP) and
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
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from . import schema as S
from .yamlio import LocDict

#: statuses a chamber reports
STATUSES = ("idle", "running", "off", "fault")

COMMON = ("driver", "safe_c", "band_c", "sim")
WATLOW_KEYS = ("transport", "port", "baudrate", "parity", "host", "tcp_port", "unit_id", "timeout_s",
               "registers")
SCPI_KEYS = ("resource", "model", "commands", "timeout_s")


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


def chamber_settings(driver: str, d: LocDict) -> dict[str, Any]:
    """Validated settings of the ``chamber:`` section for ``driver``."""
    if driver == "none":
        S.check_keys(d, ("driver",), "'chamber'")
        return {}
    keys = COMMON + (WATLOW_KEYS if driver == "watlow" else SCPI_KEYS if driver == "scpi" else ())
    S.check_keys(d, keys, f"'chamber' ({driver})")
    safe = S.get_number(d, "safe_c", 25.0, minimum=-100, maximum=200)
    band = S.number_list(d, "band_c", [-70.0, 180.0], length=2)
    if not band[0] < safe < band[1]:
        raise S.error(d, "band_c", f"band_c {band} must contain safe_c {safe:g} degC")
    out: dict[str, Any] = {"safe_c": float(safe), "band_c": (float(band[0]), float(band[1]))}
    if driver == "watlow":
        transport = S.get_str(d, "transport", "rtu", choices=("rtu", "tcp"))
        out.update(transport=transport, unit_id=int(S.get_number(d, "unit_id", 1, minimum=0, maximum=247, integer=True)),
                   timeout_s=float(S.get_number(d, "timeout_s", 1.0, minimum=0.01, maximum=60)),
                   registers=dict(S.require_mapping(d["registers"], "'registers'", d, "registers"))
                   if "registers" in d else {})
        if transport == "rtu":
            out.update(port=S.get_str(d, "port"), baudrate=int(S.get_number(d, "baudrate", 9600, minimum=300,
                                                                               integer=True)),
                       parity=S.get_str(d, "parity", "N", choices=("N", "E", "O")))
        else:
            out.update(host=S.get_str(d, "host", "127.0.0.1"),
                       tcp_port=int(S.get_number(d, "tcp_port", 502, minimum=1, maximum=65535, integer=True)))
    elif driver == "scpi":
        out.update(resource=S.get_str(d, "resource"), model=S.get_str(d, "model", "generic"),
                   commands=dict(S.require_mapping(d["commands"], "'commands'", d, "commands"))
                   if "commands" in d else {},
                   timeout_s=float(S.get_number(d, "timeout_s", 2.0, minimum=0.01, maximum=60)))
    return out


def describe_trip(state: ChamberState, band: tuple[float, float]) -> str | None:
    """The 'chamber' suspender's reason for a reading, or None when it is fine."""
    if state.status == "fault":
        return f"chamber fault: {state.fault or 'the controller reports a fault'}"
    for name, v in (("air", state.air_c), ("product", state.product_c)):
        if math.isfinite(v) and not band[0] <= v <= band[1]:
            return (f"chamber {name} temperature {v:.1f} degC outside [{band[0]:g}, {band[1]:g}] degC")
    return None
