"""Typed settings: one frozen dataclass per concept of a rig config, a procedure or a spec file,
and the one validator.

A concept's settings are a dataclass whose fields each name one YAML key, with its default and
its checks (:func:`number`, :func:`text`, :func:`flag`, :func:`duration`, :func:`mapping`,
:func:`as_written`, :func:`numbers` ([x, y, z]), :func:`per_axis` (a number or three),
:func:`matrix3`, :func:`subsection` (a nested section's own settings), :func:`items` (a list of
sections), or :func:`setting` with a reader of its own). :func:`parse` is the one
validator: unknown keys are refused with "did you mean", each value is read and checked by its
field's reader (type, range, choices), missing required keys are named, and
:meth:`Settings.check` adds the rules between fields; every error is an InputError with the
file and line (rigctl.schema).

Users: rigctl.config.linkconfig (the wired drivers' link settings, whose field names are the drivers'
keyword arguments), rigctl.config.config (the top level, ``site:``, ``recorder:``, ``table.limits``,
``traceability:``), rigctl.config.suspenders, rigctl.config.notify, rigctl.config.chamber, rigctl.engine.procedure (the
procedure file: its top level, parameters, ``defaults:``, ``settle:`` and each step kind),
rigctl.config.spec (the acceptance limits of ``--spec``), rigctl.config.frame_spec (the declared
frame format) and the emulator's sections (``table.sim``, ``imu.sim`` with ``thermal:`` and the
Gauss-Markov terms, the IMU profiles, ``pulses.sim``, ``chamber.sim``: rigctl.sim.world, .imu,
.thermal_imu, .profiles, .tap_rig, .chamber).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, TypeVar

from . import schema as S
from .yamlio import LocDict, LocList

#: reads ``d[key]`` with the field's checks: ``reader(d, key, default, **checks)``
Reader = Callable[..., Any]


def setting(default: Any = MISSING, *, read: Reader, key: str | None = None, what: bool = False,
            **check: Any) -> Any:
    """A settings field read by ``read``; ``key``: its YAML key when it differs from the field's
    name; ``what``: the reader also gets ``what=`` (how errors name the section); ``check``:
    keyword arguments of the reader (minimum, maximum, integer, allow_none, choices, positive)."""
    return field(default=default, metadata={"read": read, "key": key, "check": check, "what": what})


def internal(default: Any) -> Any:
    """A field that is not a config key (set by the program; :func:`parse` leaves its default)."""
    return field(default=default, metadata={"internal": True})


def number(default: Any = MISSING, **check: Any) -> Any:
    return setting(default, read=S.get_number, **check)


def text(default: Any = MISSING, **check: Any) -> Any:
    return setting(default, read=S.get_str, **check)


def flag(default: bool) -> Any:
    return setting(default, read=S.get_bool)


def duration(default: Any = MISSING, **check: Any) -> Any:
    """Seconds, given as a number or as text with a unit ('5 min')."""
    return setting(default, read=S.get_duration, **check)


def _mapping(d: LocDict, key: str, default: Any = None) -> LocDict:
    return S.require_mapping(d[key], f"'{key}'", d, key)


def mapping(default: Any = MISSING) -> Any:
    """A mapping (key: value lines), kept as read: a :class:`LocDict` that still knows its lines."""
    return setting(default, read=_mapping)


def _numbers(d: LocDict, key: str, default: Any = None, *, length: int | None = 3,
             minimum: float | None = None, maximum: float | None = None) -> tuple[float, ...]:
    v = S.number_list(d, key, length=length)
    for i, x in enumerate(v):
        if (minimum is not None and x < minimum) or (maximum is not None and x > maximum):
            raise S.item_error(d, key, d[key], i, f"{key!r}: entry {i + 1} = {x:g} is outside "
                               f"[{'-inf' if minimum is None else f'{minimum:g}'}, "
                               f"{'inf' if maximum is None else f'{maximum:g}'}]")
    return tuple(v)


def numbers(default: Any = MISSING, **check: Any) -> Any:
    """A list of numbers ([x, y, z] by default: ``length=3``; ``length=None``: any length),
    each within [minimum, maximum]; a tuple of floats."""
    return setting(default, read=_numbers, **check)


def _per_axis(d: LocDict, key: str, default: Any = None, *, minimum: float | None = None,
              maximum: float | None = None, integer: bool = False) -> tuple[float, float, float]:
    if isinstance(d[key], list):
        vals = S.number_list(d, key, length=3)
        for v in vals:
            if (minimum is not None and v < minimum) or (maximum is not None and v > maximum):
                raise S.error(d, key, f"{key!r} entries must be in [{minimum}, {maximum}]")
            if integer and int(v) != v:
                raise S.error(d, key, f"{key!r} entries must be whole numbers")
        return tuple(int(v) if integer else float(v) for v in vals)  # type: ignore[return-value]
    v = S.get_number(d, key, minimum=minimum, maximum=maximum, integer=integer)
    return (v, v, v)


def per_axis(default: Any = MISSING, **check: Any) -> Any:
    """One number for the three axes, or a list of three (each within [minimum, maximum]);
    a 3-tuple."""
    return setting(default, read=_per_axis, **check)


def _matrix3(d: LocDict, key: str, default: Any = None) -> tuple[tuple[float, ...], ...]:
    rows = S.get_list(d, key, length=3)
    out = []
    for i, row in enumerate(rows):
        if not (isinstance(row, list) and len(row) == 3 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in row)):
            raise S.item_error(d, key, rows, i, f"{key!r} must be a 3x3 list of rows of numbers "
                               f"(row {i + 1} is {row!r})", "e.g. [[0, 1, 0], [0, 0, 0], [-2, 0, 0]]")
        out.append(tuple(float(x) for x in row))
    return tuple(out)


def matrix3(default: Any = MISSING) -> Any:
    """A 3x3 list of rows of numbers; a tuple of three 3-tuples."""
    return setting(default, read=_matrix3)


def subsection(cls: type[Settings], what: str | None = None, *, optional: bool = False) -> Any:
    """A nested mapping read as the settings ``cls``; errors name it ``what`` (e.g.
    "'imu.sim.thermal'"), by default the parent's name and the key ("<parent>.<key>"). Absent or
    null: ``cls()``, its defaults (``optional``: None)."""
    fixed = what

    def read(d: LocDict, key: str, default: Any = None, *, what: str = "") -> Settings | None:
        name = fixed or f"{what}.{key}"
        if d[key] is None:
            return None if optional else parse(cls, LocDict(), name)
        return parse(cls, S.require_mapping(d[key], name, d, key), name)
    return setting(None if optional else cls(), read=read, what=True)


def entry(d: LocDict, key: str, i: int) -> Any:
    """Entry ``i`` of the list ``d[key]``; a mapping as a :class:`LocDict` that knows its line
    (for a list read without lines, such as a dict built in code: the key's line)."""
    entries = d[key]
    e = entries[i]
    if isinstance(e, dict) and not isinstance(e, LocDict):
        e = LocDict(e)
        e.file, e.line = d.file, (entries.line_of(i) if isinstance(entries, LocList) else d.line_of(key))
    return e


def items(cls: type[Settings], what: str | None = None, default: Any = (), *, min_length: int = 0,
          hint: str | None = None) -> Any:
    """A list of mappings (at least ``min_length``), each read as the settings ``cls`` (errors
    name ``what``, by default "<parent>.<key>", and the entry's number; ``hint``: what an entry
    looks like); a tuple."""
    fixed = what

    def read(d: LocDict, key: str, default: Any = None, *, what: str = "") -> tuple[Settings, ...]:
        if d[key] is None and not min_length:
            return ()
        name = fixed or f"{what}.{key}"
        entries = S.get_list(d, key, min_length=min_length)
        out = []
        for i in range(len(entries)):
            label = f"{name} entry {i + 1}"
            e = entry(d, key, i)
            if not isinstance(e, dict):
                raise S.item_error(d, key, entries, i, f"{label} must be a mapping (key: value lines), "
                                   f"got {e!r}", hint)
            out.append(parse(cls, e, label))
        return tuple(out)
    return setting(default, read=read, what=True)


def _as_written(d: LocDict, key: str, default: Any = None) -> Any:
    return d[key]


def as_written(default: Any = MISSING) -> Any:
    """Any value, unchecked (read later, e.g. after ``${parameter}`` substitution)."""
    return setting(default, read=_as_written)


@dataclass(frozen=True, kw_only=True)
class Settings:
    """Base of every section's settings."""

    #: other keys the section may hold (read elsewhere)
    EXTRA_KEYS: ClassVar[tuple[str, ...]] = ()
    #: added to the hint of an unknown key (e.g. where the keys are documented)
    HINT: ClassVar[str] = ""

    def check(self, d: LocDict) -> None:
        """Rules between fields (after each field is valid); raises InputError."""


T = TypeVar("T", bound=Settings)


def yaml_keys(cls: type[Settings]) -> list[str]:
    return [f.metadata.get("key") or f.name for f in fields(cls) if "read" in f.metadata]


def parse(cls: type[T], d: LocDict, what: str, extra_keys: Iterable[str] = ()) -> T:
    """The one validator: ``d`` (a config section) as ``cls``; InputError with file and line."""
    spec = {f.metadata.get("key") or f.name: f for f in fields(cls) if "read" in f.metadata}
    allowed = (*extra_keys, *cls.EXTRA_KEYS, *spec)
    for key in d:
        if key not in allowed:
            hint = S.did_you_mean(key, allowed)
            raise S.error(d, key, f"unknown key {key!r} in {what}", f"{hint}; {cls.HINT}" if cls.HINT else hint)
    values: dict[str, Any] = {}
    for key, f in spec.items():
        default = ... if f.default is MISSING else f.default
        if key not in d:
            if default is ...:
                raise S.error(d, None, f"{what} is missing {key!r}", f"add a line '{key}: ...'")
            values[f.name] = default
        else:
            check = {**f.metadata["check"], **({"what": what} if f.metadata.get("what") else {})}
            values[f.name] = f.metadata["read"](d, key, default, **check)
    out = cls(**values)
    out.check(d)
    return out


def section(m: LocDict, key: str, cls: type[T], what: str | None = None) -> T:
    """The settings of section ``key`` of mapping ``m`` (defaults when absent or null)."""
    what = what or f"'{key}'"
    if m.get(key) is None:
        return parse(cls, LocDict(), what)
    return parse(cls, S.require_mapping(m[key], what, m, key), what)
