"""Why `rigctl allan` is silent on some records with a Gauss-Markov bump of 4 B (docs/allan.md,
"Detection limits": 8 of 40), and what the Allan curve itself could say about them.

    python benchmarks/allan_gm_silent.py [--seeds 40] [--size 4] [--tc 2]

The records are the doc's protocol (benchmarks/allan_step_limit.py ``--gm-sizes 4 --gm-seeds 40
--product``): tests/test_allan_check_bounds.py's 5-minute records at 100 Hz (white N 0.2
deg/sqrt(h) + flicker B 5 deg/h, FFT-shaped) plus a first-order Gauss-Markov rate of sigma
``size`` x B and Tc ``tc`` s, seeds 0..N-1, written as a recording and run through
``rigctl.analysis.allan.compute`` (95 taus, gx). Per record:

* outcome: a Gauss-Markov term in the fit / the self-check failed / silent; B reported / truth;
* on the product's own curve (its taus, deviations and EDFs):
  - the fitted total (IEEE 952 terms, B inflated) against the 95 % band: the smallest margin
    over the hump's taus (0.5-20 s), in units of the band's half-width in log sigma (1: at the
    band's edge; > 1 outside);
  - the Gauss-Markov candidate's likelihood-ratio test (allan_gm.gm_candidate), forced on every
    record (the pipeline runs it only where the check lists a stationary bump): the generalized
    chi-square of the IEEE terms alone minus that with the term, its p-value (Bonferroni over Tc)
    against alpha 0.025;
* the Cramer-Rao (Fisher) figure of the deviations for sigma_GM^2 with Q, N, B, K, R free (and
  with K and R known at the truth's 0: the fit's bounds K, R >= 0 are active there), at
  the truth, from the deviations' exact covariance (allan_cov with the Gauss-Markov kernel) on
  the candidate's 40 taus and on all of the curve's taus past the filter (m >= 4): the expected
  generalized-chi-square gain (sigma_GM^2 / sd)^2 and the expected power at the candidate's
  threshold; beside it the same figure for Whittle's likelihood on the periodogram (N and B free).

``--null K``: instead, false adds on pure power-law noise (no Gauss-Markov process): K records
of each family of benchmarks/allan_gm_spectral.py (white + flicker, + random walk, white +
random walk, through a Butterworth, + white phase noise; 5 minutes at 100 Hz) through the same
``rigctl.analysis.allan.compute``: how often a Gauss-Markov term is in the fit, and how often
the candidate was run beside a B estimate with no bump named (the unprompted case).

Last line: one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
from scipy.stats import chi2, ncx2  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))
import test_allan_check_bounds as WF  # noqa: E402
from recording_helpers import write_recording  # noqa: E402

from rigctl.analysis import allan as AA  # noqa: E402
from rigctl.solvers import allan_cov as C  # noqa: E402
from rigctl.solvers import allan_fit as F  # noqa: E402
from rigctl.solvers import allan_gm as GM  # noqa: E402


def fisher_adev(tau0: float, ms: np.ndarray, n_phase: int, sig: float, tc: float,
                free: tuple[int, ...] = (0, 1, 2, 3, 4)) -> float:
    """sd of sigma_GM^2 estimated from the Allan variances at factors ``ms`` with the IEEE
    terms ``free`` (indices into Q, N, B, K, R; the others known, at the truth's 0) and
    sigma_GM^2 free (Tc known), generalized least squares with the exact covariance at the
    truth (N_TRUE, B_TRUE, sigma, Tc)."""
    tau = ms * tau0
    a = np.column_stack((F.design_matrix(tau)[:, list(free)], F.gm_column(tau, tc)))
    ct = C.term_covariances(tau0, ms.astype(float), n_phase, tc)
    cov = C.combine(ct, {"N": WF.N_TRUE ** 2, "B": WF.B_TRUE ** 2, "G": sig ** 2})
    # the deviations of many close taus are nearly collinear: the information through the
    # covariance's eigenvectors above 1e-12 of its largest eigenvalue (a pseudo-inverse)
    w, v = np.linalg.eigh(cov)
    keep = w > 1e-12 * w.max()
    aw = (v[:, keep].T @ a) / np.sqrt(w[keep])[:, None]
    sc = np.linalg.norm(aw, axis=0)
    info = (aw / sc).T @ (aw / sc)
    return float(math.sqrt(np.linalg.inv(info)[-1, -1]) / sc[-1])


def fisher_whittle(n: int, fs: float, sig: float, tc: float) -> float:
    """sd of sigma_GM^2 from Whittle's likelihood (white, flicker and sigma_GM^2 free, Tc
    known): J = sum_f dS_i dS_j / S^2 over the Fourier frequencies."""
    f = np.fft.rfftfreq(n, 1.0 / fs)[1:n // 2]
    a = math.exp(-1.0 / (fs * tc))
    g = (1.0 - a * a) / np.abs(1.0 - a * np.exp(-2j * math.pi * f / fs)) ** 2  # per sigma^2
    cols = np.array([np.ones_like(f), 1.0 / f, g])
    s = WF.N_TRUE ** 2 * fs + fs * WF.B_TRUE ** 2 / (4.0 * math.pi * f) + sig ** 2 * g
    info = (cols / s) @ (cols / s).T
    return float(math.sqrt(np.linalg.inv(info)[-1, -1]))


def analyse(y: np.ndarray, d: str, s: int) -> dict:
    """``rigctl allan``'s result for the x gyro of rate samples ``y`` (100 Hz), as a recording."""
    path = Path(d) / f"s{s}.h5"
    write_recording(path, WF.FS, angular_rate=np.column_stack((y, np.zeros_like(y),
                                                                np.zeros_like(y))))
    r = AA.compute(str(path), ["gx"], 95, False, None, gaps="skip")["axes"]["gx"]
    path.unlink()
    return r


