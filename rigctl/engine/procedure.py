"""YAML procedures: loading, ``include:``, parameters, and compilation into a plan of steps.

A procedure compiles into a list of :class:`Step` records that never touch hardware (the
engine executes them against whatever rig it is given). The language is documented in
docs/procedures.md.

The file is read with the typed settings of rigctl.settings, one model per concept:
:class:`ProcedureFile` (the top level), :class:`ParameterSettings` (a parameter's long form),
:class:`SamplingSettings` (``defaults:`` and a step's sampling keys), :class:`SettleSettings`,
:class:`RepeatSettings`, and one model per step kind (:data:`STEP_MODELS`). Their one validator,
:func:`rigctl.settings.parse`, gives every error its file and line and a "did you mean" for an
unknown key; the compiler here only includes files, substitutes ``${parameters}``, and expands
each validated step into the plan.
"""
from __future__ import annotations

import math
import re
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import yaml

from .. import schema as S
from ..config.config import TableLimits
from ..frames import north_pointing_angles
from ..settings import Settings, as_written, mapping, number, parse, setting, text
from ..settings import duration as seconds
from ..errors import InputError, InputErrors
from ..yamlio import LocDict, LocList, load_file_text

#: step kinds that command the climatic chamber (docs/thermal.md)
CHAMBER_KINDS = ("chamber-set", "chamber-ramp", "chamber-wait")
SOLVERS = ("accel24", "gyro-rate", "closed-loop", "allan", "sync", "report")
#: Body axis -> gimbal index [outer, middle, inner] that turns about it at zero angles.
RATE_AXIS_GIMBAL = {"x": 2, "y": 1, "z": 0}
_PARAM = re.compile(r"^\$\{([A-Za-z_][A-Za-z0-9_]*)\}$")
AXES = ("x", "y", "z")
DIRECTIONS = ("forward", "reverse")


@dataclass(frozen=True)
class SettlePolicy:
    """When the table counts as settled: reported in position (or at rate) AND every axis inside
    its position window (rad) and rate window (rad/s) continuously for ``hold_s``; give up after
    ``timeout_s``."""

    position_window: float = math.radians(0.01)
    rate_window: float = math.radians(0.05)
    hold_s: float = 2.0
    timeout_s: float = 120.0


@dataclass(frozen=True)
class Step:
    """One compiled step. Angles rad [outer, middle, inner]; rates rad/s, NaN = hold position."""

    index: int
    kind: str
    label: str
    angles: np.ndarray
    rates: np.ndarray
    sample_s: float
    discard_s: float = 0.0
    settle: SettlePolicy = field(default_factory=SettlePolicy)
    prompt: str | None = None
    expected_taps: int | None = None
    solvers: tuple[str, ...] = ()
    file: str = ""
    line: int = 0
    #: chamber steps: setpoint_c (None = keep), rate_c_per_min, stable_band_c, stable_for_s,
    #: air_band_c, timeout_s (docs/thermal.md)
    chamber: dict[str, Any] | None = None

    @property
    def is_motion(self) -> bool:
        return self.kind != "solve"

    @property
    def rate_mode(self) -> bool:
        return bool(np.any(~np.isnan(self.rates)))

    def describe(self) -> str:
        if self.kind == "solve":
            return f"solve: {', '.join(self.solvers)}"
        if self.chamber is not None:
            c = self.chamber
            sp = "current set point" if c.get("setpoint_c") is None else f"{c['setpoint_c']:g} degC"
            if self.kind == "chamber-ramp":
                return f"{self.kind:<12} {self.label:<28} to {sp} at {c['rate_c_per_min']:g} degC/min"
            if self.kind == "chamber-wait":
                return (f"{self.kind:<12} {self.label:<28} {sp}: IMU within {c['stable_band_c']:g} degC "
                        f"for {c['stable_for_s']:g} s")
            return f"{self.kind:<12} {self.label:<28} {sp}"
        ang = ", ".join(f"{math.degrees(a):g}" for a in self.angles)
        text = f"{self.kind:<12} {self.label:<28} angles [{ang}] deg"
        if self.rate_mode:
            r = [f"{math.degrees(x):+g}" for x in self.rates if not math.isnan(x)]
            text += f", rate {r[0]} deg/s"
        return text


