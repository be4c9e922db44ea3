"""Parsing of quantities written by people ("15 min", "12 h", "30 s") into SI seconds."""
from __future__ import annotations

import math
import re

_TIME_UNITS = {
    "ms": 1e-3, "s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0,
    "min": 60.0, "minute": 60.0, "minutes": 60.0,
    "h": 3600.0, "hr": 3600.0, "hour": 3600.0, "hours": 3600.0,
}
_QTY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z]*)\s*$")


#: longest duration a procedure may ask for (31 days), s: beyond it a value is a typo
MAX_DURATION_S = 31 * 86400.0


def parse_duration(value: object) -> float:
    """A duration in seconds from a number (seconds) or a string like "15 min", "12 h", "0.5 s".

    Raises ValueError with a message a person can act on.
    """
    if isinstance(value, bool):
        raise ValueError("expected a duration such as 30, '30 s', '15 min' or '12 h', not a boolean")
    if isinstance(value, (int, float)):
        seconds = float(value)
    elif isinstance(value, str):
        m = _QTY.match(value)
        if not m:
            raise ValueError(f"cannot read {value!r} as a duration; write e.g. '30 s', '15 min', '12 h'")
        unit = m.group(2) or "s"
        if unit not in _TIME_UNITS:
            raise ValueError(f"unknown time unit {unit!r} in {value!r}; use ms, s, min or h")
        seconds = float(m.group(1)) * _TIME_UNITS[unit]
    else:
        raise ValueError(f"expected a duration such as '30 s' or '15 min', got {type(value).__name__}")
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"a duration must be finite and not negative, got {value!r}")
    if seconds > MAX_DURATION_S:
        raise ValueError(f"{value!r} is longer than the longest step rigctl runs, 31 days")
    return seconds


def format_duration(seconds: float) -> str:
    """Human form of a duration: '45 s', '15 min 0 s', '12 h 0 min'."""
    if seconds < 60:
        return f"{seconds:.3g} s"
    if seconds < 3600:
        m, s = divmod(round(seconds), 60)
        return f"{m} min {s:02d} s"
    h, rem = divmod(round(seconds), 3600)
    return f"{h} h {rem // 60:02d} min"


def format_rate(hz: float) -> str:
    """A sample rate as every command prints it: 8 significant digits and Hz ('99.990001 Hz',
    '200 Hz'); enough for the rate a time column's stamps give, one form everywhere."""
    return f"{hz:.8g} Hz"


def format_bytes(n: float) -> str:
    """Human form of a byte count (SI prefixes)."""
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1000.0
    return f"{n:.3g} TB"  # pragma: no cover
