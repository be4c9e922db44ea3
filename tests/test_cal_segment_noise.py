"""Noise model of the segment means estimated from the session, and the closed loop under
time-correlated noise (bias instability + rate random walk), on synthetic sessions.

A session here is test_cal_synth's turntable plan (24 positions of 20 s, rate windows of 10 s,
ramps of 4 s, 10 s apart) with its A2 truth, after a 15-minute static warm-up from power-on
(t = 0), but the noise is the emulator's own generator (rigctl.sim.noise.NoiseGenerator) run
over the whole session at 100 Hz with the declared_only profile's coefficients
(configs/imu-profiles.yaml), and each window's mean and batch means (and the warm-up's 30-s
batch means) taken from it: the errors of different segments' means are then correlated, as on
real MEMS data. The rate windows here do not hold whole revolutions (10 s at 40-100 deg/s) and
the ramps have angular acceleration, so only the static windows give within-window contrasts.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from rigctl.sim.noise import NoiseGenerator
from rigctl.solvers import segment_cov as sc
from rigctl.solvers import segment_noise as sn
from rigctl.solvers.closed_loop import closed_loop, declared_design
from rigctl.solvers.effect_library import effect_by_name
from rigctl.solvers.noise_coefficients import triad
from rigctl.solvers.segment_stats import batch_means, self_noise_sigma
from rigctl.solvers.segments import rest_batches
from test_cal_synth import FS, make_session, segment_plan

WARMUP_S = 900.0

ACC = {"N": 5.9e-4, "B": 1.47e-4, "K": 3.0e-6}  # declared_only profile, SI
GYR = {"N": 1.22e-4, "B": 3.88e-5, "K": 1.0e-6}


def correlated_session(seed: int, effects: dict[str, np.ndarray] | None = None):
    """(SegmentTable with independent self sigmas, truth) -- see the module docstring."""
    st, truth = make_session(seed)
    dur = np.array([p["dur"] for p in segment_plan(True)])
    st.time = st.time + WARMUP_S - 60.0  # the plan starts at 60 s
    st.t_start, st.t_end = st.time - dur / 2, st.time + dur / 2
    X3, names = declared_design(st)
    y = X3 @ np.array([truth[n] for n in names])  # (K, 6) noise-free declared model
    for name, coef in (effects or {}).items():
        Xe, _ = effect_by_name(name).build(st)
        y = y + Xe @ coef
    i0, i1 = np.round(st.t_start * FS).astype(int), np.round(st.t_end * FS).astype(int)
    noise = [NoiseGenerator(triad(**p), FS, 1000 * seed + k).next(int(i1.max()) + 1) for k, p in enumerate((ACC, GYR))]
    x = np.concatenate(noise, axis=1)  # (n, 6)
    win = [x[a:b] for a, b in zip(i0, i1)]
    st.f = y[:, :3] + np.array([w[:, :3].mean(axis=0) for w in win])
    st.w = y[:, 3:] + np.array([w[:, 3:].mean(axis=0) for w in win])
    st.f_sigma = np.array([self_noise_sigma(w[:, :3], FS) for w in win])  # each window's own scatter
    st.w_sigma = np.array([self_noise_sigma(w[:, 3:], FS) for w in win])
    st.batch_means = np.array([(batch_means(w) - w.mean(axis=0) + m).T for w, m in
                               zip(win, np.concatenate([st.f, st.w], axis=1))])
    n_w = int(WARMUP_S * FS)  # static at the first position: its truth plus the noise
    st.rest = rest_batches(np.arange(n_w) / FS, y[0, :3] + x[:n_w, :3], y[0, 3:] + x[:n_w, 3:], FS)
    return st, truth


def _band(res):
    lo, hi = scipy.stats.chi2.ppf([0.005, 0.995], res.dof)
    return lo <= res.chi2 <= hi


def _covered(res, truth):
    return [bool(lo <= truth[n] <= hi) for n, (lo, hi) in zip(res.names, res.ci95) if n in truth]


@pytest.fixture(scope="module")
def clean():
    out = []
    for seed in (21, 22, 23):
        st, truth = correlated_session(seed)
        independent = closed_loop(st, truth=truth)
        models = sn.apply_session_noise(st)
        out.append((st, truth, independent, models, closed_loop(st, truth=truth)))
    return out


def test_independent_means_fail_under_time_correlated_noise(clean):
    """The defect: means treated as independent give an improbable chi2 on clean data."""
    assert sum(ind.declared.chi2_p_value < 1e-3 for _, _, ind, _, _ in clean) >= 2, \
        [ind.declared.chi2_per_dof for _, _, ind, _, _ in clean]


def test_session_noise_model_clean_chi2_coverage_no_flag(clean):
    cover = []
    for st, truth, _, models, res in clean:
        assert len(models) == 6 and st.cov is not None
        assert _band(res.final), res.final.chi2_per_dof
        assert res.effects == [] and res.unexplained == [], (res.effect_names, res.unexplained)
        cover += _covered(res.final, truth)
        # the white level comes out near the generator's (static windows: 7 contrasts each)
        n_acc = np.array([m.n_of("orientation") for m in models[:3]])
        n_gyr = np.array([m.n_of("orientation") for m in models[3:]])
        np.testing.assert_allclose(n_acc, ACC["N"], rtol=0.2)
        np.testing.assert_allclose(n_gyr, GYR["N"], rtol=0.2)
    assert len(cover) == 81 and np.mean(cover) >= 0.90, np.mean(cover)


def _window_cov(a, b, N, B, K):
    """The model covariance of the window means written out here from the unit kernels:
    N^2 diag(1/T) + B^2 C_flicker(default band) + K^2 C_rw(t0 = 0)."""
    C = N**2 * np.diag(1.0 / (b - a)) + B**2 * sc.cov_flicker(a, b) + K**2 * sc.cov_random_walk(a, b)
    return 0.5 * (C + C.T)


def test_known_coefficients_give_the_model_covariance():
    st, truth = correlated_session(24)
    models = sn.apply_session_noise(st, triad("accel", "given", **ACC), triad("gyro", "given", **GYR))
    assert [m.source for m in models] == ["given"] * 6
    np.testing.assert_allclose(st.cov[1], _window_cov(st.t_start, st.t_end, **ACC), rtol=1e-10)
    np.testing.assert_allclose(st.cov[5], _window_cov(st.t_start, st.t_end, **GYR), rtol=1e-10)
    np.testing.assert_allclose(st.w_sigma[:, 2] ** 2, np.diag(st.cov[5]))
    res = closed_loop(st, truth=truth)
    assert _band(res.final) and not res.effects and not res.unexplained
    assert np.mean(_covered(res.final, truth)) >= 0.85


# magnitudes of a MEMS warm-up (about 5 mg and 0.1-0.5 deg/s over the session): a slow effect
# must stand out of the slow noise (bias instability ~15 ug, 8 deg/h here) to be found at all
EFFECTS = {"lever_arm": np.array([0.02, -0.01, 0.015]),
           "gyro_warmup_temperature": np.array([1e-4, -8e-5, 6e-5]),
           "accel_time_drift": np.array([5e-6, 0.0, -4e-6])}


def test_variance_components_do_not_absorb_real_effects(clean):
    """The same noise with undeclared slow and rate-block effects added: the session's noise
    model stays that of the clean session (the effects are in the protected design, not in the
    noise), and the closed loop finds and names each effect."""
    st0, _, _, models0, _ = clean[0]
    st, truth = correlated_session(21, EFFECTS)
    models = sn.apply_session_noise(st)
    for m, m0 in zip(models, models0):
        for g in m0.white_by_group:
            assert np.isclose(m.n_of(g) ** 2, m0.n_of(g) ** 2, rtol=0.1), (g, m.white_by_group, m0.white_by_group)
        assert (m.B.value <= 1.3 * m0.B.value + 0.1 * m0.n_of("orientation")
                and m.K.value <= 1.5 * m0.K.value + 1e-9)
    res = closed_loop(st, truth=truth)
    assert set(res.effect_names) >= {"lever_arm", "accel_time_drift"}, res.effect_names
    assert any(n in res.effect_names for n in ("gyro_warmup_temperature", "gyro_time_drift")), res.effect_names
    assert all(e["p_adj"] < 0.01 for e in res.effects)
    assert _band(res.final), res.final.chi2_per_dof
    lever = {p["name"]: p for e in res.effects for p in e["parameters"] if e["name"] == "lever_arm"}
    for i, a in enumerate("xyz"):
        lo, hi = lever[f"lever_arm_{a}_m"]["ci95"]
        assert lo <= EFFECTS["lever_arm"][i] <= hi


def test_within_window_contrasts_are_immune_to_rotation_synchronous_signals():
    """On a window of R whole revolutions any function of the attitude has period T/R: its batch
    means hold only batch frequencies that are multiples of R, and the contrasts ignore them."""
    rng = np.random.default_rng(5)
    t = np.arange(1800) / 100.0  # 18 s, 2 revolutions at 40 deg/s
    phase = 2 * np.pi * t / 9.0
    sig = sum(rng.normal() * np.cos(k * phase) + rng.normal() * np.sin(k * phase) for k in range(1, 7))
    N = sn.within_basis(8, 2.0)
    assert N.shape == (8, 4)
    assert np.max(np.abs(N.T @ batch_means(sig)[:, 0])) < 1e-12 * np.max(np.abs(sig))
    assert np.allclose(N.T @ N, np.eye(4))
    assert sn.within_basis(8, 0.0).shape == (8, 7) and sn.within_basis(8, None).shape == (8, 0)
    assert sn.window_revolutions("rate", [0.0, 0.0, np.radians(40.0)], 18.0) == 2.0
    assert sn.window_revolutions("rate", [0.0, 0.0, np.radians(40.0)], 10.0) is None
    assert sn.window_revolutions("orientation", [0.0, 0.0, 0.0], 30.0) == 0.0


def test_fewer_segments_than_protected_columns():
    """A session with fewer segments than the protected design has columns -- a wired 24-position
    run at load 10 whose two windows came out empty gave 22 segments for 23 columns -- made
    _full_rank index its pivots with R's min(rows, columns) diagonal (IndexError in `rigctl
    calibrate`). The columns kept span X (rank from numpy), and the session's noise is estimated
    from the windows (no residual dof between them): N within 0.7-1.4 of the truth (20 windows x
    7 contrasts: 6 % sd)."""
    rng = np.random.default_rng(5)
    X = rng.standard_normal((22, 23))
    X[:, 7] = X[:, 2] - 2 * X[:, 9]
    Xr = sn._full_rank(X)
    assert Xr.shape == (22, np.linalg.matrix_rank(X)) == (22, 22)
    assert np.linalg.matrix_rank(np.hstack([Xr, X])) == 22
    st, _ = correlated_session(21)
    keep = np.flatnonzero(st.kind == "orientation")[:20]
    sub = st.subset(np.isin(np.arange(len(st)), keep))
    assert max(sn.protected_design(sub, c).shape[1] for c in range(6)) > len(sub) == 20
    models = sn.apply_session_noise(sub)
    assert len(models) == 6 and sub.cov.shape == (6, 20, 20)
    for m, truth in zip(models, [ACC] * 3 + [GYR] * 3):
        assert 0.7 < m.N.value / truth["N"] < 1.4, (m.N.value, truth["N"])


def test_a_random_walk_at_its_boundary_carries_its_bound_to_the_biases():
    """A K the data only bound (estimate 0, one-sided 95 % bound Kb) must still reach the bias's
    variance through the random walk's extrapolation to power-on, and only the bias's.

    Written out here: K^2 ~ N(0, s^2) truncated at 0 with s = Kb^2 / z_0.95 (what the bound
    says), mean E = scipy's truncnorm mean; the bias estimator's row a of V X^T Sigma^-1 (GLS on
    accel x alone: no declared parameter is shared between channels) with Sigma from the white
    and flicker terms only; the random walk's covariance of non-overlapping window means from
    t0 = 0 by hand (E[mean_i W mean_j W] = min(s, t) averaged: a_i + T_i/3 on the diagonal, the
    earlier window's mid time off it). Expected bias variance V_bb + E a C_rw a^T."""
    from dataclasses import replace
    from rigctl.solvers.noise_coefficients import Coefficient

    st, truth = correlated_session(25)
    kb = 3.0e-5  # 10 x the profile's K
    acc = triad("accel", "given", N=ACC["N"], B=ACC["B"], K=0.0)
    bounded = tuple(replace(m, K=Coefficient(0.0, upper95=kb, bound_from="fit")) for m in acc)
    gyr = triad("gyro", "given", **GYR)
    sn.apply_session_noise(st, acc, gyr)
    plain = closed_loop(st, truth=truth).final
    sn.apply_session_noise(st, bounded, gyr)
    res = closed_loop(st, truth=truth)
    fin = res.final
    assert res.effects == [] and fin.names == plain.names
    np.testing.assert_array_equal(fin.values, plain.values)  # the estimate is not touched

    a, b = np.asarray(st.t_start), np.asarray(st.t_end)
    assert np.all(a[1:] >= b[:-1])  # non-overlapping, in time order
    m, T = (a + b) / 2, b - a
    C_rw = np.minimum.outer(m, m)
    np.fill_diagonal(C_rw, a + T / 3)
    X3, names = declared_design(st)
    cols = [j for j in range(len(names)) if np.any(X3[:, 0, j])]
    X = X3[:, 0, cols]
    Si = np.linalg.inv(_window_cov(a, b, ACC["N"], ACC["B"], 0.0))
    V = np.linalg.inv(X.T @ Si @ X)
    jb = [names[j] for j in cols].index(next(n for n in names if n.startswith("accel_bias_x")))
    row = (V @ X.T @ Si)[jb]
    s = kb**2 / scipy.stats.norm.ppf(0.95)
    e_k2 = scipy.stats.truncnorm.mean(0.0, np.inf, loc=0.0, scale=s)
    i = fin.names.index(names[cols[jb]])
    np.testing.assert_allclose(plain.sigma[i] ** 2, V[jb, jb], rtol=1e-6)
    expected = V[jb, jb] + e_k2 * row @ C_rw @ row
    assert expected > 1.5 * V[jb, jb]  # the term matters here
    np.testing.assert_allclose(fin.sigma[i] ** 2, expected, rtol=1e-6)
    # every other parameter's uncertainty as before; the accel biases alone widen
    acc_bias = [k for k, n in enumerate(fin.names) if n.startswith("accel_bias_")]
    others = [k for k in range(len(fin.names)) if k not in acc_bias]
    np.testing.assert_array_equal(fin.sigma[others], plain.sigma[others])
    assert np.all(fin.sigma[acc_bias] > plain.sigma[acc_bias])
