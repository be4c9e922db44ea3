"""Small typed accessors over line-aware YAML mappings, raising errors that name file and line."""
from __future__ import annotations

import difflib
import math
from collections.abc import Iterable
from typing import Any

from .units import parse_duration
from .errors import InputError
from .yamlio import LocDict, LocList


def where(obj: Any, key: Any = None) -> tuple[str | None, int | None]:
    """The (file, line) of ``obj[key]`` (of ``obj`` itself when key is None); (None, None) if unknown."""
    if isinstance(obj, LocDict):
        return obj.file, obj.line_of(key) if key is not None else obj.line
    if isinstance(obj, LocList):
        return obj.file, obj.line_of(key) if isinstance(key, int) else obj.line
    return None, None


def error(obj: Any, key: Any, message: str, hint: str | None = None) -> InputError:
    """An InputError located at ``obj[key]`` (or at ``obj`` when key is None)."""
    file, line = where(obj, key)
    return InputError(message, file, line, hint)


def item_error(m: LocDict, key: Any, items: list, i: int, message: str, hint: str | None = None) -> InputError:
    """An InputError at entry ``i`` of the list ``m[key]`` (at the key's line for a list without
    lines of its own, such as one from a ``-p`` value)."""
    line = items.line_of(i) if isinstance(items, LocList) else where(m, key)[1]
    return InputError(message, where(m)[0], line, hint)


def require_mapping(obj: Any, what: str, parent: Any = None, key: Any = None) -> LocDict:
    if not isinstance(obj, dict):
        raise error(parent if parent is not None else obj, key,
                    f"{what} must be a mapping (key: value lines), got {_kind(obj)}")
    return obj if isinstance(obj, LocDict) else LocDict(obj)


def _kind(obj: Any) -> str:
    if obj is None:
        return "nothing"
    if isinstance(obj, dict):
        return "a mapping"
    if isinstance(obj, list):
        return "a list"
    return f"{type(obj).__name__} {obj!r}"


def did_you_mean(word: str, choices: Iterable[str], listing: str = "allowed") -> str:
    """A hint for a misspelt ``word``: "did you mean 'x'?" for the closest of ``choices``, else
    "<listing>: a, b, c" (or "<listing>: none")."""
    choices = [str(c) for c in choices]
    close = difflib.get_close_matches(str(word), choices, n=1)
    return f"did you mean {close[0]!r}?" if close else f"{listing}: {', '.join(choices) or 'none'}"


def check_keys(m: LocDict, allowed: Iterable[str], what: str,
               required: Iterable[str] = ()) -> None:
    """Unknown keys and missing required keys are errors (with a did-you-mean hint)."""
    allowed = list(allowed)
    for key in m:
        if key not in allowed:
            raise error(m, key, f"unknown key {key!r} in {what}", did_you_mean(key, allowed))
    for key in required:
        if key not in m:
            raise error(m, None, f"{what} is missing {key!r}", f"add a line '{key}: ...'")


def get_number(m: LocDict, key: str, default: Any = ..., *, minimum: float | None = None,
               maximum: float | None = None, integer: bool = False, allow_none: bool = False) -> Any:
    """A finite number from ``m[key]`` within [minimum, maximum]."""
    if key not in m:
        if default is ...:
            raise error(m, None, f"missing {key!r}", f"add a line '{key}: <number>'")
        return default
    v = m[key]
    if v is None and allow_none:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise error(m, key, f"{key!r} must be a number, got {_kind(v)}")
    if integer and int(v) != v:
        raise error(m, key, f"{key!r} must be a whole number, got {v!r}")
    if minimum is not None and v < minimum:
        raise error(m, key, f"{key!r} = {v} is below its minimum {minimum}")
    if maximum is not None and v > maximum:
        raise error(m, key, f"{key!r} = {v} is above its maximum {maximum}")
    return int(v) if integer else float(v)


def get_duration(m: LocDict, key: str, default: Any = ..., *, positive: bool = False) -> Any:
    """A duration in s from a number (s) or a string such as '15 min'."""
    if key not in m:
        if default is ...:
            raise error(m, None, f"missing {key!r}", f"add a line '{key}: 30 s'")
        return default
    try:
        v = parse_duration(m[key])
    except ValueError as exc:
        raise error(m, key, f"{key!r}: {exc}") from None
    if positive and v <= 0:
        raise error(m, key, f"{key!r} must be longer than zero")
    return v


def get_str(m: LocDict, key: str, default: Any = ..., *, choices: Iterable[str] | None = None) -> Any:
    if key not in m:
        if default is ...:
            raise error(m, None, f"missing {key!r}", f"add a line '{key}: ...'")
        return default
    v = m[key]
    if not isinstance(v, str):
        raise error(m, key, f"{key!r} must be text, got {_kind(v)}")
    if choices is not None:
        choices = list(choices)
        if v not in choices:
            raise error(m, key, f"{key!r} = {v!r} is not allowed", did_you_mean(v, choices, "choose one of"))
    return v


def get_bool(m: LocDict, key: str, default: Any = ...) -> Any:
    if key not in m:
        if default is ...:
            raise error(m, None, f"missing {key!r}")
        return default
    v = m[key]
    if not isinstance(v, bool):
        raise error(m, key, f"{key!r} must be true or false, got {_kind(v)}")
    return v


def get_list(m: LocDict, key: str, default: Any = ..., *, length: int | None = None,
             min_length: int = 0) -> Any:
    if key not in m:
        if default is ...:
            raise error(m, None, f"missing {key!r}", f"add a line '{key}: [...]'")
        return default
    v = m[key]
    if not isinstance(v, list):
        raise error(m, key, f"{key!r} must be a list, got {_kind(v)}")
    if length is not None and len(v) != length:
        raise error(m, key, f"{key!r} must have {length} entries, has {len(v)}")
    if len(v) < min_length:
        raise error(m, key, f"{key!r} must have at least {min_length} entries")
    return v


def number_list(m: LocDict, key: str, default: Any = ..., *, length: int | None = None,
                allow_none: bool = False) -> Any:
    """A list of finite numbers (None entries allowed when ``allow_none``)."""
    v = get_list(m, key, default, length=length)
    if v is default and key not in m:
        return v
    out = []
    for i, x in enumerate(v):
        if x is None and allow_none:
            out.append(None)
            continue
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise item_error(m, key, v, i, f"{key!r}: entry {i + 1} must be a number, got {_kind(x)}")
        out.append(float(x))
    return out
