"""The published results of a calibration or an Allan analysis as one flat list of parameters.

``rigctl calibrate`` stores a payload (/results/calibration, RECORDING.calibration.json) and
``rigctl allan`` a summary (/results/allan); each holds fits with many intermediate results.
What a lab publishes -- and what the verdicts, the results database, the certificate and the
report's verdict table use -- is one value per parameter with its standard uncertainty:

* turntable calibration: the closed loop's final fit (``results.closed_loop.final``);
* orientation-free calibration: the six-face fits when the poses are labelled as faces, else
  the multi-position fits (the first fit naming a parameter wins);
* Allan analysis: per axis the joint IEEE 952 fit's N, B, K (and Q, R when fitted) -- a term
  the data resolve with its Satterthwaite dof (chi-square interval), a term the data do not
  resolve as an estimate with its one-sided 95 % upper bound.

Every :class:`Measured` carries the SI name, the display (:mod:`rigctl.display_units`) and the
:class:`rigctl.solvers.conformity.Estimate` of its true value.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


from ..display_units import Display, display, noise_name
from ..solvers import distributions as stats
from ..solvers.conformity import Estimate
from ..solvers.noise_coefficients import as_coefficients

#: calibration fits in the order they are published (orientation-free payloads)
FREE_ORDER = ("faces_accel", "faces_gyro_bias", "multipos_accel", "multipos_gyro")
#: the noise terms a unit's Allan results publish
NOISE_TERMS = ("Q", "N", "B", "K", "R")
Z95 = float(stats.norm.ppf(0.975))


@dataclass(frozen=True)
class Measured:
    """One published parameter: SI name, value and standard uncertainty (SI), the estimate
    (distribution) its intervals and verdicts use, and where it came from."""

    name: str
    value: float
    u: float
    estimate: Estimate
    source: str
    kind: str  # "calibration" or "allan"

    @property
    def display(self) -> Display:
        return display(self.name)

    @property
    def interval(self) -> tuple[float, float]:
        """95 % coverage interval (SI)."""
        return self.estimate.interval()

    @property
    def coverage_factor(self) -> float:
        """k of the expanded uncertainty U = k u (95 %); for an asymmetric interval the larger
        half-width over u."""
        k = self.estimate.coverage_factor
        if math.isfinite(k):
            return k
        lo, hi = self.interval
        return max(self.value - lo, hi - self.value) / self.u if self.u > 0 else math.nan

    @property
    def dof(self) -> float:
        return self.estimate.dof


def _dof_from_k(k: float) -> float | None:
    """The Student-t dof whose 95 % two-sided factor is k (None: normal, k = 1.96)."""
    if not k > Z95 * (1 + 1e-9):
        return None
    from scipy.optimize import brentq  # here, not at import: scipy.optimize costs ~0.5 s of CPU

    return float(brentq(lambda nu: stats.t.ppf(0.975, nu) - k, 0.05, 1e7))


def _fit_params(fit: dict[str, Any], source: str) -> list[Measured]:
    out = []
    for p in fit.get("parameters") or []:
        v, s = p.get("value"), p.get("sigma")
        if v is None or s is None:
            continue
        dof = p.get("dof")
        if "dof" not in p and p.get("ci95_high") is not None and s > 0:
            dof = _dof_from_k((p["ci95_high"] - v) / s)  # payloads from before "dof" was stored
        out.append(Measured(p["name"], float(v), float(s),
                            Estimate(float(v), float(s), math.inf if dof is None else float(dof)),
                            source, "calibration"))
    return out


def from_calibration(payload: dict[str, Any]) -> list[Measured]:
    """The published parameters of a ``rigctl calibrate`` payload."""
    res = payload.get("results") or {}
    if payload.get("mode", "turntable") == "turntable":
        fin = (res.get("closed_loop") or {}).get("final")
        return _fit_params(fin, "closed_loop_final") if fin else []
    seen: dict[str, Measured] = {}
    for key in FREE_ORDER:
        for m in _fit_params(res.get(key) or {}, key):
            seen.setdefault(display(m.name).base, m)
    return list(seen.values())


def from_allan(summary: dict[str, Any]) -> list[Measured]:
    """The IEEE 952 terms of a ``rigctl allan`` result or stored summary, per axis (each axis'
    ``fit["coefficients"]``: NoiseCoefficients, or its JSON form as /results/allan stores it)."""
    out = []
    for axis, info in sorted((summary.get("axes") or {}).items()):
        sensor = info.get("sensor") or ("gyro" if axis.startswith("g") else "accel")
        stored = (info.get("fit") or {}).get("coefficients")
        if not stored:
            continue
        co = as_coefficients(stored)
        for t in NOISE_TERMS:
            c = getattr(co, t)
            name = noise_name(sensor, t, axis[-1])
            if c.resolved:
                v, nu = c.value, c.edf
                if c.ci95 is None or not nu:  # not fitted (a term left out of the fit)
                    continue
                # c = sqrt(p), Var(p) = 2 p^2 / nu  ->  u(c) = c / sqrt(2 nu) (first order)
                est = Estimate(float(v), float(v) / math.sqrt(2.0 * nu), float(nu), "chi2")
            else:
                ub, v = c.upper95, c.value
                s_p = (ub**2 - v**2) / 1.6448536269514722
                u = math.sqrt(max(s_p, 0.0)) if v == 0 else s_p / (2.0 * v)
                est = Estimate(float(v), float(min(u, ub)), math.inf, "bound", float(ub))
            out.append(Measured(name, est.value, est.u, est, f"allan {axis}", "allan"))
    return out
