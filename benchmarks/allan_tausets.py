"""Do `--taus octave` and `--taus all` agree, and do their 95 % intervals hold the truth? Many seeds.

For each profile (--profiles) and seed, the emulator's IEEE 952 noise for the profile's gyro and
accelerometer coefficients (rigctl.sim.noise.NoiseGenerator: N, the flicker cascade for B, K, R;
no front end, tones or warm-up, so the truth is the profile's coefficients) is written as a
6-axis rigctl recording of --hours at --rate-hz and run through the Allan pipeline as
`rigctl allan` does (rigctl.analysis.allan.compute), once with each tau set. Counted per axis:

  agree     octave and all agree on every term (benchmarks/allan_profiles.agree: both supported
            and their 95 % intervals overlap, or one is a bound and the other's interval starts
            below it, or both bounds)
  coverage  per tau set and term N, B, K: the 95 % interval (or the one-sided 95 % bound) holds
            the profile's value
  check     the self-check failed (a warning)

Prints a table per profile, then one JSON line (rates in per cent, the load before and after).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
TERMS = ("N", "B", "K")


def _profiles_bench():
    spec = importlib.util.spec_from_file_location("allan_profiles", ROOT / "benchmarks" / "allan_profiles.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def write_noise(path: Path, profile: str, hours: float, fs: float, seed: int, bench) -> dict:
    """A static 6-axis recording of the profile's noise only; returns the truth per axis (SI)."""
    from rigctl.sim.noise import NoiseGenerator
    from rigctl.sim.profiles import get_profile

    prof = get_profile(profile)
    n = int(round(hours * 3600 * fs))
    g = prof.gyro.noise.coefficients()
    a = prof.accel.noise.coefficients()
    w = NoiseGenerator(g, fs, np.random.SeedSequence([seed, 1])).next(n)
    f = NoiseGenerator(a, fs, np.random.SeedSequence([seed, 2])).next(n) + np.array([0.0, 0.0, 9.80665])
    h5, ds = bench._h5(path, fs)
    try:
        bench._append(ds, time=np.arange(n) / fs, counter=np.arange(n, dtype=np.uint64),
                      angular_rate=w, specific_force=f)
    finally:
        h5.close()
    truth = {}
    for axes, tri in (("gx gy gz", g), ("ax ay az", a)):
        for name, c in zip(axes.split(), tri):
            truth[name] = c.values()
    return truth


def covers(c, v: float) -> bool:
    if c.resolved:
        lo, hi = c.ci95
        return lo <= v <= hi
    return v <= c.upper95 * (1 + 1e-12)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profiles", default="consumer_mems,mti_class")
    ap.add_argument("--hours", type=float, default=2.0)
    ap.add_argument("--rate-hz", type=float, default=100.0)
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=0)
    a = ap.parse_args()
    from rigctl.analysis import allan as AA

    bench = _profiles_bench()
    load0 = bench._load()
    t0 = time.perf_counter()
    out: dict = {"hours": a.hours, "rate_hz": a.rate_hz, "seeds": a.seeds}
    tot = {"pairs": 0, "disagree": 0, "cov": {s: {t: [] for t in TERMS} for s in ("octave", "all")},
           "check_failed": {"octave": 0, "all": 0}}
    with tempfile.TemporaryDirectory(dir="/tmp") as d:
        for profile in a.profiles.split(","):
            rows = {"pairs": 0, "disagree": 0, "where": {},
                    "cov": {s: {t: [] for t in TERMS} for s in ("octave", "all")},
                    "sup": {s: {t: 0 for t in TERMS} for s in ("octave", "all")},
                    "check_failed": {"octave": 0, "all": 0}}
            for seed in range(a.first_seed, a.first_seed + a.seeds):
                path = Path(d) / f"{profile}_{seed}.h5"
                truth = write_noise(path, profile, a.hours, a.rate_hz, seed, bench)
                res = {s: AA.compute(str(path), list(truth), s) for s in ("octave", "all")}
                path.unlink()
                for ax in truth:
                    ra, rb = res["octave"]["axes"][ax], res["all"]["axes"][ax]
                    bad = bench.agree(ra, rb)
                    rows["pairs"] += 1
                    if bad:
                        rows["disagree"] += 1
                        key = f"{ax}:{''.join(bad)}"
                        rows["where"][key] = rows["where"].get(key, 0) + 1
                    for s, r in (("octave", ra), ("all", rb)):
                        co = r["fit"]["coefficients"]
                        rows["check_failed"][s] += not r["fit"]["check"]["ok"]
                        for t in TERMS:
                            c = getattr(co, t)
                            rows["cov"][s][t].append(covers(c, truth[ax][t]))
                            rows["sup"][s][t] += bool(c.resolved)
            print(f"\n== {profile}: {a.seeds} seeds x 6 axes, {a.hours:g} h at {a.rate_hz:g} Hz "
                  f"(emulator noise only)")
            print(f"octave vs all apart: {rows['disagree']} of {rows['pairs']} axes "
                  f"({100 * rows['disagree'] / rows['pairs']:.1f} %) {rows['where'] or ''}")
            print(f"{'taus':>6} {'term':>4} {'supported':>9} {'cov95_%':>8}")
            for s in ("octave", "all"):
                for t in TERMS:
                    cv = rows["cov"][s][t]
                    print(f"{s:>6} {t:>4} {rows['sup'][s][t]:>4}/{len(cv):<4} {100 * np.mean(cv):8.1f}")
                print(f"{s:>6} self-check failed: {rows['check_failed'][s]} of {rows['pairs']}")
            sys.stdout.flush()
            out[profile] = {"disagree_pct": round(100 * rows["disagree"] / rows["pairs"], 2),
                            "disagree_where": rows["where"],
                            **{f"cov95_{s}_{t}_pct": round(100 * float(np.mean(rows["cov"][s][t])), 1)
                               for s in ("octave", "all") for t in TERMS},
                            "check_failed": rows["check_failed"]}
            tot["pairs"] += rows["pairs"]
            tot["disagree"] += rows["disagree"]
            for s in ("octave", "all"):
                tot["check_failed"][s] += rows["check_failed"][s]
                for t in TERMS:
                    tot["cov"][s][t] += rows["cov"][s][t]
    wall = time.perf_counter() - t0
    out.update({"axes": tot["pairs"], "disagree_axes": tot["disagree"],
                "disagree_pct": round(100 * tot["disagree"] / max(tot["pairs"], 1), 2),
                **{f"cov95_{s}_{t}_pct": round(100 * float(np.mean(tot["cov"][s][t])), 1)
                   for s in ("octave", "all") for t in TERMS},
                "check_failed_octave": tot["check_failed"]["octave"],
                "check_failed_all": tot["check_failed"]["all"],
                "wall_s": round(wall, 1), "load_avg_start": load0, "load_avg_end": bench._load()})
    print(f"\nall profiles: octave vs all apart on {tot['disagree']} of {tot['pairs']} axes; "
          f"{wall:.0f} s (load {load0} -> {bench._load()})")
    print(json.dumps(out))


if __name__ == "__main__":
    sys.exit(main())
