"""A calibration against the emulator's truth at a family-wise false-alarm level: the check of
the wired and in-process 24-position runs (tests/test_hil_runs.py) and of its own behaviour
(tests/test_hil_cal_band.py), on {parameter: (value, 1-sigma)} dicts.

The closed loop (rigctl/solvers/closed_loop.py) adds a library effect when it is significant at
family-wise alpha = 0.01 per round (Bonferroni over the round's candidates) with dBIC < 0 and a
better cross-validation. So on a rig that has none of the library's effects it still adds one
in about 1 % of the runs, by design: measured 4 of 450 (one of them table_levelling) on wired
recordings whose windows were refilled with the declared model and fresh white noise, and 0 of
63 wired runs at 100x (50 frame, 7 VectorNav, 6 Xsens), whose window means sit on the truth
within white noise (no tilt-like signal: the tilt's chi2 with the truth known has mean 2.2 for
2 dof over the 50 frame runs, KS p = 0.21 against chi2(2)). The CI failure at c5cf9c7
(table_levelling on a frame run) was one of these false alarms.

Requiring the calibration's parameter set to be exactly the declared one made each wired run
fail at that rate, three wired runs per CI run. Instead an added effect's parameters are held to
their truth -- 0: the emulated rig has none of the library's effects (:func:`no_library_effects`)
-- inside the same family-wise band as the declared ones. A real effect still fails the check
(a table tilt of 5 sigma in 80 % of the runs, of 7 sigma always: z_c = 4.15), and so does a
declared parameter missing from the calibration or a parameter no added effect carries.
"""
from __future__ import annotations

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


def expected_values(cal: dict, truth: dict, added: dict[str, str]) -> dict[str, float]:
    """The truth of every parameter of ``cal``: the declared ones from ``truth``, 0 for those of
    the effects the closed loop added (``added``: parameter -> effect; see the module docstring).
    Fails when a declared parameter is missing or a parameter is neither declared nor added."""
    missing = sorted(set(truth) - set(cal))
    assert not missing, f"declared parameters missing from the calibration: {missing}"
    stray = sorted(set(cal) - set(truth) - set(added))
    assert not stray, f"parameters neither declared nor of an effect the closed loop added: {stray}"
    return {**truth, **{k: 0.0 for k in set(cal) - set(truth)}}


def outside_band(cal: dict, truth: dict, added: dict[str, str] | None = None,
                 family_alpha: float = FAMILY_ALPHA) -> tuple[float, dict[str, float]]:
    """(z threshold, {parameter: z} of the parameters outside the family-wise band); the family
    is every parameter of ``cal`` (declared, and those of the added effects, truth 0)."""
    from scipy.stats import norm
    want = expected_values(cal, truth, added or {})
    zc = float(norm.ppf(1 - family_alpha / (2 * len(want))))
    score = {k: (cal[k][0] - want[k]) / cal[k][1] for k in want}
    return zc, {k: v for k, v in score.items() if not abs(v) <= zc}


def same_calibration(cal: dict, truth: dict, added: dict[str, str] | None = None,
                     family_alpha: float = FAMILY_ALPHA) -> None:
    """The run's calibration finds the emulator's truth within its own intervals, all m = 27
    declared parameters -- and those of any effect the closed loop added, against 0 -- together
    at family-wise false-alarm level ``family_alpha`` (Bonferroni: each |value - truth| <= z sigma,
    z = z_(1 - alpha / 2m) = 4.13 for alpha = 1e-3 and m = 27, 4.15 for m = 29).

    Measured on 47 wired runs (16 VectorNav, 15 frame, 16 Xsens at load 10-12; the CI failure's
    accel_M_zz_ratio 3.74 sigma was on VectorNav): z = (value - truth) / sigma has mean -0.56 ..
    +0.49 and pooled sd 0.98 per parameter, median largest |z| of a run 2.21 (2.24 for 27 N(0, 1)
    draws), accel_M_zz_ratio -0.28 +- 0.89 (VectorNav -0.10 +- 0.81): no protocol offset (the CI
    run's value, 1.0003231 +- 7.2e-6, is +3.2 sigma from the truth 1.0003: far in that tail, inside
    this band). So the false-alarm rate at z = 4.13 is 1.1e-3 per run (from those means and sd).

    An added effect (about 1 % of the runs, the closed loop's design: module docstring) was
    selected for its significance, so its |z| is mostly 3.3-4 against 0: inside the band. It
    fails the check when |z| > 4.15, which the loop's false alarms reach with probability about
    7e-4 per run (20-odd parameters of the small candidates, 3.4e-5 each): the check's whole
    false-alarm rate stays near 2e-3 per run.

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
    zc, bad = outside_band(cal, truth, added, family_alpha)
    want = expected_values(cal, truth, added or {})
    score = {k: (cal[k][0] - want[k]) / cal[k][1] for k in want}
    worst = max(score, key=lambda k: abs(score[k]))
    assert not bad, (f"outside the family-wise {1 - family_alpha:.1%} band (z = {zc:.2f}): "
                     f"{ {k: (cal[k], want[k], f'{v:+.2f} sigma') for k, v in bad.items()} }; "
                     f"worst {worst} {score[worst]:+.2f}")


def assert_detects_injected_errors(cal: dict, truth: dict, added: dict[str, str] | None = None,
                                   n_sigma: float = 5.0, family_alpha: float = FAMILY_ALPHA) -> None:
    """Power of :func:`same_calibration` on this very run, on the dicts (no second run): an
    error of ``n_sigma`` of its own 1-sigma added to one declared parameter, each of the 27 in
    turn and each sign (54 cases), must be flagged -- and named -- in at least 60 % of the cases
    (the expected share for z ~ N(0, 1) is 81 % at 5 sigma, z threshold 4.13; each parameter's
    error in the direction of its present deviation is always flagged, the other one when
    |z| < 0.87; fewer than 60 % is a 4-sigma shortfall of that count). A scale error of +-5 sigma
    in accel_M_zz_ratio (the parameter of the CI failure) must be flagged in at least one
    direction (that of its present deviation; a check of the machinery itself)."""
    flagged = {(k, sign): k in outside_band({**cal, k: (cal[k][0] + sign * n_sigma * cal[k][1], cal[k][1])},
                                            truth, added, family_alpha)[1]
               for k in truth for sign in (+1, -1)}
    assert flagged["accel_M_zz_ratio", +1] or flagged["accel_M_zz_ratio", -1], \
        f"a {n_sigma:g}-sigma scale error in accel_M_zz_ratio is not flagged"
    hits = sum(flagged.values())
    assert hits >= 0.6 * 2 * len(truth), f"only {hits} of {2 * len(truth)} injected {n_sigma:g}-sigma errors flagged"


def calibration_of(payload: dict) -> tuple[dict[str, tuple[float, float]], dict[str, str]]:
    """({parameter: (value, 1-sigma)} of the closed loop's final model, {parameter: effect} of
    the effects it added) from a ``rigctl calibrate`` payload."""
    cl = payload["results"]["closed_loop"]
    cal = {p["name"]: (p["value"], p["sigma"]) for p in cl["final"]["parameters"]}
    added = {p["name"]: e["name"] for e in cl["effects"] for p in e["parameters"]}
    return cal, added
