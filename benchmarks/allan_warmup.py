"""The start-transient (warm-up) test of the Allan pipeline on many emulated captures
(rigctl.solvers.allan_drift, as rigctl.analysis.allan_drift calls it).

* False alarms: static captures of every emulator profile (and the default IMU) started long
  after power-on (``--settled-s``, default 36000 s: the warm-up is over), ``--seeds`` seeds x 6
  axes each; the share of axes where the test finds a transient, against its alpha (1e-3 per
  axis), with a 95 % upper bound (Clopper-Pearson).
* Power-on captures of consumer_mems (8 K warm-up, 270 s time constant): how often the test
  finds the transient on each axis, and how often the fitted time constant's 95 % interval
  holds 270 s (coverage), and the amplitude's the emulated one.

The samples go straight from the emulator to the solver (block means of the raw rows: the same
input the pipeline takes from its decimated phase), no recording. The last line is one JSON
object.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
G0 = 9.80665
OMEGA = 7.292115e-5
LAT = math.radians(45.0)
AXES = ("gx", "gy", "gz", "ax", "ay", "az")


#: consumer_mems at a 10 Hz output (front end 100 Hz, filters 4.2 / 4.4 Hz, no vibration): the
#: same noise terms and warm-up, a tenth of the samples (tests/test_allan_warmup.py)
TEN_HZ = {"rate_hz": 10, "effects": {"vibration": {"enabled": False}}, "frontend": {
    "internal_rate_hz": 100, "gyro_bandwidth_hz": 4.2, "accel_bandwidth_hz": 4.4}}


def capture(case: str, hours: float, seed: int, power_on_s: float,
            overrides: dict | None = None) -> tuple[np.ndarray, float]:
    """(n, 6) samples (gyro x y z, accel x y z) of a static capture, and the rate."""
    from rigctl.sim.imu import build_imu_model
    from rigctl.yamlio import load_file

    f_up = np.array([0.0, 0.0, G0])
    w_e = np.array([0.0, OMEGA * math.cos(LAT), OMEGA * math.sin(LAT)])
    if case == "default":
        cfg = load_file(ROOT / "configs" / "sim.yaml")
        fs = float(cfg["imu"]["rate_hz"])
        model = build_imu_model(cfg["imu"]["sim"], fs, seed)
        n = int(round(hours * 3600 * fs))
        t = np.arange(n) / fs
        F, W, _ = model.apply(t, np.tile(f_up, (n, 1)), np.tile(w_e, (n, 1)))
        return np.column_stack([W, F]), fs
    from rigctl.sim.error_model import ImuErrorModel
    from rigctl.sim.profiles import get_profile

    prof = get_profile(case).with_overrides({"power_on_time_s": float(power_on_s), **(overrides or {})})
    model = ImuErrorModel.from_profile(prof, seed=seed)
    fs = model.output_rate_hz
    n = int(round(hours * 3600 * fs))
    out = []
    done = 0
    while done < n:
        m = min(1 << 16, n - done)
        g = model.sample_grid(m)
        k = g.t_internal.size
        F, W, _ = model.apply(g.t_internal, np.tile(f_up, (k, 1)), np.tile(w_e, (k, 1)))
        out.append(np.column_stack([W, F])[g.keep])
        done += m
    return np.concatenate(out), fs


def detect(y: np.ndarray, fs: float) -> list[dict]:
    from rigctl.solvers import allan_drift as D

    res = []
    k = max(1, -(-y.shape[0] // D.MAX_BLOCKS))
    for i in range(y.shape[1]):
        yb = D.aggregate(y[:, i], k)
        t = D.start_transient_test(yb, k / fs)
        if t["detected"]:
            t["fit"] = D.fit_start_transient(yb, k / fs, t["best_T_s"], y.shape[0] / fs)
        res.append(t)
    return res


def clopper_pearson_upper(k: int, n: int, conf: float = 0.95) -> float:
    from scipy.stats import beta

    return 1.0 if k >= n else float(beta.ppf(conf, k + 1, n - k))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--hours", type=float, default=2.0)
    ap.add_argument("--settled-s", type=float, default=36000.0)
    ap.add_argument("--cases", default="default,consumer_mems,mti_class,tactical,declared_only")
    ap.add_argument("--power-on-seeds", type=int, default=None,
                    help="power-on captures of consumer_mems (default: --seeds)")
    ap.add_argument("--power-on-hours", type=float, default=None,
                    help="length of the power-on captures (default: --hours)")
    ap.add_argument("--power-on-10hz", action="store_true",
                    help="power-on captures at a 10 Hz output (TEN_HZ)")
    args = ap.parse_args()
    on_hours = args.power_on_hours if args.power_on_hours is not None else args.hours
    t_start = time.perf_counter()
    cases = [c for c in args.cases.split(",") if c]
    axes_tested = alarms = 0
    where = []
    p_min = []
    for case in cases:
        for seed in range(1, args.seeds + 1):
            y, fs = capture(case, args.hours, 1000 + seed, args.settled_s)
            for a, t in zip(AXES, detect(y, fs)):
                axes_tested += 1
                p_min.append(t["p_value"])
                if t["detected"]:
                    alarms += 1
                    where.append(f"{case}:{seed}:{a}:p={t['p_value']:.2g}:T={t['best_T_s']:.3g}")
        print(f"{case}: {args.seeds} stationary captures x 6 axes, alarms so far {alarms} "
              f"({time.perf_counter() - t_start:.0f} s)", flush=True)
    truth_amp = {"gx": -4.0e-3, "gy": 3.2e-3, "gz": -2.4e-3, "ax": -0.016, "ay": 0.012,
                 "az": -(0.024 + 1.0e-4 * 8.0 * G0)}
    n_on = args.power_on_seeds if args.power_on_seeds is not None else args.seeds
    found = {a: 0 for a in AXES}
    cover_tau = {a: 0 for a in AXES}
    cover_amp = {a: 0 for a in AXES}
    replicated = {a: 0 for a in AXES}
    for seed in range(1, n_on + 1):
        y, fs = capture("consumer_mems", on_hours, 2000 + seed, 0.0,
                        TEN_HZ if args.power_on_10hz else None)
        for a, t in zip(AXES, detect(y, fs)):
            if not t["detected"] or "tau_s" not in t.get("fit", {}):
                continue
            found[a] += 1
            replicated[a] += t["fit"]["replicates"] >= 4
            lo, hi = t["fit"]["tau_ci95"]
            cover_tau[a] += lo <= 270.0 <= hi
            lo, hi = t["fit"]["amp_ci95"]
            cover_amp[a] += lo <= truth_amp[a] <= hi
    print(f"power-on consumer_mems, {n_on} captures of {on_hours:g} h"
          f"{' at 10 Hz' if args.power_on_10hz else ''}: found "
          + ", ".join(f"{a} {found[a]}" for a in AXES) + "; tau 270 s in the 95 % interval "
          + ", ".join(f"{a} {cover_tau[a]}/{found[a]}" for a in AXES) + "; amplitude "
          + ", ".join(f"{a} {cover_amp[a]}/{found[a]}" for a in AXES))
    print(json.dumps({"stationary_axes": axes_tested, "false_alarms": alarms,
                      "false_alarm_rate": alarms / max(axes_tested, 1),
                      "false_alarm_rate_upper95": clopper_pearson_upper(alarms, axes_tested),
                      "alpha_per_axis": 1e-3, "false_alarm_where": where[:20],
                      "smallest_p": float(min(p_min)) if p_min else None,
                      "power_on_captures": n_on, "power_on_found": found,
                      "tau_covered": cover_tau, "amp_covered": cover_amp,
                      "intervals_from_replicates": replicated, "power_on_hours": on_hours,
                      "power_on_10hz": bool(args.power_on_10hz),
                      "hours": args.hours, "wall_s": time.perf_counter() - t_start,
                      "load": "/".join(f"{v:.2f}" for v in os.getloadavg())}))


if __name__ == "__main__":
    main()
