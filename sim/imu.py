"""Emulated IMU: the declared error models of docs/methods.md A2 plus white noise.

Accelerometer, for true specific force a (m/s^2):

    A = b_a + M_a a + k2 * a^2 (element-wise) + noise,   M_a[i,i] = S_i, M_a[i,j] = K_ji

Gyroscope, for true rate w (rad/s):

    W = d_g + M_g w + noise,                              M_g[i,i] = Sk_i, M_g[i,j] = K_ij

White noise densities: velocity random walk (m/s^2/sqrt(Hz)) and angle random walk
(rad/s/sqrt(Hz)); the per-sample standard deviation is density * sqrt(rate). Optionally the
slow IEEE 952 terms: bias instability B (flicker, Allan plateau 0.664 B between 1 s and
1e4 s) and rate / acceleration random walk K, and first-order Gauss-Markov bias terms
(``gyro_gm`` / ``accel_gm``: sigma in deg/h / mg, correlation time in s), from
:class:`rigctl.sim.noise.NoiseGenerator` (exact Allan signatures; its own seeded streams, so
the white noise is the same with or without them).

The model is built from a config mapping (see configs/sim.yaml) whose values are in the units
named by their keys, read by :func:`rigctl.settings.parse` as :class:`DeclaredImuSettings`
(with a profile: :class:`ProfileImuSettings`), and reports its truth in SI as a
JSON-serialisable dict.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from rigctl import schema as S
from rigctl.yamlio import LocDict
from rigctl.settings import Settings, items, matrix3, number, numbers, parse, setting, subsection, text
from rigctl.solvers.noise_coefficients import GaussMarkov, Triad, terms_of, to_json, triad

from . import declared_kernels as _dk
from .effects import turn_on_bias
from .noise import NoiseGenerator
from .thermal_imu import ThermalErrors, ThermalSettings

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
    #: turn-on-to-turn-on bias repeatability, 1 sigma per axis (gyro rad/s, accel m/s^2): each
    #: power cycle (:meth:`power_cycle`) draws a new turn-on bias; the first turn-on's is zero
    #: (the declared bias is the bias of the unit as it was turned on for the run)
    gyro_turn_on_sigma: float = 0.0
    accel_turn_on_sigma: float = 0.0

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x1A0]))
        self._turn_on_rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x1A3]))
        self.turn_on_gyro, self.turn_on_accel = np.zeros(3), np.zeros(3)
        self.power_cycles = 0
        self._temp_rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x7E]))
        self._slow = {}
        for name, axes, tag in (("gyro", self.gyro_noise, 0x1A1), ("accel", self.accel_noise, 0x1A2)):
            if any(m.B.value > 0 or m.K.value > 0 or m.gm for m in axes):  # the slow terms (N: below)
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
        T = np.full(n, self.temperature_c) if temperature is None else np.asarray(temperature, float)
        if n >= 2 and _dk.ready(DeclaredImuModel):  # the same floats, compiled (sim/declared_kernels.py)
            f, w = _dk.declared_deterministic(self, f_true, w_true, T, hysteresis, temperature_rate)
        else:
            f, w = self.deterministic_numpy(f_true, w_true, T, hysteresis, temperature_rate)
        s_acc, s_gyr = self._white_sigmas()
        if s_acc is not None:
            f = f + self.rng.standard_normal((n, 3)) * s_acc
        if s_gyr is not None:
            w = w + self.rng.standard_normal((n, 3)) * s_gyr
        if "accel" in self._slow:
            f = f + self._slow["accel"].next(n)
        if "gyro" in self._slow:
            w = w + self._slow["gyro"].next(n)
        if self.thermal is not None and self.thermal.temperature_noise_c > 0:
            T = T + self._temp_rng.standard_normal(n) * self.thermal.temperature_noise_c
        return f, w, T

    def deterministic_numpy(self, f_true: NDArray, w_true: NDArray, T: NDArray, hysteresis: NDArray | None,
                            temperature_rate: NDArray | None) -> tuple[NDArray, NDArray]:
        """:meth:`apply` before its noise, in numpy: bias and turn-on bias, matrix, quadratic term
        and the thermal errors at temperature T (n,) (what sim/declared_kernels.py compiles)."""
        n = f_true.shape[0]
        f = self.accel_bias + self.turn_on_accel + f_true @ self.accel_matrix.T + self.accel_quadratic * f_true**2
        w = self.gyro_bias + self.turn_on_gyro + w_true @ self.gyro_matrix.T
        if self.thermal is not None and self.thermal.active:
            H = np.zeros(n) if hysteresis is None else hysteresis
            R = np.zeros(n) if temperature_rate is None else temperature_rate
            f = f + self.thermal.error("accel", f_true, T, H, R)
            w = w + self.thermal.error("gyro", w_true, T, H, R)
        return f, w

    _white_key = (None, None, None)  # (accel_noise, gyro_noise, rate_hz) the sigmas were made for
    _white = (None, None)

    def _white_sigmas(self) -> tuple[NDArray | None, NDArray | None]:
        """Per-sample white-noise sigmas (3,) of the accelerometers and gyros, N sqrt(rate_hz)
        (None where no axis has N > 0), computed again only when the noise terms or the rate
        change (apply runs at every emulator poll)."""
        ka, kg, kr = self._white_key
        if ka is not self.accel_noise or kg is not self.gyro_noise or kr != self.rate_hz:
            n_acc, n_gyr = terms_of(self.accel_noise, "N"), terms_of(self.gyro_noise, "N")
            self._white = tuple(n * math.sqrt(self.rate_hz) if np.any(n > 0) else None for n in (n_acc, n_gyr))
            self._white_key = (self.accel_noise, self.gyro_noise, self.rate_hz)
        return self._white

    def power_cycle(self) -> tuple[NDArray, NDArray]:
        """The unit lost power and is back: a new turn-on bias b_on ~ N(0, sigma^2) per axis
        (:func:`rigctl.sim.effects.turn_on_bias`, the repeatability sigmas above, from the unit's
        own seeded stream: reproducible, and the noise streams are untouched) replaces the last
        one; the bias is now b + b_on. Returns the new turn-on biases (gyro (3,) rad/s, accel
        (3,) m/s^2)."""
        self.power_cycles += 1
        self.turn_on_gyro, self.turn_on_accel = turn_on_bias(self._turn_on_rng, self.gyro_turn_on_sigma,
                                                             self.accel_turn_on_sigma)
        return self.turn_on_gyro.copy(), self.turn_on_accel.copy()

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
            # the turn-on bias now (zero until a power cycle) and its repeatability (1 sigma)
            "accel_turn_on_bias_m_s2": self.turn_on_accel.tolist(),
            "gyro_turn_on_bias_rad_s": self.turn_on_gyro.tolist(),
            "accel_turn_on_repeatability_m_s2": self.accel_turn_on_sigma,
            "gyro_turn_on_repeatability_rad_s": self.gyro_turn_on_sigma,
            # three axes each, rigctl.solvers.noise_coefficients.to_json (as the profile model's)
            "accel_noise": [to_json(m) for m in self.accel_noise],
            "gyro_noise": [to_json(m) for m in self.gyro_noise],
        }


ZERO3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True, kw_only=True)
class GyroGaussMarkov(Settings):
    """One entry of ``imu.sim.gyro_gm``: a first-order Gauss-Markov gyro bias term, the same
    on the three axes: stationary standard deviation (deg/h) and correlation time (s)."""

    sigma_deg_h: float = number(minimum=0)
    tau_c_s: float = number(minimum=0)

    def check(self, d: LocDict) -> None:
        _positive_tau(self.tau_c_s, d)

    def term(self) -> GaussMarkov:
        return GaussMarkov(self.sigma_deg_h * DEG / 3600.0, self.tau_c_s)


@dataclass(frozen=True, kw_only=True)
class AccelGaussMarkov(Settings):
    """One entry of ``imu.sim.accel_gm``: stationary standard deviation (mg) and correlation
    time (s) of a first-order Gauss-Markov accelerometer bias term."""

    sigma_mg: float = number(minimum=0)
    tau_c_s: float = number(minimum=0)

    def check(self, d: LocDict) -> None:
        _positive_tau(self.tau_c_s, d)

    def term(self) -> GaussMarkov:
        return GaussMarkov(self.sigma_mg * 1e-3 * G0, self.tau_c_s)


def _positive_tau(tau: float, d: LocDict) -> None:
    if not tau > 0:
        raise S.error(d, "tau_c_s", "'tau_c_s' must be longer than zero",
                      "give the term's correlation time in s, e.g. tau_c_s: 300")


@dataclass(frozen=True, kw_only=True)
class DeclaredImuSettings(Settings):
    """``imu.sim`` without a profile: the declared errors, white noise, the slow IEEE 952 terms
    and Gauss-Markov terms, in field units (the unit in each key's name; docs/emulator.md)."""

    accel_bias_mg: tuple[float, ...] = numbers(ZERO3)
    accel_scale_ppm: tuple[float, ...] = numbers(ZERO3)
    accel_misalignment_urad: tuple[tuple[float, ...], ...] | None = matrix3(None)
    accel_quadratic_ug_per_g2: tuple[float, ...] = numbers(ZERO3)
    gyro_bias_deg_h: tuple[float, ...] = numbers(ZERO3)
    gyro_scale_ppm: tuple[float, ...] = numbers(ZERO3)
    gyro_misalignment_urad: tuple[tuple[float, ...], ...] | None = matrix3(None)
    accel_vrw_m_s_rth: float = number(0.0, minimum=0)
    gyro_arw_deg_rth: float = number(0.0, minimum=0)
    accel_bias_instability_mg: float = number(0.0, minimum=0)
    accel_rrw_m_s_h_rth: float = number(0.0, minimum=0)
    gyro_bias_instability_deg_h: float = number(0.0, minimum=0)
    gyro_rrw_deg_h_rth: float = number(0.0, minimum=0)
    accel_gm: tuple[AccelGaussMarkov, ...] = items(AccelGaussMarkov, "'imu.sim.accel_gm'")
    gyro_gm: tuple[GyroGaussMarkov, ...] = items(GyroGaussMarkov, "'imu.sim.gyro_gm'")
    #: turn-on-to-turn-on bias repeatability, 1 sigma per axis: a new turn-on bias at each power cycle
    accel_turn_on_repeatability_mg: float = number(0.0, minimum=0)
    gyro_turn_on_repeatability_deg_h: float = number(0.0, minimum=0)
    temperature_c: float = number(25.0)
    #: None: the config's seed
    seed: int | None = number(None, minimum=0, integer=True)
    #: None: no temperature-dependent errors
    thermal: ThermalSettings | None = subsection(ThermalSettings, "'imu.sim.thermal'", optional=True)


def _matrix(scale: tuple[float, ...], misalign: tuple[tuple[float, ...], ...] | None,
            scale_unit: float) -> NDArray:
    m = np.eye(3)
    m[np.diag_indices(3)] += np.asarray(scale) * scale_unit
    for i, row in enumerate(misalign or ()):
        for j, x in enumerate(row):
            if i != j:
                m[i, j] += float(x) * 1e-6  # urad
    return m


def _with_gm(axes: Triad, terms: tuple[Any, ...]) -> Triad:
    gm = tuple(t.term() for t in terms)
    return tuple(replace(m, gm=gm) for m in axes) if gm else axes  # type: ignore[return-value]


def build_declared_imu(o: LocDict, rate_hz: float, seed: int) -> DeclaredImuModel:
    """Declared-error IMU from the ``imu.sim`` config mapping (units in the key names)."""
    c = parse(DeclaredImuSettings, o, "'imu.sim'")
    return DeclaredImuModel(
        rate_hz=rate_hz,
        accel_bias=np.asarray(c.accel_bias_mg) * 1e-3 * G0,
        accel_matrix=_matrix(c.accel_scale_ppm, c.accel_misalignment_urad, 1e-6),
        accel_quadratic=np.asarray(c.accel_quadratic_ug_per_g2) * 1e-6 * G0 / G0**2,
        gyro_bias=np.asarray(c.gyro_bias_deg_h) * DEG / 3600,
        gyro_matrix=_matrix(c.gyro_scale_ppm, c.gyro_misalignment_urad, 1e-6),
        # VRW (m/s/sqrt(h)) -> m/s^2/sqrt(Hz): divide by 60; ARW (deg/sqrt(h)) -> rad/s/sqrt(Hz);
        # B: mg -> m/s^2, deg/h -> rad/s; K: m/s/h/sqrt(h) -> m/s^2/sqrt(s) (/ 3600 / 60),
        # deg/h/sqrt(h) -> rad/s/sqrt(s); Gauss-Markov sigma: mg, deg/h as B
        accel_noise=_with_gm(triad("accel", "emulator config (imu.sim)",
                                   N=c.accel_vrw_m_s_rth / 60.0,
                                   B=c.accel_bias_instability_mg * 1e-3 * G0,
                                   K=c.accel_rrw_m_s_h_rth / 3600.0 / 60.0), c.accel_gm),
        gyro_noise=_with_gm(triad("gyro", "emulator config (imu.sim)",
                                  N=c.gyro_arw_deg_rth * DEG / 60.0,
                                  B=c.gyro_bias_instability_deg_h * DEG / 3600.0,
                                  K=c.gyro_rrw_deg_h_rth * DEG / 3600.0 / 60.0), c.gyro_gm),
        temperature_c=c.temperature_c,
        seed=int(seed if c.seed is None else c.seed),
        thermal=None if c.thermal is None else ThermalErrors(c.thermal),
        gyro_turn_on_sigma=c.gyro_turn_on_repeatability_deg_h * DEG / 3600.0,
        accel_turn_on_sigma=c.accel_turn_on_repeatability_mg * 1e-3 * G0,
    )


def _overrides(d: LocDict, key: str, default: Any = None) -> LocDict:
    if not isinstance(d[key], dict):
        raise S.error(d, key, "'overrides' must be a mapping of profile keys",
                      "same layout as a profile of configs/imu-profiles.yaml")
    return d[key]


@dataclass(frozen=True, kw_only=True)
class ProfileImuSettings(Settings):
    """``imu.sim`` with a profile: the device profile (its name is checked against the profiles
    file), its file, the seed and the overrides (a partial profile, checked by
    :class:`rigctl.sim.profiles.ImuProfile` with file and line)."""

    profile: str = text()
    #: None: the config's seed
    seed: int | None = number(None, minimum=0, integer=True)
    #: relative to the config file; None: configs/imu-profiles.yaml
    profiles_file: str | None = text(None)
    overrides: LocDict | None = setting(None, read=_overrides)


def build_imu_model(o: LocDict, rate_hz: float, seed: int) -> Any:
    """The IMU model of an ``imu.sim`` config mapping.

    ``profile: NAME`` (a device profile of configs/imu-profiles.yaml, or of ``profiles_file``:
    consumer_mems, mti_class, tactical, declared_only, random) selects the full error model of
    :mod:`rigctl.sim.error_model` (noise with exact Allan signatures, front end, physical
    effects, clock error); ``overrides`` is deep-merged into the profile, e.g.
    ``{effects: {lever_arm: {enabled: true, r_m: [0.01, 0, 0]}}}``. The profile and the
    overrides are checked by the profile's settings (:class:`rigctl.sim.profiles.ImuProfile`):
    an unknown key, a value of the wrong kind or an enabled effect without a required key is an
    InputError naming the file and line. Without ``profile``: the declared errors above with
    white noise.
    """
    if "profile" not in o:
        return build_declared_imu(o, rate_hz, seed)
    from pathlib import Path

    from .error_model import ImuErrorModel
    from .profiles import check_merged, check_profile, get_profile, load_profiles, merged, profile_names

    c = parse(ProfileImuSettings, o, "'imu.sim' with a profile")
    path = None
    if c.profiles_file is not None:
        path = Path(o.file).parent / c.profiles_file
        if not path.is_file():
            raise S.error(o, "profiles_file", f"profiles file {str(path)!r} not found",
                          "the path is relative to the config file")
    name = S.get_str(o, "profile", choices=profile_names(path))
    seed = int(seed if c.seed is None else c.seed)
    profile, over = get_profile(name, seed=seed, path=path), c.overrides  # errors at the file's lines
    base = load_profiles(path)["profiles"].get(name)  # where a merged-profile error points
    if over is not None:
        # misspelt keys, wrong kinds: file and line
        profile = merged(profile, over, check_profile(over, "imu.sim.overrides"))
    check_merged(profile, over, base, f"profile {name!r}" + (" with imu.sim.overrides" if over else ""))
    try:
        return ImuErrorModel(profile, rate_hz=rate_hz, seed=seed)
    except (KeyError, ValueError, TypeError) as exc:
        raise S.error(o, "overrides" if "overrides" in o else "profile",
                      f"invalid IMU profile: {exc}") from None
