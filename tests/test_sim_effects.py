"""Physical effects, front end and error model of the emulated IMU: each effect's signature is
recovered from the emulator's output at the truth's magnitude (rigctl.sim.effects / frontend /
error_model / profiles). Tolerances come from the noise: 5 x the theoretical Allan deviation at
the averaging time used, unless stated."""
from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.optimize import curve_fit
from scipy.stats import chi2

from rigctl.sim import effects as fx
from rigctl.sim import noise as nz
from rigctl.sim.error_model import ImuErrorModel
from rigctl.sim.frontend import FrontEnd
from rigctl.sim.profiles import AccelProfile, GyroProfile, ImuProfile, get_profile, given, random_truth
from rigctl.solvers.noise_coefficients import terms_of

G = 9.80665
DEG = math.pi / 180


def quiet_profile(rate_hz: float = 100.0, **effects: dict) -> ImuProfile:
    """declared_only with declared errors zeroed, tactical-grade noise, the given effects on
    (each a mapping of its keys) and no other."""
    tac = get_profile("tactical")
    p = replace(get_profile("declared_only"), gyro=GyroProfile(noise=tac.gyro.noise),
                accel=AccelProfile(noise=tac.accel.noise))
    return p.with_overrides({"rate_hz": rate_hz, "effects": None}).with_overrides(
        {"effects": {k: dict(v, enabled=True) for k, v in effects.items()}})


def run(model: ImuErrorModel, n_out: int, kin, chunk: int = 20_000):
    """Drive the model: kin(t_eval) -> (f (n,3), w (n,3)). Returns t_out, F, W, T, keep."""
    out = []
    for a in range(0, n_out, chunk):
        g = model.sample_grid(min(chunk, n_out - a))
        f, w = kin(g.t_eval)
        out.append((g.t_out, *model.apply(g.t_internal, f, w), g.keep))
    return [np.concatenate([o[i] for o in out]) for i in range(5)]


def const(f, w):
    return lambda t: (np.tile(np.asarray(f, float), (len(t), 1)), np.tile(np.asarray(w, float), (len(t), 1)))


def tol(model: ImuErrorModel, sensor: str, window_s: float) -> np.ndarray:
    """5 x Allan deviation at the averaging window: bound on the error of a window-mean difference."""
    params = model.gyro_coefficients if sensor == "gyro" else model.accel_coefficients
    return 5 * np.sqrt(nz.theoretical_avar(params, window_s, model.output_rate_hz))[0]


def tol_level(model: ImuErrorModel, sensor: str, window_s: float, elapsed_s: float) -> np.ndarray:
    """5 x the standard deviation of a window mean's absolute noise level (not a difference):
    Allan variance at the window + the flicker's stationary variance + the rate random walk's
    K^2 t after ``elapsed_s`` from power-on."""
    params = model.gyro_coefficients if sensor == "gyro" else model.accel_coefficients
    fs = model.output_rate_hz
    k = terms_of(params, "K")
    var = (nz.theoretical_avar(params, window_s, fs)[0] + nz.flicker_variance(params, fs)
           + k**2 * elapsed_s)
    return 5 * np.sqrt(var)


# ---------------------------------------------------------------------------- lever arm
def test_lever_arm_centripetal_3p1_mg_at_100_dps_within_2_percent() -> None:
    r = [0.01, 0.0, 0.0]
    model = ImuErrorModel.from_profile(quiet_profile(lever_arm={"r_m": r}), seed=1)
    w = 100 * DEG
    _, F0, *_ = run(model, 6000, const([0, 0, G], [0, 0, 0]))
    _, Fp, *_ = run(model, 6000, const([0, 0, G], [0, 0, w]))
    _, Fm, *_ = run(model, 6000, const([0, 0, G], [0, 0, -w]))
    truth = -(w**2) * r[0]
    assert abs(truth) / G * 1e3 == pytest.approx(3.1, abs=0.01)  # mg
    fwd_rev = 0.5 * (Fp[:, 0].mean() + Fm[:, 0].mean()) - F0[:, 0].mean()  # does not cancel
    assert fwd_rev == pytest.approx(truth, rel=0.02)


