"""False alarms and detections of the excursion detector (rigctl.solvers.allan_excursions),
on emulated captures of every emulator profile and on the real captures in the tests.

    python benchmarks/allan_excursions.py [--hours 12] [--seeds 20] [--full-hours 2]
                                          [--no-real] [--keep DIR]

* Emulated, noise model (``--seeds`` captures of ``--hours`` per case): the default IMU
  (configs/sim.yaml) and every profile of configs/imu-profiles.yaml, each sensor's noise terms
  as the emulator draws them (rigctl.sim.noise.NoiseGenerator with the profile's
  coefficients: white noise N, bias instability B as flicker over 1-1e4 s, rate random walk K,
  the profile's Gauss-Markov terms), generated at 10 Hz (the detector's windows are >= 30 s;
  the terms are continuous-time coefficients, so their Allan deviation at those windows does
  not depend on the output rate). Six axes per capture: 6 x seeds trials per case.
* Emulated, full model (one capture of ``--full-hours`` per profile, seed 1): the whole error
  model at the profile's rate (front end, quantization, temperature, clock), captured 900 s
  after power-on as procedures/allan-overnight.yaml does.
* Real captures in tests/data (imported with `rigctl import` as benchmarks/allan_heldout.py
  does): those with no known excursion count as false-alarm trials; the ADIS16405 (two
  ~300 s excursions on ay inside its quiet stretch, issue 15) and the 10 MHz OCXO
  (frequency excursions of 30-300 s in its first 2.7 h, docs/allan.md) are reported as
  detections, not trials.

The detector runs on each axis' block means (the record averaged down to at most 2^17 blocks,
as rigctl's pipeline keeps them; rows as stored, gap-free stretches one after the other).
A false alarm: any excursion or level shift reported on an axis. Counts per case, and the
rate per axis with its Clopper-Pearson 95 % interval, against the stated family-wise
probability (rigctl.solvers.allan_excursions.ALPHA per axis).

Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.stats import beta

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
MAX_BLOCKS = 1 << 17
PROFILES = ("default", "consumer_mems", "mti_class", "tactical", "declared_only")
NOISE_RATE_HZ = 10.0
G0 = 9.80665


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def block_means(y: np.ndarray, tau0: float) -> tuple[np.ndarray, float]:
    k = max(1, -(-y.size // MAX_BLOCKS))
    n = y.size // k
    return y[: n * k].reshape(n, k).mean(axis=1), k * tau0


def detect(y: np.ndarray, tau0: float) -> dict:
    from rigctl.solvers import allan_excursions as EX

    yb, bs = block_means(np.asarray(y, dtype=float), tau0)
    # as rigctl.analysis.allan_excursions.axis_excursions: windows of >= 16 samples
    return EX.find_excursions(yb, bs, min_s=max(EX.MIN_S, EX.MIN_SAMPLES * tau0))


def coefficients(case: str):
    """(gyro, accel) noise coefficients of a case, as the emulator draws them, and the
    flicker densities."""
    if case == "default":
        from rigctl.sim.imu import build_imu_model
        from rigctl.yamlio import load_file

        cfg = load_file(ROOT / "configs" / "sim.yaml")
        m = build_imu_model(cfg["imu"]["sim"], float(cfg["imu"]["rate_hz"]), 1)
        return tuple(m.gyro_noise), tuple(m.accel_noise), 2, 2
    from rigctl.sim.profiles import get_profile

    p = get_profile(case)
    return (p.gyro.noise.coefficients(), p.accel.noise.coefficients(),
            p.gyro.noise.flicker_density(), p.accel.noise.flicker_density())


def noise_capture(case: str, hours: float, seed: int) -> dict[str, np.ndarray]:
    from rigctl.sim.noise import NoiseGenerator

    g, a, fg, fa = coefficients(case)
    n = int(round(hours * 3600 * NOISE_RATE_HZ))
    out = {}
    # each case draws its own numbers (the same seed in two cases would repeat one path:
    # a chance step in one would be counted once per case)
    for name, co, fd, tag in (("g", g, fg, 1), ("a", a, fa, 2)):
        gen = NoiseGenerator(co, NOISE_RATE_HZ,
                             np.random.SeedSequence([seed, tag, 77, PROFILES.index(case)]), fd)
        y = gen.next(n)
        out.update({f"{name}{c}": y[:, i] for i, c in enumerate("xyz")})
    return out


def full_capture(case: str, hours: float, seed: int = 1) -> tuple[dict[str, np.ndarray], float]:
    import h5py
    from allan_profiles import emulated_recording

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "cap.h5"
        info = emulated_recording(case, p, hours, seed=seed)
        with h5py.File(p, "r") as f:
            w, s = f["imu/angular_rate"][()], f["imu/specific_force"][()]
    out = {f"g{c}": w[:, i] for i, c in enumerate("xyz")}
    out.update({f"a{c}": s[:, i] for i, c in enumerate("xyz")})
    return out, 1.0 / info["rate_hz"]


def describe(r: dict, sensor: str) -> list[str]:
    fac, unit = (1000.0 / G0, "mg") if sensor == "a" else (180 / math.pi * 3600, "deg/h")
    return [f"{e['start_s']:.0f}-{e['end_s']:.0f} s {e['kind']} {e['size_si'] * fac:+.3g} {unit}"
            for e in r.get("excursions", [])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=12.0)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--full-hours", type=float, default=2.0)
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument("--keep", help="import the real captures here (default: a temporary dir)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    from rigctl.solvers import allan_excursions as EX

    per_case: dict[str, list[int]] = {}
    alarms: list[str] = []
    for case in PROFILES:
        k = n = 0
        for seed in range(1, args.seeds + 1):
            cap = noise_capture(case, args.hours, seed)
            for ax, y in cap.items():
                r = detect(y, 1.0 / NOISE_RATE_HZ)
                n += 1
                if r.get("excursions"):
                    k += 1
                    alarms.append(f"noise {case} seed {seed} {ax}: " + "; ".join(describe(r, ax[0])))
        per_case[f"noise:{case}"] = [k, n]
        print(f"noise model {case:14s} {args.hours:g} h x {args.seeds} seeds: {k} of {n} axes "
              f"with a detection", flush=True)
    for case in PROFILES if args.full_hours > 0 else ():
        cap, tau0 = full_capture(case, args.full_hours)
        k = 0
        for ax, y in cap.items():
            r = detect(y, tau0)
            if r.get("excursions"):
                k += 1
                alarms.append(f"full {case} {ax}: " + "; ".join(describe(r, ax[0])))
        per_case[f"full:{case}"] = [k, len(cap)]
        print(f"full model  {case:14s} {args.full_hours:g} h: {k} of {len(cap)} axes with a "
              "detection", flush=True)
    known: dict[str, list[str]] = {}
    if not args.no_real:
        import allan_heldout
        from allan_heldout import captures

        allan_heldout.REUSE = bool(args.keep)  # recordings already in --keep: not imported again
        tmpd = None if args.keep else tempfile.TemporaryDirectory()
        tmp = Path(args.keep or tmpd.name)
        tmp.mkdir(parents=True, exist_ok=True)
        for cap in captures(tmp):
            if cap["name"] == "MTi-G bag gap":
                continue  # the same samples as MTi-G
            k = 0
            for ax, y in cap["si"].items():
                y = np.concatenate(y) if isinstance(y, list) else np.asarray(y, dtype=float)
                r = detect(y, cap["tau0"])
                if not r["tested"]:
                    print(f"real {cap['name']} {ax}: not tested ({r['skipped']})")
                    continue
                found = describe(r, ax[0])
                if cap["name"] in ("ADIS16405", "OCXO"):
                    known.setdefault(cap["name"], []).append(f"{ax}: " + ("; ".join(found) or "none"))
                    print(f"real {cap['name']} {ax} (known excursions): " + ("; ".join(found) or "none"))
                    continue
                per_case.setdefault(f"real:{cap['name']}", [0, 0])
                per_case[f"real:{cap['name']}"][1] += 1
                if found:
                    k += 1
                    per_case[f"real:{cap['name']}"][0] += 1
                    alarms.append(f"real {cap['name']} {ax}: " + "; ".join(found))
            if cap["name"] not in ("ADIS16405", "OCXO"):
                print(f"real {cap['name']}: {k} of {per_case.get('real:' + cap['name'], [0, 0])[1]} "
                      "axes with a detection", flush=True)
    for a in alarms:
        print("  detection:", a)
    summ = {}
    for group in ("noise", "full", "real"):
        k = sum(v[0] for c, v in per_case.items() if c.startswith(group + ":"))
        n = sum(v[1] for c, v in per_case.items() if c.startswith(group + ":"))
        lo, hi = clopper_pearson(k, n) if n else (float("nan"), float("nan"))
        summ[group] = {"axes_with_detection": k, "axes": n, "rate_per_axis": k / n if n else None,
                       "cp95_per_axis": [lo, hi]}
        print(f"{group}: {k} of {n} axes, rate {k / max(n, 1):.4f}, Clopper-Pearson 95 % "
              f"[{lo:.4f}, {hi:.4f}] (stated family-wise alpha per axis {EX.ALPHA})")
    print(json.dumps({"alpha_familywise_per_axis": EX.ALPHA, "hours_noise_model": args.hours,
                      "seeds": args.seeds, "hours_full_model": args.full_hours,
                      "noise_rate_hz": NOISE_RATE_HZ,
                      **{f"{g}_false_alarm_axes": summ[g]["axes_with_detection"] for g in summ},
                      **{f"{g}_axes": summ[g]["axes"] for g in summ},
                      **{f"{g}_false_alarm_rate_cp95_per_axis": summ[g]["cp95_per_axis"] for g in summ},
                      "per_case_alarms_of_axes": per_case, "known_excursions": known,
                      "wall_s": round(time.perf_counter() - t0, 1)}))


if __name__ == "__main__":
    sys.exit(main())
