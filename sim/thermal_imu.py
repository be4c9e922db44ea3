"""Temperature-dependent errors of the emulated IMU (``imu.sim.thermal``), with their truth.

With dT = T - T_ref (T the IMU's own temperature, degC; T_ref = ``reference_c``)::

    A += sum_j dT^j (b_a,j + M_a,j f) + h_a H + r_a dT/dt
    W += sum_j dT^j (b_g,j + M_g,j w) + h_g H + r_g dT/dt          (j = 1, 2, ...)

* b_.,j (3,): bias coefficients; M_.,j (3, 3): scale (diagonal) and misalignment (off-diagonal)
  coefficients -- the declared values of sim/imu.py hold at T_ref;
* H in [-1, 1]: thermal hysteresis, a play (backlash) operator of width ``width_K`` on T
  normalised to its half-width: +1 after heating, -1 after cooling, in between while the
  temperature turns round. Bias offsets +h after heating and -h after cooling, so the two
  halves of a thermal cycle differ by 2h at the same temperature;
* dT/dt in K/s: an optional dependence on the temperature rate (thermal gradients inside the
  unit while it heats or cools).

Config (units in the key names; every key optional)::

    thermal:
      reference_c: 25
      accel_bias_mg_per_K: [..3]          accel_bias_mg_per_K2: [..3]
      accel_scale_ppm_per_K: [..3]        accel_scale_ppm_per_K2: [..3]
      accel_misalignment_urad_per_K: 3x3 (diagonal ignored)
      gyro_bias_deg_h_per_K: [..3]        gyro_bias_deg_h_per_K2: [..3]
      gyro_scale_ppm_per_K: [..3]         gyro_scale_ppm_per_K2: [..3]
      gyro_misalignment_urad_per_K: 3x3
      hysteresis: {width_K: 2, accel_bias_mg: [..3], gyro_bias_deg_h: [..3]}
      rate: {accel_bias_mg_per_K_per_min: [..3], gyro_bias_deg_h_per_K_per_min: [..3]}
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.settings import Settings, matrix3, number, numbers, subsection, yaml_keys

G0 = 9.80665
MG = 1e-3 * G0
DEG_H = math.pi / 180.0 / 3600.0
SENSORS = {"accel": ("accel_bias_mg", MG), "gyro": ("gyro_bias_deg_h", DEG_H)}
ZERO3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True, kw_only=True)
class HysteresisSettings(Settings):
    """``imu.sim.thermal.hysteresis``: width of the play operator and the bias offsets."""

    width_K: float = number(2.0, minimum=0.01, maximum=50)
    accel_bias_mg: tuple[float, ...] = numbers(ZERO3)
    gyro_bias_deg_h: tuple[float, ...] = numbers(ZERO3)


@dataclass(frozen=True, kw_only=True)
class RateSettings(Settings):
    """``imu.sim.thermal.rate``: bias per temperature rate."""

    accel_bias_mg_per_K_per_min: tuple[float, ...] = numbers(ZERO3)
    gyro_bias_deg_h_per_K_per_min: tuple[float, ...] = numbers(ZERO3)


@dataclass(frozen=True, kw_only=True)
class ThermalSettings(Settings):
    """``imu.sim.thermal`` (module docstring; units in the key names, every key optional)."""

    reference_c: float = number(25.0, minimum=-100, maximum=200)
    accel_bias_mg_per_K: tuple[float, ...] = numbers(ZERO3)
    accel_bias_mg_per_K2: tuple[float, ...] = numbers(ZERO3)
    accel_scale_ppm_per_K: tuple[float, ...] = numbers(ZERO3)
    accel_scale_ppm_per_K2: tuple[float, ...] = numbers(ZERO3)
    accel_misalignment_urad_per_K: tuple[tuple[float, ...], ...] | None = matrix3(None)
    gyro_bias_deg_h_per_K: tuple[float, ...] = numbers(ZERO3)
    gyro_bias_deg_h_per_K2: tuple[float, ...] = numbers(ZERO3)
    gyro_scale_ppm_per_K: tuple[float, ...] = numbers(ZERO3)
    gyro_scale_ppm_per_K2: tuple[float, ...] = numbers(ZERO3)
    gyro_misalignment_urad_per_K: tuple[tuple[float, ...], ...] | None = matrix3(None)
    hysteresis: HysteresisSettings = subsection(HysteresisSettings, "'imu.sim.thermal.hysteresis'")
    rate: RateSettings = subsection(RateSettings, "'imu.sim.thermal.rate'")
    temperature_noise_c: float = number(0.0, minimum=0, maximum=5)


THERMAL_KEYS = tuple(yaml_keys(ThermalSettings))


def _vec(v: tuple[float, ...], unit: float) -> np.ndarray:
    return np.asarray(v, float) * unit


def _offdiag(rows: tuple[tuple[float, ...], ...] | None) -> np.ndarray:
    m = np.zeros((3, 3))
    for i, row in enumerate(rows or ()):
        for j, x in enumerate(row):
            if i != j:
                m[i, j] = float(x) * 1e-6
    return m


class ThermalErrors:
    """The thermal part of the emulated IMU's errors (module docstring), SI inside."""

    def __init__(self, o: ThermalSettings | None = None) -> None:
        o = o or ThermalSettings()
        self.reference_c = float(o.reference_c)
        self.temperature_noise_c = float(o.temperature_noise_c)
        #: sensor -> list over power j = 1, 2 of (bias (3,), M (3, 3))
        self.poly: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        for sensor, (bias_key, unit) in SENSORS.items():
            terms = []
            for j, suffix in ((1, "per_K"), (2, "per_K2")):
                b = _vec(getattr(o, f"{bias_key}_{suffix}"), unit)
                M = np.diag(_vec(getattr(o, f"{sensor}_scale_ppm_{suffix}"), 1e-6))
                if j == 1:
                    M = M + _offdiag(getattr(o, f"{sensor}_misalignment_urad_per_K"))
                terms.append((b, M))
            self.poly[sensor] = terms
        h = o.hysteresis
        self.hyst_width = float(h.width_K)
        self.hyst = {"accel": _vec(h.accel_bias_mg, MG), "gyro": _vec(h.gyro_bias_deg_h, DEG_H)}
        r = o.rate
        self.rate = {"accel": _vec(r.accel_bias_mg_per_K_per_min, MG * 60.0),
                     "gyro": _vec(r.gyro_bias_deg_h_per_K_per_min, DEG_H * 60.0)}
        # which terms are non-zero, once (error() runs at every emulator poll)
        self._nonzero = {sensor: ([bool(np.any(b) or np.any(M)) for b, M in terms],
                                  bool(np.any(self.hyst[sensor])), bool(np.any(self.rate[sensor])))
                         for sensor, terms in self.poly.items()}
        self._active = any(any(p) or h or r for p, h, r in self._nonzero.values())

    @property
    def active(self) -> bool:
        return self._active

    def error(self, sensor: str, x: np.ndarray, T: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Additive error (n, 3) of ``sensor`` for true input x (n, 3), temperature T (n,) degC,
        hysteresis state H (n,) and temperature rate R (n,) K/s."""
        dT = (np.asarray(T, float) - self.reference_c)[:, None]
        out = np.zeros_like(x)
        p = np.ones_like(dT)
        poly_on, hyst_on, rate_on = self._nonzero[sensor]
        for (b, M), on in zip(self.poly[sensor], poly_on):
            p = p * dT
            if on:
                out += p * (b + x @ M.T)
        if hyst_on:
            out += np.asarray(H, float)[:, None] * self.hyst[sensor]
        if rate_on:
            out += np.asarray(R, float)[:, None] * self.rate[sensor]
        return out

    def truth(self) -> dict[str, Any]:
        """Coefficients in SI (key names carry the units); ``*_M_*`` rows are the sensor axis."""
        out: dict[str, Any] = {"reference_c": self.reference_c, "hysteresis_width_K": self.hyst_width}
        for sensor, terms in self.poly.items():
            unit = "m_s2" if sensor == "accel" else "rad_s"
            for j, (b, M) in enumerate(terms, start=1):
                k = "K" if j == 1 else f"K{j}"
                out[f"{sensor}_bias_{unit}_per_{k}"] = b.tolist()
                out[f"{sensor}_M_per_{k}"] = M.tolist()
            out[f"{sensor}_hysteresis_{unit}"] = self.hyst[sensor].tolist()
            out[f"{sensor}_rate_{unit}_per_K_per_s"] = self.rate[sensor].tolist()
        return out


class ThermalTrack:
    """The hysteresis state H and the temperature rate dT/dt of the IMU along the chamber's grid
    (a play operator needs the history: it runs once over each new grid point)."""

    def __init__(self, width_K: float) -> None:
        self.half = width_K / 2.0
        self.t = np.empty(0)
        self.H = np.empty(0)
        self.R = np.empty(0)
        self._p: float | None = None
        self._last: tuple[float, float] | None = None

    def extend(self, ht: np.ndarray, hp: np.ndarray) -> None:
        if ht.size == 0:
            return
        if self._last is not None:
            keep = ht > self._last[0] + 1e-12
            ht, hp = ht[keep], hp[keep]
            if ht.size == 0:
                return
        H = np.empty(ht.size)
        R = np.empty(ht.size)
        p = self._p if self._p is not None else float(hp[0])
        prev = self._last if self._last is not None else (float(ht[0]), float(hp[0]))
        for i in range(ht.size):
            T = float(hp[i])
            p = min(max(p, T - self.half), T + self.half)
            H[i] = (T - p) / self.half
            dt = float(ht[i]) - prev[0]
            R[i] = (T - prev[1]) / dt if dt > 0 else (R[i - 1] if i else 0.0)
            prev = (float(ht[i]), T)
        self._p, self._last = p, prev
        keep_from = max(0, self.t.size - 4000)
        self.t = np.concatenate([self.t[keep_from:], ht])
        self.H = np.concatenate([self.H[keep_from:], H])
        self.R = np.concatenate([self.R[keep_from:], R])

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.t.size == 0:
            return np.zeros(len(t)), np.zeros(len(t))
        return np.interp(t, self.t, self.H), np.interp(t, self.t, self.R)
