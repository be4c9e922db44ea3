"""A Gauss-Markov bump the self-check passes as flicker: `rigctl allan` runs the candidate's
likelihood-ratio test beside a B estimate too, not only at a bump the check names.

The record is tests/test_allan_check_bounds.py's (5 minutes at 100 Hz: white N 0.2 deg/sqrt(h)
+ flicker B 5 deg/h, FFT-shaped) with a first-order Gauss-Markov rate of sigma 4 B, Tc 2 s
(an AR(1) in numpy), seed 35 of the 40-record protocol of docs/allan.md ("Detection limits";
benchmarks/allan_gm_silent.py). There the IEEE 952 terms alone pass the self-check
(chi2 37.9 on 38 dof, no bump named) with the hump taken as flicker, B 2.7x its truth; before
this change `rigctl allan` said nothing (the candidate ran only at a bump the check names)
although the candidate's test on the same curve gives p = 5e-6. Expected values are the
simulation's truth: the term's Tc and sigma_GM intervals must hold it, and B beside the term
must come down to the flicker's level. The same record without the bump gets no term.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import test_allan_check_bounds as WF
from recording_helpers import write_recording

from rigctl.analysis import allan as AA

SEED = 35
SIGMA_GM, TC = 4.0 * WF.B_TRUE, 2.0


def _fit(tmp_path: Path, y: np.ndarray) -> dict:
    path = write_recording(tmp_path / "r.h5", WF.FS,
                           angular_rate=np.column_stack((y, np.zeros_like(y), np.zeros_like(y))))
    return AA.compute(str(path), ["gx"], 95, False, None, gaps="skip")["axes"]["gx"]


def test_a_bump_taken_as_flicker_gets_its_gauss_markov_term(tmp_path: Path) -> None:
    r = _fit(tmp_path, WF._noise(SEED, gm=(SIGMA_GM, TC)))
    fit = r["fit"]
    t = fit.get("gm_term")
    assert t, "no Gauss-Markov term: the bump is left in B"
    # the scenario: the IEEE 952 terms alone passed their check with B inflated
    io = fit["ieee_only"]
    assert io["check"]["ok"] and io["coefficients"].B.resolved
    assert io["coefficients"].B.value > 2.0 * WF.B_TRUE
    assert fit["gauss_markov"]["unprompted"] and fit["gauss_markov"]["p_value"] < 1e-3
    # the term holds the truth; B beside it is no longer the hump
    assert t["tc_ci95_s"][0] <= TC <= t["tc_ci95_s"][1]
    assert t["sigma_ci95_si"][0] <= SIGMA_GM <= t["sigma_ci95_si"][1]
    assert fit["coefficients"].B.value < 1.5 * WF.B_TRUE
    assert fit["check"]["ok"]
    w = " ".join(AA.check_warnings(r))
    assert "which their fit took as flicker" in w and "Gauss-Markov term was added" in w


def test_the_same_record_without_the_bump_gets_none(tmp_path: Path) -> None:
    fit = _fit(tmp_path, WF._noise(SEED))["fit"]
    assert not fit.get("gm_term")
    b = fit["coefficients"].B
    assert b.value < 2.0 * WF.B_TRUE and math.isfinite(b.value)


if __name__ == "__main__":
    pytest.main([__file__, "-q", "-n", "0"])
