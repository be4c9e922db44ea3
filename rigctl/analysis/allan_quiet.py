"""Non-stationary records: the terms fitted again on the quiet stretch, beside the whole
record's (docs/allan.md, "Non-stationary records: the quiet stretch").

When the self-check's stationarity test (:func:`rigctl.analysis.allan_drift.name_bumps`,
:mod:`rigctl.solvers.allan_stationarity`) finds the record not stationary at a run of taus
(the Allan variance there differs across the record's equal windows beyond chance: Bartlett
p below its alpha -- whether the run is then named "not stationary noise", cause
``nonstationary``, or the median window has the bump too), no stationary noise model
describes the whole record, and its fitted terms mix the noise with a disturbance in part of
it. The test also names the *quiet stretch*: the longest run of consecutive windows whose
Allan variances at the tau tested agree (Bartlett p >= its alpha), the lowest level among runs
of that length. This module takes that stretch, analyses it on its own (the same pipeline,
the same tau set, its own curve, noise identification, EDF, fit and self-check) and puts the
result in the axis' ``quiet_stretch`` -- beside the whole record's ``fit``, which is left as
it was (its terms, its self-check and its verdict stay the record's).

The rule, stated once:

* **When.** An axis gets a quiet-stretch fit when the stationarity test finds at least one
  run of its self-check not stationary (never on a record with gaps skipped: the test does
  not run there). With several such runs, the one whose tested tau lies nearest (in log tau) to the curve's floor
  (its minimum over the informative taus, hi95/lo95 <= 2) -- the taus B is read at.
* **Which stretch.** The quiet stretch that run's test names (``stationarity.quiet_samples``,
  samples of the range analysed).
* **Length limits.** At least :data:`MIN_WINDOWS` of the test's windows and at least
  :data:`MIN_FRACTION` of the range analysed (each window holds at least 10x the tau tested,
  so the stretch holds at least 20x it); at most the range less one window (a stretch as long
  as the record would mean the windows agree: the run would not have been named).
* **When none qualifies.** ``quiet_stretch`` says so (``fitted`` false, ``reason``: the
  longest stretch found and the limit it misses), and the whole record's terms are the only
  ones reported.
* **One level.** The stretch's own self-check is reported as it comes out (it may name runs
  of its own, stationary or not); no stretch of the stretch is taken.
"""
from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from ..errors import InputError

#: a quiet stretch holds at least this many of the stationarity test's windows ...
MIN_WINDOWS = 2
#: ... and at least this share of the range analysed
MIN_FRACTION = 0.25

RULE = ("the record's Allan variance at the taus of a run the self-check names is not the same "
        "across its windows (not stationary): the terms are also fitted on the quiet stretch the "
        "stationarity test names (the longest run of windows whose variances agree there; at least "
        f"{MIN_WINDOWS} windows and {100 * MIN_FRACTION:.0f} % of the range), beside the whole record's")