@dataclass
class Procedure:
    """A loaded procedure: its name, resolved parameters, the plan, and the source texts."""

    name: str
    path: str
    description: str
    parameters: dict[str, Any]
    steps: list[Step]
    sources: dict[str, str]

    @property
    def text(self) -> str:
        """The procedure's source text and that of every included file."""
        return "\n".join(f"# ---- {p}\n{t}" for p, t in self.sources.items())


def parse_overrides(items: list[str] | None) -> dict[str, Any]:
    """``-p name=value`` options into a dict; values are read as YAML scalars (safe loader)."""
    out: dict[str, Any] = {}
    for item in items or []:
        if "=" not in item:
            raise InputError(f"-p {item!r}: expected name=value", hint="for example -p warmup='5 min'")
        name, value = item.split("=", 1)
        try:
            out[name.strip()] = yaml.safe_load(value) if value.strip() else ""
        except yaml.YAMLError:
            out[name.strip()] = value
    return out


# -- the procedure file's settings: one model per concept (rigctl.settings) ---------------------
def _description(d: LocDict, key: str, default: Any = "") -> str:
    return "" if d[key] is None else str(d[key])


def _triplet(d: LocDict, key: str, default: Any = None) -> tuple[float, ...]:
    """[outer, middle, inner], degrees."""
    return tuple(S.number_list(d, key, length=3))


def _angle_rows(d: LocDict, key: str, default: Any = None) -> tuple[tuple[float, ...], ...]:
    """A list of [outer, middle, inner] in degrees, each as written (for the step's label)."""
    rows = S.get_list(d, key, min_length=1)
    for j, row in enumerate(rows):
        if not (isinstance(row, list) and len(row) == 3 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in row)):
            raise S.item_error(d, key, rows, j, f"orientation {j + 1} must be [outer, middle, inner] in degrees")
    return tuple(tuple(row) for row in rows)


def _one_of(choices: tuple[str, ...], message: str) -> Any:
    """A reader of a non-empty list whose entries are each one of ``choices``; ``message`` is
    formatted with the wrong entry."""
    def read(d: LocDict, key: str, default: Any = None) -> tuple[str, ...]:
        items = S.get_list(d, key, min_length=1)
        for j, x in enumerate(items):
            if not isinstance(x, str) or x not in choices:
                raise S.item_error(d, key, items, j, message.format(x),
                                   S.did_you_mean(str(x), choices, "choose from"))
        return tuple(items)
    return read


def _magnitudes(d: LocDict, key: str, default: Any = None) -> tuple[float, ...]:
    rates = S.number_list(d, key)
    for r in rates:
        if r <= 0:
            raise S.error(d, key, f"rates are magnitudes (> 0), got {r}", "list forward/reverse under 'directions'")
    return tuple(rates)


def _settle(d: LocDict, key: str, default: Any = None) -> SettleSettings | None:
    """``settle: {...}``; ``settle:`` with nothing = not given (the defaults' policy applies)."""
    if d[key] is None:
        return None
    return parse(SettleSettings, S.require_mapping(d[key], "'settle'", d, key), "'settle'")


def _angles_field() -> Any:
    """``angles_deg``: where the table holds, [outer, middle, inner] in degrees (default zero)."""
    return setting((0.0, 0.0, 0.0), read=_triplet)


def _settle_field() -> Any:
    return setting(None, read=_settle)


@dataclass(frozen=True, kw_only=True)
class SettleSettings(Settings):
    """``settle:`` (a step's, or under ``defaults:``): when the table counts as settled."""

    position_window_deg: float = number(0.01, minimum=1e-6)
    rate_window_dps: float = number(0.05, minimum=1e-6)
    hold: float = seconds(2.0)
    timeout: float = seconds(120.0, positive=True)

    def policy(self) -> SettlePolicy:
        return SettlePolicy(position_window=math.radians(self.position_window_deg),
                            rate_window=math.radians(self.rate_window_dps), hold_s=self.hold,
                            timeout_s=self.timeout)


