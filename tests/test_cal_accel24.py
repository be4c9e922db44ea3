"""24-position accelerometer calibration, static gyro biases and the forward/reverse rate test."""
from __future__ import annotations

import json

import numpy as np
import pytest

from rigctl import frames
from rigctl.solvers.accel24 import (accel_axis_names, calibrate_accel, calibrate_accel_axis,
                                    calibrate_gyro_bias_static)
from rigctl.solvers.calibration_result import format_table
from rigctl.solvers.gyro_rate import calibrate_gyro_rate, pair_forward_reverse
from test_cal_synth import UP, Effects, make_session

SEEDS = range(100, 120)  # the same clean sessions as the closed-loop tests (cached)


def _w_table(st):
    ang = np.array([UP[lab.split("_")[1][0]] if k != "orientation" else (0, 0, 0)
                    for lab, k in zip(st.label, st.kind)])
    return frames.gimbal_rate_body(ang, st.table_rate)


@pytest.fixture(scope="module")
def sessions():
    return [make_session(s) for s in SEEDS]


def test_noise_free_recovery_and_per_axis_form():
    st, truth = make_session(1, ramps=False)
    static = st.kind == "orientation"
    b = np.array([truth[f"accel_bias_{a}_m_s2"] for a in "xyz"])
    M = np.array([[truth[f"accel_M_{a}{c}_ratio"] for c in "xyz"] for a in "xyz"])
    q = np.array([truth[f"accel_quad_{a}_s2_per_m"] for a in "xyz"])
    fr = st.f_ref[static]
    f = b + fr @ M.T + q * fr**2
    res = calibrate_accel(f, np.full_like(f, 1e-4), fr)
    np.testing.assert_allclose(res.extra["M"], M, atol=1e-10)
    np.testing.assert_allclose(res.extra["bias_m_s2"], b, atol=1e-10)
    np.testing.assert_allclose(res.extra["quad_s2_per_m"], q, atol=1e-12)
    assert res.dof == 3 * 24 - 15 and res.chi2 < 1e-12
    # the paper's per-axis five terms are the same numbers: X = [S_y, K_xy, K_zy, a_y0, K_yy]
    ry = calibrate_accel_axis(1, f[:, 1], np.full(24, 1e-4), fr)
    assert ry.names == accel_axis_names(1) == ["accel_y_S_ratio", "accel_y_K_xy_ratio",
                                               "accel_y_K_zy_ratio", "accel_y_a0_m_s2",
                                               "accel_y_K_yy_s2_per_m"]
    np.testing.assert_allclose(ry.values, [M[1, 1], M[1, 0], M[1, 2], b[1], q[1]], atol=1e-10)
    json.dumps(res.to_dict(), allow_nan=False)
    assert "accel_M_zz_ratio" in format_table(res)


def test_accel24_gyro_bias_and_rate_coverage(sessions):
    """Each solver alone has few dof (accel 57, rate 24, bias 69), so chi2/dof of one seed scatters
    by sqrt(2/dof) ~ 0.2-0.3: checked pooled over the 20 seeds (and no seed improbable).
    Coverage: pooled >= 90 %, each parameter >= 15/20 (see test_cal_closed_loop's docstring)."""
    cover: dict[str, list[bool]] = {}
    chi2: dict[str, list[tuple[float, int]]] = {}
    for st, truth in sessions:
        static, rate = st.kind == "orientation", st.kind == "rate"
        acc = calibrate_accel(st.f[static], st.f_sigma[static], st.f_ref[static],
                              st.f_ref_outer[static])
        gb = calibrate_gyro_bias_static(st.w[static], st.w_sigma[static], st.w_ref[static])
        gr = calibrate_gyro_rate(st.w[rate], st.w_sigma[rate], st.w_ref[rate], _w_table(st)[rate])
        for res in (acc, gb, gr):
            assert res.status == "ok", res.warnings
            assert 1e-3 < res.chi2_p_value < 1 - 1e-3, (res.method, res.chi2_per_dof)
            chi2.setdefault(res.method, []).append((res.chi2, res.dof))
            for name, (lo, hi) in zip(res.names, res.ci95):
                cover.setdefault(f"{res.method}:{name}", []).append(bool(lo <= truth[name] <= hi))
    for method, v in chi2.items():
        a = np.array(v)
        assert 0.85 <= a[:, 0].sum() / a[:, 1].sum() <= 1.15, (method, a[:, 0].sum() / a[:, 1].sum())
    c = np.array(list(cover.values()), dtype=float)
    assert len(cover) == 15 + 3 + 12
    assert c.mean() >= 0.90, c.mean()
    assert min(c.mean(axis=1)) >= 0.75, {k: np.mean(v) for k, v in cover.items() if np.mean(v) < 0.75}


def test_rate_test_half_sum_keeps_rate_dependent_residuals():
    """Scale asymmetry is even in the rate: it leaves the half-difference alone and shows in the
    half-sum residuals, growing with |rate|."""
    st, truth = make_session(3, Effects(gyro_asym=np.array([0.0, 0.0, 5e-4])), ramps=False)
    rate = st.kind == "rate"
    gr = calibrate_gyro_rate(st.w[rate], st.w_sigma[rate], st.w_ref[rate], _w_table(st)[rate])
    assert gr.status == "poor_fit"
    z = [(abs(r["rate_rad_s"]), r["half_sum_residual_rad_s"][2]) for r in gr.extra["rate_residuals"]
         if r["axis"] == "z"]
    mags, res = np.array(z).T
    assert len(mags) == 3 and np.corrcoef(mags, res)[0, 1] > 0.95
    # the scale itself stays unbiased (half-difference): within its interval
    i = gr.names.index("gyro_M_zz_ratio")
    assert gr.ci95[i, 0] <= truth["gyro_M_zz_ratio"] <= gr.ci95[i, 1]


def test_pairing_and_unpaired_warning():
    wt = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 2.0, 0], [0, -2.0, 0], [0, 0, 0.5]])
    assert pair_forward_reverse(wt) == [(0, 1), (2, 3)]
    st, _ = make_session(4, ramps=False)
    rate = np.flatnonzero(st.kind == "rate")[:-1]  # drop one reverse segment
    gr = calibrate_gyro_rate(st.w[rate], st.w_sigma[rate], st.w_ref[rate], _w_table(st)[rate])
    assert any("without an opposite partner" in w for w in gr.warnings)
    assert len(gr.extra["pairs"]) == 8


def test_gyro_bias_static_sees_g_sensitivity():
    """Constant bias over positions is a testable assumption: g-sensitivity breaks it."""
    g = np.zeros((3, 3))
    g[0, 1] = 3e-5
    st, _ = make_session(5, Effects(g_sens=g), ramps=False)
    s = st.kind == "orientation"
    gb = calibrate_gyro_bias_static(st.w[s], st.w_sigma[s], st.w_ref[s])
    assert gb.status == "poor_fit" and gb.chi2_p_value < 1e-6
