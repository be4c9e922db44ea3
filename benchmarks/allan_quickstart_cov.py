"""Coverage of the truth by the quickstart's Allan step (docs/quickstart.md section 4; issue 15).

The quickstart records 5 minutes at 100 Hz with the default emulator (configs/sim.yaml: N, B and
K on every axis) and its `solve: [allan]` step runs rigctl.analysis.allan.solve_recording:
:func:`rigctl.analysis.allan.compute` of the capture, 95 log-spaced taus, fast mode, gaps
skipped. Here the same capture comes straight from the emulator's noise generator
(rigctl.sim.noise.NoiseGenerator, the coefficients configs/sim.yaml gives, a gravity / earth-rate
offset added), once per seed, is written as a recording (h5py) and goes through that same
``compute``. Per axis and term (N, B, K): how often the reported 95 % interval (a resolved term)
or 95 % upper bound (an unresolved one) contains the truth, with a Clopper-Pearson 95 % interval
on that share; also how often the term is resolved, and the shares of the misses below / above.

The last line is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

from _common import ROOT  # first: one BLAS thread before numpy loads; tests/, benchmarks/ importable

import numpy as np  # noqa: E402
from scipy.stats import beta  # noqa: E402

from recording_helpers import write_recording  # noqa: E402

from rigctl.analysis import allan as AA  # noqa: E402
from rigctl.sim.imu import build_imu_model  # noqa: E402
from rigctl.sim.noise import NoiseGenerator  # noqa: E402
from rigctl.solvers.noise_coefficients import as_coefficients, in_field_units  # noqa: E402
from rigctl.yamlio import load_file  # noqa: E402

AXES = ("gx", "gy", "gz", "ax", "ay", "az")


def clopper_pearson(k: int, n: int, conf: float = 0.95) -> tuple[float, float]:
    """Exact binomial interval of a share k/n."""
    a = (1 - conf) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def default_noise(config: Path = ROOT / "configs" / "sim.yaml") -> tuple[float, dict]:
    """(IMU rate in Hz, {"gyro": triad, "accel": triad}) of a config's declared IMU."""
    cfg = load_file(config)
    rate = float(cfg["imu"]["rate_hz"])
    m = build_imu_model(cfg["imu"]["sim"], rate, 1)
    return rate, {"gyro": m.gyro_noise, "accel": m.accel_noise}


def one_capture(path: Path, noise: dict, fs: float, n: int, seed: int) -> dict:
    """The reported coefficients (field units: value, ci95, upper95, resolved) of each axis."""
    g = NoiseGenerator(noise["gyro"], fs, np.random.SeedSequence([seed, 1])).next(n)
    a = NoiseGenerator(noise["accel"], fs, np.random.SeedSequence([seed, 2])).next(n)
    g = g + np.array([3e-5, 0.0, 5e-5])  # earth rate at 45 deg (rad/s)
    a = a + np.array([0.0, 0.0, 9.80638])
    write_recording(path, fs, angular_rate=g, specific_force=a)
    res = AA.compute(str(path), list(AXES), 95, False, None, gaps="skip")
    out = {}
    for ax, r in res["axes"].items():
        co = as_coefficients(r["fit"]["coefficients"])
        row = {}
        for t in "NBK":
            c, unit = in_field_units(co, t)
            row[t] = {"resolved": bool(c.resolved), "value": float(c.value) if c.resolved else None,
                      "ci95": [float(v) for v in c.ci95] if c.resolved else None,
                      "upper95": None if c.resolved else float(c.upper95),
                      "bound_from": c.bound_from, "unit": unit}
        row["gm"] = bool(r["fit"].get("gm"))
        row["R_resolved"] = bool(co.R.resolved)  # a ramp the emulator does not have (R = 0)
        chk = r["fit"]["check"]
        row["check_ok"] = bool(chk["ok"])
        row["check_completed"] = completed_check(chk)
        out[ax] = row
    return out


