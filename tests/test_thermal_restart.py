"""A thermal calibration across an IMU restart is not trusted.

A unit that lost power comes back with a new turn-on bias; the thermal model has one bias
polynomial in temperature per axis, so a fit over windows from both sides takes the step for a
temperature dependence. The in-process emulator on the virtual clock (seconds): three short soaks
(10, 40, 25 degC; six positions and six rate windows each), the power lost 1 s into the first
position of the 40-degC soak and back 3 s later with a 2 mg higher x accelerometer bias
(tests/test_engine_rewarm.py does the same on procedures/24pos.yaml). The engine records the
``device-restart`` and warms the unit again; ``rigctl calibrate`` must then say NOT TRUSTWORTHY
and name the windows, the chamber steps (soaks) and the temperatures on each side. The same run
without the power loss is trusted and has no such note.

Before: the thermal path never looked at restarts: the run below came out with the x bias slope
at 0.118 +- 0.002 mg/K (truth 0.05) and no warning.
"""
from __future__ import annotations

import h5py
import numpy as np

from rigctl.analysis.calibration import calibrate
from rigctl.analysis.thermal import thermal_info

from helpers import NO_TURN_ON_DRAW, derived_config
from hil_support import RunPoints, point_options, run, sampling
from hil_support import power_loss as unit_power_loss
from test_thermal import SIM_THERMAL

CYCLE = """  - orientations:
      angles_deg: [[0, 0, 0], [0, 0, 180], [0, -90, 0], [0, 90, 0], [0, 0, 90], [0, 0, -90]]
      sample: 4 s
  - rates: {axes: [x, y, z], rates_dps: [100], directions: [forward, reverse], revolutions: 1}
"""
PROC = "procedure: thermal-restart\ndefaults:\n  settle: {hold: 0.5 s, timeout: 60 s}\n  discard: 0.5 s\nsteps:\n" \
    "  - warmup: {duration: 10 s}\n" + "".join(
        f"  - chamber-wait: {{setpoint_c: {c}, stable_band_c: 0.5, stable_for: 10 s, label: soak {c} degC}}\n" + CYCLE
        for c in (10, 40, 25))
#: the bias the unit comes back with after its power loss, on x (2 mg): a new turn-on bias
STEP_M_S2 = 2e-3 * 9.80665


def _run(tmp_path, power_loss: bool):
    cfg = derived_config(tmp_path, imu__rate_hz=50, imu__sim__thermal=SIM_THERMAL, **NO_TURN_ON_DRAW,
                         chamber__sim={"heat_max_c_per_min": 20, "cool_max_c_per_min": 20, "product_tau_s": 20})
    (tmp_path / "proc.yaml").write_text(PROC)
    points = RunPoints([])
    if power_loss:  # the 7th orientation is the first position of the 40-degC soak
        points.actions.append((sampling("orientation", after_samples=50, finished=6),
                               unit_power_loss(points, np.array([STEP_M_S2, 0.0, 0.0]))))
    res, _ = run(tmp_path / "proc.yaml", cfg, tmp_path / "runs", {}, point_options(points))
    assert bool(points.fired) == power_loss
    return res.recording


def _sides(rec):
    """From the recording's own segments and events: the restarts' times and, per restart, the
    windows (complete orientation / rate segments) and the chamber steps in effect on each side."""
    with h5py.File(rec, "r") as f:
        s = {k: f["segments"][k][()] for k in ("kind", "status", "step", "label", "t_start", "t_end")}
        ev = [float(t) for t, k in zip(f["events/time"][()], f["events/kind"][()]) if k == b"device-restart"]
    name = [f"step {int(n) + 1} ({lab.decode()})" for n, lab in zip(s["step"], s["label"])]
    win = np.isin(s["kind"], (b"orientation", b"rate")) & (s["status"] == b"complete")
    chamber = np.flatnonzero(s["kind"] == b"chamber-wait")
    out = []
    for t in ev:
        sides = {}
        for key, sel in (("before", win & (s["t_end"] <= t)), ("after", win & (s["t_start"] >= t))):
            rows = np.flatnonzero(sel)
            soak = [max((c for c in chamber if s["t_start"][c] <= s["t_start"][i]), key=lambda c: s["t_start"][c])
                    for i in rows]
            sides[key] = ([name[i] for i in rows], [name[c] for c in sorted(set(soak))])
        out.append((t, sides))
    return out


def test_a_thermal_calibration_across_a_restart_is_not_trustworthy(tmp_path):
    rec = _run(tmp_path, power_loss=True)
    ((t, sides),) = _sides(rec)
    assert len(sides["before"][0]) == 12 and len(sides["after"][0]) == 24, sides
    assert sides["before"][1] == ["step 2 (soak 10 degC)"], sides
    assert sides["after"][1] == ["step 15 (soak 40 degC)", "step 28 (soak 25 degC)"], sides
    payload, text, _ = calibrate(rec, store=False)
    assert payload["mode"] == "thermal" and payload["trustworthy"] is False
    (note,) = payload["device_restarts"]
    assert abs(note["time_s"] - t) < 1e-9
    assert (note["before"], note["within_before"]) == sides["before"]
    assert (note["after"], note["within_after"]) == sides["after"]
    lo, hi = note["temperature_before_c"]
    assert 9 < lo <= hi < 11 and note["temperature_after_c"][1] > 39, note
    assert "STATUS: NOT TRUSTWORTHY: IMU restarted at t = " in text
    assert "in step 2 (soak 10 degC); IMU" in text and "in step 15 (soak 40 degC), step 28 (soak 25 degC)" in text
    assert payload["reasons"] and "temperature dependence" in payload["reasons"][0]
    assert thermal_info(payload, rec)["trustworthy"] is False  # rigctl apply-cal warns


def test_a_thermal_calibration_without_a_restart_is_unchanged(tmp_path):
    rec = _run(tmp_path, power_loss=False)
    assert _sides(rec) == []
    payload, text, _ = calibrate(rec, store=False)
    assert payload["mode"] == "thermal" and payload["device_restarts"] == [] and payload["reasons"] == []
    assert payload["trustworthy"] is True, {s: d["status"] for s, d in payload["sensors"].items()}
    assert "NOT TRUSTWORTHY" not in text and "STATUS" not in text and "restarted" not in text
    assert thermal_info(payload, rec)["trustworthy"] is True
