"""Batch analysis of many recordings on Dask, and the lot summary.

Each recording is one task, :func:`analyse_one` (the same calibration / Allan pipelines as
``rigctl calibrate`` and ``rigctl allan``, storing into the recording and its JSON as they
do); the tasks run on Dask's local multiprocessing scheduler (``workers`` processes) or on a
``dask.distributed`` cluster (a scheduler address). A task never raises: a recording that
fails returns its error, and the others go on. The caller writes the results database from
the collected results (one writer: SQLite has one), so the database holds exactly what
serial runs would have written.

:func:`summarise` gives per lot the yield (PASS / FAIL / INDETERMINATE counts of the overall
verdicts) and each parameter's distribution across units (n, mean, standard deviation, min,
max in the display unit, and the smallest and largest of the units' own 1-sigma uncertainties).
"""
from __future__ import annotations

import math
import os
import traceback
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from . import allan as allan_pipeline
from ..jsonable import jsonable
from . import calibration
from ..solvers.conformity import FAIL, INDETERMINATE, PASS, overall
from ..config.spec import load_spec
from . import production
from ..display_units import format_value
from ..errors import RigctlError
from ..recording.results_place import DEFAULT_NAME, default_path

ANALYSES = ("calibrate", "allan")

#: a parameter whose largest unit uncertainty is more than this many times the smallest is
#: named under the lot summary: its mean and sd mix well and poorly determined units
UNEVEN_U = 10.0


def analyse_one(recording: str, analyses: tuple[str, ...] = ("calibrate",), spec_path: str | None = None,
                rule: str | None = None, noise: str = "auto") -> dict[str, Any]:
    """Analyse one recording (runs in a worker). Returns {"recording", "ok", "results":
    {kind: payload}, "error"}; never raises."""
    out: dict[str, Any] = {"recording": recording, "ok": False, "results": {}, "error": None}
    try:
        spec = load_spec(spec_path, rule) if spec_path else None
        if "calibrate" in analyses:
            payload, _, _ = calibration.calibrate(recording, noise, True, None, spec)
            out["results"]["calibration"] = payload
        if "allan" in analyses:
            axes = list(allan_pipeline.AXES)
            rng, where, _ = allan_pipeline.choose_range(recording, axes)
            res = allan_pipeline.compute(recording, axes, 95, False, rng, gaps="skip")  # Stable32; count in res["gaps"]
            res["segment"] = where
            res["verdicts"] = production.verdicts_for(spec, "allan", res)
            allan_pipeline.store(recording, res)
            out["results"]["allan"] = jsonable(res, keep_nonfinite=True)
        out["ok"] = True
    except Exception as exc:  # noqa: BLE001 - reported per recording; the batch goes on
        # rigctl's own errors are the one line the command would print; anything else is a
        # fault, named by its type (the traceback is kept beside it)
        out["error"] = str(exc) if isinstance(exc, RigctlError) else f"{type(exc).__name__}: {exc}"
        out["traceback"] = traceback.format_exc()
    return out


