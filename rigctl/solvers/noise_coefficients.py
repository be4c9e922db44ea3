"""IEEE Std 952 noise coefficients: the one type for the emulator, the solvers and the results.

A :class:`NoiseCoefficients` is the noise of ONE channel (one axis of a gyro or of an
accelerometer); a sensor's three axes are a tuple of three (:data:`Triad`). Every value is SI;
"u" is the rate unit, rad/s for a gyro and m/s^2 for an accelerometer.

==== ======================================= ================== ==================== ===========================
term name                                    SI unit            rate PSD S(f)        Allan variance sigma^2(tau)
==== ======================================= ================== ==================== ===========================
Q    angle / velocity quantization           u s   (rad, m/s)   (2 pi f)^2 Q^2 tau0  3 Q^2 / tau^2
N    angle / velocity random walk            u sqrt(s)          N^2                  N^2 / tau
B    bias instability (flicker, 1/f)         u                  (B^2 / 2 pi) / f     (2 ln2 / pi) B^2 (plateau)
K    rate / acceleration random walk         u / sqrt(s)        (K / 2 pi)^2 / f^2   K^2 tau / 3
R    rate / acceleration ramp                u / s              R^2 / (2 pi f)^3     R^2 tau^2 / 2
GM   first-order Gauss-Markov: sigma (u),    u, s               2 sigma^2 Tc /       (2 sigma^2 Tc / tau)
     correlation time Tc (s)                                    (1 + (2 pi f Tc)^2)  [1 - Tc/(2 tau)(3 - 4 e^{-tau/Tc} + e^{-2 tau/Tc})]
==== ======================================= ================== ==================== ===========================

S(f) is the rate PSD in IEEE 952's convention, the one for which

    sigma^2(tau) = 4 int_0^inf S(f) sin^4(pi f tau) / (pi f tau)^2 df

(so white rate noise of "density" N gives N^2 / tau: N in u/sqrt(Hz) = u sqrt(s)); the Allan
variance of the set is the sum of its terms (:meth:`NoiseCoefficients.avar`). B's 1/f band is
[``flicker_tau_min_s``, ``flicker_tau_max_s``] (the plateau; the emulator and the segment
covariance extend the 1/f PSD a decade beyond it, :mod:`rigctl.solvers.segment_cov`). Q's PSD
holds below the Nyquist frequency 1/(2 tau0).

Each term is a :class:`Coefficient`: an estimate, and, when the coefficient was measured, its
68 %/95 % interval, or -- for a term the data do not resolve -- a one-sided 95 % upper bound
(``upper95``; ``value`` is then the unconstrained estimate below it, which the calibration uses
rather than zero: docs/calibration.md section 10). A given coefficient (a datasheet, the
emulator's profile) is a bare value.

Where they come from and go to:

* the emulator's profiles (configs/imu-profiles.yaml, ``imu.sim.overrides``): a ``noise:``
  section read as its settings (:meth:`rigctl.sim.profiles.NoiseSection.coefficients`), whose
  keys (:data:`CONFIG_KEYS`: the unit in the key name) are checked with file and line by :mod:`rigctl.sim.profiles`, and of the declared ``imu.sim``
  section (field units, :mod:`rigctl.sim.imu`); the emulator generates every term, Gauss-Markov
  terms included (:mod:`rigctl.sim.noise`);
* the Allan fit (:func:`rigctl.solvers.allan_fit.fit_terms`: ``fit["coefficients"]``);
* the recording's /results/allan (:mod:`rigctl.analysis.results`: stored and read through
  :func:`to_json` / :func:`from_json`);
* the calibration's segment covariance (:meth:`NoiseCoefficients.cov`), the thermal fit and the
  pose covariance of the multi-position fits.

A coefficient set estimated from a calibration session (REML,
:func:`rigctl.solvers.segment_noise.estimate_channel_noise`) may carry a white level per segment
group (``white_by_group``: N per group, u sqrt(s)), the covariance of its variance components
(``theta_cov``) and the fit's details (``details``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import segment_cov as sc

TERMS = ("Q", "N", "B", "K", "R")
PLATEAU = 2.0 * math.log(2.0) / math.pi  # sigma^2 / B^2 on the flicker plateau (0.664^2)
SENSORS = ("gyro", "accel")
#: SI unit of each term per sensor
SI_UNITS = {"gyro": {"Q": "rad", "N": "rad/sqrt(s)", "B": "rad/s", "K": "rad/s/sqrt(s)",
                     "R": "rad/s^2"},
            "accel": {"Q": "m/s", "N": "m/s/sqrt(s)", "B": "m/s^2", "K": "m/s^2/sqrt(s)",
                      "R": "m/s^3"}}
_DEG = 180.0 / math.pi
G0 = 9.80665  # m/s^2, standard gravity (for mg)
#: (field unit label, factor from SI) per sensor and term: what reports print
FIELD_UNITS = {
    "gyro": {"Q": ("deg", _DEG), "N": ("deg/sqrt(h)", _DEG * 60.0),
             "B": ("deg/h", _DEG * 3600.0), "K": ("deg/h/sqrt(h)", _DEG * 3600.0 * 60.0),
             "R": ("deg/h/h", _DEG * 3600.0 ** 2)},
    "accel": {"Q": ("m/s", 1.0), "N": ("m/s/sqrt(h)", 60.0),
              "B": ("mg", 1000.0 / G0), "K": ("m/s/h/sqrt(h)", 3600.0 * 60.0),
              "R": ("m/s/h/h", 3600.0 ** 2)},
}
#: IEEE 952 names of the terms per sensor
TERM_NAMES = {"gyro": {"Q": "angle_quantization", "N": "angle_random_walk",
                       "B": "bias_instability", "K": "rate_random_walk", "R": "rate_ramp"},
              "accel": {"Q": "velocity_quantization", "N": "velocity_random_walk",
                        "B": "bias_instability", "K": "acceleration_random_walk",
                        "R": "acceleration_ramp"}}
#: the emulator's profile keys of a ``noise:`` section (unit in the key name) per sensor and term
CONFIG_KEYS = {
    "gyro": {"Q": "Q_rad", "N": "N_rad_per_s_per_sqrt_hz", "B": "B_rad_per_s",
             "K": "K_rad_per_s2_per_sqrt_hz", "R": "R_rad_per_s2"},
    "accel": {"Q": "Q_m_per_s", "N": "N_m_per_s2_per_sqrt_hz", "B": "B_m_per_s2",
              "K": "K_m_per_s3_per_sqrt_hz", "R": "R_m_per_s3"},
}
#: keys of a ``noise:`` section besides the terms: the flicker band (s); the emulator's cascade
#: density (``flicker_pairs_per_decade``) is read by rigctl.sim.error_model.
BAND_KEYS = ("flicker_tau_min_s", "flicker_tau_max_s")
#: a ``noise:`` section's Gauss-Markov terms: ``gm: [{<sigma key>: .., tau_c_s: ..}, ...]``, the
#: stationary standard deviation in the sensor's SI rate unit and the correlation time in s
GM_KEY = "gm"
GM_SIGMA_KEYS = {"gyro": "sigma_rad_per_s", "accel": "sigma_m_per_s2"}


#: what set a bound (Coefficient.bound_from), as reports print it: the fit's one-sided 95 %
#: bound; the curve's own limit (its measured minimum, where the IEEE 952 model needs its own
#: error); the same limit read off the curve's family-wise upper 95 % band
BOUND_SOURCES = {"fit": "95 % upper bound", "curve": "the curve's own limit",
                 "band": "the curve's 95 % limit"}


@dataclass(frozen=True)
class Coefficient:
    """One noise coefficient, SI: an estimate and what is known of its uncertainty.

    value: the estimate (for a bound: the unconstrained estimate, <= upper95);
    ci68, ci95: two-sided intervals (lo, hi) of a resolved term; upper95: the one-sided 95 %
    upper bound of a term the data do not resolve (None: resolved or given);
    edf: Satterthwaite degrees of freedom of the estimate; bound_from: what set the bound
    (a key of :data:`BOUND_SOURCES`).
    """

    value: float = 0.0
    ci68: tuple[float, float] | None = None
    ci95: tuple[float, float] | None = None
    upper95: float | None = None
    edf: float | None = None
    bound_from: str | None = None

    def __post_init__(self) -> None:
        if not self.value >= 0.0:
            raise ValueError(f"a noise coefficient is >= 0, got {self.value!r}")

    @property
    def resolved(self) -> bool:
        """False when only an upper bound is known."""
        return self.upper95 is None

    @property
    def cautious(self) -> float:
        """The estimate of a resolved term, the 95 % upper bound of one known only as a bound:
        the value a consumer that must not be over-confident takes (the Kalibr export)."""
        return self.value if self.upper95 is None else self.upper95

    @property
    def interval95(self) -> tuple[float, float]:
        """The 95 % interval: ``ci95`` of a resolved term, [0, upper95] of a bound."""
        if self.upper95 is not None:
            return (0.0, float(self.upper95))
        if self.ci95 is None:
            raise ValueError("this coefficient has no 95 % interval (a given value)")
        return (float(self.ci95[0]), float(self.ci95[1]))

    def scaled(self, factor: float) -> "Coefficient":
        """The same coefficient in another unit (every number times ``factor`` > 0)."""
        f = float(factor)
        return Coefficient(self.value * f, _mul(self.ci68, f), _mul(self.ci95, f),
                           None if self.upper95 is None else self.upper95 * f, self.edf,
                           self.bound_from)


def _mul(ci: tuple[float, float] | None, f: float) -> tuple[float, float] | None:
    return None if ci is None else (ci[0] * f, ci[1] * f)


def _coef(x: Any) -> Coefficient:
    return x if isinstance(x, Coefficient) else Coefficient(float(x))


@dataclass(frozen=True)
class GaussMarkov:
    """A first-order Gauss-Markov term: stationary standard deviation ``sigma`` (u) and
    correlation time ``tau_c_s`` (s); ``tau_c_ci95``: Tc's 95 % interval (s) where it was
    estimated (the Allan fit), None where given; ``tau_c_ci95_open``: (lower, upper) True where
    that end is the end of the Tc range searched, not the data's (the profile's 95 % set still
    reached it): the true end lies beyond it, written "[<lo, hi]" / "[lo, >hi]"."""

    sigma: Coefficient
    tau_c_s: float
    tau_c_ci95: tuple[float, float] | None = None
    tau_c_ci95_open: tuple[bool, bool] = (False, False)

    def tc_interval_text(self, digits: int = 3) -> str:
        """Tc's 95 % interval as text (:func:`tc_interval_text`; '' where none)."""
        return "" if self.tau_c_ci95 is None else tc_interval_text(self.tau_c_ci95,
                                                                   self.tau_c_ci95_open, digits)

    def __post_init__(self) -> None:
        object.__setattr__(self, "sigma", _coef(self.sigma))
        if not self.tau_c_s > 0:
            raise ValueError(f"a Gauss-Markov correlation time is > 0, got {self.tau_c_s!r}")


