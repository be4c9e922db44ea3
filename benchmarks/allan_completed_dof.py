"""How lenient is the completed self-check's chi-square (issue 15)? Its p-value under several
rules for the degrees of freedom, on curves the model describes and on curves it does not.

The self-check (rigctl.solvers.allan_fit, docs/allan.md "Self-check") decides on the completed
total: the resolved terms plus each bounded term at one value in [0, its 95 % bound]
(_admissible_completion); its chi-square's dof are the taus less the non-zero terms, so a
bounded term the completion left at 0 is not counted though the completion could have moved
it. Per fit this recomputes the completed p-value from the fit's own chi-square with

* ``cur``: the fit's rule (the taus less the resolved terms less the bounded terms above 0);
* ``all``: every bounded term subtracted (the completion's free parameters, k of them);
* ``chibar``: the chi-bar-square mixture of a fit with k non-negativity constraints, weights
  binom(k, j) / 2^k on the dof less j (orthogonal columns' weights);

and prints, per case, how many p-values fall below 0.05 and 0.01 (the decision is p >= 0.01,
MODEL_ERROR_P), a Kolmogorov-Smirnov test against uniform and the decile histogram.

Cases (the curves are computed in plain numpy by the tests' generators):
``null_wf``: white + flicker rate noise, 5 min at 100 Hz, 40 taus (tests/test_allan_check_bounds.py:
B present, often unresolved); ``null_wrw``: white + rate random walk, 1 h at 20 Hz, 40 taus
(tests/test_allan_false_alarms.py: Q, B, R truly 0); ``gmF``: null_wf plus a Gauss-Markov rate,
Tc 2 s, sigma F x B (a bump outside the model); ``stepF``: null_wf plus a rate step of F x B at
half the record; ``rampF``: null_wf plus a rate ramp of F x B over the record (R is in the model:
not a misfit). ``--quickstart-seeds``: also the quickstart's capture through
rigctl.analysis.allan.compute (benchmarks/allan_quickstart_cov.py), 6 axes per seed.
The last line is one JSON object.
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import _common  # noqa: F401  first: one BLAS thread before numpy loads; tests/, benchmarks/ importable

import numpy as np  # noqa: E402
from scipy.stats import chi2, kstest  # noqa: E402

import allan_quickstart_cov as QS  # noqa: E402
import test_allan_check_bounds as WF  # noqa: E402
import test_allan_false_alarms as WRW  # noqa: E402

from rigctl.solvers import allan_fit as F  # noqa: E402


def one_fit(case: str, seed: int) -> dict:
    """The fit of one synthetic curve of ``case`` (see the module's docstring)."""
    if case == "null_wrw":
        ms = WRW._factors("40")
        tau, dev, edf = WRW._curve(WRW._series(8100 + seed, False), ms)
        return F.fit_terms(tau, dev, edf, "gyro", tau0=1.0 / WRW.FS, n_phase=WRW.N_SAMPLES + 1)
    kind, f = case.rstrip("0123456789."), float(case.lstrip("abcdefghijklmnopqrstuvwxyz_") or 0)
    y = WF._noise(seed, gm=(f * WF.B_TRUE, 2.0) if kind == "gm" else None)
    if kind == "step":
        y[y.size // 2:] += f * WF.B_TRUE
    elif kind == "ramp":
        y = y + f * WF.B_TRUE * np.arange(y.size) / y.size
    elif kind not in ("gm", "null_wf"):
        raise SystemExit(f"unknown case {case!r}: null_wf, null_wrw, gmF, stepF, rampF")
    tau, dev, edf, n_phase = WF._curve(y)
    return F.fit_terms(tau, dev, edf, "gyro", tau0=1.0 / WF.FS, n_phase=n_phase)


def p_values(r: dict) -> dict:
    """The completed p-value under each dof rule (module docstring)."""
    fr = r["fraction_of_bound"]
    k, x, d = len(fr), r["chi2"], r["dof_rep"]
    return {"cur": r["p_value"], "all": float(chi2.sf(x, max(1, d - k))),
            "chibar": float(sum(math.comb(k, j) / 2 ** k * chi2.sf(x, max(1, d - j))
                                for j in range(k + 1)))}


def summary(name: str, rows: list[dict]) -> dict:
    """Print and return the counts below 0.05 / 0.01, KS p and deciles of each rule."""
    out = {"n": len(rows), "moved_mean": float(np.mean([sum(v > 0 for v in r["fraction_of_bound"]
                                                            .values()) for r in rows])),
           "bounded_mean": float(np.mean([len(r["fraction_of_bound"]) for r in rows]))}
    print(f"{name}: {len(rows)} fits, bounded terms {out['bounded_mean']:.2f} on average, "
          f"{out['moved_mean']:.2f} moved above 0 by the completion")
    for rule in ("cur", "all", "chibar"):
        p = np.array([p_values(r)[rule] for r in rows])
        hist = np.histogram(p, bins=10, range=(0.0, 1.0))[0].tolist()
        out[rule] = {"below_0.05": int(np.sum(p < 0.05)), "below_0.01": int(np.sum(p < 0.01)),
                     "ks_p": float(kstest(p, "uniform").pvalue), "deciles": hist}
        r = out[rule]
        print(f"  {rule:6s} p<0.05 {r['below_0.05']:4d}  p<0.01 {r['below_0.01']:4d}"
              f"  KS p {r['ks_p']:.3g}  deciles {hist}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="null_wf,null_wrw,gm4,step3,ramp5")
    ap.add_argument("--seeds", type=int, default=400)
    ap.add_argument("--quickstart-seeds", type=int, default=0)
    a = ap.parse_args()
    res = {}
    t0 = time.perf_counter()
    for case in a.cases.split(","):
        res[case] = summary(case, [QS.completed_check(one_fit(case, s)["check"])
                                   for s in range(a.seeds)])
    if a.quickstart_seeds:
        fs, noise = QS.default_noise()
        n = int(round(5 * 60 * fs))
        rows = []
        with tempfile.TemporaryDirectory() as d:
            for s in range(a.quickstart_seeds):
                cap = QS.one_capture(Path(d) / f"s{s}.h5", noise, fs, n, s)
                rows += [cap[ax]["check_completed"] for ax in QS.AXES]
        res["quickstart"] = summary("quickstart", rows)
    print(f"{time.perf_counter() - t0:.0f} s")
    print(json.dumps(res))


if __name__ == "__main__":
    main()