def null_table(k: int) -> dict:
    """False adds of the Gauss-Markov term on pure power-law records (``--null``)."""
    import allan_gm_spectral as SP
    out: dict = {}
    with tempfile.TemporaryDirectory() as d:
        for kind in SP.FAMILIES:
            c = {"records": k, "gm_added": 0, "unprompted_added": 0, "b_estimate": 0,
                 "check_failed": 0}
            for s in range(k):
                fit = analyse(SP.family(kind, 300_000 + s), d, s)["fit"]
                io = (fit.get("ieee_only") or {}).get("coefficients") or fit["coefficients"]
                c["b_estimate"] += bool(io.B.resolved)
                c["gm_added"] += bool(fit.get("gm_term"))
                c["unprompted_added"] += bool((fit.get("gauss_markov") or {}).get("unprompted"))
                c["check_failed"] += not fit["check"]["ok"]
            out[kind] = c
            print(f"{kind:6s}: Gauss-Markov term added {c['gm_added']} of {k} (unprompted "
                  f"{c['unprompted_added']}); B an estimate {c['b_estimate']}; check failed "
                  f"{c['check_failed']}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--null", type=int, default=0, help="false adds: records per family")
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--size", type=float, default=4.0, help="sigma_GM in units of B")
    ap.add_argument("--tc", type=float, default=2.0)
    a = ap.parse_args()
    t0 = time.perf_counter()
    if a.null:
        res = null_table(a.null)
        print(json.dumps({"null": res, "wall_s": round(time.perf_counter() - t0, 1)}))
        return
    sig = a.size * WF.B_TRUE
    rows = []
    fisher = None
    with tempfile.TemporaryDirectory() as d:
        for s in range(a.seeds):
            r = analyse(WF._noise(s, gm=(sig, a.tc)), d, s)
            fit = r["fit"]
            tau, dev, edf = np.asarray(r["tau_s"]), np.asarray(r["adev_rad/s"]), np.asarray(r["edf"])
            n_phase = int(r["n_samples"]) + 1
            has_gm, failed = bool(fit.get("gm_term")), not fit["check"]["ok"]
            unprompted = bool((fit.get("gauss_markov") or {}).get("unprompted"))
            fit0 = (fit.get("ieee_only") or {}).get("coefficients") or fit["coefficients"]
            b_rep = fit["coefficients"].B
            # the IEEE terms' total (the fit without the term) against the band, hump taus
            f0 = F.fit_terms(tau, dev, edf, "gyro", tau0=1.0 / WF.FS, n_phase=n_phase)
            tot = np.sqrt(F.model_avar(tau, {k: getattr(f0["coefficients"], k).value
                                             for k in F.TERMS}))
            lo, hi = WF._band(dev, edf)
            w = (tau >= 0.5) & (tau <= 20.0)
            half = 0.5 * np.log(hi / lo)
            z = np.log(tot / dev) / half  # 0 at the data, +-1 at the band's edges
            gm = GM.gm_candidate(tau, dev, edf, 1.0 / WF.FS, n_phase)
            row = {"seed": s, "outcome": "gm" if has_gm else ("failed" if failed else "silent"),
                   "unprompted": unprompted,
                   "gm_tc_s": (fit.get("gm_term") or {}).get("tc_s"),
                   "gm_tc_covered": bool(has_gm and fit["gm_term"]["tc_ci95_s"][0] <= a.tc
                                         <= fit["gm_term"]["tc_ci95_s"][1]),
                   "gm_sigma_b": ((fit.get("gm_term") or {}).get("sigma_si", math.nan)
                                  / WF.B_TRUE),
                   "gm_sigma_covered": bool(has_gm and fit["gm_term"]["sigma_ci95_si"][0] <= sig
                                            <= fit["gm_term"]["sigma_ci95_si"][1]),
                   "b_over_truth": float(b_rep.value / WF.B_TRUE),
                   "b_resolved": bool(b_rep.resolved),
                   "b_ieee_over_truth": float(fit0.B.value / WF.B_TRUE),
                   "hump_z_max": float(np.max(np.abs(z[w]))),
                   "hump_z_at_s": float(tau[w][np.argmax(np.abs(z[w]))]),
                   "hump_z_min": float(np.min(z[w])),
                   "cand_stat": float(gm.get("statistic", math.nan)),
                   "cand_p": float(gm.get("p_value", math.nan)),
                   "cand_detected": bool(gm.get("detected")),
                   "cand_tc": float(gm.get("tc_s", math.nan)),
                   "cand_n_looks": float(gm.get("n_looks", math.nan))}
            if fisher is None:
                ms = np.round(tau * WF.FS).astype(np.int64)
                sel = np.flatnonzero(ms >= F.B_TEST_M_MIN)
                sd40 = fisher_adev(1.0 / WF.FS, ms[sel[F._thin(sel.size, 40)]], n_phase, sig, a.tc)
                try:
                    sd_all = fisher_adev(1.0 / WF.FS, ms[sel], n_phase, sig, a.tc)
                except np.linalg.LinAlgError:
                    sd_all = math.nan
                sd_qnb = fisher_adev(1.0 / WF.FS, ms[sel[F._thin(sel.size, 40)]], n_phase, sig,
                                     a.tc, free=(0, 1, 2))
                sd_w = fisher_whittle(WF.N_SAMPLES, WF.FS, sig, a.tc)
                thr = float(chi2.isf(2.0 * GM.GM_TEST_ALPHA / row["cand_n_looks"], 1))
                fisher = {"sd_var_adev40": sd40, "sd_var_adev_all": sd_all,
                          "sd_var_adev40_qnb": sd_qnb,
                          "sd_var_whittle": sd_w, "cand_threshold_stat": thr}
                for k, sd in (("adev40", sd40), ("adev_all", sd_all), ("adev40_qnb", sd_qnb),
                              ("whittle", sd_w)):
                    lam = (sig ** 2 / sd) ** 2
                    fisher[f"expected_gain_{k}"] = lam
                    fisher[f"power_{k}"] = float(ncx2.sf(thr, 1, lam)) if np.isfinite(lam) else None
                print("Fisher: " + json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                                               for k, v in fisher.items()}), flush=True)
            rows.append(row)
            print(f"seed {s:2d} {row['outcome']:6s}{'*' if unprompted else ' '} B {row['b_over_truth']:.2f}x "
                  f"(IEEE-only {row['b_ieee_over_truth']:.2f}x) hump |z| max "
                  f"{row['hump_z_max']:.2f} at {row['hump_z_at_s']:.3g} s; candidate stat "
                  f"{row['cand_stat']:.2f} p {row['cand_p']:.3g} Tc {row['cand_tc']:.3g}",
                  flush=True)
    silent = [r for r in rows if r["outcome"] == "silent"]
    out = {"seeds": a.seeds, "size_b": a.size, "tc_s": a.tc,
           "gm": sum(r["outcome"] == "gm" for r in rows),
           "gm_unprompted": sum(r["unprompted"] for r in rows),
           "failed": sum(r["outcome"] == "failed" for r in rows),
           "silent": len(silent), "silent_seeds": [r["seed"] for r in silent],
           "silent_cand_detected": sum(r["cand_detected"] for r in silent),
           "gm_tc_range_s": [min((r["gm_tc_s"] for r in rows if r["gm_tc_s"]), default=None),
                             max((r["gm_tc_s"] for r in rows if r["gm_tc_s"]), default=None)],
           "gm_sigma_range_b": [min((r["gm_sigma_b"] for r in rows if r["gm_tc_s"]), default=None),
                                max((r["gm_sigma_b"] for r in rows if r["gm_tc_s"]), default=None)],
           "gm_tc_covered": sum(r["gm_tc_covered"] for r in rows),
           "gm_sigma_covered": sum(r["gm_sigma_covered"] for r in rows),
           "fisher": fisher, "rows": rows, "wall_s": round(time.perf_counter() - t0, 1)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
