"""An SCPI climatic chamber through PyVISA (pyvisa-py backend: ``TCPIP::host::port::SOCKET``
and ``ASRL/dev/ttyUSB0::INSTR`` resources, no vendor VISA library needed).

Chambers speak SCPI-like dialects; the command set is a table per model (:data:`MODELS`),
and any entry can be replaced in the config (``commands:``). Templates take ``{value}`` (degC)
and ``{rate}`` (degC/min); queries return one number (or a word for the status)::

    key          generic                 what
    identify     *IDN?
    set          SOUR:TEMP {value:.3f}   target set point
    rate         SOUR:TEMP:RATE {rate:.4f}  ramp rate for the next set point (0 = a step)
    setpoint     SOUR:TEMP?
    air          MEAS:TEMP?              chamber (air) temperature
    product      MEAS:TEMP2?             second input (product); "" = none
    status       STAT?                   IDLE | RUNNING | OFF | FAULT[:reason]
    error        SYST:ERR?               0,"No error" when the last command was accepted

Errors: a VISA I/O error or a timeout is a lost link (:class:`rigctl.devices.LinkLost`); an
error the chamber reports after a write is :class:`rigctl.devices.DeviceFault`.
"""
from __future__ import annotations

import math
import threading
from typing import Any

from rigctl.config.chamber import ChamberState
from rigctl.devices import Clock, DeviceFault, LinkLost

MODELS: dict[str, dict[str, str]] = {
    "generic": {"identify": "*IDN?", "set": "SOUR:TEMP {value:.3f}", "rate": "SOUR:TEMP:RATE {rate:.4f}",
                "setpoint": "SOUR:TEMP?", "air": "MEAS:TEMP?", "product": "MEAS:TEMP2?", "status": "STAT?",
                "error": "SYST:ERR?"},
}


class ScpiChamber:
    """Chamber protocol (rigctl.config.chamber) over PyVISA."""

    name = "chamber"

    def __init__(self, resource: str, clock: Clock, *, model: str = "generic", commands: dict[str, str] | None = None,
                 timeout_s: float = 2.0, safe_c: float = 25.0, backend: str = "@py") -> None:
        if model not in MODELS:
            raise ValueError(f"unknown SCPI chamber model {model!r}; known: {', '.join(MODELS)}")
        self.resource, self.clock, self.timeout_s, self.safe_c = resource, clock, float(timeout_s), float(safe_c)
        self.cmd = dict(MODELS[model], **(commands or {}))
        self.backend = backend
        self.rm: Any = None
        self.inst: Any = None
        self.lock = threading.Lock()
        self.identity = {"device_id": "", "protocol": f"SCPI chamber ({resource})"}

    def connect(self) -> None:
        import pyvisa

        with self.lock:
            try:
                if self.rm is None:
                    self.rm = pyvisa.ResourceManager(self.backend)
                self.inst = self.rm.open_resource(self.resource, read_termination="\n", write_termination="\n",
                                                  timeout=int(self.timeout_s * 1000))
            except (pyvisa.errors.Error, OSError, ValueError) as exc:
                self.inst = None
                raise LinkLost(self.name, f"cannot open {self.resource}: {exc}") from exc
        idn = self._query(self.cmd["identify"])
        self.identity["device_id"] = idn.strip()

    def close(self) -> None:
        with self.lock:
            for obj in (self.inst, self.rm):
                try:
                    if obj is not None:
                        obj.close()
                except Exception:  # noqa: BLE001 - closing a dead link
                    pass
            self.inst = self.rm = None

    def _io(self, fn: str, text: str) -> str:
        import pyvisa

        with self.lock:
            if self.inst is None:
                raise LinkLost(self.name, f"{self.resource} not open")
            try:
                out = getattr(self.inst, fn)(text)
            except (pyvisa.errors.Error, OSError) as exc:
                try:
                    self.inst.close()
                except Exception:  # noqa: BLE001
                    pass
                self.inst = None
                raise LinkLost(self.name, f"{text!r} on {self.resource} failed: {exc}") from exc
        return out if isinstance(out, str) else ""

    def _query(self, text: str) -> str:
        return self._io("query", text)

    def _number(self, key: str) -> float:
        q = self.cmd.get(key) or ""
        if not q:
            return math.nan
        reply = self._query(q).strip()
        try:
            return float(reply.split(",")[0])
        except ValueError:
            raise DeviceFault(f"chamber: {q!r} answered {reply!r}, not a number") from None

    def _write_checked(self, text: str) -> None:
        self._io("write", text)
        if self.cmd.get("error"):
            err = self._query(self.cmd["error"]).strip()
            if not err.startswith(("0", "+0")):
                raise DeviceFault(f"chamber refused {text!r}: {err}")

    def set_setpoint(self, value_c: float, ramp_c_per_min: float | None = None) -> None:
        if self.cmd.get("rate"):
            self._write_checked(self.cmd["rate"].format(rate=float(ramp_c_per_min or 0.0)))
        self._write_checked(self.cmd["set"].format(value=float(value_c)))

    def read(self) -> ChamberState:
        t = self.clock.now()
        air, prod, sp = self._number("air"), self._number("product"), self._number("setpoint")
        word = self._query(self.cmd["status"]).strip() if self.cmd.get("status") else "IDLE"
        status, _, reason = word.partition(":")
        status = status.lower() if status.lower() in ("idle", "running", "off", "fault") else "running"
        return ChamberState(time=t, air_c=air, product_c=prod, setpoint_c=sp, status=status, fault=reason)

    def stop(self) -> None:
        self.set_setpoint(self.safe_c, None)

    def identify(self) -> str:
        """Connect and ask *IDN? (rigctl validate --devices)."""
        self.connect()
        return f"SCPI chamber: {self.identity['device_id']}"
