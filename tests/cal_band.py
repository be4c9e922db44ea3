"""A calibration against the emulator's truth at a family-wise false-alarm level: the check of
the wired and in-process 24-position runs (tests/test_hil_runs.py) and of its own behaviour
(tests/test_hil_cal_band.py), on {parameter: (value, 1-sigma)} dicts.

The closed loop (rigctl/solvers/closed_loop.py) adds a library effect when it is significant at
family-wise alpha = 0.01 per round (Bonferroni over the round's candidates) with dBIC < 0 and a
better cross-validation. So on a rig that has none of the library's effects it still adds one
in about 1 % of the runs, by design: measured 8 of 700 (one of them table_levelling) on wired
recordings whose windows were refilled with the declared model and fresh white noise, and 0 of
77 wired runs at 100x (50 frame, 7 VectorNav, 20 Xsens), whose window means sit on the truth
within white noise (no tilt-like signal: the tilt's chi2 with the truth known has mean 2.2 for
2 dof over the 50 frame runs, KS p = 0.21 against chi2(2)). The CI failure at c5cf9c7
(table_levelling on a frame run) was one of these false alarms.

Requiring the calibration's parameter set to be exactly the declared one made each wired run
fail at that rate, three wired runs per CI run. Holding the added parameters to 0 in the same
per-parameter band is no cure: the loop picks an effect because it is large, so its parameters
sit at |z| ~ 3.4-4.3 against 0, and a spurious regressor drags the declared parameters it
correlates with into that tail too (of the 4 refilled runs above: table_tilt_north_rad +4.23
against z_c = 4.14; accel_time_drift +4.16 with accel_bias_x +4.18 and accel_quad_x -4.28 in the
final fit). So :func:`check_calibration`, when the loop added something:

* holds the declared parameters of the *declared* fit (the model before the loop's additions) to
  the truth in the family-wise band. Under the emulator's truth that model is right, and its
  estimates are independent of the residual contrasts on which the loop decides (and from which
  the session's noise model is estimated), so its z stay N(0, 1) whatever the loop did: the 4
  runs' largest |z| there are 3.11, 2.60, 2.18, 1.68. With nothing added, the final model is
  the declared one and is checked as before.
* holds each added effect's parameters together to 0: chi2 = b^T C^-1 b (C: their covariance in
  the final fit, k of them), flagged when P(chi2_k > chi2) x L < ``family_alpha`` with L the
  number of effects in the loop's library (Bonferroni over every effect it could add, so a false
  alarm of the loop fails this with probability <= family_alpha per run, whichever it picks).
  The 4 spurious effects above: P x L = 0.0029, 0.0085, 0.0023 and 4.5e-4 (lever_arm: flagged).
  A real effect is flagged: a table tilt of 60 / -50 urad at 8 urad 1-sigma has chi2 ~ 90.

So the check fails at most about 2e-3 per run on noise (1.1e-3 declared, <= 1e-3 effects).
Measured on 250 more refilled runs: the exact-set check failed 4 (1.6 %: 4 additions), this one
1 (the declared fit's gyro_bias_z_rad_s at +4.14 sigma, beside a gyro_time_drift addition); on
the 8 additions of all 700 refilled runs it fails 2; all 77 valid wired recordings pass it. It
still fails on a declared parameter outside its band, a real effect, a declared parameter
missing from the calibration, or a parameter no added effect carries.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: family-wise false-alarm level of one calibration check (all its parameters together); see
#: :func:`same_calibration` for why 1e-3 and what it still detects
FAMILY_ALPHA = 1e-3


def truth_parameters(truth_imu: dict) -> dict[str, float]:
    """The emulator's declared IMU errors (``/truth`` imu, SI) under the calibration's parameter
    names, read off its vectors and matrices here (not from the calibration's own truth table)."""
    out: dict[str, float] = {}
    for i, a in enumerate("xyz"):
        out[f"accel_bias_{a}_m_s2"] = truth_imu["accel_bias_m_s2"][i]
        out[f"accel_quad_{a}_s2_per_m"] = truth_imu["accel_quadratic_per_m_s2"][i]
        out[f"gyro_bias_{a}_rad_s"] = truth_imu["gyro_bias_rad_s"][i]
        for j, b in enumerate("xyz"):
            out[f"accel_M_{a}{b}_ratio"] = truth_imu["accel_matrix"][i][j]
            out[f"gyro_M_{a}{b}_ratio"] = truth_imu["gyro_matrix"][i][j]
    return out


def no_library_effects(truth: dict) -> None:
    """The emulated rig of ``truth`` (the emulator's whole /truth) has none of the closed loop's
    library effects, so each parameter of an effect the loop adds is truly 0: the IMU is the
    declared model (bias, scale and misalignment, quadratic: no g-sensitivity, asymmetry, lever
    arm or delay, which only a profile IMU has), at its thermal reference temperature (the idle chamber's), and
    the table's axes neither wobble nor ripple. The table's base is level by construction (the
    emulator computes gravity and Earth rate in the body from the gimbal angles alone,
    rigctl.frames.body_references): it has no tilt or azimuth error to declare."""
    imu = truth["imu"]
    assert imu["model"] == "declared" and "effects" not in imu, imu.get("model")
    ch = truth["chamber"]
    assert (ch["initial_c"], ch["self_heating_c"]) == (imu["thermal"]["reference_c"], 0.0), \
        f"the emulated IMU starts at {ch['initial_c']} degC, not at its thermal reference"
    for ax in truth["table"]["axes"]:
        moving = {k: ax[k] for k in ("wobble_rad", "rate_ripple_per_rev_fraction", "rate_ripple_fraction")
                  if ax[k]}
        assert not moving, f"the emulated table has {moving}: library effects with a non-zero truth"


def outside_band(cal: dict, truth: dict, family_alpha: float = FAMILY_ALPHA) -> tuple[float, dict[str, float]]:
    """(z threshold, {parameter: z} of the parameters outside the family-wise band)."""
    from scipy.stats import norm
    assert set(cal) == set(truth)
    zc = float(norm.ppf(1 - family_alpha / (2 * len(truth))))
    score = {k: (cal[k][0] - truth[k]) / cal[k][1] for k in truth}
    return zc, {k: v for k, v in score.items() if not abs(v) <= zc}


def same_calibration(cal: dict, truth: dict, family_alpha: float = FAMILY_ALPHA) -> None:
    """The run's calibration finds the emulator's truth within its own intervals, all m = 27
    parameters together at family-wise false-alarm level ``family_alpha`` (Bonferroni: each
    |value - truth| <= z sigma, z = z_(1 - alpha / 2m) = 4.13 for alpha = 1e-3).

    Measured on 47 wired runs (16 VectorNav, 15 frame, 16 Xsens at load 10-12; the CI failure's
    accel_M_zz_ratio 3.74 sigma was on VectorNav): z = (value - truth) / sigma has mean -0.56 ..
    +0.49 and pooled sd 0.98 per parameter, median largest |z| of a run 2.21 (2.24 for 27 N(0, 1)
    draws), accel_M_zz_ratio -0.28 +- 0.89 (VectorNav -0.10 +- 0.81): no protocol offset (the CI
    run's value, 1.0003231 +- 7.2e-6, is +3.2 sigma from the truth 1.0003: far in that tail, inside
    this band). So the false-alarm rate at z = 4.13 is 1.1e-3 per run (from those means and sd).

    Compared with the truth, not with the in-process run's calibration as before: that one is a
    single fixed noise realisation (virtual clock, seed 1: the same in every CI run), so a wired
    run's z against it was not N(0, 1) but centred on minus the reference's own error (its
    accel_M_zz_ratio lies 2.18 sigma below the truth: wired z +1.38 +- 0.62), and its sigma
    sqrt(s_w^2 + s_r^2) ~ 1.4 s_w carried the reference's noise, which cost power: a 5-sigma error
    in one parameter was flagged in 30 % of the cases at z = 4.13 (65 % at the old 3.11, where
    each run failed with probability 1.4 %, three such runs per CI run), against 81 % now. The
    in-process run meets the same band (test_hil_runs.test_inprocess_calibration_finds_the_truth,
    deterministic), so wired and in-process calibrations agree through the truth.

    Why 1e-3 and not 5 %: three runs per CI run make this check (Xsens, VectorNav, frame); at
    5 % each (z = 3.11: 5.2 % per run measured) one CI run in seven would fail on noise alone.
    Power is checked on every run, on the dicts, by :func:`assert_detects_injected_errors`."""
    zc, bad = outside_band(cal, truth, family_alpha)
    score = {k: (cal[k][0] - truth[k]) / cal[k][1] for k in truth}
    worst = max(score, key=lambda k: abs(score[k]))
    assert not bad, (f"outside the family-wise {1 - family_alpha:.1%} band (z = {zc:.2f}): "
                     f"{ {k: (cal[k], truth[k], f'{v:+.2f} sigma') for k, v in bad.items()} }; "
                     f"worst {worst} {score[worst]:+.2f}")


def assert_detects_injected_errors(cal: dict, truth: dict, n_sigma: float = 5.0,
                                   family_alpha: float = FAMILY_ALPHA) -> None:
    """Power of :func:`same_calibration` on this very run, on the dicts (no second run): an
    error of ``n_sigma`` of its own 1-sigma added to one parameter, each of the 27 in turn and
    each sign (54 cases), must be flagged -- and named -- in at least 60 % of the cases (the
    expected share for z ~ N(0, 1) is 81 % at 5 sigma, z threshold 4.13; each parameter's error
    in the direction of its present deviation is always flagged, the other one when |z| < 0.87;
    fewer than 60 % is a 4-sigma shortfall of that count). A scale error of +-5 sigma in
    accel_M_zz_ratio (the parameter of the CI failure) must be flagged in at least one direction
    (that of its present deviation; a check of the machinery itself)."""
    flagged = {(k, sign): k in outside_band({**cal, k: (cal[k][0] + sign * n_sigma * cal[k][1], cal[k][1])},
                                            truth, family_alpha)[1]
               for k in truth for sign in (+1, -1)}
    assert flagged["accel_M_zz_ratio", +1] or flagged["accel_M_zz_ratio", -1], \
        f"a {n_sigma:g}-sigma scale error in accel_M_zz_ratio is not flagged"
    hits = sum(flagged.values())
    assert hits >= 0.6 * 2 * len(truth), f"only {hits} of {2 * len(truth)} injected {n_sigma:g}-sigma errors flagged"


@dataclass
class Calibration:
    """A closed-loop calibration as the check needs it ({parameter: (value, 1-sigma)}, SI)."""

    final: dict[str, tuple[float, float]]       # the loop's final model (the published one)
    declared: dict[str, tuple[float, float]]    # the declared model's fit, before any addition
    #: effect -> (its parameter names, values, covariance) in the final model
    effects: dict[str, tuple[list[str], np.ndarray, np.ndarray]] = field(default_factory=dict)


def _params(fit: dict) -> dict[str, tuple[float, float]]:
    return {p["name"]: (p["value"], p["sigma"]) for p in fit["parameters"]}


def calibration_of(closed_loop: dict) -> Calibration:
    """:class:`Calibration` of a closed loop's JSON (``rigctl calibrate``'s
    payload["results"]["closed_loop"], or ClosedLoopResult.to_dict())."""
    final = closed_loop["final"]
    names = [p["name"] for p in final["parameters"]]
    cov = np.asarray(final["covariance"], dtype=float)
    effects = {}
    for e in closed_loop["effects"]:
        mine = [p["name"] for p in e["parameters"]]
        idx = [names.index(n) for n in mine]
        effects[e["name"]] = (mine, np.array([p["value"] for p in e["parameters"]]), cov[np.ix_(idx, idx)])
    return Calibration(_params(final), _params(closed_loop["declared"]), effects)


def effects_outside_zero(effects: dict[str, tuple[list[str], np.ndarray, np.ndarray]], n_library: int,
                         family_alpha: float = FAMILY_ALPHA) -> dict[str, float]:
    """{effect: P(chi2_k > b^T C^-1 b) x n_library} of the added effects whose parameters are not
    0 together at family-wise ``family_alpha`` over the ``n_library`` effects the loop could add."""
    from scipy.stats import chi2
    out = {}
    for name, (_, b, C) in effects.items():
        p = float(chi2.sf(float(b @ np.linalg.solve(C, b)), len(b))) * n_library
        if not p >= family_alpha:
            out[name] = p
    return out


def check_calibration(cal: Calibration, truth: dict[str, float], n_library: int,
                      family_alpha: float = FAMILY_ALPHA) -> None:
    """The closed loop's calibration against the truth ``truth`` (declared parameters) of a rig
    with none of the library's effects (see the module docstring): the declared parameters in
    the family-wise band (of the final model, or of the declared fit when the loop added an
    effect), with the band's power on this run, and each added effect 0 within its own
    uncertainty at family-wise ``family_alpha`` over the ``n_library`` effects it could add."""
    assert set(cal.declared) == set(truth), sorted(set(cal.declared) ^ set(truth))
    added = {n for names, _, _ in cal.effects.values() for n in names}
    missing, stray = sorted(set(truth) - set(cal.final)), sorted(set(cal.final) - set(truth) - added)
    assert not missing, f"declared parameters missing from the final model: {missing}"
    assert not stray, f"parameters neither declared nor of an effect the closed loop added: {stray}"
    declared = cal.declared if cal.effects else {k: cal.final[k] for k in truth}
    same_calibration(declared, truth, family_alpha)
    assert_detects_injected_errors(declared, truth, family_alpha=family_alpha)
    bad = effects_outside_zero(cal.effects, n_library, family_alpha)
    assert not bad, (f"added effects not 0 within their uncertainty (P x {n_library} effects < {family_alpha:g}): "
                     + "; ".join(f"{k} {v:.2g}: " + ", ".join(f"{n} {x / np.sqrt(c):+.2f} sigma" for n, x, c in
                                                             zip(cal.effects[k][0], cal.effects[k][1],
                                                                 np.diag(cal.effects[k][2])))
                                 for k, v in bad.items()))
