"""Closed-loop statistics on the emulator: false flags on clean seeds, detection per effect.

Runs `rigctl run procedures/full-calibration.yaml` (shortened: warm-up and sample window
via -p) for N seeds of configs/sim.yaml (declared errors + white noise) and for N seeds of the
effects profile of tests/test_calibrate_emulated.py, then reads /results/calibration.
Prints per-seed lines and, last, one JSON object:
  false_flag_rate_clean, coverage95_clean (pooled over parameters), chi2_per_dof_clean_median,
  detection_rate_<effect>, run_wall_s_mean.
Usage: python benchmarks/calibration.py [--seeds 20] [--warmup "1 min"] [--sample "10 s"]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import h5py  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from test_calibrate_emulated import PROFILES  # noqa: E402

CODE = ("import sys, rigctl.sim.profiles as P; P.DEFAULT_PATH = sys.argv[1]; "
        "from rigctl.cli import main; sys.exit(main(sys.argv[2:]))")


def one(tmp: Path, seed: int, profile: str | None, warmup: str, sample: str) -> dict:
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    cfg["seed"] = seed
    prof = tmp / "profiles.yaml"
    prof.write_text(yaml.safe_dump({"profiles": PROFILES, "random": {"base": "effects_test"}}))
    if profile:
        cfg["imu"]["sim"] = {"profile": profile, "seed": seed}
    (tmp / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    out = tmp / f"runs-{profile}-{seed}"
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-c", CODE, str(prof), "run", "procedures/full-calibration.yaml", "--config",
                    str(tmp / "cfg.yaml"), "-p", f"warmup={warmup}", "-p", f"sample={sample}", "--out", str(out)],
                   check=True, capture_output=True, cwd=ROOT)
    wall = time.monotonic() - t0
    rec = next(out.glob("*/recording.h5"))
    with h5py.File(rec, "r") as f:
        p = json.loads(f["results/calibration"].attrs["json"])
    cl = p["results"]["closed_loop"]
    ci = {q["name"]: (q["ci95_low"], q["ci95_high"]) for q in cl["final"]["parameters"]}
    cover = [ci[e["name"]][0] <= e["truth"] <= ci[e["name"]][1] for e in cl["truth_errors"]]
    return {"seed": seed, "profile": profile or "sim.yaml", "effects": [e["name"] for e in cl["effects"]],
            "unexplained": len(cl["unexplained"]), "chi2_per_dof": cl["final"]["chi2_per_dof"],
            "covered": sum(cover), "n_params": len(cover), "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--warmup", default="1 min")
    ap.add_argument("--sample", default="10 s")
    a = ap.parse_args()
    clean, eff = [], []
    with tempfile.TemporaryDirectory() as d:
        for s in range(1, a.seeds + 1):
            clean.append(one(Path(d), s, None, a.warmup, a.sample))
            print(json.dumps(clean[-1]), flush=True)
            eff.append(one(Path(d), s, "effects_test", a.warmup, a.sample))
            print(json.dumps(eff[-1]), flush=True)
    names = ("lever_arm", "gyro_g_sensitivity", "gyro_scale_nonlinearity", "accel_scale_asymmetry")
    chi = sorted(r["chi2_per_dof"] for r in clean)
    summary = {
        "seeds": a.seeds,
        "false_flag_rate_clean": sum(bool(r["effects"]) or r["unexplained"] > 0 for r in clean) / len(clean),
        "coverage95_clean": sum(r["covered"] for r in clean) / sum(r["n_params"] for r in clean),
        "chi2_per_dof_clean_median": chi[len(chi) // 2],
        **{f"detection_rate_{n}": sum(n in r["effects"] for r in eff) / len(eff) for n in names},
        "run_wall_s_mean": sum(r["wall_s"] for r in clean + eff) / len(clean + eff),
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