def test_lever_arm_formula_matches_cross_products() -> None:
    rng = np.random.default_rng(0)
    w, dw, r = rng.standard_normal((50, 3)), rng.standard_normal((50, 3)), rng.standard_normal(3)
    rr = np.broadcast_to(r, w.shape)
    assert np.allclose(fx.lever_arm_specific_force(w, dw, r), np.cross(w, np.cross(w, rr)) + np.cross(dw, rr), atol=1e-13)


def test_lever_arm_tangential_term_during_rate_step() -> None:
    r, alpha = [0.02, 0.0, 0.0], 5.0  # m, rad/s^2
    model = ImuErrorModel.from_profile(quiet_profile(lever_arm={"r_m": r}), seed=2)

    def kin(t):
        w = np.zeros((len(t), 3))
        w[:, 2] = alpha * np.clip(t - 1.0, 0.0, 0.4)
        return np.tile([0, 0, G], (len(t), 1)), w

    t, F, *_ = run(model, 200, kin)
    acc = (t > 1.05) & (t < 1.35)
    still = t < 0.95
    measured = F[acc, 1].mean() - F[still, 1].mean()
    centripetal_y = 0.0  # w x (w x r) lies along -x
    assert measured - centripetal_y == pytest.approx(alpha * r[0], rel=0.02)


# ---------------------------------------------------------------------------- thermal
def test_warmup_time_constant_recovered_from_gyro_and_temperature() -> None:
    wu = given(get_profile("consumer_mems").effects.warmup)
    model = ImuErrorModel.from_profile(quiet_profile(warmup=wu), seed=3)
    t, _, W, T, _ = run(model, 180_000, const([0, 0, G], [0, 0, 0]))
    blocks = W[:, 0].reshape(-1, 1000).mean(axis=1)
    tb = t.reshape(-1, 1000).mean(axis=1)

    def expo(x, a, c, tau):
        return a + c * np.exp(-x / tau)

    p, _ = curve_fit(expo, tb, blocks, p0=[0.0, -1e-3, 200.0])
    assert p[2] == pytest.approx(wu["tau_s"], rel=0.05)
    assert p[1] == pytest.approx(-wu["gyro_bias_tc_rad_per_s_per_K"][0] * wu["dT_degC"], rel=0.05)
    pT, _ = curve_fit(expo, t, T, p0=[30.0, -5.0, 200.0])
    assert pT[2] == pytest.approx(wu["tau_s"], rel=0.01)
    assert pT[0] == pytest.approx(wu["T0_degC"] + wu["dT_degC"], abs=0.05)
    settled = np.exp(-900.0 / wu["tau_s"])
    assert settled < 0.05  # settles within the 15-minute warm-up


def test_scale_temperature_coefficient_during_warmup() -> None:
    """At a constant rate the warm-up transient's amplitude grows by s_tc * dT * w (scale tempco)."""
    wu = given(get_profile("consumer_mems").effects.warmup)
    w = 100 * DEG

    def amplitude(rate: float, seed: int) -> float:
        model = ImuErrorModel.from_profile(quiet_profile(warmup=wu), seed=seed)
        t, _, W, _, _ = run(model, 120_000, const([0, 0, G], [rate, 0, 0]))
        tb, yb = t.reshape(-1, 1000).mean(axis=1), W[:, 0].reshape(-1, 1000).mean(axis=1)
        X = np.column_stack([np.ones_like(tb), np.exp(-tb / wu["tau_s"])])
        return float(np.linalg.lstsq(X, yb, rcond=None)[0][1])

    c0, c1 = amplitude(0.0, 21), amplitude(w, 22)
    s_tc = (c1 - c0) / (-wu["dT_degC"] * w)
    assert c0 == pytest.approx(-wu["gyro_bias_tc_rad_per_s_per_K"][0] * wu["dT_degC"], rel=0.05)
    assert s_tc == pytest.approx(wu["gyro_scale_tc_per_K"][0], rel=0.05)


