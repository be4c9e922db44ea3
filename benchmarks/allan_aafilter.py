"""The fit and its self-check on filtered IMU-like noise: an anti-aliasing low-pass
(docs/allan.md, "The sensor's anti-aliasing filter: its taus left out of the fit").

Records: benchmarks/allan_gm_spectral.py's ``wf_bw`` (white N 0.2 deg/sqrt(h) + flicker B 5 deg/h
+ random walk K 3 deg/h/sqrt(h) drawn at 1 kHz, a 2nd-order Butterworth at 40 Hz, every 10th
sample kept: 5 minutes at 100 Hz, the filter at 0.8 of the output's Nyquist) and ``wfk`` (the
same noise unfiltered, the control); seeds 100000.. ; the curve and the fit of
tests/test_allan_check_bounds.py (40 log-spaced taus, exact overlapping ADEV, NIST EDF,
``fit_terms(..., tau0, n_phase)``).

Per family: how often the check fails, where (the run at tau0 "data below the fit", and the run
that carries the chi-square), the cause the check names, S = sigma^2 tau / N^2 at m = 1, 2, 4
(1 on a white-noise line), N against its truth and against the output's own white level (95 %
interval holds it, ratio), and the filter's region rigctl left out of the fit
(``check.filter_excluded``: on how many records, its first fitted m); then, for comparison,
the same fit given only the taus of m >= 2, 4, 8, 16 samples (a fixed start: what rigctl does
not do; its region is read from the curve, allan_fit.filter_region).

    python benchmarks/allan_aafilter.py [--records 20]

Last line: one JSON object. 20 + 20 records, five starts each: ~45 s.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.signal import butter, lfilter

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

import test_allan_check_bounds as WF  # noqa: E402
from allan_gm_spectral import family  # noqa: E402

from rigctl.solvers import allan_fit as F  # noqa: E402


def aliased_white() -> float:
    """N of the filtered record's own white noise over N_TRUE. Every 10th point of the
    Butterworth's 1 kHz output is kept without averaging, so the aliased power stays: the
    sampled sequence's PSD at f -> 0 is N^2 sum_k |H(f + k fs)|^2, i.e. N^2 (R(0) + 2 sum_k
    R(k tau0)) / (unit-gain R at 1 kHz) with R the filter's autocorrelation at the 10 ms lags
    (scipy.signal, independent of rigctl)."""
    b, a = butter(2, 40.0 / 500.0)
    h = lfilter(b, a, np.r_[1.0, np.zeros(4000)])
    acf = np.correlate(h, h, "full")[h.size - 1:]
    return float(np.sqrt((acf[0] + 2.0 * acf[10::10].sum()) * 10.0))


def one(kind: str, seed: int, m_min: int, n_out: float) -> dict:
    """Fit one record's curve from m >= m_min samples; the check's and N's figures."""
    tau, dev, edf, n_phase = WF._curve(family(kind, seed))
    keep = np.round(tau * WF.FS) >= m_min
    fit = F.fit_terms(tau[keep], dev[keep], edf[keep], "gyro", tau0=1.0 / WF.FS,
                      n_phase=n_phase)
    c, n = fit["check"], fit["coefficients"].N
    runs = c["outside"]
    first = [r for r in runs if r["tau_from_s"] <= tau[0] * 1.001 and "below" in r["side"]]
    carried = c.get("chi2_carried_by") or {}
    fe = c.get("filter_excluded")
    return {"fail": not c["ok"], "first_below": bool(first),
            "filter_m_to": fe["m_to"] if fe else None,
            "named_filter": any("low-pass" in r["likely"] for r in runs),
            "first_ratio": first[0]["data_over_fit"] if first else None,
            "carried_short": bool(carried) and carried["tau_to_s"] <= 0.05 + 1e-9,
            "carried_share": carried.get("chi2_share"),
            "s_over_n2": (dev[:3] ** 2 * tau[:3] / WF.N_TRUE ** 2).tolist(),
            "n_ratio": n.value / WF.N_TRUE,
            "n_covered": bool(n.ci95 and n.ci95[0] <= WF.N_TRUE <= n.ci95[1]),
            "n_covered_output": bool(n.ci95 and n.ci95[0] <= n_out <= n.ci95[1])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=20)
    a = ap.parse_args()
    alias = aliased_white()
    out: dict = {"wf_bw_output_N_over_N_true": round(alias, 4)}
    print(f"wf_bw: the sampled output's own N = {alias:.4f} N_TRUE (aliased power)", flush=True)
    for kind in ("wf_bw", "wfk"):
        n_out = WF.N_TRUE * (alias if kind == "wf_bw" else 1.0)
        for m_min in (1, 2, 4, 8, 16):
            rs = [one(kind, 100_000 + s, m_min, n_out) for s in range(a.records)]
            nr = [r["n_ratio"] for r in rs]
            row = {"fail": sum(r["fail"] for r in rs),
                   "n_covered": sum(r["n_covered"] for r in rs),
                   "n_covered_output": sum(r["n_covered_output"] for r in rs),
                   "n_ratio_min_med_max": [round(min(nr), 3), round(float(np.median(nr)), 3),
                                           round(max(nr), 3)]}
            if m_min == 1:
                mt = [r["filter_m_to"] for r in rs if r["filter_m_to"] is not None]
                row["filter_excluded"] = len(mt)
                row["filter_first_fitted_m"] = {str(int(v)): mt.count(v) for v in sorted(set(mt))}
                fr = [r["first_ratio"] for r in rs if r["first_ratio"] is not None]
                sh = [r["carried_share"] for r in rs if r["carried_short"]]
                s = np.array([r["s_over_n2"] for r in rs])
                row.update({"first_tau_below": sum(r["first_below"] for r in rs),
                            "named_filter": sum(r["named_filter"] for r in rs),
                            "first_ratio_range": [round(min(fr), 3), round(max(fr), 3)] if fr
                            else None,
                            "chi2_carried_by_tau_le_0.05s": len(sh),
                            "carried_share_range": [round(min(sh), 2), round(max(sh), 2)] if sh
                            else None,
                            "S_over_N2_m1_m2_m4_median": np.round(np.median(s, axis=0), 3).tolist()})
            out[f"{kind}_m>={m_min}"] = row
            print(kind, f"m >= {m_min}:", row, flush=True)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