@dataclass(frozen=True)
class NoiseCoefficients:
    """IEEE 952 coefficients of one channel, SI (module docstring for units and equations).

    Q, N, B, K, R: :class:`Coefficient` (a float is taken as a given value); gm: Gauss-Markov
    terms; flicker_tau_min_s / flicker_tau_max_s: B's plateau (s); sensor: "gyro", "accel" or ""
    (units unknown); source: where the numbers come from; white_by_group: N (u sqrt(s)) per
    segment group of a session estimate (None: N everywhere); theta_cov: covariance of the
    estimated variance components (N_g^2 per group label, B^2, K^2); details: the estimate's
    details (JSON-able).
    """

    Q: Coefficient = Coefficient()
    N: Coefficient = Coefficient()
    B: Coefficient = Coefficient()
    K: Coefficient = Coefficient()
    R: Coefficient = Coefficient()
    gm: tuple[GaussMarkov, ...] = ()
    flicker_tau_min_s: float = 1.0
    flicker_tau_max_s: float = 1.0e4
    sensor: str = ""
    source: str = ""
    white_by_group: Mapping[str, float] | None = None
    theta_cov: NDArray[np.float64] | None = field(default=None, compare=False, repr=False)
    details: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        for t in TERMS:
            object.__setattr__(self, t, _coef(getattr(self, t)))
        object.__setattr__(self, "gm", tuple(self.gm))
        if not self.flicker_tau_max_s > self.flicker_tau_min_s > 0:
            raise ValueError("the flicker band needs 0 < flicker_tau_min_s < flicker_tau_max_s")
        if self.sensor not in ("", *SENSORS):
            raise ValueError(f"sensor is 'gyro', 'accel' or '', got {self.sensor!r}")

    def as_json(self) -> dict[str, Any]:
        """:func:`to_json` (what rigctl.jsonable and /results store)."""
        return to_json(self)

    # ---------------------------------------------------------------- values
    def value(self, term: str) -> float:
        """The estimate of ``term`` (Q, N, B, K or R), SI."""
        return getattr(self, term).value

    def values(self) -> dict[str, float]:
        """{term: estimate} (SI)."""
        return {t: self.value(t) for t in TERMS}

    def with_values(self, **values: float) -> "NoiseCoefficients":
        """A copy with some terms replaced by given values."""
        return replace(self, **{t: Coefficient(float(v)) for t, v in values.items()})

    def n_of(self, group: str) -> float:
        """White level N (u sqrt(s)) of a segment group."""
        if self.white_by_group is None:
            return self.N.value
        return float(self.white_by_group.get(str(group), self.N.value))

    # ---------------------------------------------------------------- statistics
    def avar(self, tau_s: ArrayLike) -> NDArray[np.float64]:
        """Allan variance (u^2) at cluster times tau (s), same shape as tau."""
        tau = np.asarray(tau_s, dtype=np.float64)
        q, n, b, k, r = (self.value(t) for t in TERMS)
        out = 3.0 * q**2 / tau**2 + n**2 / tau + PLATEAU * b**2 + k**2 * tau / 3.0 + r**2 * tau**2 / 2.0
        for g in self.gm:
            out = out + g.sigma.value**2 * sc.ou_avar(tau, g.tau_c_s)
        return out

    def psd(self, f_hz: ArrayLike, tau0_s: float | None = None) -> NDArray[np.float64]:
        """Rate PSD S(f) (u^2/Hz, IEEE 952's convention, module docstring) at f > 0; Q's term
        needs the sample interval ``tau0_s`` (left out without it); B's 1/f holds everywhere."""
        f = np.asarray(f_hz, dtype=np.float64)
        q, n, b, k, r = (self.value(t) for t in TERMS)
        w = 2.0 * np.pi * f
        out = n**2 + b**2 / (2.0 * np.pi * f) + (k / (2.0 * np.pi)) ** 2 / f**2 + r**2 / w**3
        if tau0_s is not None:
            out = out + w**2 * q**2 * tau0_s
        for g in self.gm:
            out = out + 2.0 * g.sigma.value**2 * g.tau_c_s / (1.0 + (w * g.tau_c_s) ** 2)
        return out

    def cov(self, a: ArrayLike, b: ArrayLike, groups: Sequence[str] | None = None, t0: float = 0.0,
            flicker: NDArray[np.float64] | None = None, rw: NDArray[np.float64] | None = None
            ) -> NDArray[np.float64]:
        """(K, K) covariance of the means of windows [a, b] (s; run time) of this channel.

        groups: the windows' segment groups (white level :meth:`n_of`); t0: the random walk's
        origin (power-on), s; flicker, rw: the unit components (B = 1 on this band, K = 1 from
        t0) when already computed. R is deterministic: left out (the closed loop's time drift).
        """
        a = np.asarray(a, dtype=np.float64)
        b = np.asarray(b, dtype=np.float64)
        groups = ["*"] * a.size if groups is None else groups
        nw = np.array([self.n_of(str(g)) ** 2 for g in groups])
        C = np.diag(nw / (b - a))
        q, bb, k = self.Q.value, self.B.value, self.K.value
        if q:
            C = C + q**2 * sc.cov_quantization(a, b)
        if bb:
            if flicker is None:
                flicker = sc.cov_flicker(a, b, sc.flicker_bank(self.flicker_tau_min_s, self.flicker_tau_max_s))
            C = C + bb**2 * flicker
        if k:
            C = C + k**2 * (sc.cov_random_walk(a, b, t0) if rw is None else rw)
        for g in self.gm:
            C = C + g.sigma.value**2 * sc.cov_ou(a, b, g.tau_c_s)
        return 0.5 * (C + C.T)