@dataclass(frozen=True, kw_only=True)
class SamplingSettings(Settings):
    """The sampling policy: a file's ``defaults:`` (for its steps and its includes), and the same
    keys on a step (each step kind takes those its model declares). None = not given here."""

    #: what applies where neither the step nor any ``defaults:`` gives a value
    SAMPLE_S: ClassVar[float] = 30.0
    DISCARD_S: ClassVar[float] = 1.0
    settle: SettleSettings | None = _settle_field()
    sample: float | None = seconds(None)
    discard: float | None = seconds(None)

    @classmethod
    def of(cls, s: Settings) -> SamplingSettings:
        """The sampling keys a step's settings hold (None for those its kind does not take)."""
        return cls(**{f.name: getattr(s, f.name, None) for f in fields(cls)})

    def over(self, outer: SamplingSettings) -> SamplingSettings:
        """These settings where given, else ``outer``'s."""
        return SamplingSettings(**{f.name: getattr(outer, f.name) if getattr(self, f.name) is None
                                   else getattr(self, f.name) for f in fields(self)})

    def resolve(self) -> tuple[SettlePolicy, float, float]:
        """(settling policy, sampling window s, discarded transient s), defaults filled in."""
        return (self.settle.policy() if self.settle is not None else SettlePolicy(),
                self.SAMPLE_S if self.sample is None else self.sample,
                self.DISCARD_S if self.discard is None else self.discard)


@dataclass(frozen=True, kw_only=True)
class ParameterSettings(Settings):
    """A parameter in its long form, ``name: {default: ..., description: ..., unit: ...}`` (the
    short form ``name: value`` is the default alone)."""

    default: Any = as_written()
    description: str = text("")
    unit: str = text("")


@dataclass(frozen=True, kw_only=True)
class ProcedureFile(Settings):
    """A procedure file's top level. ``defaults`` and ``steps`` are read raw here: their values
    may hold ``${parameters}``, substituted before :class:`SamplingSettings` and the steps'
    models read them."""

    procedure: str | None = text(None)
    description: str = setting("", read=_description)
    parameters: LocDict | None = mapping(None)
    defaults: Any = as_written(None)
    steps: list = setting(read=S.get_list)


@dataclass(frozen=True, kw_only=True)
class RepeatSettings(Settings):
    """``repeat``: its steps ``count`` times."""

    count: int = number(minimum=1, maximum=10000, integer=True)
    steps: list = setting(read=S.get_list, min_length=1)


@dataclass(frozen=True, kw_only=True)
class WarmupStep(Settings):
    """``warmup``: go to the angles, settle, record for the duration (one segment)."""

    duration: float = seconds(positive=True)
    angles_deg: tuple[float, ...] = _angles_field()
    label: str = text("warm-up")


@dataclass(frozen=True, kw_only=True)
class CaptureStep(Settings):
    """``capture``: a static capture (for Allan analysis)."""

    duration: float = seconds(positive=True)
    angles_deg: tuple[float, ...] = _angles_field()
    label: str = text("static capture")
    settle: SettleSettings | None = _settle_field()
    discard: float | None = seconds(None)


@dataclass(frozen=True, kw_only=True)
class WaitStep(Settings):
    """``wait``: hold and record (with a prompt to the operator)."""

    duration: float = seconds()
    prompt: str | None = text(None)
    angles_deg: tuple[float, ...] = _angles_field()
    label: str = text("wait")


@dataclass(frozen=True, kw_only=True)
class TapsStep(Settings):
    """``taps``: prompt the operator, record the window in which the taps fall."""

    count: int = number(minimum=1, maximum=10000, integer=True)
    prompt: str | None = text(None)
    duration: float = seconds(60.0, positive=True)
    angles_deg: tuple[float, ...] = _angles_field()
    label: str | None = text(None)
    settle: SettleSettings | None = _settle_field()


def setpoint(required: bool = True) -> Any:
    return number(MISSING if required else None, minimum=-100.0, maximum=200.0)


@dataclass(frozen=True, kw_only=True)
class ChamberSetStep(Settings):
    """``chamber-set``: a new chamber set point (a step), and go on (docs/thermal.md)."""

    setpoint_c: float = setpoint()
    label: str | None = text(None)


@dataclass(frozen=True, kw_only=True)
class ChamberRampStep(Settings):
    """``chamber-ramp``: the chamber ramps to the set point while the next steps run."""

    setpoint_c: float = setpoint()
    rate_c_per_min: float = number(minimum=0.01, maximum=100.0)
    label: str | None = text(None)


