"""False alarms of the IEEE 952 fit on pure noise, over many seeds (the bigger runs behind
tests/test_allan_false_alarms.py, whose series, curves and EDFs this script reuses).

* false B: white noise + rate random walk (no bias instability), 1 h at 20 Hz, raw and through
  a 3-tap low-pass (1/4, 1/2, 1/4), with octave and 40 log-spaced taus: how often B comes out
  as an estimate (design: B_TEST_ALPHA, 2.5 %); and through a 2nd-order Butterworth at 4 Hz
  on a 200 Hz stream decimated to 20 Hz (an IMU's anti-aliasing filter);
* self-check on the same raw noise, octave and dense ('all') taus: how often it fails, and how
  often some informative tau is outside its pointwise band / the family-wise band (by > 10 %);
* self-check on N + B + K with an octave Gauss-Markov flicker (tests/allan_synth.py), the gyro
  and accelerometer coefficients of mti_class and consumer_mems, 2 h at 100 Hz (the flicker is
  an approximation, so part of these departures are real model error).

Prints one line per case, then one JSON object (rates in per cent, times in s).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np
from scipy.signal import butter, lfilter

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
import test_allan_false_alarms as T  # noqa: E402 - the tests' own series and curves
from allan_synth import synth_rate  # noqa: E402

from rigctl.solvers import allan as A  # noqa: E402
from rigctl.solvers import allan_edf as E  # noqa: E402
from rigctl.solvers import allan_fit as F  # noqa: E402

FLICKER = {"mti_class_gyro": (1.22e-4, 3.88e-5, 1e-6, "gyro"),
           "mti_class_accel": (5.9e-4, 1.47e-4, 3e-6, "accel"),
           "consumer_mems_gyro": (8.73e-5, 4.85e-5, 2e-6, "gyro"),
           "consumer_mems_accel": (3.92e-3, 1.5e-3, 3e-5, "accel")}


def _fit(tau, dev, edf, sensor="gyro", tau0=1.0 / T.FS, n_phase=T.N_SAMPLES + 1):
    return F.fit_terms(tau, dev, edf, sensor, tau0=tau0, n_phase=n_phase)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--flicker-seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=20_000)
    args = ap.parse_args()
    t_start = time.time()
    out: dict = {"seeds": args.seeds, "flicker_seeds": args.flicker_seeds,
                 "b_test_alpha_pct": 100 * F.B_TEST_ALPHA,
                 "check_alpha_pct": 100 * F.CHECK_ALPHA}
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    for lowpass in (False, True):
        for kind in ("octave", "40"):
            ms = T._factors(kind)
            n_b = 0
            for s in seeds:
                n_b += _fit(*T._curve(T._series(s, lowpass), ms))["coefficients"].B.resolved
            key = f"false_b_{'lowpass' if lowpass else 'raw'}_{kind}_pct"
            out[key] = 100.0 * n_b / args.seeds
            print(f"{key}: {out[key]:.1f} ({n_b} of {args.seeds})", flush=True)
    # a real IMU's filter: 2nd-order Butterworth at 4 Hz on a 200 Hz stream, every 10th kept
    up = 10
    bb, aa = butter(2, 4.0 / (T.FS * up / 2.0))
    for kind in ("octave", "40"):
        ms = T._factors(kind)
        n_b = 0
        for s in seeds:
            rng = np.random.default_rng(s)
            dt, n = 1.0 / (T.FS * up), T.N_SAMPLES * up
            y = (rng.standard_normal(n) * (T.N_TRUE / math.sqrt(dt))
                 + np.cumsum(rng.standard_normal(n)) * (T.K_TRUE * math.sqrt(dt)))
            y = lfilter(bb, aa, y)[::up]
            n_b += _fit(*T._curve(y, ms))["coefficients"].B.resolved
        key = f"false_b_butterworth_{kind}_pct"
        out[key] = 100.0 * n_b / args.seeds
        print(f"{key}: {out[key]:.1f} ({n_b} of {args.seeds})", flush=True)
    for kind in ("octave", "all"):
        ms = T._factors(kind)
        c = {"fail": 0, "pointwise": 0, "familywise": 0}
        for s in seeds:
            ch = _fit(*T._curve(T._series(s, False), ms))["check"]
            c["fail"] += not ch["ok"]
            c["pointwise"] += ch["n_outside"] > 0
            c["familywise"] += ch["n_outside_familywise"] > 0
        for k, v in c.items():
            out[f"check_{k}_white_rw_{kind}_pct"] = 100.0 * v / args.seeds
        print(f"white + RW, {kind} ({len(ms)} taus): check failed {c['fail']}, some tau outside "
              f"the pointwise band {c['pointwise']}, the family-wise band {c['familywise']} "
              f"of {args.seeds}", flush=True)
    fs, n = 100.0, int(2 * 3600 * 100)
    c = {k: {"fail": 0, "pointwise": 0, "familywise": 0, "n": 0} for k in ("octave", "all")}
    for s in range(args.first_seed, args.first_seed + args.flicker_seeds):
        for j, (nn, bb, kk, sensor) in enumerate(FLICKER.values()):
            y = synth_rate(n, fs, nn, bb, kk, seed=100 * s + j)
            x = A.phase_from_rate(y, 1.0 / fs)
            for kind in c:
                ms = A.tau_factors(n + 1, kind, "oadev")
                if kind == "all":
                    ms = A.snap_fast(ms)
                    ms = ms[ms <= A.max_factor(n + 1, "oadev")]
                r = A.oadev(y, 1.0 / fs, ms, data_type="rate", mode="exact")
                edf = E.confidence("oadev", x, r.m, r.dev)["edf"]
                ch = _fit(r.tau_s, r.dev, edf, sensor, 1.0 / fs, r.n_phase)["check"]
                c[kind]["n"] += 1
                c[kind]["fail"] += not ch["ok"]
                c[kind]["pointwise"] += ch["n_outside"] > 0
                c[kind]["familywise"] += ch["n_outside_familywise"] > 0
    for kind, v in c.items():
        for k in ("fail", "pointwise", "familywise"):
            out[f"check_{k}_flicker_{kind}_pct"] = 100.0 * v[k] / max(v["n"], 1)
        print(f"N + B + K (octave Gauss-Markov flicker), {kind}: check failed {v['fail']}, some "
              f"tau outside the pointwise band {v['pointwise']}, the family-wise band "
              f"{v['familywise']} of {v['n']}", flush=True)
    out["wall_s"] = round(time.time() - t_start, 1)
    out["load_1min"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