def completed_check(check: dict) -> dict:
    """The self-check's completed chi-square, its dof, the resolved total's dof and the
    bounded terms' fractions of their bounds (benchmarks/allan_completed_dof.py)."""
    return {"chi2": float(check["completed"]["chi2"]), "dof": int(check["completed"]["dof"]),
            "dof_rep": int(check["dof"]), "p_value": float(check["completed"]["p_value"]),
            "fraction_of_bound": {k: float(v["fraction_of_bound"])
                                  for k, v in check["bounded_terms"].items()}}


def truths(noise: dict) -> dict:
    """{axis: {term: truth in the field unit the summary line uses}}."""
    out = {}
    for ax in AXES:
        tri = noise["gyro" if ax[0] == "g" else "accel"]
        m = tri["xyz".index(ax[1])]
        out[ax] = {t: float(in_field_units(m, t)[0].value) for t in "NBK"}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--keep", help="write every seed's coefficients to this JSON file")
    a = ap.parse_args()
    fs, noise = default_noise()
    n = int(round(a.minutes * 60 * fs))
    tv = truths(noise)
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        for s in range(a.first_seed, a.first_seed + a.seeds):
            rows.append(one_capture(Path(d) / f"s{s}.h5", noise, fs, n, s))
            if (s - a.first_seed + 1) % 25 == 0:
                print(f"{s - a.first_seed + 1} seeds, {time.perf_counter() - t0:.0f} s", flush=True)
    if a.keep:
        Path(a.keep).write_text(json.dumps({"truth": tv, "rows": rows}))
    summary = report(tv, rows)
    print(json.dumps(summary))


def report(tv: dict, rows: list[dict]) -> dict:
    """Print the coverage table; return its figures."""
    print(f"{'axis':>4} {'term':>4} {'truth':>10} {'resolved':>8} {'covered':>8} "
          f"{'coverage_%':>10} {'CP95_%':>13} {'miss_low':>8} {'miss_high':>9}")
    summary = {}
    for ax in AXES:
        for t in "NBK":
            v = tv[ax][t]
            res = cov = low = high = 0
            for r in rows:
                c = r[ax][t]
                if c["resolved"]:
                    res += 1
                    lo, hi = c["ci95"]
                    ok = lo <= v <= hi
                    low += v > hi  # the interval lies below the truth
                    high += v < lo
                else:
                    ok = v <= c["upper95"]
                    low += not ok
                cov += ok
            n = len(rows)
            lo, hi = clopper_pearson(cov, n)
            print(f"{ax:>4} {t:>4} {v:10.4g} {res:>8} {cov:>8} {100 * cov / n:10.1f} "
                  f"{100 * lo:6.1f}-{100 * hi:5.1f} {low:>8} {high:>9}")
            summary[f"{ax}_{t}"] = {"n": n, "covered": cov, "resolved": res, "miss_low": low,
                                    "miss_high": high, "cp95": [lo, hi]}
    for ax in AXES:  # spurious ramps (truth R = 0) and failed self-checks
        summary[f"{ax}_R_resolved"] = sum(bool(r[ax].get("R_resolved")) for r in rows)
        summary[f"{ax}_check_failed"] = sum(not r[ax].get("check_ok", True) for r in rows)
    print("R resolved (truth 0) / self-check failed per axis: " + ", ".join(
        f"{ax} {summary[f'{ax}_R_resolved']}/{summary[f'{ax}_check_failed']}" for ax in AXES))
    for t in "NBK":
        k = sum(summary[f"{ax}_{t}"]["covered"] for ax in AXES)
        n = sum(summary[f"{ax}_{t}"]["n"] for ax in AXES)
        lo, hi = clopper_pearson(k, n)
        print(f"all axes {t}: {k}/{n} = {100 * k / n:.1f} % (CP95 {100 * lo:.1f}-{100 * hi:.1f} %)")
    return summary


if __name__ == "__main__":
    main()
