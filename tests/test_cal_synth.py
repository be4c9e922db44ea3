"""Tiny local generator of turntable calibration data (A2 models, known truth), and its checks.

Other tests/test_cal_*.py import :func:`make_session` from here. Samples are generated at
100 Hz per segment with white noise plus first-order Gauss-Markov (coloured) noise, passed
through the A2 sensor models plus any undeclared effect, then reduced to a SegmentTable with
rigctl.solvers.segment_stats (noise model: the generator's analytic Allan curve).

Design (the lead's convention: body = ENU at table zero, C_b^n = Rz(outer) Ry(middle) Rx(inner)):
24 static positions (X, Y, Z north, phi = 0..315 deg in 45 deg steps, 20 s each), rate tests
+-40, +-63, +-100 deg/s about body x, y, z with that axis up (outer axis spins, 10 s each), and
optionally 12 ramp windows (+-30 deg/s^2 for 4 s about each axis, for the time delay).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from rigctl import frames
from rigctl.solvers.segment_stats import AllanCurve, gauss_markov_avar, segment_mean
from rigctl.solvers.segments import SegmentTable

FS = 100.0
LAT = np.radians(48.15)
HEIGHT = 520.0
G = frames.normal_gravity(LAT, HEIGHT)
D2R = np.pi / 180.0

# noise (per axis): white density N (unit*sqrt(s)), Gauss-Markov sigma and time constant
ACC_N, GYR_N = 5.9e-4, 5.8e-5
TC = 0.5
ACC_GM, GYR_GM = np.sqrt(5.0) * ACC_N, np.sqrt(5.0) * GYR_N

# axis-up attitudes for the rate tests: [outer, middle, inner]
UP = {"x": (0.0, -np.pi / 2, 0.0), "y": (0.0, 0.0, np.pi / 2), "z": (0.0, 0.0, 0.0)}


def noise_curve(n_white: float, gm: float) -> AllanCurve:
    tau = np.logspace(-2.5, 4, 80)
    av = n_white**2 / tau + gauss_markov_avar(tau, gm, TC)
    return AllanCurve(tau=tau, adev=np.repeat(np.sqrt(av)[:, None], 3, axis=1))


ACC_CURVE, GYR_CURVE = noise_curve(ACC_N, ACC_GM), noise_curve(GYR_N, GYR_GM)


def random_truth(rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "b_a": rng.normal(0, 0.02, 3), "M_a": np.eye(3) + rng.normal(0, 1e-3, (3, 3)),
        "q_a": rng.normal(0, 1e-4, 3), "b_g": rng.normal(0, 5e-4, 3),
        "M_g": np.eye(3) + rng.normal(0, 1e-3, (3, 3)),
    }


def truth_names(t: dict[str, np.ndarray]) -> dict[str, float]:
    """The truth under the solvers' parameter names."""
    ax = "xyz"
    out = {}
    for i in range(3):
        out[f"accel_bias_{ax[i]}_m_s2"] = t["b_a"][i]
        out[f"accel_quad_{ax[i]}_s2_per_m"] = t["q_a"][i]
        out[f"gyro_bias_{ax[i]}_rad_s"] = t["b_g"][i]
        for j in range(3):
            out[f"accel_M_{ax[i]}{ax[j]}_ratio"] = t["M_a"][i, j]
            out[f"gyro_M_{ax[i]}{ax[j]}_ratio"] = t["M_g"][i, j]
    return out


@dataclass
class Effects:
    """Undeclared effects (all zero by default)."""

    g_sens: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))  # rad/s per m/s^2
    accel_asym: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_asym: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_n3: np.ndarray = field(default_factory=lambda: np.zeros(3))  # s^2/rad^2
    lever: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m
    delay_s: float = 0.0
    acc_tc: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m/s^2/K
    gyr_tc: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad/s/K
    tilt: np.ndarray = field(default_factory=lambda: np.zeros(2))  # rad (east, north)
    nonorth: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad, gimbal axes (see _chain)
    gyr_scale_tc: np.ndarray = field(default_factory=lambda: np.zeros(3))  # 1/K
    bias_jump: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m/s^2 accel step at t = 400 s (not in the library)
    rate_rectification: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m/s^2 per rad/s of |w| (not in the library)