#: a sensor's three axes (x, y, z)
Triad = tuple[NoiseCoefficients, NoiseCoefficients, NoiseCoefficients]


def triad(sensor: str = "", source: str = "", flicker_tau_min_s: float = 1.0,
          flicker_tau_max_s: float = 1.0e4, **terms: ArrayLike) -> Triad:
    """Three axes from given values: each term a number (all axes) or three numbers (x, y, z)."""
    per = {t: np.broadcast_to(np.asarray(v, dtype=np.float64), (3,)) for t, v in terms.items()}
    return tuple(NoiseCoefficients(**{t: float(v[i]) for t, v in per.items()}, sensor=sensor,
                                   source=source, flicker_tau_min_s=float(flicker_tau_min_s),
                                   flicker_tau_max_s=float(flicker_tau_max_s))
                 for i in range(3))  # type: ignore[return-value]


def triad_avar(axes: Sequence[NoiseCoefficients], tau_s: ArrayLike) -> NDArray[np.float64]:
    """Allan variance of each axis: (..., 3) for (...,) tau."""
    return np.stack([m.avar(tau_s) for m in axes], axis=-1)


def terms_of(axes: Sequence[NoiseCoefficients], term: str) -> NDArray[np.float64]:
    """(len(axes),) estimates of one term across axes, SI."""
    return np.array([m.value(term) for m in axes], dtype=np.float64)