# ---------------------------------------------------------------------------- clock
def test_clock_ppm_recovered_from_sample_count() -> None:
    fs, ppm, T_end = 100.0, 85.0, 12 * 3600.0
    clk = fx.ClockModel(fs, drift_ppm=ppm, wander_ppm=1.0, wander_tau_s=1800.0, seed=4)
    ts, es = [], []
    while not ts or ts[-1][-1] < T_end:
        t, _, e = clk.next(500_000)
        ts.append(t)
        es.append(e)
    t, e = np.concatenate(ts), np.concatenate(es)
    count = int(np.sum(t < T_end))
    est = (T_end * fs / count - 1) * 1e6  # slow clock (positive drift): fewer samples
    truth_mean = e[: count].mean()
    assert est == pytest.approx(truth_mean, abs=1e6 / (T_end * fs) + 0.05)
    assert est == pytest.approx(ppm, abs=3.0)


def test_dropped_samples_rate_and_chunk_invariance() -> None:
    kw = dict(rate_hz=100.0, drop_probability=1e-4, drop_max_burst=32, seed=9)
    one = fx.ClockModel(**kw).next(1_000_000)[1]
    c = fx.ClockModel(**kw)
    parts = np.concatenate([c.next(k)[1] for k in (333_333, 333_333, 333_334)])
    assert np.array_equal(one, parts)
    lost = np.sum(~one)
    expected = 1e6 * 1e-4 * 16.5
    assert abs(lost - expected) < 5 * math.sqrt(100) * 19


# ---------------------------------------------------------------------------- sensor effects
def test_g_sensitivity_and_anisoelastic_from_plus_minus_g() -> None:
    gs = given(get_profile("consumer_mems").effects.g_sensitivity)
    model = ImuErrorModel.from_profile(quiet_profile(g_sensitivity=gs), seed=5)
    Gm = np.array(gs["G_rad_per_s_per_m_per_s2"])
    A = np.array(gs["anisoelastic_rad_per_s_per_m2_per_s4"])
    e = tol(model, "gyro", 60.0)
    for j in range(3):
        f = np.zeros(3)
        f[j] = G
        Wp = run(model, 6000, const(f, [0, 0, 0]))[2].mean(axis=0)
        Wm = run(model, 6000, const(-f, [0, 0, 0]))[2].mean(axis=0)
        W0 = run(model, 6000, const([0, 0, 0], [0, 0, 0]))[2].mean(axis=0)
        assert np.all(np.abs((Wp - Wm) / 2 - Gm[:, j] * G) < e)
        assert np.all(np.abs((Wp + Wm) / 2 - W0 - A[:, j] * G**2) < e)


def test_accel_scale_asymmetry() -> None:
    u = get_profile("consumer_mems").effects.accel_scale_asymmetry.asymmetry
    model = ImuErrorModel.from_profile(quiet_profile(accel_scale_asymmetry={"asymmetry": u}), seed=6)
    e = tol(model, "accel", 60.0)
    for j in range(3):
        f = np.zeros(3)
        f[j] = G
        Fp = run(model, 6000, const(f, [0, 0, 0]))[1].mean(axis=0)
        Fm = run(model, 6000, const(-f, [0, 0, 0]))[1].mean(axis=0)
        assert abs((Fp[j] + Fm[j]) - u[j] * G) < 2 * e[j]
        assert abs((Fp[j] - Fm[j]) / (2 * G) - 1.0) < e[j] / G


