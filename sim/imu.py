"""Emulated IMU: the declared error models of docs/methods.md A2 plus white noise.

Accelerometer, for true specific force a (m/s^2):

    A = b_a + M_a a + k2 * a^2 (element-wise) + noise,   M_a[i,i] = S_i, M_a[i,j] = K_ji

Gyroscope, for true rate w (rad/s):

    W = d_g + M_g w + noise,                              M_g[i,i] = Sk_i, M_g[i,j] = K_ij

White noise densities: velocity random walk (m/s^2/sqrt(Hz)) and angle random walk
(rad/s/sqrt(Hz)); the per-sample standard deviation is density * sqrt(rate). Optionally the
slow IEEE 952 terms: bias instability B (flicker, Allan plateau 0.664 B between 1 s and
1e4 s) and rate / acceleration random walk K, from :class:`rigctl.sim.noise.NoiseGenerator`
(exact Allan signatures; its own seeded streams, so the white noise is the same with or
without them).

The model is built from a config mapping (see configs/sim.yaml) whose values are in the units
named by their keys, and reports its truth in SI as a JSON-serialisable dict.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigctl import schema as S
from rigctl.yamlio import LocDict
from rigctl.solvers.noise_coefficients import Triad, terms_of, to_json, triad

from .noise import NoiseGenerator

G0 = 9.80665  # m/s^2 per g (for mg / ppm conversions in config values)
DEG = math.pi / 180.0


@dataclass
class DeclaredImuModel:
    """Declared deterministic errors and white noise, SI units."""

    rate_hz: float
    accel_bias: NDArray = field(default_factory=lambda: np.zeros(3))
    accel_matrix: NDArray = field(default_factory=lambda: np.eye(3))
    accel_quadratic: NDArray = field(default_factory=lambda: np.zeros(3))
    gyro_bias: NDArray = field(default_factory=lambda: np.zeros(3))
    gyro_matrix: NDArray = field(default_factory=lambda: np.eye(3))
    #: each sensor's noise, three axes' IEEE 952 coefficients (SI): white N (rate unit/sqrt(Hz)),
    #: bias instability B, random walk K (the config's keys are in field units: :func:`declared_model`)
    accel_noise: Triad = field(default_factory=lambda: triad("accel"))
    gyro_noise: Triad = field(default_factory=lambda: triad("gyro"))
    temperature_c: float = 25.0
    seed: int = 0
    #: temperature-dependent errors (sim/thermal_imu.py), None = none
    thermal: Any = None

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x1A0]))
        self._temp_rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x7E]))
        self._slow = {}
        for name, axes, tag in (("gyro", self.gyro_noise, 0x1A1), ("accel", self.accel_noise, 0x1A2)):
            if any(m.B.value > 0 or m.K.value > 0 for m in axes):  # the slow terms (N: below)
                slow = tuple(m.with_values(Q=0.0, N=0.0, R=0.0) for m in axes)
                self._slow[name] = NoiseGenerator(slow, self.rate_hz,
                                                  np.random.SeedSequence([self.seed, tag]))

    def apply(self, t: NDArray, f_true: NDArray, w_true: NDArray,
              w_dot: NDArray | None = None, temperature: NDArray | None = None,
              hysteresis: NDArray | None = None,
              temperature_rate: NDArray | None = None) -> tuple[NDArray, NDArray, NDArray]:
        """Measured specific force, rate and temperature for true inputs ((n,3) arrays).
        ``temperature`` (n,) degC: the IMU's temperature (a chamber), else ``temperature_c``;
        with ``thermal`` errors, ``hysteresis`` (n,) and ``temperature_rate`` (n,) K/s too."""
        n = f_true.shape[0]
        f = self.accel_bias + f_true @ self.accel_matrix.T + self.accel_quadratic * f_true**2
        w = self.gyro_bias + w_true @ self.gyro_matrix.T
        T = np.full(n, self.temperature_c) if temperature is None else np.asarray(temperature, float)
        if self.thermal is not None and self.thermal.active:
            H = np.zeros(n) if hysteresis is None else hysteresis
            R = np.zeros(n) if temperature_rate is None else temperature_rate
            f = f + self.thermal.error("accel", f_true, T, H, R)
            w = w + self.thermal.error("gyro", w_true, T, H, R)
        n_acc, n_gyr = terms_of(self.accel_noise, "N"), terms_of(self.gyro_noise, "N")
        if np.any(n_acc > 0):
            f = f + self.rng.standard_normal((n, 3)) * (n_acc * math.sqrt(self.rate_hz))
        if np.any(n_gyr > 0):
            w = w + self.rng.standard_normal((n, 3)) * (n_gyr * math.sqrt(self.rate_hz))
        if "accel" in self._slow:
            f = f + self._slow["accel"].next(n)
        if "gyro" in self._slow:
            w = w + self._slow["gyro"].next(n)
        if self.thermal is not None and self.thermal.temperature_noise_c > 0:
            T = T + self._temp_rng.standard_normal(n) * self.thermal.temperature_noise_c
        return f, w, T

    def truth(self) -> dict[str, Any]:
        extra = {"thermal": self.thermal.truth()} if self.thermal is not None else {}
        return {**extra,
            "model": "declared",
            "rate_hz": self.rate_hz,
            "accel_bias_m_s2": self.accel_bias.tolist(),
            "accel_matrix": self.accel_matrix.tolist(),
            "accel_quadratic_per_m_s2": self.accel_quadratic.tolist(),
            "gyro_bias_rad_s": self.gyro_bias.tolist(),
            "gyro_matrix": self.gyro_matrix.tolist(),
            # three axes each, rigctl.solvers.noise_coefficients.to_json (as the profile model's)
            "accel_noise": [to_json(m) for m in self.accel_noise],
            "gyro_noise": [to_json(m) for m in self.gyro_noise],
        }


def _matrix(o: LocDict, scale_key: str, misalign_key: str, scale_unit: float) -> NDArray:
    m = np.eye(3)
    scale = S.number_list(o, scale_key, [0.0, 0.0, 0.0], length=3)
    m[np.diag_indices(3)] += np.asarray(scale) * scale_unit
    if misalign_key in o:
        rows = S.get_list(o, misalign_key, length=3)
        for i, row in enumerate(rows):
            if not (isinstance(row, list) and len(row) == 3):
                raise S.error(o, misalign_key, f"{misalign_key!r} must be a 3x3 list of rows")
            for j, x in enumerate(row):
                if i != j:
                    m[i, j] += float(x) * 1e-6  # urad
    return m


def build_declared_imu(o: LocDict, rate_hz: float, seed: int) -> DeclaredImuModel:
    """Declared-error IMU from the ``imu.sim`` config mapping (units in the key names)."""
    S.check_keys(o, ("accel_bias_mg", "accel_scale_ppm", "accel_misalignment_urad",
                     "accel_quadratic_ug_per_g2", "gyro_bias_deg_h", "gyro_scale_ppm",
                     "gyro_misalignment_urad", "accel_vrw_m_s_rth", "gyro_arw_deg_rth",
                     "accel_bias_instability_mg", "accel_rrw_m_s_h_rth",
                     "gyro_bias_instability_deg_h", "gyro_rrw_deg_h_rth",
                     "temperature_c", "seed", "thermal"), "'imu.sim'")
    thermal = None
    if "thermal" in o:
        from .thermal_imu import ThermalErrors
        thermal = ThermalErrors(S.require_mapping(o["thermal"], "'imu.sim.thermal'", o, "thermal"))
    return DeclaredImuModel(
        rate_hz=rate_hz,
        accel_bias=np.asarray(S.number_list(o, "accel_bias_mg", [0.0] * 3, length=3)) * 1e-3 * G0,
        accel_matrix=_matrix(o, "accel_scale_ppm", "accel_misalignment_urad", 1e-6),
        accel_quadratic=np.asarray(S.number_list(o, "accel_quadratic_ug_per_g2", [0.0] * 3, length=3))
        * 1e-6 * G0 / G0**2,
        gyro_bias=np.asarray(S.number_list(o, "gyro_bias_deg_h", [0.0] * 3, length=3)) * DEG / 3600,
        gyro_matrix=_matrix(o, "gyro_scale_ppm", "gyro_misalignment_urad", 1e-6),
        # VRW (m/s/sqrt(h)) -> m/s^2/sqrt(Hz): divide by 60; ARW (deg/sqrt(h)) -> rad/s/sqrt(Hz);
        # B: mg -> m/s^2, deg/h -> rad/s; K: m/s/h/sqrt(h) -> m/s^2/sqrt(s) (/ 3600 / 60),
        # deg/h/sqrt(h) -> rad/s/sqrt(s)
        accel_noise=triad("accel", "emulator config (imu.sim)",
                          N=S.get_number(o, "accel_vrw_m_s_rth", 0.0, minimum=0) / 60.0,
                          B=S.get_number(o, "accel_bias_instability_mg", 0.0, minimum=0) * 1e-3 * G0,
                          K=S.get_number(o, "accel_rrw_m_s_h_rth", 0.0, minimum=0) / 3600.0 / 60.0),
        gyro_noise=triad("gyro", "emulator config (imu.sim)",
                         N=S.get_number(o, "gyro_arw_deg_rth", 0.0, minimum=0) * DEG / 60.0,
                         B=S.get_number(o, "gyro_bias_instability_deg_h", 0.0, minimum=0) * DEG / 3600.0,
                         K=S.get_number(o, "gyro_rrw_deg_h_rth", 0.0, minimum=0) * DEG / 3600.0 / 60.0),
        temperature_c=S.get_number(o, "temperature_c", 25.0),
        seed=int(S.get_number(o, "seed", seed, minimum=0, integer=True)),
        thermal=thermal,
    )


def _deep_merge(base: dict, over: Any, where: LocDict, key: str) -> dict:
    if not isinstance(over, dict):
        raise S.error(where, key, f"{key!r} must be a mapping of profile keys")
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            out[k] = _deep_merge(base[k], v, over, k)
        else:
            out[k] = v
    return out


def build_imu_model(o: LocDict, rate_hz: float, seed: int) -> Any:
    """The IMU model of an ``imu.sim`` config mapping.

    ``profile: NAME`` (a device profile of configs/imu-profiles.yaml, or of ``profiles_file``:
    consumer_mems, mti_class, tactical, declared_only, random) selects the full error model of
    :mod:`rigctl.sim.error_model` (noise with exact Allan signatures, front end, physical
    effects, clock error); ``overrides`` is deep-merged into the profile, e.g.
    ``{effects: {lever_arm: {enabled: true, r_m: [0.01, 0, 0]}}}``. The profile and the
    overrides are checked against the profile schema (:data:`rigctl.sim.profiles.PROFILE_SCHEMA`):
    an unknown key, a value of the wrong kind or an enabled effect without a required key is an
    InputError naming the file and line. Without ``profile``: the declared errors above with
    white noise.
    """
    if "profile" not in o:
        return build_declared_imu(o, rate_hz, seed)
    from pathlib import Path

    from .error_model import ImuErrorModel
    from .profiles import _coerce, check_merged, check_profile, get_profile, profile_names

    S.check_keys(o, ("profile", "seed", "profiles_file", "overrides"), "'imu.sim' with a profile")
    path = None
    if "profiles_file" in o:
        path = Path(o.file).parent / S.get_str(o, "profiles_file")
        if not path.is_file():
            raise S.error(o, "profiles_file", f"profiles file {str(path)!r} not found",
                          "the path is relative to the config file")
    name = S.get_str(o, "profile", choices=profile_names(path))
    seed = int(S.get_number(o, "seed", seed, minimum=0, integer=True))
    profile = get_profile(name, seed=seed, path=path)  # checked against the profile schema
    base, over = profile, o.get("overrides")
    if "overrides" in o:
        if not isinstance(over, dict):
            raise S.error(o, "overrides", "'overrides' must be a mapping of profile keys",
                          "same layout as a profile of configs/imu-profiles.yaml")
        check_profile(over, "imu.sim.overrides")  # misspelt keys, wrong kinds: file and line
        profile = _deep_merge(profile, over, o, "overrides")
    check_merged(profile, over, base, f"profile {name!r}" + (" with imu.sim.overrides" if over else ""))
    try:
        profile = _coerce(profile)
        return ImuErrorModel.from_profile(profile, rate_hz=rate_hz, seed=seed)
    except (KeyError, ValueError, TypeError) as exc:
        raise S.error(o, "overrides" if "overrides" in o else "profile",
                      f"invalid IMU profile: {exc}") from None