@dataclass(frozen=True, kw_only=True)
class ChamberWaitStep(Settings):
    """``chamber-wait``: soak until the chamber and the IMU are stable (None: the current set
    point)."""

    setpoint_c: float | None = setpoint(required=False)
    stable_band_c: float = number(0.1, minimum=0.001, maximum=20.0)
    stable_for: float = seconds(300.0, positive=True)
    air_band_c: float = number(1.0, minimum=0.01, maximum=50.0)
    timeout: float = seconds(4 * 3600.0, positive=True)
    expect: float | None = seconds(None)
    angles_deg: tuple[float, ...] = _angles_field()
    label: str | None = text(None)


@dataclass(frozen=True, kw_only=True)
class SolveStep(Settings):
    """``solve``: solvers run after the recording is closed."""

    solvers: tuple[str, ...] = setting(read=_one_of(SOLVERS, "unknown solver {!r}"))


@dataclass(frozen=True, kw_only=True)
class OrientationsStep(Settings):
    """``orientations``: a list of [outer, middle, inner], or the 24-position pattern."""

    angles_deg: tuple[tuple[float, ...], ...] | None = setting(None, read=_angle_rows)
    pattern: str | None = text(None, choices=("24-position",))
    axes: tuple[str, ...] = setting(AXES, read=_one_of(AXES, "axis {!r} must be x, y or z"))
    step_deg: float = number(45.0, minimum=1e-3, maximum=360.0)
    count: int = number(8, minimum=1, maximum=360, integer=True)
    label: str | None = text(None)
    settle: SettleSettings | None = _settle_field()
    sample: float | None = seconds(None)
    discard: float | None = seconds(None)

    def check(self, d: LocDict) -> None:
        if (self.angles_deg is None) == (self.pattern is None):
            raise S.error(d, None, "'orientations' needs either 'angles_deg' (a list of "
                          "[outer, middle, inner]) or 'pattern: 24-position'")


@dataclass(frozen=True, kw_only=True)
class RatesStep(Settings):
    """``rates``: one window per axis x rate x direction."""

    rates_dps: tuple[float, ...] = setting(read=_magnitudes)
    axes: tuple[str, ...] = setting(AXES, read=_one_of(AXES, "axis {!r} must be x, y or z"))
    directions: tuple[str, ...] = setting(DIRECTIONS, read=_one_of(
        DIRECTIONS, "direction {!r} must be forward or reverse"))
    dwell: float | None = seconds(None)
    revolutions: float | None = number(None, minimum=0.01, allow_none=True)
    angles_deg: tuple[float, ...] = _angles_field()
    label: str | None = text(None)
    settle: SettleSettings | None = _settle_field()
    sample: float | None = seconds(None)
    discard: float | None = seconds(None)

    def check(self, d: LocDict) -> None:
        if "dwell" in d and "revolutions" in d:
            raise S.error(d, "revolutions", "give either 'dwell' or 'revolutions', not both")


#: step kind -> its settings (besides ``include:`` and ``repeat:``, which the compiler reads)
STEP_MODELS: dict[str, type[Settings]] = {
    "warmup": WarmupStep, "orientations": OrientationsStep, "rates": RatesStep, "capture": CaptureStep,
    "taps": TapsStep, "wait": WaitStep, "solve": SolveStep, "chamber-set": ChamberSetStep,
    "chamber-ramp": ChamberRampStep, "chamber-wait": ChamberWaitStep}
STEP_KINDS = (*STEP_MODELS, "repeat")


def _or(value: Any, default: Any) -> Any:
    return default if value is None else value


