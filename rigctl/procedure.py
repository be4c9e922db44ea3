"""YAML procedures: loading, ``include:``, parameters, and compilation into a plan of steps.

A procedure compiles into a list of :class:`Step` records that never touch hardware (the
engine executes them against whatever rig it is given). The language is documented in
docs/procedures.md.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from . import schema as S
from .config import TableLimits
from .frames import north_pointing_angles
from .yamlio import InputError, InputErrors, LocDict, LocList, load_file

STEP_KINDS = ("warmup", "orientations", "rates", "capture", "taps", "wait", "solve",
              "chamber-set", "chamber-ramp", "chamber-wait", "repeat")
#: step kinds that command the climatic chamber (docs/thermal.md)
CHAMBER_KINDS = ("chamber-set", "chamber-ramp", "chamber-wait")
SOLVERS = ("accel24", "gyro-rate", "closed-loop", "allan", "sync", "report")
#: Body axis -> gimbal index [outer, middle, inner] that turns about it at zero angles.
RATE_AXIS_GIMBAL = {"x": 2, "y": 1, "z": 0}
_PARAM = re.compile(r"^\$\{([A-Za-z_][A-Za-z0-9_]*)\}$")
_SAMPLING_KEYS = ("settle", "sample", "discard")


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


class _Compiler:
    def __init__(self, overrides: dict[str, Any], limits: TableLimits | None) -> None:
        self.overrides = overrides
        self.limits = limits
        self.params: dict[str, Any] = {}
        self.param_lines: dict[str, tuple[str, int]] = {}
        self.sources: dict[str, str] = {}
        self.steps: list[Step] = []
        self.errors: list[InputError] = []
        self.stack: list[Path] = []
        self.description = ""
        self.steps_line = 1

    # -- files -------------------------------------------------------------------------------
    def load(self, path: Path, inc_parent: Any = None, inc_key: Any = None) -> LocDict:
        resolved = path.resolve()
        if resolved in self.stack:
            chain = " -> ".join(p.name for p in [*self.stack, resolved])
            raise S.error(inc_parent, inc_key, f"include cycle: {chain}", "remove the circular include")
        try:
            raw = load_file(path)
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
        S.check_keys(m, ("procedure", "description", "parameters", "defaults", "steps"),
                     "the procedure", required=("steps",))
        self.sources[str(path)] = path.read_text(encoding="utf-8")
        return m

    def declare_params(self, m: LocDict) -> None:
        if "parameters" not in m:
            return
        params = S.require_mapping(m["parameters"], "'parameters'", m, "parameters")
        for name, spec in params.items():
            if not isinstance(name, str) or not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", name):
                raise S.error(params, name, f"parameter name {name!r} is not a valid identifier")
            if isinstance(spec, dict):
                spec = S.require_mapping(spec, f"parameter {name!r}")
                S.check_keys(spec, ("default", "description", "unit"), f"parameter {name!r}",
                             required=("default",))
                default = spec["default"]
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

    def subst(self, value: Any, where: Any, key: Any) -> Any:
        """Replace ``${name}`` values by the parameter's value, recursively."""
        if isinstance(value, str):
            m = _PARAM.match(value.strip())
            if m:
                if m.group(1) not in self.params:
                    raise S.error(where, key, f"unknown parameter ${{{m.group(1)}}}",
                                  "declare it under 'parameters:'")
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
    def compile_file(self, path: Path, defaults: dict[str, Any] | None = None,
                     inc_parent: Any = None, inc_key: Any = None) -> str:
        m = self.load(path, inc_parent, inc_key)
        self.declare_params(m)
        if not self.stack:
            self.description = str(m.get("description", "") or "")
        self.stack.append(path.resolve())
        try:
            local_defaults = dict(defaults or {})
            if "defaults" in m:
                d = S.require_mapping(self.subst(m["defaults"], m, "defaults"), "'defaults'", m, "defaults")
                S.check_keys(d, _SAMPLING_KEYS, "'defaults'")
                local_defaults.update(d)
                local_defaults["__where__"] = d
            steps = S.get_list(m, "steps")
            if not self.stack[:-1]:
                self.steps_line = m.line_of("steps")
            for i, item in enumerate(steps):
                try:
                    self.compile_item(path, steps, i, item, local_defaults)
                except InputError as exc:
                    self.errors.append(exc)
        finally:
            self.stack.pop()
        return S.get_str(m, "procedure", path.stem)

    def compile_item(self, path: Path, steps: LocList, i: int, item: Any,
                     defaults: dict[str, Any]) -> None:
        if not isinstance(item, dict) or len(item) != 1:
            raise S.error(steps, i, "each step must be one 'kind: {options}' entry",
                          f"kinds: {', '.join(STEP_KINDS)}, or 'include: FILE'")
        item = S.require_mapping(item, "a step")
        (kind, body), = item.items()
        if kind == "repeat":
            r = S.require_mapping(self.subst(body, item, kind), "'repeat'", item, kind)
            r.line, r.file = item.line_of(kind), item.file
            S.check_keys(r, ("count", "steps"), "'repeat'", required=("count", "steps"))
            count = S.get_number(r, "count", minimum=1, maximum=10000, integer=True)
            inner = S.get_list(r, "steps", min_length=1)
            for _ in range(int(count)):
                for j, sub in enumerate(inner):
                    self.compile_item(path, inner, j, sub, defaults)
            return
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
        getattr(self, f"_{kind.replace('-', '_')}")(opts, defaults)

    def _policy(self, o: LocDict, defaults: dict[str, Any]) -> tuple[SettlePolicy, float, float]:
        where = defaults.get("__where__")
        settle_src = o.get("settle", defaults.get("settle"))
        policy = SettlePolicy()
        if settle_src is not None:
            owner = o if "settle" in o else where
            s = S.require_mapping(settle_src, "'settle'", owner, "settle")
            S.check_keys(s, ("position_window_deg", "rate_window_dps", "hold", "timeout"), "'settle'")
            policy = SettlePolicy(
                position_window=math.radians(S.get_number(s, "position_window_deg", 0.01, minimum=1e-6)),
                rate_window=math.radians(S.get_number(s, "rate_window_dps", 0.05, minimum=1e-6)),
                hold_s=S.get_duration(s, "hold", 2.0),
                timeout_s=S.get_duration(s, "timeout", 120.0, positive=True))
        sample = S.get_duration(o, "sample", None)
        if sample is None:
            sample = S.get_duration(where, "sample", 30.0) if where is not None else 30.0
        discard = S.get_duration(o, "discard", None)
        if discard is None:
            discard = S.get_duration(where, "discard", 1.0) if where is not None else 1.0
        return policy, sample, discard

    def _angles(self, o: LocDict, key: str = "angles_deg") -> np.ndarray:
        return np.radians(np.asarray(S.number_list(o, key, [0.0, 0.0, 0.0], length=3)))

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

    def _warmup(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("duration", "angles_deg", "label"), "'warmup'", required=("duration",))
        self.add(o, "duration", kind="warmup", label=S.get_str(o, "label", "warm-up"),
                 angles=self._angles(o), sample_s=S.get_duration(o, "duration", positive=True),
                 settle=self._policy(LocDict(), d)[0])

    def _capture(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("duration", "angles_deg", "label", "settle", "discard"), "'capture'",
                     required=("duration",))
        policy, _, discard = self._policy(o, d)
        self.add(o, "duration", kind="capture", label=S.get_str(o, "label", "static capture"),
                 angles=self._angles(o), sample_s=S.get_duration(o, "duration", positive=True),
                 discard_s=discard, settle=policy)

    def _wait(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("duration", "prompt", "angles_deg", "label"), "'wait'", required=("duration",))
        self.add(o, "duration", kind="wait", label=S.get_str(o, "label", "wait"),
                 angles=self._angles(o), sample_s=S.get_duration(o, "duration"),
                 prompt=S.get_str(o, "prompt", None), settle=self._policy(LocDict(), d)[0])

    def _taps(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("prompt", "count", "duration", "angles_deg", "label", "settle"), "'taps'",
                     required=("count",))
        policy, _, _ = self._policy(o, d)
        count = S.get_number(o, "count", minimum=1, maximum=10000, integer=True)
        self.add(o, "count", kind="taps", label=S.get_str(o, "label", f"{count} taps"),
                 angles=self._angles(o), sample_s=S.get_duration(o, "duration", 60.0, positive=True),
                 prompt=S.get_str(o, "prompt", f"Tap the IMU {count} times"), expected_taps=count,
                 settle=policy)

    # -- the climatic chamber (docs/thermal.md) ----------------------------------------------
    def _setpoint(self, o: LocDict, required: bool) -> float | None:
        if not required and "setpoint_c" not in o:
            return None
        return float(S.get_number(o, "setpoint_c", minimum=-100.0, maximum=200.0))

    def _chamber_set(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("setpoint_c", "label"), "'chamber-set'", required=("setpoint_c",))
        sp = self._setpoint(o, True)
        self.add(o, "setpoint_c", kind="chamber-set", label=S.get_str(o, "label", f"chamber {sp:g} degC"),
                 angles=np.zeros(3), sample_s=0.0, chamber={"setpoint_c": sp, "rate_c_per_min": None})

    def _chamber_ramp(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("setpoint_c", "rate_c_per_min", "label"), "'chamber-ramp'",
                     required=("setpoint_c", "rate_c_per_min"))
        sp = self._setpoint(o, True)
        rate = float(S.get_number(o, "rate_c_per_min", minimum=0.01, maximum=100.0))
        self.add(o, "setpoint_c", kind="chamber-ramp", label=S.get_str(o, "label", f"ramp to {sp:g} degC"),
                 angles=np.zeros(3), sample_s=0.0, chamber={"setpoint_c": sp, "rate_c_per_min": rate})

    def _chamber_wait(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("setpoint_c", "stable_band_c", "stable_for", "air_band_c", "timeout", "expect",
                         "angles_deg", "label"), "'chamber-wait'")
        sp = self._setpoint(o, False)
        c = {"setpoint_c": sp, "rate_c_per_min": None,
             "stable_band_c": float(S.get_number(o, "stable_band_c", 0.1, minimum=0.001, maximum=20.0)),
             "stable_for_s": float(S.get_duration(o, "stable_for", 300.0, positive=True)),
             "air_band_c": float(S.get_number(o, "air_band_c", 1.0, minimum=0.01, maximum=50.0)),
             "timeout_s": float(S.get_duration(o, "timeout", 4 * 3600.0, positive=True))}
        expect = S.get_duration(o, "expect", None)
        label = S.get_str(o, "label", "soak" + (f" at {sp:g} degC" if sp is not None else ""))
        self.add(o, "setpoint_c" if sp is not None else None, kind="chamber-wait", label=label,
                 angles=self._angles(o), settle=self._policy(LocDict(), d)[0],
                 sample_s=float(expect) if expect is not None else c["stable_for_s"], chamber=c)

    def _solve(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("solvers",), "'solve'", required=("solvers",))
        names = S.get_list(o, "solvers", min_length=1)
        for j, n in enumerate(names):
            if n not in SOLVERS:
                raise InputError(f"unknown solver {n!r}", o.file, names.line_of(j),
                                 f"choose from {', '.join(SOLVERS)}")
        self.add(o, "solvers", kind="solve", label="solve", angles=np.zeros(3), sample_s=0.0,
                 solvers=tuple(names))

    def _orientations(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("angles_deg", "pattern", "axes", "step_deg", "count", "label", *_SAMPLING_KEYS),
                     "'orientations'")
        policy, sample, discard = self._policy(o, d)
        if ("angles_deg" in o) == ("pattern" in o):
            raise S.error(o, None, "'orientations' needs either 'angles_deg' (a list of "
                          "[outer, middle, inner]) or 'pattern: 24-position'")
        if "angles_deg" in o:
            rows = S.get_list(o, "angles_deg", min_length=1)
            for j, row in enumerate(rows):
                if not (isinstance(row, list) and len(row) == 3 and all(
                        isinstance(x, (int, float)) and not isinstance(x, bool) for x in row)):
                    raise InputError(f"orientation {j + 1} must be [outer, middle, inner] in degrees",
                                     o.file, rows.line_of(j))
                self.add(o, "angles_deg", kind="orientation", label=f"angles {list(row)} deg",
                         angles=np.radians(np.asarray(row, float)), sample_s=sample,
                         discard_s=discard, settle=policy)
            return
        S.get_str(o, "pattern", choices=("24-position",))
        axes = S.get_list(o, "axes", ["x", "y", "z"], min_length=1)
        step_deg = S.get_number(o, "step_deg", 45.0, minimum=1e-3, maximum=360.0)
        count = S.get_number(o, "count", 8, minimum=1, maximum=360, integer=True)
        for j, ax in enumerate(axes):
            if ax not in ("x", "y", "z"):
                raise InputError(f"axis {ax!r} must be x, y or z", o.file,
                                 axes.line_of(j) if isinstance(axes, LocList) else o.line_of("axes"))
            for k in range(count):
                phi = k * step_deg
                self.add(o, "pattern", kind="orientation", label=f"{ax} north, phi {phi:g} deg",
                         angles=np.asarray(north_pointing_angles(ax, math.radians(phi))),
                         sample_s=sample, discard_s=discard, settle=policy)

    def _rates(self, o: LocDict, d: dict[str, Any]) -> None:
        S.check_keys(o, ("axes", "rates_dps", "directions", "dwell", "revolutions", "angles_deg",
                         "label", *_SAMPLING_KEYS), "'rates'", required=("rates_dps",))
        policy, sample, discard = self._policy(o, d)
        axes = S.get_list(o, "axes", ["x", "y", "z"], min_length=1)
        rates = S.number_list(o, "rates_dps")
        directions = S.get_list(o, "directions", ["forward", "reverse"], min_length=1)
        for j, dname in enumerate(directions):
            if dname not in ("forward", "reverse"):
                raise S.error(o, "directions", f"direction {dname!r} must be forward or reverse")
        if "dwell" in o and "revolutions" in o:
            raise S.error(o, "revolutions", "give either 'dwell' or 'revolutions', not both")
        revs = S.get_number(o, "revolutions", None, minimum=0.01, allow_none=True)
        dwell = S.get_duration(o, "dwell", None)
        start = self._angles(o)
        for ax in axes:
            if ax not in RATE_AXIS_GIMBAL:
                raise S.error(o, "axes", f"axis {ax!r} must be x, y or z")
            for r in rates:
                if r <= 0:
                    raise S.error(o, "rates_dps", f"rates are magnitudes (> 0), got {r}",
                                  "list forward/reverse under 'directions'")
                for dname in directions:
                    w = math.radians(r) * (1 if dname == "forward" else -1)
                    vec = np.full(3, np.nan)
                    vec[RATE_AXIS_GIMBAL[ax]] = w
                    if revs is not None:
                        window = revs * 2 * math.pi / abs(w)
                    elif dwell is not None:
                        window = dwell
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
    m_name = c.compile_file(p)
    c.check_overrides()
    if c.errors:
        raise InputErrors(c.errors) if len(c.errors) > 1 else c.errors[0]
    if not c.steps:
        raise InputError("the procedure has no steps", p, c.steps_line, "list at least one step")
    return Procedure(name=m_name, path=str(p), description=c.description,
                     parameters={k: c.value_of(k) for k in c.params}, steps=c.steps, sources=c.sources)
