"""IMU restarts in a recording (application layer): the ``device-restart`` events (the unit
lost power mid-procedure; docs/daemon.md) with calibration windows on both sides, and the lines
that say so. One piece for the 24-position / rate calibration
(:mod:`rigctl.analysis.calibration`, docs/calibration.md section 2) and the thermal one
(:mod:`rigctl.analysis.thermal`, docs/thermal.md): a restart gives the unit a new turn-on bias,
which neither model has a term for.
"""
from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..recording.recording_reader import check_need
from ..recording.segment_builder import CAL_KINDS, open_recording


def device_restart_events(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """The recording's ``device-restart`` events (the engine saw the IMU's driver count a restart:
    docs/daemon.md): their times (s, /imu/time's axis) and messages; none in a recording without
    /events (an import)."""
    with open_recording(path) as f:
        return _device_restarts(f, Path(path))


def _device_restarts(f: h5py.File, p: Path) -> tuple[np.ndarray, list[str]]:
    """:func:`device_restart_events` of the open recording ``f`` (the file ``p``); its /events
    checked as a reader's (InputError, not KeyError) when it has them."""
    if "events" not in f:  # (a recording imported from a log has none)
        return np.empty(0), []
    check_need(f, p, ("events",))
    ev_t, ev_k, ev_m = (f["events"][k][()] for k in ("time", "kind", "message"))
    sel = np.asarray(ev_k) == b"device-restart"
    return np.asarray(ev_t, float)[sel], [m.decode("utf-8", "replace") for m in np.asarray(ev_m)[sel]]


#: a constant bias under the solvers' names (rigctl.solvers.segments.truth_from_emulator, the
#: thermal fit's truth_coefficients): one value that a power cycle of the unit does not keep
_CONSTANT_BIAS = re.compile(r"^(accel|gyro)_bias_[xyz]_(m_s2|rad_s)$")


def truth_power_cycles(f: h5py.File) -> np.ndarray:
    """The run times (s, /imu/time's axis) at which the emulated IMU was power-cycled and came
    back with another turn-on bias: the rows of /truth/imu_power_cycles (docs/data-format.md) whose
    drawn biases differ from the ones before (the first row: from the turn-on bias /truth's
    params_json holds; a repeatability of 0 draws the same bias again). None in a recording
    without that table (a real rig, an import, an older emulated recording)."""
    g = f.get("truth/imu_power_cycles")
    if not isinstance(g, h5py.Group) or "time_s" not in g:
        return np.empty(0)
    t = np.asarray(g["time_s"][()], float)
    drawn = np.hstack([np.asarray(g[k][()], float).reshape(t.size, 3)
                       for k in ("gyro_turn_on_bias_rad_s", "accel_turn_on_bias_m_s2")])
    imu = json.loads(f["truth"].attrs.get("params_json", "{}")).get("imu", {})
    first = [imu.get(k, imu.get(alt)) for k, alt in (("gyro_turn_on_bias_rad_s", "gyro_turn_on_bias_rad_per_s"),
                                                      ("accel_turn_on_bias_m_s2", "accel_turn_on_bias_m_per_s2"))]
    before = np.vstack([np.hstack([np.zeros(3) if b is None else np.asarray(b, float).reshape(3) for b in first]),
                        drawn[:-1]])
    return t[np.any(drawn != before, axis=1)]


def truth_across_power_cycles(f: h5py.File, truth: dict[str, float] | None) -> tuple[dict[str, float] | None, str]:
    """``truth`` (solver names -> true value, from /truth's params_json: the unit as it was turned
    on for the run) without the constant biases when the emulated IMU was power-cycled during the
    recording (:func:`truth_power_cycles`): each cycle drew a new turn-on bias
    (/truth/imu_power_cycles), so the bias was not one value -- compared with the first turn-on's
    it would call the fit wrong by the drawn step. Returns (the truth to compare with, a line saying
    why the biases are left out; "" when nothing is)."""
    cycles = truth_power_cycles(f)
    if truth is None or not cycles.size:
        return truth, ""
    kept = {k: v for k, v in truth.items() if not _CONSTANT_BIAS.match(k)}
    at = ", ".join(f"{x:.1f}" for x in cycles[:4]) + (" ..." if cycles.size > 4 else "")
    return kept, (f"biases not compared with the emulator's truth: the IMU was power-cycled at t = {at} s "
                  "and drew a new turn-on bias each time (/truth/imu_power_cycles); the other parameters "
                  "are compared")


def time_base_restarts(t: np.ndarray) -> np.ndarray:
    """The rows at which a record's time base began again behind its last stamp, t[k] < t[k-1]:
    the device time restarted, so the unit lost power (as drivers/xsens_decode.py counts
    ``device_restarts``). A jump forward is not one -- a gap, or a reconnect's reconfiguration
    (the decoder's ``time_restarts`` counts those too, and a power loss is not what they are)."""
    t = np.asarray(t, float)
    return np.flatnonzero(np.diff(t) < 0) + 1


def restarts_by_row(path: str | Path, t: np.ndarray) -> list[dict[str, Any]]:
    """Every IMU restart of a recording whose /imu/time is ``t``, as a row of /imu (the first
    sample of the new turn-on), sorted: its ``device-restart`` events (:func:`device_restart_events`;
    the row is the first sample at or after the event's time) and the rows where the time base began
    again behind its last stamp (:func:`time_base_restarts`). Each ``{"row", "time_s", "event",
    "seen"}`` (and ``at`` where ``time_s`` alone does not place it): ``time_s`` the first sample's
    time after it, ``seen`` how it shows in the record."""
    t = np.asarray(t, float)
    ev_t, ev_m = device_restart_events(path)
    out = [{"row": int(np.searchsorted(t, x)), "time_s": float(x), "event": m, "seen": "device-restart"}
           for x, m in zip(ev_t, ev_m)]
    for k in time_base_restarts(t):
        at = f"row {int(k)} of /imu (/imu/time {t[k - 1]:.6g} s -> {t[k]:.6g} s)"
        out.append({"row": int(k), "time_s": float(t[k]), "at": at, "seen": "time base began again",
                    "event": f"/imu/time began again behind its last stamp at {at}"})
    return sorted(out, key=lambda n: n["row"])


def window_sides(found: list[dict[str, Any]], rows: np.ndarray, group: np.ndarray) -> list[dict[str, Any]]:
    """The restarts of :func:`restarts_by_row` with windows on both sides, for :func:`restart_lines`:
    ``rows`` (n, 2) each window's first and end (exclusive) row of /imu, ``group`` (n,) the name of
    each window's group (a pose). ``before`` / ``after``: each group once, in order, with its count
    of windows on that side (``pose 'z up' (12 windows)``); ``windows_before`` / ``windows_after``:
    the windows' indices. A window that straddles a restart is on neither side."""
    rows = np.asarray(rows, int).reshape(-1, 2)

    def names(sel: np.ndarray) -> list[str]:
        g = [str(x) for x in np.asarray(group)[sel]]
        return [f"{x} ({g.count(x)} window{'s' if g.count(x) > 1 else ''})" for x in dict.fromkeys(g)]
    out = []
    for n in found:
        rb, ra = np.flatnonzero(rows[:, 1] <= n["row"]), np.flatnonzero(rows[:, 0] >= n["row"])
        if rb.size and ra.size:
            out.append({**n, "before": names(rb), "after": names(ra),
                        "windows_before": rb.tolist(), "windows_after": ra.tolist()})
    return out


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
    with open_recording(path) as f:  # once: the events and the segments of one state of the file
        ev_t, ev_m = _device_restarts(f, Path(path))
        if not ev_t.size:
            return []
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
    for t, m in zip(ev_t, ev_m):
        rb, ra = np.flatnonzero(used & (seg["t_end"] <= t)), np.flatnonzero(used & (seg["t_start"] >= t))
        if rb.size and ra.size:
            out.append({"time_s": float(t), "event": m,
                        "before": [names[i] for i in rb], "after": [names[i] for i in ra]})
            if within:
                out[-1].update(within_before=in_effect(rb), within_after=in_effect(ra))
    return out


#: what a bias step across a restart does to the turntable calibration, and what to do
TABLE_RESTART = ("a bias step between them is absorbed into scale factor / misalignment -- measure the positions "
                 "of one side again after a warm-up, or calibrate one side only")


def restart_lines(notes: list[dict[str, Any]], what: str = "positions", consequence: str = TABLE_RESTART,
                   context: Callable[[dict[str, Any], str], str] | None = None) -> list[str]:
    """One line per restart of :func:`restart_notes` (or :func:`window_sides`), naming the ``what`` (positions, windows) on
    each side; ``context(note, 'before' | 'after')`` adds to a side's list (the thermal run's
    chamber steps and temperatures); ``consequence``: what the step does to the fit, and the remedy."""
    def span(names: list[str]) -> str:
        return ", ".join(names) if len(names) <= 4 else f"{names[0]} ... {names[-1]} ({len(names)} {what})"

    def side(n: dict[str, Any], key: str) -> str:
        return span(n[key]) + (context(n, key) if context else "")

    def at(n: dict[str, Any]) -> str:
        return n.get("at") or f"t = {n['time_s']:.1f} s"
    return [f"IMU restarted at {at(n)} ({n.get('seen', 'device-restart')}: power lost): {what} measured before it "
            f"({side(n, 'before')}) and after it ({side(n, 'after')}) have different turn-on biases; {consequence}"
            for n in notes]


def untrusted_lines(reasons: list[str]) -> list[str]:
    """The end of a thermal result's text when it is not trusted for ``reasons`` (the lines of
    :func:`restart_lines`): a blank line, each as a warning, and the STATUS line; none without."""
    return ["", *(f"warning: {line}" for line in reasons), f"STATUS: NOT TRUSTWORTHY: {reasons[0]}"] if reasons else []