def in_field_units(m: NoiseCoefficients, term: str) -> tuple[Coefficient, str]:
    """``term`` of ``m`` (which must know its sensor) in the unit reports print, and that unit."""
    unit, fac = FIELD_UNITS[m.sensor][term]
    return getattr(m, term).scaled(fac), unit


def as_coefficients(x: NoiseCoefficients | Mapping[str, Any]) -> NoiseCoefficients:
    """A result's coefficients, live (NoiseCoefficients) or as stored (:func:`to_json`'s form)."""
    return x if isinstance(x, NoiseCoefficients) else from_json(x)


def resolved_values(m: NoiseCoefficients) -> dict[str, float]:
    """{term: estimate} with the terms known only as an upper bound at 0: the model an Allan fit
    reports and checks against the curve (the calibration uses :meth:`NoiseCoefficients.values`,
    the bounded terms at their estimate: docs/calibration.md section 10)."""
    return {t: (c.value if c.resolved else 0.0) for t, c in ((t, getattr(m, t)) for t in TERMS)}


def power_on_k2(m: NoiseCoefficients) -> float:
    """K^2 (SI^2) that the biases' extrapolation to power-on carries beyond the covariance's.

    The covariance uses a bounded term's estimate (:meth:`NoiseCoefficients.values`). Where that
    estimate of the random walk sits on its boundary 0 (REML's K of one session, often: docs/
    calibration.md, Limits) the power-on term K^2 (t - t0) would vanish from the biases' variance,
    although the data permit K up to its one-sided 95 % bound. The biases then carry K^2's
    expectation under what the bound says of it (rigctl.solvers.conformity.Estimate "bound":
    K^2 ~ N(0, s^2) truncated at 0, s = upper95^2 / z_0.95): E[K^2] = s sqrt(2 / pi), about
    0.49 upper95^2 -- a bias's variance is linear in K^2, so this is its variance averaged over
    K. 0 for a resolved K or a bounded one estimated above 0 (the covariance already holds it).
    The same rule for the session's model and an Allan capture's."""
    k = m.K
    if k.resolved or k.value > 0.0 or not k.upper95:
        return 0.0
    return float(k.upper95) ** 2 / 1.6448536269514722 * float(np.sqrt(2.0 / np.pi))


