"""One conversion of results to JSON-ready Python values, for every layer (solvers included:
it does no I/O).

:func:`jsonable` turns numpy arrays into lists and numpy scalars into Python numbers, recursively
through dicts, lists and tuples, and drops private keys (a leading ``_``, e.g. the Allan
pipeline's ``_unit``). Non-finite floats (NaN, +-inf) become ``None`` -- JSON has no such numbers
and strict readers refuse Python's ``NaN``/``Infinity`` tokens -- unless ``keep_nonfinite`` is
set: the Allan results group keeps them (an unbounded interval end stays ``inf`` for the report
and the database, which read that JSON back with Python's own json module).
An object with an ``as_json()`` method (:class:`rigctl.solvers.noise_coefficients.NoiseCoefficients`)
is converted by it. Anything else that JSON cannot hold becomes its ``str``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["jsonable"]


def jsonable(obj: Any, *, keep_nonfinite: bool = False) -> Any:
    """A JSON-ready copy of ``obj`` (see the module docstring)."""
    if callable(getattr(obj, "as_json", None)):  # a typed result (NoiseCoefficients)
        return jsonable(obj.as_json(), keep_nonfinite=keep_nonfinite)
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v, keep_nonfinite=keep_nonfinite) for k, v in obj.items()
                if not str(k).startswith("_")}
    if isinstance(obj, np.ndarray):
        obj = obj.tolist()
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, keep_nonfinite=keep_nonfinite) for v in obj]
    if obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if keep_nonfinite or math.isfinite(x) else None
    return str(obj)
