"""Short excursions of a static capture, found before the fit and reported in the field's
units (docs/allan.md, "Short excursions before the fit").

The test is :func:`rigctl.solvers.allan_excursions.find_excursions` on each axis' block means
(the streamed record's decimated phase, :func:`rigctl.analysis.allan_drift.block_means`);
this module puts its result in the axis' ``excursions`` (times in s from the start of the
range analysed, rows of the range in ``samples``, sizes in the deviation's field unit: mg,
deg/h), groups the axes' excursions that overlap in time into the record's ``excursions``
(the axes that move together), marks those inside an axis' quiet stretch, and words them.

Like the spikes, excursions are reported and never folded silently into the noise: the
whole record's fit sees them (they are part of the record), and the text says so, axis by
axis; by default (``--excursions exclude``) those inside an axis' quiet stretch are left out
of its fit, their windows gaps handled as the record's own gaps are
(:func:`rigctl.analysis.allan_quiet.add_quiet_stretches`); ``--excursions report`` keeps them
in it.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..solvers import allan_excursions as EX
from ..solvers import allan_step as ST
from ..solvers.noise_coefficients import as_coefficients
from .allan_drift import LEVEL_UNITS


def axis_excursions(ybar: np.ndarray, block_s: float, tau0: float, sensor: str,
                    fit: dict[str, Any] | None = None) -> dict[str, Any]:
    """The detector's result for one axis, with each excursion's size in the field unit
    (``size_<unit>``) and its rows of the range analysed (``samples``: [first, end)).

    A record too short for it (960 s) gets the step test against the fit's noise levels
    instead (:func:`short_record_step`, in ``step_test``), when ``fit`` is given: a step it
    finds is reported as a level shift, as the detector's are."""
    r = EX.find_excursions(ybar, block_s, min_s=max(EX.MIN_S, EX.MIN_SAMPLES * tau0))
    if not r.get("tested") and fit is not None:
        r["step_test"] = st = short_record_step(ybar, block_s, fit)
        if st.get("found"):
            k = int(round(st["t_s"] / block_s))
            r["excursions"] = [{"start_s": st["t_s"], "end_s": st["t_s"], "duration_s": 0.0,
                                "size_si": st["size_si"], "kind": "level shift",
                                "z_start": st["z"], "z_end": float("nan"), "blocks": [k, k],
                                "found_by": "step test"}]
    unit, fac = LEVEL_UNITS[sensor]
    r["unit"] = unit
    for e in r.get("excursions", []):
        e[f"size_{unit}"] = e["size_si"] * fac
        e["samples"] = [int(round(e["start_s"] / tau0)), int(round(e["end_s"] / tau0))]
    if r.get("tested"):
        r[f"robust_adev_{unit}"] = [v * fac for v in r["robust_adev_si"]]
    return r


def short_record_step(ybar: np.ndarray, block_s: float, fit: dict[str, Any]) -> dict[str, Any]:
    """:func:`rigctl.solvers.allan_step.step_test` with the fit's 95 % upper ends of Q, N, B
    and K (a term's bound where it is one); not run beside a Gauss-Markov term (the test's
    covariance has none: said in ``skipped``)."""
    if fit.get("gm_term"):
        return {"tested": False, "found": False,
                "skipped": "the fit has a Gauss-Markov term, which the step test's noise "
                           "model does not hold"}
    co = as_coefficients(fit["coefficients"])
    levels = {}
    for t in ("Q", "N", "B", "K"):
        c = getattr(co, t)
        hi = c.ci95[1] if c.resolved and c.ci95 is not None else c.upper95
        levels[t] = float(hi) if hi is not None and np.isfinite(hi) else 0.0
    return ST.step_test(ybar, block_s, levels)