def run_batch(recordings: Iterable[str], analyses: tuple[str, ...], spec_path: str | None, rule: str | None,
              workers: int | None = None, scheduler: str | None = None, noise: str = "auto",
              on_done: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Run :func:`analyse_one` over ``recordings`` on Dask; results in the input order.

    ``scheduler``: a dask.distributed scheduler address (tcp://127.0.0.1:8786); else the local
    multiprocessing scheduler with ``workers`` processes (default: the CPU count).
    """
    import dask  # optional dependency: rigctl[batch]

    recs = [str(r) for r in recordings]
    tasks = [dask.delayed(analyse_one, pure=False)(r, analyses, spec_path, rule, noise) for r in recs]
    if scheduler:
        from distributed import Client, as_completed

        with Client(scheduler, timeout="30s") as client:
            futures = client.compute(tasks)
            index = {f.key: i for i, f in enumerate(futures)}
            out: list[dict[str, Any] | None] = [None] * len(futures)
            for fut in as_completed(futures):
                res = fut.result()
                out[index[fut.key]] = res
                if on_done:
                    on_done(res)
        return [r for r in out if r is not None]
    results = list(dask.compute(*tasks, scheduler="processes", num_workers=workers or None))
    if on_done:
        for r in results:
            on_done(r)
    return results


def lot_of(recording: str | Path) -> str:
    """A recording's lot: the folder that holds its run directory (runs/LOT/<run>/recording.h5 ->
    LOT) -- the last path part above the run."""
    p = Path(recording).resolve()
    return (p.parent.parent if p.name == "recording.h5" else p.parent).name


def summarise(results: list[dict[str, Any]], lots: dict[str, str], with_spec: bool = True) -> dict[str, Any]:
    """Yield and parameter distributions per lot (display units); ``with_spec``: the batch was
    given a spec (without one no recording has a verdict and none is listed for lacking one).

    The yield is PASS / (PASS + FAIL + INDETERMINATE) over the recordings that have a verdict;
    with a spec, an analysed recording it gave no verdict (nothing the spec names measured in it,
    e.g. a thermal run) is listed under ``no_verdict`` and is not in the yield."""
    per_lot: dict[str, dict[str, Any]] = {}
    for r in results:
        lot = lots[r["recording"]]
        L = per_lot.setdefault(lot, {"recordings": 0, "failed": [], "verdicts": {PASS: 0, FAIL: 0, INDETERMINATE: 0},
                                     "no_verdict": [], "params": {}})
        L["recordings"] += 1
        if not r["ok"]:
            L["failed"].append({"recording": r["recording"], "error": r["error"]})
            continue
        vs = [p["verdicts"]["overall"] for p in r["results"].values() if p.get("verdicts")]
        if vs:
            L["verdicts"][overall(vs)] += 1
        elif with_spec:
            L["no_verdict"].append(r["recording"])
        for kind, payload in r["results"].items():
            for m in production.measured(kind, payload):
                d = m.display
                L["params"].setdefault((d.base, d.unit), []).append((d.value(m.value), d.sigma(m.u)))
    out = {}
    for lot, L in sorted(per_lot.items()):
        decided = sum(L["verdicts"].values())
        params = {}
        for (base, unit), vals in L["params"].items():
            v = np.array([x for x, _ in vals], dtype=float)
            params[base] = {"unit": unit, "n": int(v.size), "mean": float(v.mean()),
                            "sd": float(v.std(ddof=1)) if v.size > 1 else math.nan,
                            "min": float(v.min()), "max": float(v.max()),
                            "median_u": float(np.median([u for _, u in vals])),
                            "min_u": float(np.min([u for _, u in vals])),
                            "max_u": float(np.max([u for _, u in vals]))}
        out[lot] = {"recordings": L["recordings"], "analysed": L["recordings"] - len(L["failed"]),
                    "failed": L["failed"], "verdicts": L["verdicts"], "no_verdict": L["no_verdict"],
                    "spec": with_spec,
                    "yield": L["verdicts"][PASS] / decided if decided else None, "parameters": params}
    return out


def database_home(recordings: Iterable[str]) -> Path:
    """The folder that holds all the run directories: the common folder of each recording's
    default results database (rigctl.recording.results_place.default_path: needs no db extra)."""
    return Path(os.path.commonpath([str(default_path(r).parent) for r in recordings]))


def store_in_database(results: list[dict[str, Any]], lots: dict[str, str], target: str | None,
                      home: Path) -> str:
    """Write every analysed recording of a batch to the results database through one engine
    (one writer); ``target`` None: results.sqlite in ``home``, "none": nothing. Returns the
    line to print ("" when nothing was written: also for the default database without the db
    extra, as for one analysis; an explicit ``target`` without it is refused before the batch,
    rigctl.analysis.production.check_database_option)."""
    if target == "none":
        return ""
    if target is None:
        try:
            from ..recording import results_db  # noqa: F401 - optional dependency (rigctl[db])
        except ImportError:
            return ""
    db = production.results_db_module("rigctl batch")
    target = target or str(home / DEFAULT_NAME)
    line = ""
    engine = db.open_db(target)
    try:
        for r in results:
            for kind, payload in r["results"].items():
                line = production.to_database(r["recording"], kind, payload, target,
                                              lot=lots[r["recording"]], engine=engine)
    finally:
        engine.dispose()
    return line


def summary_text(summary: dict[str, Any]) -> str:
    """The lot summary as a table."""
    lines = []
    for lot, s in summary.items():
        v = s["verdicts"]
        decided = v["PASS"] + v["FAIL"] + v["INDETERMINATE"]
        if not s["spec"]:
            y = "n/a (no spec)"
        elif s["yield"] is None:
            y = "n/a (no recording with a verdict)"
        else:
            y = f"{100 * s['yield']:.0f} % of {decided} with a verdict"
        counts = f"PASS {v['PASS']}, FAIL {v['FAIL']}, INDETERMINATE {v['INDETERMINATE']}"
        if s["spec"]:
            counts += f", no verdict {len(s['no_verdict'])}"
        lines.append(f"lot {lot}: {s['recordings']} recordings, {s['analysed']} analysed, {len(s['failed'])} failed; "
                     f"yield {y} ({counts})")
        lines.append(f"  {'parameter':<32} {'unit':<14} {'n':>3} {'mean':>12} {'sd':>10} {'min':>12} {'max':>12}"
                     f" {'u min':>10} {'u max':>10}")
        uneven = []
        for name, p in s["parameters"].items():
            ref = p["median_u"]  # digits from the units' typical uncertainty
            f = [format_value(p[k], ref)[0] for k in ("mean", "min", "max")]
            sd = format_value(p["sd"], ref)[0] if p["sd"] == p["sd"] else "n/a"
            u = [format_value(p[k], p[k])[1] for k in ("min_u", "max_u")]
            lines.append(f"  {name:<32} {p['unit']:<14} {p['n']:>3} {f[0]:>12} {sd:>10} {f[1]:>12} {f[2]:>12}"
                         f" {u[0]:>10} {u[1]:>10}")
            if p["n"] > 1 and p["max_u"] > UNEVEN_U * p["min_u"]:
                uneven.append(name)
        lines.append("  (u min, u max: the smallest and largest of the units' own 1-sigma uncertainties)")
        if uneven:
            lines.append(f"  warning: {len(uneven)} parameter(s) with one unit's 1-sigma more than {UNEVEN_U:g}x "
                         f"another's ({', '.join(uneven)}): a unit whose analysis could not determine them "
                         "(e.g. gyro scale from a recording with no rate segments) is in the mean and sd; "
                         "look at those units before using the lot's distribution")
        for rec in s["no_verdict"]:  # with a spec: the analysed recordings it gave no verdict on
            lines.append(f"  NO VERDICT {rec}: nothing the spec names was measured in it (not in the yield)")
        for fl in s["failed"]:
            lines.append(f"  FAILED {fl['recording']}: {fl['error']}")
    return "\n".join(lines)