def segment_plan(ramps: bool) -> list[dict]:
    plan = []
    for axis in "xyz":
        for k in range(8):
            plan.append({"kind": "orientation", "label": f"{axis}N_{45 * k}",
                         "a0": np.array(frames.north_pointing_angles(axis, np.radians(45.0 * k))),
                         "rate0": np.zeros(3), "acc": np.zeros(3), "dur": 20.0})
    for axis in "xyz":
        for r in (40.0, 63.0, 100.0):
            for sgn in (1, -1):
                plan.append({"kind": "rate", "label": f"rate_{axis}{sgn * r:+.0f}", "a0": np.array(UP[axis]),
                             "rate0": np.array([sgn * r * D2R, 0, 0]), "acc": np.zeros(3), "dur": 10.0})
    if ramps:
        for axis in "xyz":
            for r0, a in ((0.0, 30.0), (120.0, -30.0), (0.0, -30.0), (-120.0, 30.0)):
                plan.append({"kind": "ramp", "label": f"ramp_{axis}{a:+.0f}", "a0": np.array(UP[axis]),
                             "rate0": np.array([r0 * D2R, 0, 0]), "acc": np.array([a * D2R, 0, 0]), "dur": 4.0})
    return plan


_CACHE: dict[tuple[int, bool], tuple[SegmentTable, dict[str, float]]] = {}


def make_session(seed: int, eff: Effects | None = None, ramps: bool = True):
    """Returns (SegmentTable with the nominal references, truth dict under solver names).

    Clean sessions (eff None) are cached per process and handed out as copies.
    """
    if eff is None:
        if (seed, ramps) not in _CACHE:
            _CACHE[(seed, ramps)] = _make_session(seed, Effects(), ramps)
        return copy.deepcopy(_CACHE[(seed, ramps)])
    return _make_session(seed, eff, ramps)


def _make_session(seed: int, eff: Effects, ramps: bool):
    rng = np.random.default_rng(seed)
    tr = random_truth(rng)
    plan = segment_plan(ramps)
    om_n = frames.earth_rate_enu(LAT)
    rot_tilt = Rotation.from_rotvec([eff.tilt[0], eff.tilt[1], 0.0]).as_matrix()  # base -> ENU
    cols = {k: [] for k in ("f", "w", "fs", "ws", "fr", "wr", "fo", "wo", "wc", "wa", "fa", "t", "T",
                            "wd", "att", "ang", "tab", "kind", "label")}
    t_now = 60.0
    for seg in plan:
        n = int(seg["dur"] * FS)
        t = np.arange(n) / FS
        ang = seg["a0"] + np.outer(t, seg["rate0"]) + 0.5 * np.outer(t**2, seg["acc"])
        grate = seg["rate0"] + np.outer(t, seg["acc"])
        f_nom, w_nom = frames.body_references(ang, grate, LAT, HEIGHT, G)
        c_bn, w_tab = _chain(ang, grate, eff.nonorth)
        c_nb = np.swapaxes(c_bn, 1, 2)
        wdot = np.gradient(w_tab, 1 / FS, axis=0) if np.any(seg["acc"]) else np.zeros_like(w_tab)
        # truth seen by the sensor: tilted base, lever arm
        f_true = c_nb @ (rot_tilt.T @ np.array([0, 0, G]))
        w_true = c_nb @ (rot_tilt.T @ om_n) + w_tab
        f_true = f_true + np.cross(wdot, eff.lever) + np.cross(w_true, np.cross(w_true, eff.lever))
        temp = 25.0 + 8.0 * (1 - np.exp(-(t_now + t) / 600.0))
        A = tr["b_a"] + f_true @ tr["M_a"].T + tr["q_a"] * f_true**2 + eff.accel_asym * np.abs(f_true)
        A = A + np.outer(temp - 25.0, eff.acc_tc) + np.outer(np.linalg.norm(w_tab, axis=1), eff.rate_rectification)
        A = A + np.outer(t_now + t > 400.0, eff.bias_jump)
        W = tr["b_g"] + w_true @ tr["M_g"].T + f_true @ eff.g_sens.T + eff.gyro_asym * np.abs(w_true)
        W = W + eff.gyro_n3 * w_true**3 - eff.delay_s * wdot + np.outer(temp - 25.0, eff.gyr_tc)
        W = W + (temp - 25.0)[:, None] * eff.gyr_scale_tc * w_true
        A = A + _noise(rng, n, ACC_N, ACC_GM)
        W = W + _noise(rng, n, GYR_N, GYR_GM)
        ma, mw = segment_mean(A, FS, ACC_CURVE), segment_mean(W, FS, GYR_CURVE)
        for key, val in (("f", ma.mean), ("w", mw.mean), ("fs", ma.sigma), ("ws", mw.sigma),
                         ("fr", f_nom.mean(0)), ("wr", w_nom.mean(0)),
                         ("fo", np.einsum("ni,nj->ij", f_nom, f_nom) / n),
                         ("wo", np.einsum("ni,nj->ij", w_nom, w_nom) / n), ("wc", (w_nom**3).mean(0)),
                         ("wa", np.abs(w_nom).mean(0)), ("fa", np.abs(f_nom).mean(0)),
                         ("t", t_now + seg["dur"] / 2), ("T", temp.mean()), ("wd", wdot.mean(0)),
                         ("att", frames.gimbal_dcm(ang).mean(0)), ("ang", ang.mean(0)), ("tab", grate.mean(0)), ("kind", seg["kind"]),
                         ("label", seg["label"])):
            cols[key].append(val)
        t_now += seg["dur"] + 10.0
    st = SegmentTable(kind=np.array(cols["kind"]), label=np.array(cols["label"]),
                      f=np.array(cols["f"]), w=np.array(cols["w"]), f_sigma=np.array(cols["fs"]),
                      w_sigma=np.array(cols["ws"]), f_ref=np.array(cols["fr"]), w_ref=np.array(cols["wr"]),
                      time=np.array(cols["t"]), temperature=np.array(cols["T"]),
                      table_rate=np.array(cols["tab"]), ang_accel=np.array(cols["wd"]),
                      attitude=np.array(cols["att"]), angles=np.array(cols["ang"]),
                      earth_rate_n=om_n, gravity_m_s2=G,
                      f_ref_outer=np.array(cols["fo"]), w_ref_outer=np.array(cols["wo"]),
                      w_ref_cube=np.array(cols["wc"]), w_ref_abs=np.array(cols["wa"]),
                      f_ref_abs=np.array(cols["fa"]), temperature_ref=25.0)
    return st, truth_names(tr)