class _Compiler:
    def __init__(self, overrides: dict[str, Any], limits: TableLimits | None) -> None:
        self.overrides = overrides
        self.limits = limits
        self.params: dict[str, Any] = {}
        self.param_lines: dict[str, tuple[str, int]] = {}
        #: (file, line) of each value a ``-p`` override replaced -> the parameter's name
        self.override_sites: dict[tuple[str | None, int | None], str] = {}
        self.sources: dict[str, str] = {}
        self.steps: list[Step] = []
        self.errors: list[InputError] = []
        self.stack: list[Path] = []
        self.description = ""
        self.steps_line = 1

    # -- files -------------------------------------------------------------------------------
    def load(self, path: Path, resolved: Path, inc_parent: Any = None,
             inc_key: Any = None) -> tuple[ProcedureFile, LocDict]:
        if resolved in self.stack:
            chain = " -> ".join(p.name for p in [*self.stack, resolved])
            raise S.error(inc_parent, inc_key, f"include cycle: {chain}", "remove the circular include")
        try:
            raw, text = load_file_text(path)
        except InputError as exc:
            if inc_parent is not None and exc.message == "file not found":
                raise S.error(inc_parent, inc_key, f"included file {str(path)!r} not found",
                              "paths are relative to the including file") from None
            raise
        if raw is None:
            raise InputError("the procedure file is empty", path, 1, "add 'steps:' with a list of steps")
        if not isinstance(raw, dict):
            raise InputError("a procedure must be a mapping with a 'steps:' list", path, 1,
                             "see docs/procedures.md")
        m = S.require_mapping(raw, "a procedure")
        f = parse(ProcedureFile, m, "the procedure")
        self.sources[str(path)] = text
        return f, m

    def declare_params(self, params: LocDict | None) -> None:
        for name, spec in (params or {}).items():
            if not isinstance(name, str) or not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", name):
                raise S.error(params, name, f"parameter name {name!r} is not a valid identifier")
            if isinstance(spec, dict):
                default = parse(ParameterSettings, S.require_mapping(spec, f"parameter {name!r}"),
                                f"parameter {name!r}").default
            else:
                default = spec
            if name not in self.params:  # the including (outer) file's default wins
                self.params[name] = default
                self.param_lines[name] = (params.file, params.line_of(name))

    def check_overrides(self) -> None:
        for name in self.overrides:
            if name not in self.params:
                raise InputError(f"-p {name}: the procedure has no parameter {name!r}",
                                 hint=S.did_you_mean(name, sorted(self.params), "its parameters"))

    def value_of(self, name: str) -> Any:
        return self.overrides[name] if name in self.overrides else self.params[name]

    def blame_override(self, exc: InputError) -> InputError:
        """``exc`` about a value a ``-p NAME=VALUE`` option put there, reworded to name the option
        the user typed rather than the procedure line that uses it; any other error unchanged."""
        name = self.override_sites.get((exc.file, exc.line))
        if name is None:
            return exc
        message = re.sub(r"^'[^']*':\s*", "", exc.message)  # "'duration': cannot read ..." -> "cannot read ..."
        return InputError(f"-p {name}={self.overrides[name]!r}: {message}",
                          hint=f"parameter {name!r} is used at {exc.file}:{exc.line}")

    def subst(self, value: Any, where: Any, key: Any) -> Any:
        """Replace ``${name}`` values by the parameter's value, recursively."""
        if isinstance(value, str):
            m = _PARAM.match(value.strip())
            if m:
                if m.group(1) not in self.params:
                    raise S.error(where, key, f"unknown parameter ${{{m.group(1)}}}",
                                  "declare it under 'parameters:'")
                if m.group(1) in self.overrides:
                    self.override_sites[S.where(where, key)] = m.group(1)
                return self.value_of(m.group(1))
            if "${" in value:
                raise S.error(where, key, f"{value!r}: a parameter must be the whole value, as '${{name}}'")
            return value
        if isinstance(value, LocDict):
            out = LocDict()
            out.file, out.line, out.key_lines = value.file, value.line, dict(value.key_lines)
            for k, v in value.items():
                out[k] = self.subst(v, value, k)
            return out
        if isinstance(value, LocList):
            out_l = LocList(self.subst(v, value, i) for i, v in enumerate(value))
            out_l.file, out_l.line, out_l.item_lines = value.file, value.line, list(value.item_lines)
            return out_l
        return value

    # -- steps -------------------------------------------------------------------------------
    def compile_file(self, path: Path, defaults: SamplingSettings | None = None,
                     inc_parent: Any = None, inc_key: Any = None) -> str:
        resolved = path.resolve()
        f, m = self.load(path, resolved, inc_parent, inc_key)
        self.declare_params(f.parameters)
        if not self.stack:
            self.description = f.description
        self.stack.append(resolved)
        try:
            local = defaults or SamplingSettings()
            if "defaults" in m:
                d = S.require_mapping(self.subst(f.defaults, m, "defaults"), "'defaults'", m, "defaults")
                local = parse(SamplingSettings, d, "'defaults'").over(local)
            if not self.stack[:-1]:
                self.steps_line = m.line_of("steps")
            for i, item in enumerate(f.steps):
                try:
                    self.compile_item(path, f.steps, i, item, local)
                except InputError as exc:
                    self.errors.append(exc)
        finally:
            self.stack.pop()
        return f.procedure if f.procedure is not None else path.stem

    def compile_item(self, path: Path, steps: LocList, i: int, item: Any, defaults: SamplingSettings) -> None:
        if not isinstance(item, dict) or len(item) != 1:
            raise S.error(steps, i, "each step must be one 'kind: {options}' entry",
                          f"kinds: {', '.join(STEP_KINDS)}, or 'include: FILE'")
        item = S.require_mapping(item, "a step")
        (kind, body), = item.items()
        if kind == "include":
            target = self.subst(body, item, kind)
            if not isinstance(target, str):
                raise S.error(item, kind, "include takes a file name")
            self.compile_file(path.parent / target, defaults, item, kind)
            return
        if kind not in STEP_KINDS:
            S.check_keys(item, (*STEP_KINDS, "include"), "the step")  # raises: unknown kind
        body = self.subst(body if body is not None else LocDict(), item, kind)
        opts = S.require_mapping(body, f"the {kind!r} step", item, kind)
        opts.line, opts.file = item.line_of(kind), item.file  # "missing ..." points at the step
        if kind == "repeat":
            r = parse(RepeatSettings, opts, "'repeat'")
            for _ in range(r.count):
                for j, sub in enumerate(r.steps):
                    self.compile_item(path, r.steps, j, sub, defaults)
            return
        s = parse(STEP_MODELS[kind], opts, f"'{kind}'")
        getattr(self, f"_{kind.replace('-', '_')}")(s, opts, defaults)

    def add(self, o: LocDict, key: Any, **kw: Any) -> None:
        nan3 = np.full(3, np.nan)
        step = Step(index=len(self.steps), file=o.file, line=o.line_of(key) if key else o.line,
                    rates=kw.pop("rates", nan3), **kw)
        if self.limits is not None:
            try:
                self.limits.check(step.angles, step.rates)
            except ValueError as exc:
                raise InputError(str(exc), step.file, step.line,
                                 "change the demand or the table limits in the config") from None
        self.steps.append(step)

    @staticmethod
    def _radians(deg: tuple[float, ...]) -> np.ndarray:
        return np.radians(np.asarray(deg, dtype=float))

    def _warmup(self, s: WarmupStep, o: LocDict, d: SamplingSettings) -> None:
        self.add(o, "duration", kind="warmup", label=s.label, angles=self._radians(s.angles_deg),
                 sample_s=s.duration, settle=d.resolve()[0])

    def _capture(self, s: CaptureStep, o: LocDict, d: SamplingSettings) -> None:
        policy, _, discard = SamplingSettings.of(s).over(d).resolve()
        self.add(o, "duration", kind="capture", label=s.label, angles=self._radians(s.angles_deg),
                 sample_s=s.duration, discard_s=discard, settle=policy)

    def _wait(self, s: WaitStep, o: LocDict, d: SamplingSettings) -> None:
        self.add(o, "duration", kind="wait", label=s.label, angles=self._radians(s.angles_deg),
                 sample_s=s.duration, prompt=s.prompt, settle=d.resolve()[0])

    def _taps(self, s: TapsStep, o: LocDict, d: SamplingSettings) -> None:
        policy = SamplingSettings.of(s).over(d).resolve()[0]
        self.add(o, "count", kind="taps", label=_or(s.label, f"{s.count} taps"),
                 angles=self._radians(s.angles_deg), sample_s=s.duration,
                 prompt=_or(s.prompt, f"Tap the IMU {s.count} times"),
                 expected_taps=s.count, settle=policy)

    # -- the climatic chamber (docs/thermal.md) ----------------------------------------------
    def _chamber_set(self, s: ChamberSetStep, o: LocDict, d: SamplingSettings) -> None:
        self.add(o, "setpoint_c", kind="chamber-set", label=_or(s.label, f"chamber {s.setpoint_c:g} degC"),
                 angles=np.zeros(3), sample_s=0.0, chamber={"setpoint_c": s.setpoint_c, "rate_c_per_min": None})

    def _chamber_ramp(self, s: ChamberRampStep, o: LocDict, d: SamplingSettings) -> None:
        self.add(o, "setpoint_c", kind="chamber-ramp", label=_or(s.label, f"ramp to {s.setpoint_c:g} degC"),
                 angles=np.zeros(3), sample_s=0.0,
                 chamber={"setpoint_c": s.setpoint_c, "rate_c_per_min": s.rate_c_per_min})

    def _chamber_wait(self, s: ChamberWaitStep, o: LocDict, d: SamplingSettings) -> None:
        sp = s.setpoint_c
        c = {"setpoint_c": sp, "rate_c_per_min": None, "stable_band_c": s.stable_band_c,
             "stable_for_s": s.stable_for, "air_band_c": s.air_band_c, "timeout_s": s.timeout}
        label = _or(s.label, "soak" + (f" at {sp:g} degC" if sp is not None else ""))
        self.add(o, "setpoint_c" if sp is not None else None, kind="chamber-wait", label=label,
                 angles=self._radians(s.angles_deg), settle=d.resolve()[0],
                 sample_s=s.expect if s.expect is not None else s.stable_for, chamber=c)

    def _solve(self, s: SolveStep, o: LocDict, d: SamplingSettings) -> None:
        self.add(o, "solvers", kind="solve", label="solve", angles=np.zeros(3), sample_s=0.0,
                 solvers=s.solvers)

    def _orientations(self, s: OrientationsStep, o: LocDict, d: SamplingSettings) -> None:
        policy, sample, discard = SamplingSettings.of(s).over(d).resolve()
        if s.angles_deg is not None:
            for row in s.angles_deg:
                self.add(o, "angles_deg", kind="orientation", label=f"angles {list(row)} deg",
                         angles=self._radians(row), sample_s=sample, discard_s=discard, settle=policy)
            return
        for ax in s.axes:
            for k in range(s.count):
                phi = k * s.step_deg
                self.add(o, "pattern", kind="orientation", label=f"{ax} north, phi {phi:g} deg",
                         angles=np.asarray(north_pointing_angles(ax, math.radians(phi))),
                         sample_s=sample, discard_s=discard, settle=policy)

    def _rates(self, s: RatesStep, o: LocDict, d: SamplingSettings) -> None:
        policy, sample, discard = SamplingSettings.of(s).over(d).resolve()
        start = self._radians(s.angles_deg)
        for ax in s.axes:
            for r in s.rates_dps:
                for dname in s.directions:
                    w = math.radians(r) * (1 if dname == "forward" else -1)
                    vec = np.full(3, np.nan)
                    vec[RATE_AXIS_GIMBAL[ax]] = w
                    if s.revolutions is not None:
                        window = s.revolutions * 2 * math.pi / abs(w)
                    elif s.dwell is not None:
                        window = s.dwell
                    else:
                        window = sample
                    self.add(o, "rates_dps", kind="rate", label=f"{ax} {dname} {r:g} deg/s",
                             angles=start, rates=vec, sample_s=window, discard_s=discard,
                             settle=policy)


def load_procedure(path: str | Path, overrides: dict[str, Any] | None = None,
                   limits: TableLimits | None = None) -> Procedure:
    """Load, include, substitute parameters, validate and compile a procedure.

    Raises InputError (or InputErrors listing each) naming the file and line of every problem,
    including demands outside ``limits`` -- all before anything moves.
    """
    p = Path(path)
    c = _Compiler(overrides or {}, limits)
    try:
        m_name = c.compile_file(p)
    except InputError as exc:
        raise c.blame_override(exc) from None
    c.check_overrides()
    if c.errors:
        errors = [c.blame_override(e) for e in c.errors]
        raise InputErrors(errors) if len(errors) > 1 else errors[0]
    if not c.steps:
        raise InputError("the procedure has no steps", p, c.steps_line, "list at least one step")
    return Procedure(name=m_name, path=str(p), description=c.description,
                     parameters={k: c.value_of(k) for k in c.params}, steps=c.steps, sources=c.sources)
