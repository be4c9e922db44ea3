"""Thermal calibration on the emulator: soak vs ramp for the same unit, and ramp coverage.

1. **Soak vs ramp** (one run each, the same emulated unit: configs/sim.yaml's declared errors
   and thermal coefficients, seed 1): `rigctl run procedures/thermal-soak.yaml` (four
   temperatures, each soaked until the IMU is stable, then 24 orientations and rates) and
   `rigctl run procedures/thermal-ramp.yaml` (room -> 50 -> -10 -> room degC at 2 degC/min with
   rotate-and-static cycles), each followed by `rigctl calibrate`. Reported: rig time and wall
   time of each run, and the uncertainty of every thermal coefficient (per group: median sigma,
   and the median over coefficients of sigma_ramp / sigma_soak), with the share of 95 %
   intervals covering the truth.
2. **Ramp coverage** (``--seeds N``, default 0): the ramp for seeds 1..N (noise drawn anew, the
   unit the same): pooled coverage of the 63 coefficients' 95 % intervals, chi2/dof in band,
   thermal effects flagged (the unit has none: every flag is false), wall time per run.

Prints a table and, last, one JSON object (units in the keys).
Usage: python benchmarks/thermal.py [--seeds 20] [--jobs 2] [--no-compare] [--keep DIR]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import h5py  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RIGCTL = [sys.executable, "-m", "rigctl.cli"]


def group(name: str) -> str:
    n = re.sub(r"^(accel|gyro)_", "", name)
    if "per_K" not in n:
        return "reference_temperature"
    kind = "bias" if n.startswith("bias") else "scale" if n.startswith("scale") else \
        "misalignment" if n.startswith("misalignment") else "other"
    return f"{kind}_per_K2" if n.endswith("_per_K2") else f"{kind}_per_K"


def run_and_calibrate(proc: str, cfg: Path, out: Path, params: list[str] = ()) -> dict:
    t0 = time.perf_counter()
    r = subprocess.run([*RIGCTL, "run", proc, "--config", str(cfg), "--out", str(out), *params],
                       cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{proc} failed: {r.stderr[-2000:]}")
    rec = sorted(out.glob("*/recording.h5"))[-1]
    c = subprocess.run([*RIGCTL, "calibrate", str(rec), "--db", "none"], cwd=ROOT, capture_output=True, text=True)
    if c.returncode != 0:
        raise SystemExit(f"calibrate failed: {c.stderr[-2000:]}")
    with h5py.File(rec, "r") as f:
        payload = json.loads(f["results/thermal"].attrs["json"])
        rig_s = float(f["imu/time"][-1])
    return {"payload": payload, "rig_s": rig_s, "wall_s": wall, "recording": str(rec)}


def sigmas(payload: dict) -> dict[str, float]:
    return {q["name"]: q["sigma"] for s in payload["sensors"].values() for q in s["parameters"]}


def config(tmp: Path, seed: int) -> Path:
    d = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    d["seed"] = seed
    p = tmp / f"sim-seed{seed}.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=0, help="ramp coverage study over seeds 1..N")
    ap.add_argument("--keep", help="keep the recordings in this directory")
    ap.add_argument("--no-compare", action="store_true", help="skip the soak-vs-ramp comparison (only --seeds)")
    ap.add_argument("--jobs", type=int, default=1, help="ramp seeds run this many at a time")
    args = ap.parse_args()
    tmp = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="rigctl-thermal-bench-"))
    tmp.mkdir(parents=True, exist_ok=True)
    result: dict = {}
    if not args.no_compare:
        result.update(compare(tmp))
    if args.seeds:
        result.update(seeds(tmp, args.seeds, args.jobs))
    print(json.dumps(result))


def compare(tmp: Path) -> dict:
    cfg = config(tmp, 1)
    soak = run_and_calibrate("procedures/thermal-soak.yaml", cfg, tmp / "soak")
    ramp = run_and_calibrate("procedures/thermal-ramp.yaml", cfg, tmp / "ramp")
    s_soak, s_ramp = sigmas(soak["payload"]), sigmas(ramp["payload"])
    groups: dict[str, list] = {}
    for name in s_soak.keys() & s_ramp.keys():
        groups.setdefault(group(name), []).append((s_soak[name], s_ramp[name]))
    print(f"{'':24s}{'soak':>14s}{'ramp':>14s}")
    print(f"{'rig time, h':24s}{soak['rig_s'] / 3600:14.2f}{ramp['rig_s'] / 3600:14.2f}")
    print(f"{'wall time, s':24s}{soak['wall_s']:14.1f}{ramp['wall_s']:14.1f}")
    cov = {k: v["payload"]["truth_coverage"] for k, v in (("soak", soak), ("ramp", ramp))}
    print(f"{'truth in 95 % CI':24s}{cov['soak']['inside']:>10d}/{cov['soak']['total']:<3d}"
          f"{cov['ramp']['inside']:>10d}/{cov['ramp']['total']:<3d}")
    ratio = {}
    for g, pairs in sorted(groups.items()):
        a = np.array(pairs)
        ratio[g] = float(np.median(a[:, 1] / a[:, 0]))
        print(f"sigma ramp/soak {g:<24s} median {ratio[g]:.3g} ({len(pairs)} coefficients)")
    result = {"soak_rig_time_h": soak["rig_s"] / 3600, "ramp_rig_time_h": ramp["rig_s"] / 3600,
              "soak_wall_s": soak["wall_s"], "ramp_wall_s": ramp["wall_s"],
              "soak_coverage_fraction": cov["soak"]["fraction"], "ramp_coverage_fraction": cov["ramp"]["fraction"],
              **{f"sigma_ratio_ramp_over_soak_{g}": v for g, v in ratio.items()}}
    return result


def seeds(tmp: Path, n: int, jobs: int) -> dict:
    """The ramp for seeds 1..n (``jobs`` at a time): pooled coverage, chi2/dof, flags, wall time."""
    from concurrent.futures import ThreadPoolExecutor

    inside = total = in_band = fits = flags = 0
    walls, chi = [], {"accel": [], "gyro": []}

    def one(seed: int) -> tuple[int, dict]:
        return seed, run_and_calibrate("procedures/thermal-ramp.yaml", config(tmp, seed), tmp / f"ramp-{seed}")

    with ThreadPoolExecutor(max(1, jobs)) as pool:
        for seed, r in pool.map(one, range(1, n + 1)):
            c = r["payload"]["truth_coverage"]
            inside, total = inside + c["inside"], total + c["total"]
            for name, s in r["payload"]["sensors"].items():
                fits += 1
                in_band += s["status"] == "ok"
                flags += len(s["accepted"])
                chi[name].append(s["chi2_per_dof"])
            walls.append(r["wall_s"])
            print(f"seed {seed}: {c['inside']}/{c['total']} covered, chi2/dof "
                  + ", ".join(f"{k} {s['chi2_per_dof']:.3g} ({s['status']})" for k, s in r["payload"]["sensors"].items())
                  + f", flags {[s['accepted'] for s in r['payload']['sensors'].values()]}, run {r['wall_s']:.1f} s wall",
                  flush=True)
    return {"ramp_seeds": n, "ramp_pooled_coverage_fraction": inside / total, "ramp_covered_count": inside,
            "ramp_coefficients_count": total, "ramp_chi2_in_99pct_band_fraction": in_band / fits,
            "ramp_accel_chi2_per_dof_median": float(np.median(chi["accel"])),
            "ramp_gyro_chi2_per_dof_median": float(np.median(chi["gyro"])), "ramp_false_flags_count": flags,
            "ramp_run_wall_s_max": max(walls), "ramp_run_wall_s_median": float(np.median(walls)),
            "ramp_jobs_at_a_time": jobs}


if __name__ == "__main__":
    main()