def test_gyro_scale_nonlinearity_fit_recovers_k2_k3() -> None:
    nl = given(get_profile("consumer_mems").effects.gyro_nonlinearity)
    model = ImuErrorModel.from_profile(quiet_profile(gyro_nonlinearity=nl), seed=7)
    rates = np.array([-100, -63, -40, 0, 40, 63, 100]) * DEG
    means = np.array([run(model, 3000, const([0, 0, G], [w, 0, 0]))[2][:, 0].mean() for w in rates])
    X = np.column_stack([np.ones_like(rates), rates, rates**2, rates**3])
    coef = np.linalg.lstsq(X, means, rcond=None)[0]
    e = tol(model, "gyro", 30.0)[0]
    assert coef[2] == pytest.approx(nl["k2_per_rad_per_s"][0], abs=e / rates.max() ** 2)
    assert coef[3] == pytest.approx(nl["k3_per_rad2_per_s2"][0], abs=e / rates.max() ** 3)
    assert abs(coef[2]) > 3 * e / rates.max() ** 2  # the signature is well above the noise bound


def test_time_delay_seen_as_offset_of_a_rate_ramp() -> None:
    d = 2.0e-3
    model = ImuErrorModel.from_profile(quiet_profile(time_delay={"delay_s": d}), seed=8)
    alpha = 1.0
    t, _, W, *_ = run(model, 1000, lambda te: (np.tile([0, 0, G], (len(te), 1)),
                                               np.column_stack([np.zeros(len(te)), np.zeros(len(te)), alpha * te])))
    est = np.mean(alpha * t - W[:, 2]) / alpha
    assert est == pytest.approx(d, rel=0.02)


def test_vibration_amplitude_from_sine_fit() -> None:
    vib = {"freqs_hz": [47.3], "accel_amp_m_per_s2": [[0.02, 0.015, 0.03]], "gyro_amp_rad_per_s": [[1e-4, 1.5e-4, 1e-4]]}
    p = quiet_profile(rate_hz=1000.0, vibration=vib).with_overrides(
        {"accel": {"noise": None}, "gyro": {"noise": None}}).with_overrides(  # low noise: the test is about the sines
        {"accel": {"noise": {"N_m_per_s2_per_sqrt_hz": 2e-4}}, "gyro": {"noise": {"N_rad_per_s_per_sqrt_hz": 1e-6}}})
    model = ImuErrorModel.from_profile(p, seed=9)
    t, F, W, *_ = run(model, 20_000, const([0, 0, G], [0, 0, 0]))
    X = np.column_stack([np.sin(2 * np.pi * 47.3 * t), np.cos(2 * np.pi * 47.3 * t), np.ones_like(t)])
    for data, amp in ((F, vib["accel_amp_m_per_s2"][0]), (W, vib["gyro_amp_rad_per_s"][0])):
        c = np.linalg.lstsq(X, data, rcond=None)[0]
        white = np.std(data - X @ c, axis=0)  # residual noise per sample
        bound = 5 * white * math.sqrt(2 / len(t))  # 5 sigma of a fitted amplitude
        assert np.all(np.abs(np.hypot(c[0], c[1]) - amp) < bound)
        assert np.all(bound < 0.05 * np.asarray(amp))
    assert np.allclose(model.truth()["effects"]["vibration"]["phase_rad"], model.vib_phase)


def test_turn_on_bias_drawn_per_power_on_with_configured_sigma() -> None:
    sig = 5e-3
    prof = quiet_profile(turn_on_bias={"gyro_sigma_rad_per_s": sig, "accel_sigma_m_per_s2": 0.02})
    draws = np.array([ImuErrorModel.from_profile(prof, seed=s).turn_on_gyro for s in range(150)]).ravel()
    n = draws.size
    assert sig**2 * chi2.ppf(0.0005, n) / n < np.mean(draws**2) < sig**2 * chi2.ppf(0.9995, n) / n
    model = ImuErrorModel.from_profile(prof, seed=3)
    W = run(model, 6000, const([0, 0, G], [0, 0, 0]))[2].mean(axis=0)
    assert np.all(np.abs(W - model.turn_on_gyro) < tol_level(model, "gyro", 60.0, 120.0))
    assert model.truth()["gyro_turn_on_bias_rad_per_s"] == model.turn_on_gyro.tolist()


