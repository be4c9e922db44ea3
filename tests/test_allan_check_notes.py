"""The note under an axis' table when the self-check passes on the family-wise band: "as chance
allows for a fit consistent with the curve" only where the chi-square over all taus agrees.
Seen on a 5-minute bag (synthetic N + B + K, gy): 24 of 67 informative taus outside the 95 %
band, none outside the family-wise band by more than 10 %, chi-square 123.8 on 39 dof, p =
9.2e-11 -- and the note called the fit consistent with the curve, the goodness line under it
"beyond its 99 % point". The check dicts here are written out (numbers of that capture).
Since a chi-square beyond its 99 % point is never a pass, the solver writes that check with
``ok: false`` and ``chi2_beyond_99: true``: the taus are then named in the warnings, as a
finding, and no note is left to call the fit consistent."""
from __future__ import annotations

from scipy.stats import chi2 as chi2_dist

from rigctl.analysis.allan import check_notes, check_warnings


def _result(p_value: float, chi2: float) -> dict:
    beyond = p_value < 0.01  # as rigctl.solvers.allan_fit writes the check
    check = {"ok": not beyond, "chi2_beyond_99": beyond, "chi2_carried_by": None,
             "n_informative": 67, "n_outside_familywise": 0, "n_outside": 24,
             "outside": [{"tau_from_s": 1.85, "tau_to_s": 5.78, "side": "data above the fit",
                          "worst_tau_s": 5.78, "data_over_fit": 1.164, "likely": "a bump"}],
             "outside_small": [], "outside_past_prefix": [], "front_excluded": None,
             "chi2": chi2, "dof": 39, "p_value": p_value, "model_error_rel": 0.0}
    return {"fit": {"check": check}}


def test_a_chi_square_beyond_its_99_point_is_not_called_consistent():
    """123.8 on 39 dof is beyond its 99 % point (scipy: p = 9.2e-11 < 0.01): the check fails
    (it passed before on the family-wise band alone), the warnings say it is a finding and
    name the 24 taus; no note calls the fit consistent."""
    assert chi2_dist.sf(123.8, 39) < 0.01
    r = _result(9.2e-11, 123.8)
    assert check_notes(r) == []
    warns = check_warnings(r)
    text = " ".join(warns)
    assert "consistent with the curve" not in text and "as chance allows" not in text
    assert "self-check failed" in warns[0] and "a finding, not a pass" in warns[0], warns
    assert "beyond its 99 % point" in warns[0] and "p = 9.2e-11" in warns[0], warns
    assert "24 of 67 informative taus" in text and "family-wise" in text, warns


def test_a_chi_square_within_its_99_point_keeps_the_chance_note():
    notes = check_notes(_result(0.12, 48.3))
    assert len(notes) == 1 and "as chance allows for a fit consistent with the curve" in notes[0]
