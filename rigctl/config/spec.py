"""Specification files: acceptance limits per parameter (``--spec SPEC.yaml``).

A spec is a YAML mapping (configs/spec-example.yaml)::

    spec: MEMS IMU acceptance, example          # a name (printed and stored)
    decision_rule: guarded                      # guarded (default) or simple
    parameters:
      accel_bias_[xyz]: {within: 5 mg}          # -5 mg .. +5 mg
      gyro_angle_random_walk_[xyz]: {upper: 0.3 deg/sqrt(h)}
      accel_scale_error_x: {lower: -2000 ppm, upper: 2000 ppm}

Parameter keys are the display names of the results (``rigctl calibrate`` / ``rigctl allan``
print them in the first column, without the unit) or shell-style patterns of them
(``*``, ``?``, ``[xyz]``). Each has ``lower`` and/or ``upper``, or ``within`` (a symmetric
+-limit), each a number with the parameter's display unit (``5 mg``) or its SI unit; a number
without a unit is in the display unit. The file is read by the typed settings of rigctl.settings
(:class:`SpecSettings`, one :class:`LimitSettings` per parameter): errors name the file and line,
and an unknown key gets a "did you mean".
"""
from __future__ import annotations

import fnmatch
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import schema as S
from ..display_units import NOISE_SI, NOISE_UNITS, SUFFIXES, Display
from ..settings import Settings, mapping, parse, setting, text
from ..solvers.conformity import RULES
from ..errors import InputError
from ..yamlio import LocDict, load_file

_QTY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*?)\s*$")
#: every unit a limit may be written in (display units and SI units of the results)
KNOWN_UNITS = frozenset([u for _, u, _, _ in SUFFIXES] + [si for _, _, _, si in SUFFIXES]
                        + [u for t in NOISE_UNITS.values() for u, _ in t.values()]
                        + [u for t in NOISE_SI.values() for u in t.values()] + ["ppm", "urad", "1"])


@dataclass(frozen=True)
class Limit:
    """One spec entry: a pattern of display names, limits as written (number, unit or ''),
    and where it was written."""

    pattern: str
    lower: tuple[float, str] | None
    upper: tuple[float, str] | None
    file: str
    line: int

    def matches(self, base: str) -> bool:
        return fnmatch.fnmatchcase(base, self.pattern)

    def si(self, disp: Display) -> tuple[float | None, float | None]:
        """(lower, upper) in SI for a parameter shown as ``disp``; InputError (file, line) when
        a limit's unit does not fit that parameter."""
        def conv(lim: tuple[float, str] | None) -> float | None:
            if lim is None:
                return None
            v, unit = lim
            if unit in ("", disp.unit):
                return disp.to_si(v)
            if unit == disp.si_unit:
                return v
            raise InputError(f"limit of {self.pattern!r} in {unit!r}, but {disp.base} is in "
                             f"{disp.unit} (SI {disp.si_unit})", self.file, self.line,
                             hint=f"write the limit in {disp.unit}")
        return conv(self.lower), conv(self.upper)

    def text(self, disp: Display) -> str:
        """The tolerance as people read it, in the display unit: '[-5, 5] mg', '<= 0.3 deg/sqrt(h)'."""
        lo, hi = self.si(disp)
        lo_d, hi_d = disp.value(lo) if lo is not None else None, disp.value(hi) if hi is not None else None
        if lo_d is not None and hi_d is not None:
            return f"[{lo_d:g}, {hi_d:g}] {disp.unit}"
        return f"<= {hi_d:g} {disp.unit}" if hi_d is not None else f">= {lo_d:g} {disp.unit}"


@dataclass(frozen=True)
class Spec:
    """A loaded specification."""

    name: str
    rule: str
    limits: tuple[Limit, ...]
    path: str

    def limit_for(self, base: str) -> Limit | None:
        """The first entry whose pattern matches the display name ``base``."""
        return next((lim for lim in self.limits if lim.matches(base)), None)