def to_config(axes: Sequence[NoiseCoefficients], sensor: str) -> dict[str, Any]:
    """A profile's ``noise:`` section for these axes (inverse of :meth:`rigctl.sim.profiles.NoiseSection.coefficients`; SI values;
    Gauss-Markov terms must be the same on the three axes)."""
    if any(m.gm != axes[0].gm for m in axes):
        raise ValueError("a profile's Gauss-Markov terms hold for the three axes alike")
    out: dict[str, Any] = {}
    for t, k in CONFIG_KEYS[sensor].items():
        v = terms_of(axes, t)
        out[k] = float(v[0]) if np.all(v == v[0]) else v.tolist()
    out["flicker_tau_min_s"] = axes[0].flicker_tau_min_s
    out["flicker_tau_max_s"] = axes[0].flicker_tau_max_s
    if axes[0].gm:
        out[GM_KEY] = [{GM_SIGMA_KEYS[sensor]: g.sigma.value, "tau_c_s": g.tau_c_s} for g in axes[0].gm]
    return out


# ------------------------------------------------------------------------------ JSON (results)
def coefficient_json(c: Coefficient) -> dict[str, Any]:
    """JSON form of one Coefficient (SI; what /results stores; inverse :func:`coefficient_from`)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in
            ((f.name, getattr(c, f.name)) for f in fields(c)) if v is not None}


def tc_interval_text(ci: Sequence[float], open_ends: Sequence[bool] | None = None,
                     digits: int = 3) -> str:
    """A Gauss-Markov Tc's 95 % interval (s) as "[lo, hi]", an end that is the end of the Tc
    range searched, not the data's, written open: "[<lo, hi]", "[lo, >hi]". The one spelling
    of every output (text, warnings, JSON readers, the HTML report, the Kalibr comments)."""
    o_lo, o_hi = (bool(v) for v in (open_ends or (False, False)))
    return (f"[{'<' if o_lo else ''}{float(ci[0]):.{digits}g}, "
            f"{'>' if o_hi else ''}{float(ci[1]):.{digits}g}]")


def coefficient_from(d: Mapping[str, Any]) -> Coefficient:
    """Inverse of :func:`coefficient_json`."""
    def pair(x: Any) -> tuple[float, float] | None:
        return None if x is None else (float(x[0]), float(x[1]))
    return Coefficient(float(d.get("value", 0.0)), pair(d.get("ci68")), pair(d.get("ci95")),
                       None if d.get("upper95") is None else float(d["upper95"]),
                       None if d.get("edf") is None else float(d["edf"]), d.get("bound_from"))


def to_json(m: NoiseCoefficients) -> dict[str, Any]:
    """JSON-able form (SI; the units are :data:`SI_UNITS` of ``sensor``): what /results stores."""
    out: dict[str, Any] = {"sensor": m.sensor, "source": m.source, "units": dict(SI_UNITS.get(m.sensor, {})),
                           "flicker_tau_min_s": m.flicker_tau_min_s, "flicker_tau_max_s": m.flicker_tau_max_s,
                           **{t: coefficient_json(getattr(m, t)) for t in TERMS}}
    if m.gm:
        out["gm"] = [{"sigma": coefficient_json(g.sigma), "tau_c_s": g.tau_c_s,
                      **({} if g.tau_c_ci95 is None else {"tau_c_ci95_s": list(g.tau_c_ci95),
                                                          "tau_c_ci95_open": list(g.tau_c_ci95_open)})}
                     for g in m.gm]
    if m.white_by_group is not None:
        out["white_by_group"] = {str(k): float(v) for k, v in m.white_by_group.items()}
    return out


def from_json(d: Mapping[str, Any]) -> NoiseCoefficients:
    """Inverse of :func:`to_json`."""
    return NoiseCoefficients(**{t: coefficient_from(d.get(t) or {}) for t in TERMS},
                             gm=tuple(GaussMarkov(coefficient_from(g["sigma"]), float(g["tau_c_s"]),
                                                  None if g.get("tau_c_ci95_s") is None else
                                                  (float(g["tau_c_ci95_s"][0]),
                                                   float(g["tau_c_ci95_s"][1])),
                                                  tuple(bool(v) for v in g.get(
                                                      "tau_c_ci95_open") or (False, False)))
                                      for g in d.get("gm") or ()),
                             flicker_tau_min_s=float(d.get("flicker_tau_min_s", 1.0)),
                             flicker_tau_max_s=float(d.get("flicker_tau_max_s", 1.0e4)),
                             sensor=str(d.get("sensor", "")), source=str(d.get("source", "")),
                             white_by_group=(None if d.get("white_by_group") is None
                                             else {str(k): float(v) for k, v in d["white_by_group"].items()}))
