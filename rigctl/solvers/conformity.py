"""Conformity decisions: PASS / FAIL / INDETERMINATE of a measured value against its limits.

JCGM 106:2012 ("The role of measurement uncertainty in conformity assessment") and ISO
14253-1:2017. A measured parameter is described by the state of knowledge of its true value
given the measurement (:class:`Estimate`): normal or scaled-shifted Student t with the
result's degrees of freedom (value y, standard uncertainty u), or for an IEEE 952 noise
coefficient the scaled chi-square of its Allan fit. Its 95 % coverage interval [lo, hi] is
what the commands print (for the normal case lo, hi = y -+ U, U = k u, k = 1.96; Student t:
k = t_0.975(nu)).

Rules (:data:`RULES`):

* ``guarded`` (guarded acceptance and guarded rejection, JCGM 106 8.3 with guard band
  w = U, the ISO 14253-1 zones): PASS when the whole interval is inside the tolerance
  (lo >= TL and hi <= TU: acceptance interval [TL + U, TU - U]); FAIL when the whole interval is
  outside (hi < TL or lo > TU); otherwise INDETERMINATE. A PASS then carries a probability of
  false accept of at most 2.5 % (at a one-sided limit; at most 5 % between two limits closer
  than 2 U), a FAIL a probability of false reject of at most 2.5 %.
* ``simple`` (simple acceptance, JCGM 106 8.2, "shared risk"): PASS when y is inside the
  tolerance, FAIL otherwise; nothing is INDETERMINATE, and the risk is stated per
  parameter: for a PASS the probability that the true value is outside the tolerance
  (up to 50 % for y on a limit), for a FAIL the probability that it is inside.

The conformance probability p_c = P(TL <= true value <= TU | measurement) (JCGM 106 7.3) is
computed for every parameter under either rule from the same distribution.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from . import distributions as stats

PASS, FAIL, INDETERMINATE = "PASS", "FAIL", "INDETERMINATE"
RULES = ("guarded", "simple")
#: coverage probability of the intervals (and of the guard band) the decisions use
COVERAGE = 0.95
_Z_ONE = float(stats.norm.ppf(0.95))


@dataclass(frozen=True)
class Estimate:
    """What a measurement says about one parameter's true value (one unit, SI or any unit as
    long as the limits use the same one).

    kind ``"t"``: (true - value) / u follows Student t with ``dof`` degrees of freedom (normal
    for dof = inf). ``"chi2"``: a noise coefficient c = sqrt(p) whose p was estimated with
    Satterthwaite dof ``dof``: value^2 dof / p follows chi-square(dof) (the interval of
    rigctl.solvers.allan_fit). ``"bound"``: a noise term the data do not resolve: p = c^2
    follows N(value^2, s^2) truncated at 0, with s from the one-sided 95 % upper bound
    ``upper`` = sqrt(value^2 + 1.645 s); its interval is [0, upper] (nothing excludes zero),
    so against an upper limit it can PASS (upper <= TU) or be INDETERMINATE, never FAIL.
    """

    value: float
    u: float = 0.0
    dof: float = math.inf
    kind: str = "t"
    upper: float = math.nan

    def cdf(self, x: float) -> float:
        """P(true value <= x | measurement)."""
        if not math.isfinite(x):
            return 1.0 if x > 0 else 0.0
        if self.kind == "t":
            if self.u <= 0:
                return 1.0 if x >= self.value else 0.0
            z = (x - self.value) / self.u
            return float(stats.norm.cdf(z) if math.isinf(self.dof) else stats.t.cdf(z, self.dof))
        if x <= 0:
            return 0.0
        if self.kind == "chi2":
            return float(stats.chi2.sf(self.dof * self.value**2 / x**2, self.dof))
        if self.kind == "bound":
            m, s = self.value**2, (self.upper**2 - self.value**2) / _Z_ONE
            if s <= 0:
                return 1.0 if x >= self.value else 0.0
            f0 = stats.norm.cdf(-m / s)  # mass below 0, truncated away
            return float((stats.norm.cdf((x * x - m) / s) - f0) / (1.0 - f0))
        raise ValueError(f"unknown estimate kind {self.kind!r}")

    def interval(self, coverage: float = COVERAGE) -> tuple[float, float]:
        """The probabilistically symmetric coverage interval [lo, hi] ("bound": [0, upper])."""
        q = (1.0 - coverage) / 2.0
        if self.kind == "t":
            k = stats.norm.ppf(1 - q) if math.isinf(self.dof) else stats.t.ppf(1 - q, self.dof)
            return self.value - k * self.u, self.value + k * self.u
        if self.kind == "chi2":
            q_hi, q_lo = stats.chi2.ppf(1 - q, self.dof), stats.chi2.ppf(q, self.dof)
            if not (q_hi > 0 and q_lo > 0):  # dof ~ 0 (a term held where the model fails):
                return 0.0, math.inf  # its quantiles underflow; nothing is known
            return (self.value * math.sqrt(self.dof / q_hi),
                    self.value * math.sqrt(self.dof / q_lo))
        return 0.0, self.upper  # a term the data do not resolve: [0, one-sided 95 % bound]

    @property
    def coverage_factor(self) -> float:
        """k of U = k u for the symmetric kinds ("t"); NaN for the asymmetric ones."""
        if self.kind != "t":
            return math.nan
        q = (1.0 + COVERAGE) / 2.0
        return float(stats.norm.ppf(q) if math.isinf(self.dof) else stats.t.ppf(q, self.dof))


@dataclass(frozen=True)
class Decision:
    """The outcome for one parameter: verdict, the interval it was based on, the conformance
    probability and the risk the verdict carries (false accept for a PASS, false reject for a
    FAIL, NaN for INDETERMINATE)."""

    verdict: str
    rule: str
    lo: float
    hi: float
    p_conform: float
    risk: float


def decide(est: Estimate, lower: float | None, upper: float | None, rule: str = "guarded") -> Decision:
    """The verdict of ``est`` against the tolerance [lower, upper] (either may be None: a
    one-sided limit) under ``rule`` ("guarded" or "simple"; see the module docstring)."""
    if rule not in RULES:
        raise ValueError(f"decision rule {rule!r}: use one of {', '.join(RULES)}")
    if lower is None and upper is None:
        raise ValueError("a tolerance needs a lower or an upper limit")
    tl = -math.inf if lower is None else float(lower)
    tu = math.inf if upper is None else float(upper)
    if not tl < tu:
        raise ValueError(f"empty tolerance [{tl}, {tu}]")
    lo, hi = est.interval()
    pc = max(0.0, min(1.0, est.cdf(tu) - est.cdf(tl)))
    if rule == "guarded":
        if lo >= tl and hi <= tu:
            return Decision(PASS, rule, lo, hi, pc, 1.0 - pc)
        if hi < tl or lo > tu:
            return Decision(FAIL, rule, lo, hi, pc, pc)
        return Decision(INDETERMINATE, rule, lo, hi, pc, math.nan)
    inside = tl <= est.value <= tu
    return Decision(PASS if inside else FAIL, rule, lo, hi, pc, 1.0 - pc if inside else pc)


def overall(verdicts: list[str]) -> str:
    """FAIL if any FAIL, else INDETERMINATE if any is (or nothing was decided), else PASS."""
    if FAIL in verdicts:
        return FAIL
    if not verdicts or INDETERMINATE in verdicts:
        return INDETERMINATE
    return PASS
