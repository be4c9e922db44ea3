"""IMU restarts in a recording (application layer): the ``device-restart`` events (the unit
lost power mid-procedure; docs/daemon.md) with calibration windows on both sides, and the lines
that say so. One piece for the 24-position / rate calibration
(:mod:`rigctl.analysis.calibration`, docs/calibration.md section 2) and the thermal one
(:mod:`rigctl.analysis.thermal`, docs/thermal.md): a restart gives the unit a new turn-on bias,
which neither model has a term for.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..recording.segment_builder import CAL_KINDS, open_recording


def restart_notes(path: str | Path, within: tuple[bytes, ...] = ()) -> list[dict[str, Any]]:
    """The IMU restarts (``device-restart`` events: it lost power) with calibration positions on
    both sides: ``{"time_s", "event", "before", "after"}``, ``before`` / ``after`` naming the
    complete orientation / rate segments (``step N (label)``) that ended before / started after it.
    ``within``: segment kinds (the chamber steps of a thermal run) whose step in effect at each of
    those positions (the last of these kinds started at or before it) is named too, in
    ``within_before`` / ``within_after`` (each step once, in order).

    A restart gives the unit a new turn-on bias: the model b + M a fitted over positions with two
    biases has no term for the step between them, so it goes into the scale factors and
    misalignments (and the residuals) -- the result is not a calibration of either state."""
    with open_recording(path) as f:
        if "events" not in f:  # (a recording imported from a log has none)
            return []
    with open_recording(path, also=("events",)) as f:  # its datasets checked: InputError, not KeyError
        ev_t, ev_k, ev_m = (f["events"][k][()] for k in ("time", "kind", "message"))
        seg = {k: f["segments"][k][()] for k in ("kind", "status", "step", "label", "t_start", "t_end",
                                                  "first_sample", "last_sample")}
    used = np.isin(seg["kind"], CAL_KINDS) & (seg["status"] == b"complete") & \
        (seg["last_sample"] - seg["first_sample"] >= 2)
    names = [f"step {int(seg['step'][i]) + 1} ({seg['label'][i].decode()})" for i in range(len(used))]
    outer = np.flatnonzero(np.isin(seg["kind"], within)) if within else np.empty(0, int)

    def in_effect(rows: np.ndarray) -> list[str]:
        """The ``within`` steps in effect at these positions, each once, in order."""
        idx = [outer[seg["t_start"][outer] <= seg["t_start"][i]] for i in rows]
        return list(dict.fromkeys(names[int(o[np.argmax(seg["t_start"][o])])] for o in idx if o.size))

    out = []
    for t, k, m in zip(ev_t, ev_k, ev_m):
        if k != b"device-restart":
            continue
        rb, ra = np.flatnonzero(used & (seg["t_end"] <= t)), np.flatnonzero(used & (seg["t_start"] >= t))
        if rb.size and ra.size:
            out.append({"time_s": float(t), "event": m.decode("utf-8", "replace"),
                        "before": [names[i] for i in rb], "after": [names[i] for i in ra]})
            if within:
                out[-1].update(within_before=in_effect(rb), within_after=in_effect(ra))
    return out


#: what a bias step across a restart does to the turntable calibration, and what to do
TABLE_RESTART = ("a bias step between them is absorbed into scale factor / misalignment -- measure the positions "
                 "of one side again after a warm-up, or calibrate one side only")


def restart_lines(notes: list[dict[str, Any]], what: str = "positions", consequence: str = TABLE_RESTART,
                   context: Callable[[dict[str, Any], str], str] | None = None) -> list[str]:
    """One line per restart of :func:`restart_notes`, naming the ``what`` (positions, windows) on
    each side; ``context(note, 'before' | 'after')`` adds to a side's list (the thermal run's
    chamber steps and temperatures); ``consequence``: what the step does to the fit, and the remedy."""
    def span(names: list[str]) -> str:
        return ", ".join(names) if len(names) <= 4 else f"{names[0]} ... {names[-1]} ({len(names)} {what})"

    def side(n: dict[str, Any], key: str) -> str:
        return span(n[key]) + (context(n, key) if context else "")
    return [f"IMU restarted at t = {n['time_s']:.1f} s (device-restart: power lost): {what} measured before it "
            f"({side(n, 'before')}) and after it ({side(n, 'after')}) have different turn-on biases; {consequence}"
            for n in notes]