def _rodrigues(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = angle[:, None, None]
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * (K @ K)


def _chain(ang: np.ndarray, rates: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """C_b^n and table body rate for gimbal axes outer z, middle (0, cos d0, sin d0), inner (1, d1, d2)."""
    axes = [np.array([0.0, 0, 1]), np.array([0.0, np.cos(d[0]), np.sin(d[0])]), np.array([1.0, d[1], d[2]])]
    axes = [a / np.linalg.norm(a) for a in axes]
    Ro, Rm, Ri = (_rodrigues(a, ang[:, j]) for j, a in enumerate(axes))
    RiT, RmT = np.swapaxes(Ri, 1, 2), np.swapaxes(Rm, 1, 2)
    w = (np.einsum("nij,nj->ni", RiT, np.einsum("nij,nj->ni", RmT, rates[:, :1] * axes[0]))
         + np.einsum("nij,nj->ni", RiT, rates[:, 1:2] * axes[1]) + rates[:, 2:3] * axes[2])
    return Ro @ Rm @ Ri, w


def _noise(rng: np.random.Generator, n: int, n_white: float, gm: float) -> np.ndarray:
    white = rng.normal(0, n_white * np.sqrt(FS), (n, 3))
    phi = np.exp(-1 / (FS * TC))
    burn = int(5 * TC * FS)
    e = rng.normal(0, gm * np.sqrt(1 - phi**2), (n + burn, 3))
    x = lfilter([1.0], [1.0, -phi], e, axis=0)[burn:]
    return white + x


# ----------------------------------------------------------------------------- checks
def test_local_gimbal_chain_matches_frames():
    rng = np.random.default_rng(0)
    ang, rates = rng.uniform(-3, 3, (20, 3)), rng.normal(0, 1, (20, 3))
    c, w = _chain(ang, rates, np.zeros(3))
    np.testing.assert_allclose(c, frames.gimbal_dcm(ang), atol=1e-12)
    np.testing.assert_allclose(w, frames.gimbal_rate_body(ang, rates), atol=1e-12)


def test_generator_references_match_a3():
    """Static X-north positions see g (0, sin phi, cos phi) and Earth rate (W cosL, W sinL sin phi, ...)."""
    st, _ = make_session(0, ramps=False)
    W = frames.EARTH_RATE_RAD_S
    for k in range(8):
        phi = np.radians(45.0 * k)
        np.testing.assert_allclose(st.f_ref[k], G * np.array([0, np.sin(phi), np.cos(phi)]), atol=1e-12)
        np.testing.assert_allclose(st.w_ref[k], W * np.array([np.cos(LAT), np.sin(LAT) * np.sin(phi),
                                                              np.sin(LAT) * np.cos(phi)]), atol=1e-15)
    rate = st.kind == "rate"
    assert rate.sum() == 18
    # rate about the up axis: |w| equals the commanded rate plus the Earth-rate vertical part
    np.testing.assert_allclose(np.abs(st.w_ref[rate]).max(axis=1),
                               np.abs(st.table_rate[rate, 0]) + np.sign(st.table_rate[rate, 0])
                               * W * np.sin(LAT), rtol=1e-9)