def group(axes: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The axes' excursions merged where their windows overlap (a level shift counts as its
    instant): [{"start_s", "end_s", "axes": [...], "members": [{"axis", "start_s", "end_s",
    "kind", "size", "unit"}, ...]}], in time order -- the axes listed moved together (an axis
    may have more than one member when others' excursions join them)."""
    items = []
    for a, r in axes.items():
        ex = (r.get("excursions") or {}).get("excursions") or []
        unit = (r.get("excursions") or {}).get("unit", "")
        for e in ex:
            items.append((e["start_s"], e["end_s"], a, e, unit))
    items.sort(key=lambda t: (t[0], t[1]))
    out: list[dict[str, Any]] = []
    for s, t, a, e, unit in items:
        if out and s <= out[-1]["end_s"] and t >= out[-1]["start_s"]:
            g = out[-1]
            g["end_s"] = max(g["end_s"], t)
            g["start_s"] = min(g["start_s"], s)
        else:
            g = {"start_s": s, "end_s": t, "axes": [], "members": []}
            out.append(g)
        if a not in g["axes"]:
            g["axes"].append(a)
        g["members"].append({"axis": a, "start_s": e["start_s"], "end_s": e["end_s"],
                             "kind": e["kind"], "size": e[f"size_{unit}"], "unit": unit})
    for g in out:  # each axis' excursions: the axes that moved with it
        for a in g["axes"]:
            for e in (axes[a].get("excursions") or {}).get("excursions") or []:
                if g["start_s"] <= e["start_s"] <= g["end_s"]:
                    e["moving_with"] = [b for b in g["axes"] if b != a]
    return out


def mark_quiet(r: dict[str, Any], tau0: float) -> None:
    """In the axis' ``quiet_stretch`` (when there is one), the axis' excursions that lie in
    it (``excursions_inside``): times from the range's start."""
    q = r.get("quiet_stretch")
    ex = (r.get("excursions") or {}).get("excursions") or []
    if not q or not ex:
        return
    a, b = q["t_s"]
    q["excursions_inside"] = [e for e in ex if e["end_s"] > a and e["start_s"] < b]


def describe(e: dict[str, Any], unit: str) -> str:
    """One excursion in words: 't = 2150-2478 s (328 s), +1.26 mg'."""
    size = f"{e[f'size_{unit}']:+.3g} {unit}"
    if e["kind"] == "level shift":
        return f"a level shift at t = {e['start_s']:.0f} s ({size}, the step found)"
    what = {"to the start": ", from the start of the range",
            "to the end": ", to the end of the range"}.get(e["kind"], "")
    return f"t = {e['start_s']:.0f}-{e['end_s']:.0f} s ({e['duration_s']:.0f} s{what}), {size}"


def sentences(r: dict[str, Any]) -> list[str]:
    """The axis' excursions as warnings (what, where, how large, with which axes it moved;
    that the fit sees them); [] when none was found or the test did not run."""
    x = r.get("excursions") or {}
    ex = x.get("excursions") or []
    if not ex:
        return []
    unit = x["unit"]
    parts = []
    for e in ex:
        text = describe(e, unit)
        if e.get("moving_with"):
            text += f", moving with {', '.join(e['moving_with'])}"
        parts.append(text)
    st = x.get("step_test") or {}
    if st.get("found"):
        head = (f"a step of the level found before the fit (the record is too short for the "
                f"window test, so a step was looked for against the fit's noise levels: "
                f"z {st['z']:+.2f} beyond {st['threshold_z']:.2f}, and the level holds on "
                f"both sides: the sides' least-squares means differ by z "
                f"{st['hold']['z']:+.2f} beyond {st['hold']['threshold_z']:.2f} against the "
                f"noise without its random walk; false-alarm probability {st['alpha']:g} per "
                f"axis on Gaussian white, flicker and random-walk noise; a phone gyro that "
                f"dwells on its levels alarmed in 0 of 207 5-minute windows (docs/allan.md, "
                f"Detection limits); the fit's terms have absorbed it): ")
    else:
        head = (f"{len(ex)} short excursion(s) of the level found before the fit (windows of "
                f"{x['min_s']:.3g} s to 1/{round(1 / EX.MAX_FRACTION)} of the record, judged "
                f"against the record's own robust Allan deviation there; family-wise "
                f"false-alarm probability {x['alpha']:g} per axis): ")
    return [head + "; ".join(parts) + ". Not the sensor's stationary noise: they are in the "
            "whole record's samples and fit; inside a quiet stretch they are left out of its fit "
            "(--excursions exclude, the default; --excursions report keeps them)"]


def quiet_sentence(q: dict[str, Any], unit: str) -> list[str]:
    """The excursions inside the quiet stretch, named, and whether they were left out of its
    fit ([] if none)."""
    inside = q.get("excursions_inside") or []
    if not inside:
        return []
    head = (f"the quiet stretch holds {len(inside)} of the excursions found: "
            + "; ".join(describe(e, unit) for e in inside)
            + " (the stationarity test's windows are too long to see them)")
    ex = q.get("excursions_excluded")
    if ex:
        return [f"{head}; left out of its fit (--excursions exclude, {ex['n_samples']} samples "
                f"in {len(ex['samples'])} window(s)): {ex['handled']}"]
    return [f"{head}; they are in its fit (--excursions report): to leave them out, "
            "--excursions exclude (the default)"]