def test_declared_errors_from_six_positions() -> None:
    model = ImuErrorModel.from_profile(get_profile("declared_only"), seed=10)
    e = tol(model, "accel", 60.0)  # differences of window means
    e_level = tol_level(model, "accel", 60.0, 6 * 60.0)  # absolute level of a window mean
    k2 = model.accel_k2
    for j in range(3):
        f = np.zeros(3)
        f[j] = G
        Fp = run(model, 6000, const(f, [0, 0, 0]))[1].mean(axis=0)
        Fm = run(model, 6000, const(-f, [0, 0, 0]))[1].mean(axis=0)
        assert np.all(np.abs((Fp - Fm) / (2 * G) - model.accel_M[:, j]) < e / G)
        quad = np.where(np.arange(3) == j, k2 * G**2, 0.0)
        assert np.all(np.abs((Fp + Fm) / 2 - model.accel_bias - quad) < e_level)


def test_declared_gyro_scale_and_misalignment_from_forward_reverse_rates() -> None:
    model = ImuErrorModel.from_profile(get_profile("declared_only"), seed=11)
    w = 100 * DEG
    e = tol(model, "gyro", 30.0)
    for j in range(3):
        rate = np.zeros(3)
        rate[j] = w
        Wp = run(model, 3000, const([0, 0, G], rate))[2].mean(axis=0)
        Wm = run(model, 3000, const([0, 0, G], -rate))[2].mean(axis=0)
        assert np.all(np.abs((Wp - Wm) / (2 * w) - model.gyro_M[:, j]) < e / w)
        assert np.all(np.abs((Wp + Wm) / 2 - model.gyro_bias) < tol_level(model, "gyro", 30.0, 6 * 30.0))


# ---------------------------------------------------------------------------- table geometry
def test_table_levelling_north_and_nonorthogonality_signatures() -> None:
    lx, north = 5e-5, 2e-4
    C, _ = fx.table_attitude_and_rate(np.zeros((1, 3)), np.zeros((1, 3)), level_x_rad=lx, north_rad=north)
    f_body = C[0].T @ np.array([0, 0, G])
    assert abs(f_body[1]) == pytest.approx(G * math.sin(lx), rel=1e-9)
    lat, omega = math.radians(40.0), 7.292115e-5
    w_body = fx.table_attitude_and_rate(np.zeros((1, 3)), np.zeros((1, 3)), north_rad=north)[0][0].T @ np.array(
        [0, omega * math.cos(lat), omega * math.sin(lat)])
    assert abs(w_body[0]) == pytest.approx(omega * math.cos(lat) * math.sin(north), rel=1e-9)
    d = 1e-4  # inner axis tilted towards z: x accelerometer sees g sin(2d) at inner = 180 deg
    C, _ = fx.table_attitude_and_rate(np.array([[0, 0, math.pi]]), np.zeros((1, 3)), nonorth_rad=(0, 0, d))
    assert (C[0].T @ np.array([0, 0, G]))[0] == pytest.approx(G * math.sin(2 * d), rel=1e-6)
    C0, _ = fx.table_attitude_and_rate(np.array([[0, 0, math.pi]]), np.zeros((1, 3)))
    assert abs((C0[0].T @ np.array([0, 0, G]))[0]) < 1e-12


def test_table_body_rate_from_gimbal_rates() -> None:
    ang = np.array([[0.3, -0.2, 1.1]])
    rates = np.array([[0.1, 0.2, 0.3]])
    C, w = fx.table_attitude_and_rate(ang, rates)
    h = 1e-6
    C2, _ = fx.table_attitude_and_rate(ang + h * rates, rates)
    Om = C[0].T @ (C2[0] - C[0]) / h  # skew(w_body)
    assert np.allclose([Om[2, 1], Om[0, 2], Om[1, 0]], w[0], atol=1e-5)