def _informative_floor_tau(r: dict[str, Any]) -> float | None:
    """The tau of the curve's minimum over its informative taus (hi95/lo95 <= 2), or None."""
    unit = r.get("_unit")
    if unit is None:
        return None
    tau = np.asarray(r["tau_s"], dtype=float)
    dev = np.asarray(r[f"adev_{unit}"], dtype=float)
    lo, hi = np.asarray(r[f"lo95_{unit}"], dtype=float), np.asarray(r[f"hi95_{unit}"], dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = np.isfinite(dev) & (lo > 0) & (hi / lo <= 2.0)
    if not ok.any():
        return None
    return float(tau[ok][np.argmin(dev[ok])])


def nonstationary_run(r: dict[str, Any]) -> dict[str, Any] | None:
    """The run of the axis' self-check whose quiet stretch is taken (module docstring: of the
    runs the stationarity test finds not stationary, the one nearest the floor), or None."""
    runs = [o for o in (r.get("fit") or {}).get("check", {}).get("outside") or []
            if (o.get("stationarity") or {}).get("tested")
            and not o["stationarity"].get("stationary", True)
            and "quiet_samples" in o["stationarity"]]
    if not runs:
        return None
    t_floor = _informative_floor_tau(r)
    if t_floor is None or len(runs) == 1:
        return runs[0]
    return min(runs, key=lambda o: abs(math.log(o["stationarity"]["tau_s"] / t_floor)))


def choose(r: dict[str, Any], tau0: float) -> dict[str, Any] | None:
    """The quiet stretch of one analysed axis by the rule (module docstring): None when the
    stationarity test finds no run not stationary; else {"fitted": whether it qualifies (the analysis not run yet),
    "rule", "run" (the run and its test), "samples" [a, b) of the range analysed, "t_s",
    "fraction", "windows", "deviation_ratio_at_run" (the stretch's deviation over the record's
    at the tau tested), "reason" when it does not qualify}."""
    o = nonstationary_run(r)
    if o is None:
        return None
    st = o["stationarity"]
    a, b = (int(v) for v in st["quiet_samples"])
    n = int(r["n_samples"])
    k = int(st["windows"])
    windows = int(round((b - a) * tau0 / st["window_s"])) if st.get("window_s") else 0
    out = {"fitted": False, "rule": RULE,
           "run": {"tau_from_s": o["tau_from_s"], "tau_to_s": o["tau_to_s"],
                   "tau_tested_s": st["tau_s"], "p_value": st["p_value"], "alpha": st["alpha"],
                   "windows": k, "window_s": st["window_s"]},
           "samples": [a, b], "t_s": [a * tau0, b * tau0], "fraction": (b - a) / max(n, 1),
           "windows": windows, "deviation_ratio_at_run": float(st["quiet"][2]),
           "min_windows": MIN_WINDOWS, "min_fraction": MIN_FRACTION}
    if windows < MIN_WINDOWS or (b - a) < MIN_FRACTION * n:
        out["reason"] = (f"no quiet stretch qualifies: the longest whose windows agree at "
                         f"{st['tau_s']:.3g} s, t = {a * tau0:.0f}-{b * tau0:.0f} s, holds {windows} of the "
                         f"{k} windows ({100 * (b - a) / max(n, 1):.0f} % of the range); a fit of its own "
                         f"needs at least {MIN_WINDOWS} windows and {100 * MIN_FRACTION:.0f} % of the range")
        return out
    if b - a >= n:  # cannot happen for a run named not stationary (the windows disagree)
        out["reason"] = "the stretch is the whole range: nothing to fit beside it"
        return out
    out["fitted"] = True
    return out


#: the analysis' keys kept in ``quiet_stretch`` (the same meaning as the axis' own)
KEPT = ("sensor", "n_samples", "mode", "spikes", "quantization", "tones", "warmup", "tau_s", "m",
        "stride", "n_terms", "alpha", "edf", "fit", "piecewise", "temperature", "_si", "_unit")


#: what to do with the short excursions found before the fit
#: (:mod:`rigctl.analysis.allan_excursions`): report them only, or also leave those inside
#: an axis' quiet stretch out of its fit (their windows gaps, handled as ``--gaps`` says)
EXCURSION_MODES = ("report", "exclude")
#: the default: leave them out of the quiet stretch's fit (the stretch is the record without
#: its disturbances; the whole record's fit keeps them either way). On the real captures in
#: tests/data every window it leaves out is an event the other axes show too (docs/allan.md,
#: "Short excursions before the fit")
DEFAULT_EXCURSIONS = "exclude"


def _excluded(r: dict[str, Any], qa: int, qb: int) -> list[tuple[int, int]]:
    """The axis' excursion windows inside samples [qa, qb) of the range, clipped (level
    shifts, which have no window, are not among them)."""
    ex = (r.get("excursions") or {}).get("excursions") or []
    out = []
    for e in ex:
        a, b = (int(v) for v in e["samples"])
        a, b = max(a, qa), min(b, qb)
        if b > a:
            out.append((a, b))
    return sorted(out)


def _pieces(qa: int, qb: int, drop: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """[qa, qb) without the windows ``drop`` (sorted, inside it)."""
    out, at = [], qa
    for a, b in drop:
        if a > at:
            out.append((at, a))
        at = max(at, b)
    if qb > at:
        out.append((at, qb))
    return out


def add_quiet_stretches(result: dict[str, Any],
                        analyse: Callable[..., dict[str, Any]],
                        corrections: dict[str, dict] | None = None,
                        excursions: str = DEFAULT_EXCURSIONS, gaps: str = "skip") -> int:
    """Each axis of ``result`` (:func:`rigctl.analysis.allan.compute`'s) whose self-check
    names a run not stationary gets ``quiet_stretch`` (:func:`choose`); where it qualifies,
    the stretch analysed by ``analyse(axes, (first, last) rows of the recording, corrections)``
    (:func:`rigctl.analysis.allan.compute_once`) is merged in (its curve, fit, self-check,
    screening: the keys :data:`KEPT`). ``corrections``: per axis, the temperature term the
    whole record had subtracted (rows relative to the range's start; shifted to the
    stretch's). Returns the number of axes fitted on a quiet stretch.

    With ``excursions="exclude"`` the axis' excursions inside the stretch
    (``excursions_excluded``: their windows, samples and how they were handled) are left
    out of its fit as gaps made on purpose, handled as the record's gaps are (``gaps``):
    skipped (Allan terms touching one left out, Stable32's), bridged (said so), the longest
    piece without one analysed, or refused (no fit, the reason saying what to do);
    ``analyse`` then takes a fourth argument, the rows [a, b) of the recording to leave out.
    The stretch's ``pieces``: the samples [a, b) of the range its fit ran over."""
    tau0 = 1.0 / float(result["sample_rate_hz"])
    s0 = int(result.get("first_sample", 0))
    done = 0
    for a, r in result["axes"].items():
        q = choose(r, tau0)
        if q is None:
            continue
        r["quiet_stretch"] = q
        if not q["fitted"]:
            continue
        qa, qb = q["samples"]
        drop = _excluded(r, qa, qb) if excursions == "exclude" else []
        q["pieces"] = [[qa, qb]]
        if drop:
            unit = (r.get("excursions") or {}).get("unit", "")
            q["excursions_excluded"] = {
                "windows_s": [[a * tau0, b * tau0] for a, b in drop],
                "samples": [[a, b] for a, b in drop],
                "n_samples": int(sum(b - a for a, b in drop)), "gaps": gaps,
                "handled": {"skip": "skipped (Allan terms touching a window left out, as the "
                                    "record's gaps are: Stable32)",
                            "bridge": "bridged on request (--gaps bridge): the samples on either "
                                      "side joined, taus spanning a window biased",
                            "longest": "the longest piece of the stretch without one analysed "
                                       "(--gaps longest)",
                            "refuse": "refused (--gaps refuse)"}[gaps], "unit": unit}
            if gaps == "refuse":
                q["fitted"] = False
                q["reason"] = (f"{len(drop)} excursion(s) inside the quiet stretch would leave gaps "
                               "(--excursions exclude) and --gaps refuse refuses gaps: --gaps skip "
                               "leaves out every Allan term that touches one (Stable32), --gaps "
                               "longest fits the longest piece without one")
                continue
            if gaps == "longest":
                qa, qb = max(_pieces(qa, qb, drop), key=lambda p: p[1] - p[0])
                q["pieces"] = [[qa, qb]]
                drop = []
            else:
                q["pieces"] = [list(p) for p in _pieces(qa, qb, drop)]
        corr = None
        if corrections and a in corrections:
            c = corrections[a]
            corr = {a: {**c, "rows": (np.asarray(c["rows"], dtype=float) - qa).tolist()}}
        try:
            got = (analyse([a], (s0 + qa, s0 + qb), corr, [(s0 + x, s0 + y) for x, y in drop])
                   if drop else analyse([a], (s0 + qa, s0 + qb), corr))
        except InputError as exc:  # too short for its own analysis, or a gap found there
            q["fitted"] = False
            q["reason"] = f"the quiet stretch could not be analysed on its own: {exc}"
            continue
        rq = got["axes"][a]
        q.update({k: rq[k] for k in KEPT if k in rq})
        for k in rq:
            if k.startswith(("adev_", "lo68_", "hi68_", "lo95_", "hi95_")):
                q[k] = rq[k]
        q["first_sample"] = int(got.get("first_sample", s0 + qa))
        done += 1
    return done