def _quantity(m: LocDict, key: str, default: Any = None) -> tuple[float, str]:
    """A limit as written: (number, unit or '')."""
    v = m[key]
    if isinstance(v, bool):
        raise S.error(m, key, f"{key!r} must be a number with its unit, e.g. '5 mg'")
    if isinstance(v, (int, float)):
        num, unit = float(v), ""
    elif isinstance(v, str) and _QTY.match(v):
        g = _QTY.match(v)
        num, unit = float(g.group(1)), g.group(2)
    else:
        raise S.error(m, key, f"cannot read {v!r} as a limit", "write a number and its unit, e.g. '5 mg'")
    if not math.isfinite(num):
        raise S.error(m, key, f"{key!r} must be finite")
    if unit and unit not in KNOWN_UNITS:
        raise S.error(m, key, f"unknown unit {unit!r} in {v!r}",
                      "use the unit rigctl prints for that parameter (mg, deg/h, ppm, urad, "
                      "deg/sqrt(h), m/s/sqrt(h), ...)")
    return num, unit


def quantity() -> Any:
    return setting(None, read=_quantity)


@dataclass(frozen=True, kw_only=True)
class LimitSettings(Settings):
    """One parameter's limits: ``lower`` and/or ``upper``, or ``within`` (a symmetric
    +-limit), each a number with its unit."""

    lower: tuple[float, str] | None = quantity()
    upper: tuple[float, str] | None = quantity()
    within: tuple[float, str] | None = quantity()

    def check(self, d: LocDict) -> None:
        if self.within is not None and (self.lower is not None or self.upper is not None):
            raise S.error(d, "within", "give either 'within' or 'lower'/'upper', not both")
        if self.within is not None and self.within[0] <= 0:
            raise S.error(d, "within", "'within' must be positive (the +- half-width)")

    def bounds(self) -> tuple[tuple[float, str] | None, tuple[float, str] | None]:
        """(lower, upper) as written (``within`` as -w, +w)."""
        if self.within is not None:
            (w, unit) = self.within
            return (-w, unit), (w, unit)
        return self.lower, self.upper


@dataclass(frozen=True, kw_only=True)
class SpecSettings(Settings):
    """A spec file's top level; ``parameters`` maps display names (or patterns) to
    :class:`LimitSettings`."""

    spec: str | None = text(None)
    decision_rule: str = text("guarded", choices=RULES)
    parameters: LocDict | None = mapping(None)

    def check(self, d: LocDict) -> None:
        if self.parameters is None:
            raise S.error(d, None, "the spec has no 'parameters' section",
                          "add 'parameters:' with limits, as in configs/spec-example.yaml")


def load_spec(path: str | Path, rule: str | None = None) -> Spec:
    """Read and validate a spec file; ``rule`` overrides its decision_rule. InputError with
    file and line on any problem."""
    p = Path(path)
    raw = load_file(p)
    if raw is None:
        raise InputError("the spec file is empty", p, hint="see configs/spec-example.yaml")
    f = parse(SpecSettings, S.require_mapping(raw, "a spec file"), "the spec file")
    params = f.parameters
    limits = []
    for key, entry in params.items():
        line = params.line_of(key)
        if not isinstance(key, str) or not key.strip():
            raise InputError("a parameter name must be text", str(p), line)
        e = S.require_mapping(entry, f"the limits of {key!r}", params, key)
        lo, hi = parse(LimitSettings, e, f"the limits of {key!r}").bounds()
        if lo is None and hi is None:
            raise InputError(f"{key!r} has no limit", str(p), line, "give lower, upper or within")
        if lo is not None and hi is not None and lo[1] == hi[1] and not lo[0] < hi[0]:
            raise S.error(e, "upper", f"{key!r}: upper {hi[0]:g} is not above lower {lo[0]:g}")
        limits.append(Limit(key.strip(), lo, hi, str(p), line))
    return Spec(name=f.spec if f.spec is not None else p.stem, rule=rule or f.decision_rule,
                limits=tuple(limits), path=str(p))
