"""A term held at the curve's own limit whose fit carries no information is a bound, not an
estimate (docs/allan.md, "An estimate needs one degree of freedom").

The recording is test_cli_hostile's: a short emulated 24-position run (the table moves, so the
accelerometer's curve is the table's motion, not noise; the IEEE 952 model needs ~110 % of
sigma^2 as its own error). The fit holds the velocity random walk at the curve's limit at tau0
and keeps it (held_needed), but the misfit inflates its sd to thousands of times its value:
Satterthwaite EDF ~1e-7. It was reported as an estimate with 95 % interval [0, inf) and stored
in the results database with no upper end; now it is a bound at the curve's limit, printed,
written to JSON and stored like every other bound ([0, limit], no dof). The limit is read here
off the deviation table with numpy and scipy's chi-square (the informative taus, hi95/lo95 <=
2, up to the first that is not; min sigma sqrt(tau))."""
from __future__ import annotations

import contextlib
import io
import json
import math
import sqlite3

import numpy as np
from scipy.stats import chi2

from helpers import ROOT

from rigctl import cli
from rigctl.analysis import results as R
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.run.runner import run_procedure

SQRT_H = 60.0  # m/s/sqrt(s) -> m/s/sqrt(h)


def _moving_table_recording(tmp_path):
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    proc = load_procedure(ROOT / "procedures" / "24pos.yaml", {"warmup": "5 s", "sample": "1 s"},
                          cfg.limits)
    res = run_procedure(proc, cfg, tmp_path / "runs", console=io.StringIO(), install_signals=False)
    assert res.exit_code == 0, res.message
    return res.recording


def test_a_held_term_without_degrees_of_freedom_is_a_bound_at_the_curve_limit(tmp_path):
    rec = _moving_table_recording(tmp_path)
    out_json, db = tmp_path / "allan.json", tmp_path / "results.sqlite"
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(["allan", str(rec), "--axes", "ax", "--json", str(out_json),
                         "--db", str(db)])
    assert code == 0, err.getvalue()
    r = json.loads(out_json.read_text())["axes"]["ax"]

    # the curve's limit on N, read off the table here
    tau = np.asarray(r["tau_s"], dtype=float)
    dev = np.asarray(r["adev_m/s^2"], dtype=float)
    edf = np.asarray(r["edf"], dtype=float)
    hi = dev * np.sqrt(edf / chi2.ppf(0.025, edf))
    lo = dev * np.sqrt(edf / chi2.ppf(0.975, edf))
    informative = np.logical_and.accumulate(hi <= 2.0 * lo)
    assert informative.sum() > 20
    n_limit = float(np.min(dev[informative] * np.sqrt(tau[informative])))

    n = r["fit"]["coefficients"]["N"]
    assert "edf" not in n and "ci95" not in n, n  # not an estimate
    assert n["bound_from"] == "curve"
    assert math.isclose(n["upper95"], n_limit, rel_tol=1e-9)
    # the fit held N there and knew nothing more: its EDF is ~0 (what made it [0, inf) before)
    term = r["fit"]["terms"]["N"]
    assert term["held_at_curve_limit"]
    assert 0.0 <= term["edf_below_estimate"] < 1e-3

    # printed like every other bound, in the field unit
    line = next(ln for ln in out.getvalue().splitlines() if "velocity_random_walk:" in ln)
    assert f"< {n_limit * SQRT_H:.5g} m/s/sqrt(h) (the curve's own limit" in line, line
    assert "inf" not in line

    # the conformity path: a bound, interval [0, limit]
    m = next(x for x in R.from_allan({"axes": {"ax": r}}) if x.name == "accel_noise_N_x")
    assert m.estimate.kind == "bound"
    assert m.estimate.interval() == (0.0, n["upper95"])

    # the results database: [0, limit] in m/s/sqrt(h), no dof (a bound), not an open interval
    with contextlib.closing(sqlite3.connect(db)) as con:
        dof, ci_lo, ci_hi, unit = con.execute(
            "select dof, ci95_low, ci95_high, unit from results where name_si = ?",
            ("accel_noise_N_x",)).fetchone()
    assert dof is None and ci_lo == 0.0 and unit == "m/s/sqrt(h)"
    assert ci_hi is not None and math.isclose(ci_hi, n_limit * SQRT_H, rel_tol=1e-9)