# ---------------------------------------------------------------------------- front end
def test_frontend_minus_3db_at_bandwidth_and_chunk_invariance() -> None:
    fe = FrontEnd(100.0, 1000.0, bandwidth_hz=20.0, order=2)
    t = np.arange(200_000) / 1000.0
    x = np.column_stack([np.sin(2 * np.pi * 20.0 * t)] * 3)
    y = fe.filter_decimate(x)
    amp = np.sqrt(2) * y[5000:, 0].std()
    assert amp == pytest.approx(1 / math.sqrt(2), rel=0.01)
    fe2 = FrontEnd(100.0, 1000.0, bandwidth_hz=20.0, order=2)
    parts = np.concatenate([fe2.filter_decimate(x[a:a + 30_000]) for a in range(0, len(x), 30_000)])
    assert np.array_equal(parts, y)


def test_frontend_lsb_and_saturation() -> None:
    lsb, fs = 1 / 131 * DEG, 250 * DEG
    fe = FrontEnd(100.0, lsb=lsb, full_scale=fs)
    y = fe.digitize(np.array([[0.1234, 300 * DEG, -400 * DEG]] * 4))
    assert np.allclose(y[:, 0] / lsb, np.round(y[:, 0] / lsb), atol=1e-9)
    assert np.all(y[:, 1] == fs) and np.all(y[:, 2] == -fs)
    assert fe.saturated_count.tolist() == [0, 4, 4]


# ---------------------------------------------------------------------------- whole model
def _spin(t):
    w = np.zeros((len(t), 3))
    w[:, 2] = 1.0 * np.sin(0.5 * t)
    return np.tile([0, 0, G], (len(t), 1)), w


def test_error_model_chunked_equals_one_piece_and_same_seed_same_data() -> None:
    prof = get_profile("consumer_mems")
    a = run(ImuErrorModel.from_profile(prof, seed=12), 3000, _spin, chunk=3000)
    b = run(ImuErrorModel.from_profile(prof, seed=12), 3000, _spin, chunk=701)
    c = run(ImuErrorModel.from_profile(prof, seed=13), 3000, _spin, chunk=3000)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)
    assert not np.allclose(a[2], c[2])


def test_truth_is_json_with_units_and_profiles_load() -> None:
    for name in ("consumer_mems", "mti_class", "tactical", "declared_only", "random"):
        model = ImuErrorModel.from_profile(get_profile(name, seed=1), seed=1)
        truth = json.loads(json.dumps(model.truth()))
        assert truth["output_rate_hz"] == model.output_rate_hz
        assert "gyro_bias_rad_per_s" in truth and "accel_lsb_m_per_s2" in truth
    off = ImuErrorModel.from_profile(get_profile("declared_only"), seed=1).truth()["effects"]
    assert not any(v["enabled"] for v in off.values())


def test_random_truth_is_seeded_and_within_spread() -> None:
    base = get_profile("mti_class")
    a, b, c = random_truth(base, 1), random_truth(base, 1), random_truth(base, 2)
    assert a == b and a != c
    for s in ("gyro", "accel"):
        for k, v in given(getattr(base, s).noise).items():
            if k[:2] in ("Q_", "N_", "B_", "K_", "R_") and v > 0:
                assert v / 2 <= getattr(getattr(a, s).noise, k) <= 2 * v
    assert np.allclose(np.diag(np.array(a.gyro.misalignment_rad)), 0.0)


def test_table_geometry_matches_rigctl_frames_when_ideal() -> None:
    from rigctl import frames

    rng = np.random.default_rng(0)
    ang, rates = rng.uniform(-3, 3, (50, 3)), rng.uniform(-2, 2, (50, 3))
    f, w = fx.table_body_references(ang, rates, 0.7, 9.8)
    f_ref, w_ref = frames.body_references(ang, rates, 0.7, 0.0, 9.8)
    assert np.allclose(f, f_ref, atol=1e-12) and np.allclose(w, w_ref, atol=1e-15)
    f2, _ = fx.table_body_references(ang, rates, 0.7, 9.8, level_x_rad=1e-4)
    assert 0.5e-4 * 9.8 < np.max(np.abs(f2 - f_ref)) < 1.5e-4 * 9.8
