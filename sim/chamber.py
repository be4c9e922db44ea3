"""Emulated climatic chamber: air temperature, the IMU's temperature, and the controller's state.

One physics object (:class:`ChamberPhysics`) on the world's run time, advanced lazily on a
fixed grid of ``step_s`` (0.5 s) by whoever reads it first (the IMU, a chamber server, a device):

* **set point**: a target ``setpoint_c`` reached either at once (a step) or by a linear ramp at
  ``ramp_c_per_min`` (the working set point moves towards the target at that rate);
* **air**: a second-order loop towards the working set point (natural period ``air_period_s``,
  damping ``air_damping`` < 1 gives overshoot on a step), its rate of change limited to
  ``heat_max_c_per_min`` when heating and ``cool_max_c_per_min`` when cooling (the plant's
  heater and compressor);
* **product** (the IMU on the table inside): a first-order lag behind the air with time
  constant ``product_tau_s``, plus ``self_heating_c`` (the unit's own dissipation);
* **status**: ``running`` / ``idle`` (set point reached), ``fault`` while a fault is injected
  (:meth:`inject_fault`), and the controller's view (air temperature, working and target set
  points, ramp rate) for the wire servers.

Nothing here knows about a protocol: :mod:`rigctl.sim.chamber_servers` serves it as a Watlow
F4 over Modbus and as an SCPI chamber over TCP; :class:`SimChamberDevice` hands it to the
engine in-process. ``history(t)`` gives the product temperature at any already computed time
(linear between grid points), which the emulated IMU reads for its temperature-dependent errors.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl import schema as S
from rigctl.settings import Settings, number, parse, yaml_keys
from rigctl.yamlio import LocDict

@dataclass(frozen=True, kw_only=True)
class ChamberParams(Settings):
    """``chamber.sim``: the emulated chamber's physics (module docstring), units in the key
    names; every key optional. Read by :func:`rigctl.settings.parse` (:func:`chamber_params`)."""

    initial_c: float = number(25.0, minimum=-100, maximum=200)
    air_period_s: float = number(120.0, minimum=1.0, maximum=1e5)
    air_damping: float = number(0.6, minimum=0.1, maximum=5.0)
    heat_max_c_per_min: float = number(5.0, minimum=0.01, maximum=100)
    cool_max_c_per_min: float = number(3.0, minimum=0.01, maximum=100)
    product_tau_s: float = number(240.0, minimum=0.0, maximum=1e5)
    self_heating_c: float = number(0.0, minimum=0.0, maximum=50)
    step_s: float = number(0.5, minimum=0.01, maximum=10.0)
    min_c: float = number(-70.0, minimum=-200, maximum=200)
    max_c: float = number(180.0, minimum=-200, maximum=400)
    #: the controller reports 'idle' (set point reached) inside this band
    stable_band_c: float = number(0.3, minimum=0.0, maximum=10)

    def check(self, d: LocDict) -> None:
        if not self.min_c < self.initial_c < self.max_c:
            raise S.error(d, "initial_c" if "initial_c" in d else None,
                          f"'initial_c' {self.initial_c:g} degC must lie inside "
                          f"[min_c, max_c] = [{self.min_c:g}, {self.max_c:g}] degC")


#: keys of ``chamber.sim`` (units in the names)
CHAMBER_SIM_KEYS = tuple(yaml_keys(ChamberParams))


def chamber_params(o: LocDict | None) -> ChamberParams:
    """The ``chamber.sim`` mapping of a rig config (all keys optional)."""
    return parse(ChamberParams, o or LocDict(), "'chamber.sim'")


class ChamberPhysics:
    """Air and product temperature on a fixed grid of run time (see the module docstring)."""

    HISTORY_S = 600.0  # grid history kept for :meth:`history`, s

    def __init__(self, p: ChamberParams) -> None:
        self.p = p
        self.lock = threading.RLock()
        self.t = 0.0
        self.air = p.initial_c
        self.air_rate = 0.0  # degC/s
        self.product = p.initial_c + p.self_heating_c
        self.target = p.initial_c       # commanded set point
        self.working = p.initial_c      # working set point (moves at the ramp rate)
        self.ramp_c_per_min = 0.0       # 0 = step
        self.fault: str | None = None
        self.running = True             # False: controller off (safe idle, air drifts to ambient)
        self.ambient_c = p.initial_c
        # grid history as numpy arrays (the hardware loop reads it every few ms: no list copies)
        self._h = np.empty((3, 4096))
        self._h[:, 0] = (0.0, self.product, self.air)
        self._n = 1

    # -- commands ---------------------------------------------------------------------------
    def set_setpoint(self, t: float, value_c: float, ramp_c_per_min: float | None = None) -> None:
        """New target; ``ramp_c_per_min`` None/0 = a step of the working set point."""
        if not self.p.min_c <= value_c <= self.p.max_c:
            raise ValueError(f"set point {value_c:g} degC outside the chamber's range "
                             f"[{self.p.min_c:g}, {self.p.max_c:g}] degC")
        with self.lock:
            self.advance(t)
            self.target = float(value_c)
            self.ramp_c_per_min = float(ramp_c_per_min or 0.0)
            if self.ramp_c_per_min <= 0:
                self.working = self.target
            self.running = True

    def set_ramp_rate(self, t: float, ramp_c_per_min: float) -> None:
        with self.lock:
            self.advance(t)
            self.ramp_c_per_min = max(0.0, float(ramp_c_per_min))

    def stop(self, t: float, safe_c: float | None = None) -> None:
        """Safe state: ``safe_c`` as a step set point (controller on), or the controller off."""
        with self.lock:
            self.advance(t)
            if safe_c is None:
                self.running = False
            else:
                self.target = self.working = float(safe_c)
                self.ramp_c_per_min = 0.0
                self.running = True

    def inject_fault(self, t: float, reason: str | None) -> None:
        """A controller fault (e.g. 'high-limit trip'); None clears it. While faulted the
        controller stops regulating (air drifts to ambient)."""
        with self.lock:
            self.advance(t)
            self.fault = reason

    # -- physics ----------------------------------------------------------------------------
    def advance(self, t: float) -> None:
        """Integrate up to run time ``t`` (grid steps of ``step_s``)."""
        p = self.p
        with self.lock:
            h = p.step_s
            wn = 2 * math.pi / p.air_period_s
            heat, cool = p.heat_max_c_per_min / 60.0, p.cool_max_c_per_min / 60.0
            while self.t + h <= t + 1e-9:
                if self.ramp_c_per_min > 0 and self.working != self.target:
                    dw = self.ramp_c_per_min / 60.0 * h
                    d = self.target - self.working
                    self.working = self.target if abs(d) <= dw else self.working + math.copysign(dw, d)
                regulating = self.running and self.fault is None
                goal = self.working if regulating else self.ambient_c
                # second-order loop: x'' = wn^2 (goal - x) - 2 zeta wn x', rate-limited
                acc = wn * wn * (goal - self.air) - 2 * p.air_damping * wn * self.air_rate
                if not regulating:  # no loop: first-order drift towards ambient
                    acc = ((goal - self.air) / 1800.0 - self.air_rate) / h
                rate = min(max(self.air_rate + acc * h, -cool), heat)
                self.air_rate = rate
                self.air += rate * h
                tau = p.product_tau_s
                target_p = self.air + p.self_heating_c
                if tau <= 0:
                    self.product = target_p
                else:
                    self.product = target_p + (self.product - target_p) * math.exp(-h / tau)
                self.t += h
                if self._n == self._h.shape[1]:
                    if self._n > 2_000_000:  # nobody reads the history: bound it
                        self._trim(self.t - self.HISTORY_S)
                    else:
                        self._h = np.concatenate([self._h, np.empty_like(self._h)], axis=1)
                self._h[:, self._n] = (self.t, self.product, self.air)
                self._n += 1

    def _trim(self, t_keep: float) -> None:
        """Forget grid points before ``t_keep`` (keeping at least two)."""
        i = min(int(np.searchsorted(self._h[0, :self._n], t_keep)), self._n - 2)
        if i > 0:
            self._h[:, : self._n - i] = self._h[:, i:self._n].copy()
            self._n -= i

    def history(self, t: np.ndarray) -> np.ndarray:
        """Product temperature (degC) at run times ``t`` (integrating further if needed)."""
        t = np.asarray(t, float)
        with self.lock:
            if not t.size:
                return np.empty(0)
            self.advance(float(t.max()) + self.p.step_s)
            out = np.interp(t, self._h[0, :self._n], self._h[1, :self._n])
            if self._n > 4 * self.HISTORY_S / self.p.step_s:
                self._trim(float(t.min()) - self.HISTORY_S)
            return out

    def grid_since(self, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """(times, product temperatures) of the grid points after ``t0`` (kept history only)."""
        with self.lock:
            ht = self._h[0, :self._n]
            i = int(np.searchsorted(ht, t0, side="right"))
            return ht[i:].copy(), self._h[1, i:self._n].copy()

    def state(self, t: float) -> dict[str, Any]:
        """What the controller shows: air (its control sensor), product (second input), set points."""
        with self.lock:
            self.advance(t)
            at_sp = abs(self.air - self.target) <= self.p.stable_band_c and self.working == self.target
            status = "fault" if self.fault else ("off" if not self.running else
                                                 ("idle" if at_sp else "running"))
            return {"time": self.t, "air_c": self.air, "product_c": self.product,
                    "setpoint_c": self.target, "working_setpoint_c": self.working,
                    "ramp_c_per_min": self.ramp_c_per_min, "status": status, "fault": self.fault or ""}

    def truth(self) -> dict[str, Any]:
        return {"model": "second-order air loop, rate-limited; first-order product lag",
                **{k: getattr(self.p, k) for k in CHAMBER_SIM_KEYS}}
