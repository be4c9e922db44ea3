"""Allan curves for the report, from /results/allan (written by ``rigctl allan``).

Per axis the stored datasets are tau_s (s) and adev / lo68 / hi68 / lo95 / hi95 in the
field unit (deg/h for gyros, mg for accelerometers; dataset names with "/" spelled "_per_"),
the JSON summary holds the joint IEEE 952 fit. When the results lack an axis' curve arrays, a
quick curve (30 log-spaced taus, fast mode) is computed from the recording with the same
pipeline as ``rigctl allan`` (:func:`rigctl.analysis.allan.compute`: overlapping ADEV from
:mod:`rigctl.solvers.allan`, Greenhall EDF intervals, joint fit) and marked ``quick``.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InputError
from ..jsonable import jsonable

if TYPE_CHECKING:  # pragma: no cover
    from .report import RunData

#: sensor -> (display unit, factor from SI); the same as rigctl.analysis.allan.DEV_UNITS
DEV_UNITS = {"gyro": ("deg/h", 180.0 / np.pi * 3600.0), "accel": ("mg", 1000.0 / 9.80665)}
QUICK_TAUS = 30


def _ds(unit: str) -> str:
    return unit.replace("/", "_per_")


def allan_curves(data: "RunData", log: Callable[..., None] | None = None) -> dict[str, dict[str, Any]]:
    """{axis: {sensor, unit, factor, tau_s, adev, lo68, hi68, lo95, hi95, fit, quiet_stretch,
    quick}}
    (computed once per RunData, then cached)."""
    if "allan_curves" not in data.cache:
        data.cache["allan_curves"] = _curves(data, log)
    return data.cache["allan_curves"]


def _curves(data: "RunData", log: Callable[..., None] | None) -> dict[str, dict[str, Any]]:
    res = data.results.get("allan")
    if not res:
        return {}
    summary = res.get("json") or {}
    arrays = res.get("arrays") or {}
    out: dict[str, dict[str, Any]] = {}
    missing: list[str] = []
    for axis, info in (summary.get("axes") or {}).items():
        sensor = info.get("sensor", "gyro" if axis.startswith("g") else "accel")
        unit, fac = DEV_UNITS.get(sensor, DEV_UNITS["gyro"])
        u = _ds(unit)
        tau = arrays.get(f"{axis}/tau_s")
        dev = arrays.get(f"{axis}/adev_{u}")
        if tau is None or dev is None:
            missing.append(axis)
            continue
        cv = {"sensor": sensor, "unit": unit, "factor": fac, "tau_s": np.asarray(tau, float),
              "adev": np.asarray(dev, float), "fit": info.get("fit"),
              "piecewise": info.get("piecewise"), "quiet_stretch": info.get("quiet_stretch"),
              "excursions": info.get("excursions"), "quick": False}
        for k in ("lo68", "hi68", "lo95", "hi95"):
            v = arrays.get(f"{axis}/{k}_{u}")
            cv[k] = None if v is None else np.asarray(v, float)
        out[axis] = cv
    if missing:
        out.update(_quick(data, missing, summary, log))
    return out


def _quick(data: "RunData", axes: list[str], summary: dict[str, Any],
           log: Callable[..., None] | None) -> dict[str, dict[str, Any]]:
    from ..analysis import allan as allan_pipeline

    try:
        res = allan_pipeline.compute(str(data.recording), [a for a in axes if a in allan_pipeline.AXES],
                                     taus=QUICK_TAUS, gaps="skip",  # a quick curve, marked so
                                     quiet_stretch=False)
    except (InputError, OSError, ValueError) as exc:
        if log:
            log("warning", f"report: no Allan curve for {', '.join(axes)}: {exc}")
        return {}
    out = {}
    for axis, r in res["axes"].items():
        unit, fac = DEV_UNITS[r["sensor"]]
        stored = (summary.get("axes") or {}).get(axis) or {}
        out[axis] = {"sensor": r["sensor"], "unit": unit, "factor": fac,
                     "tau_s": np.asarray(r["tau_s"], float), "adev": np.asarray(r[f"adev_{unit}"]),
                     "lo68": np.asarray(r[f"lo68_{unit}"]), "hi68": np.asarray(r[f"hi68_{unit}"]),
                     "lo95": np.asarray(r[f"lo95_{unit}"]), "hi95": np.asarray(r[f"hi95_{unit}"]),
                     "fit": stored.get("fit") or jsonable(r["fit"], keep_nonfinite=True),
                     "piecewise": stored.get("piecewise") or jsonable(r["piecewise"], keep_nonfinite=True),
                     "quick": True}
    return out
