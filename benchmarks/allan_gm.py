"""False-add and detection rates of the Gauss-Markov candidate (rigctl.solvers.allan_gm).

    python benchmarks/allan_gm.py [--series N] [--hours H]

Simulated at 100 Hz, H hours each (default 1), the overlapping ADEV at 60 log-spaced factors
(plain numpy) with rigctl's white-FM EDF, then gm_candidate:
  white_rw  N = 1e-3 u sqrt(s) + K = 1e-5 u/sqrt(s)                       (false adds)
  nbk       the same + a flicker floor (one AR(1) per decade of Tc, 0.1..1e5 s,
            3e-5 u in all)                                                  (false adds)
  gm_*      N = 1e-3 + a Gauss-Markov process (Tc, sigma) as named          (detections; Tc
            and sigma_GM inside their 95 % intervals)
Per family: found / series, the binomial 95 % upper bound of the rate (false adds), coverage.
With --fit, each gm_* series the candidate finds is also fitted jointly with the term
(allan_fit.fit_terms(gm=...), the covariance of the estimates from allan_cov with the GM kernel,
as rigctl allan does): B's presence test there (the truth has no B: its adds are false adds),
B reported as an estimate, and Tc inside the fit's 95 % interval are counted.
Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
from scipy.signal import lfilter
from scipy.stats import beta

from rigctl.solvers import allan_edf as E
from rigctl.solvers import allan_fit as F
from rigctl.solvers import allan_gm as GM

TAU0 = 0.01


def ar1(n: int, tc_samples: float, sd: float, rng: np.random.Generator) -> np.ndarray:
    phi = math.exp(-1.0 / tc_samples)
    return lfilter([sd * math.sqrt(1 - phi * phi)], [1.0, -phi], rng.standard_normal(n),
                   zi=[phi * rng.standard_normal() * sd])[0]


def oadev(y: np.ndarray, ms: np.ndarray) -> np.ndarray:
    x = np.concatenate(([0.0], np.cumsum(y))) * TAU0
    return np.array([math.sqrt(np.mean((x[2 * m:] - 2 * x[m:-m] + x[:-2 * m]) ** 2)
                               / (2.0 * (m * TAU0) ** 2)) for m in ms])


def series(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    y = 1e-3 / math.sqrt(TAU0) * rng.standard_normal(n)
    if kind in ("white_rw", "nbk"):
        y += np.cumsum(rng.standard_normal(n)) * 1e-5 * math.sqrt(TAU0)
    if kind == "nbk":
        y += 3e-5 * sum(ar1(n, 10.0 ** k / TAU0, 1.0, rng) for k in range(-1, 6)) / math.sqrt(7)
    if kind.startswith("gm_"):
        _, tc, s = kind.split("_")
        y += ar1(n, float(tc) / TAU0, float(s), rng)
    return y


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--series", type=int, default=60)
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--families", default="white_rw,nbk,gm_5_1e-3,gm_20_3e-4,gm_20_1.5e-4",
                    help="comma-separated: white_rw, nbk, gm_<Tc s>_<sigma>")
    ap.add_argument("--fit", action="store_true",
                    help="gm_* families: the joint fit with the term too (B's presence test)")
    args = ap.parse_args()
    n = int(args.hours * 3600 / TAU0)
    ms = np.unique(np.round(np.logspace(0, math.log10(n // 9), 60)).astype(int))
    edf = np.array([E.edf("oadev", 0, int(m), n + 1) for m in ms])
    t0 = time.time()
    out = {}
    for kind in args.families.split(","):
        found = cov_tc = cov_s = 0
        fits = b_add = b_est = fit_tc = 0
        for seed in range(args.series):
            rng = np.random.default_rng(7000 + seed)
            dev = oadev(series(kind, n, rng), ms)
            r = GM.gm_candidate(ms * TAU0, dev, edf, TAU0, n + 1)
            found += r["detected"]
            if r["detected"] and kind.startswith("gm_"):
                _, tc, s = kind.split("_")
                cov_tc += r["tc_ci95_s"][0] <= float(tc) <= r["tc_ci95_s"][1]
                cov_s += r["sigma_gm_ci95_si"][0] <= float(s) <= r["sigma_gm_ci95_si"][1]
                if args.fit:
                    fit = F.fit_terms(ms * TAU0, dev, edf, "gyro", tau0=TAU0, n_phase=n + 1,
                                      gm={"tc_grid_s": r["tc_grid_s"]})
                    fits += 1
                    bt = (fit["terms"].get("B") or {}).get("presence_test") or {}
                    b_add += bool(bt.get("tested") and bt["p_value"] < F.B_TEST_ALPHA)
                    b_est += bool(fit["coefficients"].B.resolved)
                    lo, hi = fit["gm_term"]["tc_ci95_s"]
                    fit_tc += lo <= float(tc) <= hi
        up = float(beta.ppf(0.95, found + 1, args.series - found)) if found < args.series else 1.0
        out[kind] = {"found": found, "series": args.series, "rate_upper95": up,
                     "tc_covered": cov_tc, "sigma_covered": cov_s}
        if fits:
            out[kind].update({"fits": fits, "b_test_adds": b_add, "b_estimates": b_est,
                              "fit_tc_covered": fit_tc})
        print(f"{kind:14s} found {found:3d}/{args.series}  rate upper 95 % {up:.3f}  "
              f"Tc in its interval {cov_tc}/{found}  sigma in its interval {cov_s}/{found}"
              + (f"  | joint fit: B test adds {b_add}/{fits}, B estimates {b_est}/{fits}, "
                 f"Tc in the fit's interval {fit_tc}/{fits}" if fits else ""),
              flush=True)
    print(json.dumps({"series_per_family": args.series, "hours": args.hours,
                      **{f"found_{k}": v["found"] for k, v in out.items()},
                      **{f"rate_upper95_{k}": round(v["rate_upper95"], 4) for k, v in out.items()
                         if not k.startswith("gm_")},
                      **{f"b_test_adds_{k}": v["b_test_adds"] for k, v in out.items() if "fits" in v},
                      **{f"fits_{k}": v["fits"] for k, v in out.items() if "fits" in v},
                      "wall_s": round(time.time() - t0, 1)}))


if __name__ == "__main__":
    main()
