"""Calibration statistics on the emulator: false flags, coverage, chi2, detection per effect.

Two studies (both run the emulator through `rigctl run`, then read the calibration):

1. **White noise** (the closed loop's guard): `procedures/full-calibration.yaml` shortened (-p
   warmup, sample) for N seeds of configs/sim.yaml (declared errors + white noise) and of the
   effects profile of tests/test_calibrate_emulated.py (g-sensitivity, accel scale asymmetry,
   lever arm, gyro nonlinearity): false-flag rate, pooled coverage, detection rate per effect.
2. **Time-correlated noise** (bias instability + rate random walk, the real-MEMS case): the full
   procedure (15-min warm-up, 30-s windows) for N seeds of each profile -- declared_only, and
   mti_class / tactical with every extra effect disabled by overrides. Each recording is
   calibrated several ways: "independent" (segment means treated as independent, each with its
   own batch-means sigma: the behaviour before segment covariances), "session" (covariance from
   the noise model REML-estimated from the session: what `rigctl calibrate` does without
   /results/allan) and "coeffs" (covariance from the profile's true IEEE 952 coefficients: what
   /results/allan gives); with --overnight-hours (default 12) also "overnight": the
   /results/allan of a 12 h static capture of the same emulated unit (another seed), analysed by
   `rigctl allan` -- what `rigctl calibrate --noise OVERNIGHT.h5` does. Per run: closed-loop
   chi2/dof and whether it lies in its 99 % chi-square band, accel24 / gyro-rate chi2/dof, any
   effect or unexplained structure flagged, and how many of the 27 declared parameters' 95 % intervals cover /truth.

Prints per-run JSON lines, a table, and last one JSON object of headline figures.
Usage: python benchmarks/calibration.py [--seeds 6] [--corr-seeds 10] [--profiles declared_only,...]
       [--recordings DIR]   (keep the study-2 recordings there and reuse them on the next run)
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
import numpy as np  # noqa: E402
import scipy.stats  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))
from allan_quickstart_cov import clopper_pearson  # noqa: E402  (exact binomial interval)
from test_calibrate_emulated import PROFILES  # noqa: E402

CODE = ("import sys, rigctl.sim.profiles as P; P.DEFAULT_PATH = sys.argv[1]; "
        "from rigctl.cli import main; sys.exit(main(sys.argv[2:]))")
EFFECTS_OFF = {k: {"enabled": False} for k in ("warmup", "turn_on_bias", "g_sensitivity", "accel_scale_asymmetry",
                                               "gyro_nonlinearity", "lever_arm", "time_delay", "vibration",
                                               "clock", "table_geometry")}
CORR_PROFILES = ("declared_only", "mti_class", "tactical")


# ------------------------------------------------------------------------------ study 1
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


# ------------------------------------------------------------------------------ study 2
def record(tmp: Path, seed: int, profile: str) -> tuple[Path, dict]:
    """Emulated 24-position + rate-test recording (no solve step) of one profile and seed
    (reused when ``tmp`` already holds it: see --recordings)."""
    out = tmp / f"corr-{profile}-{seed}"
    if (done := _complete_recording(out)) is not None:
        return done
    proc = tmp / "record.yaml"
    proc.write_text(yaml.safe_dump({"procedure": "bench-record", "steps": [
        {"include": str(ROOT / "procedures" / "24pos.yaml")}, {"include": str(ROOT / "procedures" / "rates.yaml")}]}))
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    cfg["seed"] = seed
    cfg["imu"]["sim"] = {"profile": profile, "seed": seed}
    if profile != "declared_only":
        cfg["imu"]["sim"]["overrides"] = {"effects": EFFECTS_OFF}
    (tmp / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    subprocess.run([sys.executable, "-m", "rigctl.cli", "run", str(proc), "--config", str(tmp / "cfg.yaml"),
                    "--out", str(out)], check=True, capture_output=True, cwd=ROOT)
    done = _complete_recording(out)
    if done is None:
        raise RuntimeError(f"{out}: the run ended without a complete recording")
    return done


def _complete_recording(out: Path) -> tuple[Path, dict] | None:
    """The newest complete recording under ``out`` (a run directory each) and the emulator's
    truth for the IMU, or None: a part-done recording left by an interrupted run (its status
    not 'complete', or unreadable) is passed over, not analysed."""
    for rec in sorted(out.glob("*/recording.h5"), reverse=True):   # run dirs start with a UTC stamp
        try:
            with h5py.File(rec, "r") as f:
                if f["run/status"][0] == b"complete":
                    return rec, json.loads(f["truth"].attrs["params_json"])["imu"]
        except (OSError, KeyError):
            continue
    return None


def overnight(tmp: Path, profile: str, hours: float, seed: int = 1000) -> Path:
    """A ``hours`` static capture of the same emulated unit (profile, effects as in record())
    analysed by ``rigctl allan``: what `rigctl calibrate --noise FILE.h5` reads (reused when
    ``tmp`` already holds it)."""
    out = tmp / f"overnight-{profile}-{hours:g}h"
    for rec in sorted(out.glob("*/recording.h5")):
        with h5py.File(rec, "r") as f:
            if "results/allan" in f:
                return rec
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    cfg["seed"] = seed
    cfg["imu"]["sim"] = {"profile": profile, "seed": seed}
    if profile != "declared_only":
        cfg["imu"]["sim"]["overrides"] = {"effects": EFFECTS_OFF}
    (tmp / f"cfg-overnight-{profile}.yaml").write_text(yaml.safe_dump(cfg))
    subprocess.run([sys.executable, "-m", "rigctl.cli", "run", str(ROOT / "procedures" / "allan-overnight.yaml"),
                    "--config", str(tmp / f"cfg-overnight-{profile}.yaml"), "-p", "warmup=1 min",
                    "-p", f"capture={hours:g} h", "--out", str(out)], check=True, capture_output=True, cwd=ROOT)
    return next(out.glob("*/recording.h5"))


#: the declared parameters' groups the coverage is reported for (names as in /truth)
GROUPS = ("accel_bias", "gyro_bias", "scale", "misalignment", "quadratic")


def param_group(name: str) -> str:
    """The coverage group of a declared parameter: accel_bias, gyro_bias, scale (M's diagonal),
    misalignment (M off the diagonal) or quadratic."""
    if "_bias_" in name:
        return name.split("_bias_")[0] + "_bias"
    if "_M_" in name:
        ij = name.split("_M_")[1][:2]
        return "scale" if ij[0] == ij[1] else "misalignment"
    return "quadratic"


def _summary(sess: dict, truth: dict) -> dict:
    cl = sess["closed_loop"]
    fin = cl.final
    ci = dict(zip(fin.names, fin.ci95))
    cover = [bool(ci[e["name"]][0] <= e["truth"] <= ci[e["name"]][1]) for e in cl.truth_errors]
    lo, hi = scipy.stats.chi2.ppf([0.005, 0.995], fin.dof) / fin.dof
    out = {"chi2_per_dof": fin.chi2_per_dof, "in_band99": bool(lo <= fin.chi2_per_dof <= hi),
           "p": fin.chi2_p_value, "flagged": bool(cl.effects or cl.unexplained),
           "effects": cl.effect_names, "unexplained": len(cl.unexplained),
           "covered": int(sum(cover)), "n_params": len(cover),
           "bias_covered": int(sum(c for c, e in zip(cover, cl.truth_errors) if "bias" in e["name"])),
           "by_group": {g: [int(sum(c for c, e in zip(cover, cl.truth_errors) if param_group(e["name"]) == g)),
                            sum(param_group(e["name"]) == g for e in cl.truth_errors)] for g in GROUPS}}
    for k in ("accel24", "gyro_rate"):
        r = sess.get(k)
        if r is not None:
            out[f"{k}_chi2_per_dof"] = r.chi2_per_dof
            a, b = scipy.stats.chi2.ppf([0.005, 0.995], r.dof) / r.dof
            out[f"{k}_in_band99"] = bool(a <= r.chi2_per_dof <= b)
    return out


def calibrate_ways(rec: Path, truth_params: dict, night: Path | None = None) -> dict:
    """The recording calibrated with each noise model: independent, session, coeffs and (with
    ``night``) overnight, the /results/allan of another recording of the same unit."""
    from rigctl.analysis.calibration import _truth, noise_from_allan
    from rigctl.recording.segment_builder import build_segment_table, open_recording
    from rigctl.solvers.closed_loop import calibrate_session
    from rigctl.solvers.segment_noise import apply_session_noise
    from rigctl.solvers.noise_coefficients import from_json

    with open_recording(rec) as f:
        truth = _truth(f)
    out = {}
    seg = build_segment_table(rec)
    out["independent"] = _summary(calibrate_session(seg, truth=truth), truth)
    seg = build_segment_table(rec)
    t0 = time.monotonic()
    models = apply_session_noise(seg)
    out["session"] = _summary(calibrate_session(seg, truth=truth), truth)
    out["session"]["calibrate_s"] = time.monotonic() - t0
    out["session"]["B_over_true"] = [m.B.value / b if b else None for m, b in zip(models, _true_b(truth_params))]
    nm = [tuple(from_json(d) for d in truth_params[f"{s}_noise"]) for s in ("accel", "gyro")]
    seg = build_segment_table(rec, noise_f=nm[0], noise_w=nm[1])
    apply_session_noise(seg, nm[0], nm[1])
    out["coeffs"] = _summary(calibrate_session(seg, truth=truth), truth)
    if night is not None:
        with open_recording(night) as f:
            nm = noise_from_allan(f)
        seg = build_segment_table(rec, noise_f=nm[0], noise_w=nm[1])
        apply_session_noise(seg, nm[0], nm[1])
        out["overnight"] = _summary(calibrate_session(seg, truth=truth), truth)
    return out


def _true_b(tp: dict) -> list[float]:
    return [d["B"]["value"] for s in ("accel", "gyro") for d in tp[f"{s}_noise"]]


def corr_study(seeds: int, profiles: list[str], keep: str | None = None, night_h: float = 12.0
               ) -> tuple[dict, dict]:
    rows = []
    modes = ("independent", "session", "coeffs") + (("overnight",) if night_h > 0 else ())
    with tempfile.TemporaryDirectory() as d:
        where = Path(keep) if keep else Path(d)
        where.mkdir(parents=True, exist_ok=True)
        for prof in profiles:
            t0 = time.monotonic()
            night = overnight(where, prof, night_h) if night_h > 0 else None
            if night is not None:
                print(f"{prof}: {night_h:g} h overnight capture analysed by rigctl allan in "
                      f"{time.monotonic() - t0:.0f} s: {night}", flush=True)
            for s in range(1, seeds + 1):
                t0 = time.monotonic()
                rec, truth = record(where, s, prof)
                res = calibrate_ways(rec, truth, night)
                row = {"profile": prof, "seed": s, "wall_s": time.monotonic() - t0, **res}
                rows.append(row)
                print(json.dumps(row, default=float), flush=True)
                if not keep:
                    rec.unlink()
    print()
    print(f"{'profile':<14} {'noise model':<12} {'runs':>4} {'chi2/dof median':>16} {'in 99% band':>12} "
          f"{'no flag':>8} {'coverage':>9} {'bias cov.':>9} {'accel24 in band':>16} {'gyro-rate in band':>18}")
    summary: dict = {}
    for prof in profiles:
        sub = [r for r in rows if r["profile"] == prof]
        for mode in modes:
            x = [r[mode] for r in sub]
            n = len(x)
            med = float(np.median([v["chi2_per_dof"] for v in x]))
            band = sum(v["in_band99"] for v in x) / n
            noflag = sum(not v["flagged"] for v in x) / n
            cov = sum(v["covered"] for v in x) / sum(v["n_params"] for v in x)
            bcov = sum(v["bias_covered"] for v in x) / (6 * n)
            a24 = sum(v.get("accel24_in_band99", False) for v in x) / n
            gr = sum(v.get("gyro_rate_in_band99", False) for v in x) / n
            print(f"{prof:<14} {mode:<12} {n:>4} {med:>16.3f} {band:>12.2f} {noflag:>8.2f} {cov:>9.3f} "
                  f"{bcov:>9.3f} {a24:>16.2f} {gr:>18.2f}")
            summary[f"{prof}_{mode}"] = {"chi2_per_dof_median": med, "frac_in_99_band": band,
                                         "frac_no_flag": noflag, "coverage95_pooled": cov,
                                         "bias_coverage95": bcov}
    print()
    print("coverage of the 95 % intervals per parameter group: covered/intervals, % [Clopper-Pearson 95 %]")
    groups: dict = {}
    for prof in [*profiles, "all"]:
        sub = [r for r in rows if prof in ("all", r["profile"])]
        for mode in modes:
            cells = []
            for g in GROUPS:
                k = sum(r[mode]["by_group"][g][0] for r in sub)
                n = sum(r[mode]["by_group"][g][1] for r in sub)
                lo, hi = clopper_pearson(k, n) if n else (float("nan"),) * 2
                cells.append(f"{g} {k}/{n} {100 * k / max(n, 1):.1f} [{100 * lo:.1f}, {100 * hi:.1f}]")
                groups[f"{prof}_{mode}_{g}_coverage95"] = [k, n, lo, hi]
            print(f"{prof:<14} {mode:<12} " + "; ".join(cells))
    return summary, groups


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=6, help="white-noise study seeds (0: skip)")
    ap.add_argument("--corr-seeds", type=int, default=10, help="time-correlated study seeds (0: skip)")
    ap.add_argument("--profiles", default=",".join(CORR_PROFILES))
    ap.add_argument("--warmup", default="1 min")
    ap.add_argument("--sample", default="10 s")
    ap.add_argument("--recordings", help="keep (and reuse) the study-2 recordings in this directory")
    ap.add_argument("--overnight-hours", type=float, default=12.0,
                    help="static capture per profile for the 'overnight' noise model (0: skip)")
    a = ap.parse_args()
    summary: dict = {}
    if a.corr_seeds > 0:
        corr, groups = corr_study(a.corr_seeds, [p for p in a.profiles.split(",") if p], a.recordings,
                                  a.overnight_hours)
        summary.update(groups)  # [covered, intervals, Clopper-Pearson low, high] per group
        for k, v in corr.items():
            if not k.endswith("_independent"):
                summary[f"{k}_bias_coverage95"] = v["bias_coverage95"]
            if k.endswith("_session") or k.endswith("_independent") or k.endswith("_overnight"):
                summary[f"{k}_frac_in_99_band"] = v["frac_in_99_band"]
                summary[f"{k}_frac_no_flag"] = v["frac_no_flag"]
                summary[f"{k}_coverage95"] = v["coverage95_pooled"]
    if a.seeds > 0:
        clean, eff = [], []
        with tempfile.TemporaryDirectory() as d:
            for s in range(1, a.seeds + 1):
                clean.append(one(Path(d), s, None, a.warmup, a.sample))
                print(json.dumps(clean[-1]), flush=True)
                eff.append(one(Path(d), s, "effects_test", a.warmup, a.sample))
                print(json.dumps(eff[-1]), flush=True)
        names = ("lever_arm", "gyro_g_sensitivity", "gyro_scale_nonlinearity", "accel_scale_asymmetry")
        chi = sorted(r["chi2_per_dof"] for r in clean)
        summary.update({
            "seeds_white": a.seeds,
            "false_flag_rate_clean": sum(bool(r["effects"]) or r["unexplained"] > 0 for r in clean) / len(clean),
            "coverage95_clean": sum(r["covered"] for r in clean) / sum(r["n_params"] for r in clean),
            "chi2_per_dof_clean_median": chi[len(chi) // 2],
            **{f"detection_rate_{n}": sum(n in r["effects"] for r in eff) / len(eff) for n in names},
            "run_wall_s_mean": sum(r["wall_s"] for r in clean + eff) / len(clean + eff),
        })
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
