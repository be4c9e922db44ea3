"""An independent generator of table-less multi-position sessions (hand-placed poses joined by
rotations), for testing the closed loop. It imports nothing from rigctl: its sensor model and
its effects are written here from their physical definitions, not from the solver's library.

World frame: x north, y west, z up; gravity g along -z, so a resting accelerometer reads
f = R^T (0, 0, g) (R: body -> world). Earth rate at latitude 45 deg: Omega (cos lat, 0, sin lat)
in the world frame. A motion from pose p to p+1 turns about a fixed body axis a by theta with a
raised-cosine rate profile: angle(t) = theta (t/T - sin(2 pi t/T) / (2 pi)); each gyro sample is
the exact mean rate over its sample interval, so the product of the sample increments is the
motion exactly.

Sensor: u_a = b_a + M_a f + (effect) + n_a; u_g = b_g + M_g w + (effect) + n_g, white noise
(accelerometer 1 mg, gyro 0.05 deg/s per sample at 100 Hz). Each effect's amplitude is set so that
it lifts its sub-model's chi2/dof clearly above the 99 % band (about 2 to 10): these sessions test
that an effect is named right, not how small an effect can be seen.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

G = 9.80665
OMEGA = 7.292115e-5
LAT = np.radians(45.0)
DEG = np.pi / 180
UG = 1e-6 * G

#: in-library effects: name -> the sub-model(s) the loop may name it in (the cross-coupling's
#: common part shows in the magnitudes, its split between the axes only in the directions)
IN_LIBRARY = {
    "accel_quadratic": "accel", "accel_cross_quadratic": ("accel", "gyro_rotation"), "accel_scale_asymmetry": "accel",
    "accel_bias_time_drift": "accel", "gyro_g_sensitivity": "gyro_static", "gyro_anisoelastic": "gyro_static",
    "gyro_bias_time_drift": "gyro_static", "gyro_scale_asymmetry": "gyro_rotation",
    "accel_bias_temperature": "accel", "gyro_bias_temperature": "gyro_static",
    "gyro_scale_nonlinearity": "gyro_rotation",
}
#: effects no candidate describes
OUTSIDE = ("accel_previous_pose_hysteresis", "gyro_bias_rotation_sense")


def make_session(seed: int, effect: str | None = None, n_poses: int = 40, fs: float = 100.0,
                 pose_s: float = 3.0, move_s: float = 1.5, rest_s: float = 20.0, noise: float = 1.0,
                 amplitude: float = 1.0) -> tuple[np.ndarray, list[dict]]:
    """(samples (n, 8): t, f_x.. (m/s^2), w_x.. (rad/s), temperature (degC); segments) of one session; ``amplitude``
    scales the effect."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / fs
    # attitudes: a random start, then turns of 60-150 deg about random body axes
    R = [Rotation.random(random_state=rng.integers(1 << 31))]
    axes, angles = [], []
    for _ in range(n_poses - 1):
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        th = np.radians(rng.uniform(60, 150))
        axes.append(a)
        angles.append(th)
        R.append(R[-1] * Rotation.from_rotvec(a * th))
    n_rest, n_pose, n_move = int(rest_s * fs), int(pose_s * fs), int(move_s * fs)
    att, rate, segs, pose_of = [], [], [], []
    t0 = 0

    def still(r: Rotation, n: int, label: str, p: int) -> None:
        nonlocal t0
        att.append(np.repeat(r.as_matrix()[None], n, axis=0))
        rate.append(np.zeros((n, 3)))
        pose_of.append(np.full(n, p))
        segs.append({"label": label, "start": t0, "end": t0 + n, "kind": "orientation"})
        t0 += n

    still(R[0], n_rest + n_pose, "rest+pose 0", 0)
    for p in range(1, n_poses):
        a, th = axes[p - 1], angles[p - 1]
        tk = np.arange(n_move + 1) * dt
        T = n_move * dt
        c = tk / T - np.sin(2 * np.pi * tk / T) / (2 * np.pi)
        inc = th * np.diff(c)
        rate.append(np.outer(inc / dt, a))
        mid = th * (c[:-1] + c[1:]) / 2
        att.append((R[p - 1] * Rotation.from_rotvec(np.outer(mid, a))).as_matrix())
        pose_of.append(np.full(n_move, -1))
        t0 += n_move
        still(R[p], n_pose, f"pose {p}", p)
    Rm = np.concatenate(att)
    w = np.concatenate(rate)
    pid = np.concatenate(pose_of)
    n = len(w)
    t = np.arange(n) * dt
    f = np.einsum("nji,j->ni", Rm, np.array([0.0, 0.0, G]))
    earth = np.einsum("nji,j->ni", Rm, OMEGA * np.array([np.cos(LAT), 0.0, np.sin(LAT)]))
    w_true = w + earth
    # declared errors (what a base model must absorb)
    b_a = rng.normal(0, 20e-3 * G, 3)
    M_a = np.eye(3) + np.diag(rng.normal(0, 5e-3, 3)) + rng.normal(0, 2e-3, (3, 3)) * (1 - np.eye(3))
    b_g = rng.normal(0, 0.5 * DEG, 3)
    M_g = np.eye(3) + np.diag(rng.normal(0, 5e-3, 3)) + rng.normal(0, 2e-3, (3, 3)) * (1 - np.eye(3))
    ua = b_a + f @ M_a.T
    ug = b_g + w_true @ M_g.T
    th_ = (t - t.mean()) / 3600.0
    # the unit warms up after power-on: +5 K with a 2-minute time constant, 0.01 K sensor noise
    temp = 25.0 + 5.0 * (1.0 - np.exp(-t / 120.0)) + rng.normal(0, 0.01, n)
    dT = temp - temp.mean()
    sgn = amplitude * rng.choice([-1.0, 1.0], 3)
    if effect == "accel_quadratic":
        ua += sgn * np.array([1800, 1500, 1800]) * UG / G ** 2 * f ** 2
    elif effect == "accel_cross_quadratic":
        ua += sgn * np.array([700, 600, 700]) * UG / G ** 2 * np.stack([f[:, 1] * f[:, 2], f[:, 0] * f[:, 2],
                                                                       f[:, 0] * f[:, 1]], axis=1)
    elif effect == "accel_scale_asymmetry":
        ua += sgn * np.array([1500, 1200, 1500]) * 1e-6 * np.abs(f)
    elif effect == "accel_bias_time_drift":
        ua += sgn * np.array([20, 15, 20]) * 1e-3 * G * th_[:, None]
    elif effect == "accel_bias_temperature":
        ua += sgn * np.array([0.5, 0.4, 0.5]) * 1e-3 * G * dT[:, None]
    elif effect == "gyro_bias_temperature":
        ug += sgn * np.array([40.0, 30.0, 40.0]) * DEG / 3600 * dT[:, None]
    elif effect == "gyro_g_sensitivity":
        Gs = rng.choice([-1, 1], (3, 3)) * rng.uniform(0.01, 0.03, (3, 3)) * DEG / G
        ug += f @ Gs.T
    elif effect == "gyro_anisoelastic":
        ug += sgn * 0.05 * DEG / G ** 2 * np.stack([f[:, 1] * f[:, 2], f[:, 0] * f[:, 2], f[:, 0] * f[:, 1]], axis=1)
    elif effect == "gyro_bias_time_drift":
        ug += sgn * np.array([1500, 1200, 1500]) * DEG / 3600 * th_[:, None]
    elif effect == "gyro_scale_asymmetry":
        ug += sgn * np.array([3000, 2500, 3000]) * 1e-6 * np.abs(w)
    elif effect == "gyro_scale_nonlinearity":
        ug += sgn * np.array([2000, 2000, 2000]) * 1e-6 * w * np.abs(w)
    elif effect == "accel_previous_pose_hysteresis":
        # the bias remembers the gravity direction of the pose before (a hysteresis)
        up = f / G
        prev = np.zeros_like(up)
        for p in range(1, n_poses):
            prev[pid == p] = up[pid == p - 1][0]
        ua += 1.0e-3 * G * prev
    elif effect == "gyro_bias_rotation_sense":
        # the gyro bias of a pose depends on the sense of the motion that led to it
        sense = np.zeros(n)
        for p in range(1, n_poses):
            sense[pid == p] = np.sign(axes[p - 1][0])
        ug += np.outer(sense, np.array([40.0, 40.0, 40.0]) * DEG / 3600)
    elif effect is not None:
        raise ValueError(effect)
    ua += rng.normal(0, noise * 1e-3 * G, ua.shape)
    ug += rng.normal(0, noise * 0.05 * DEG, ug.shape)
    return np.column_stack([t, ua, ug, temp]), segs


def write_csv(path: Path, seed: int, effect: str | None = None, **kw: float) -> Path:
    """The session as a CSV (t, ax..gz in m/s^2 and rad/s, temp in degC) and its sections JSON."""
    x, segs = make_session(seed, effect, **kw)
    # np.savetxt(path, x, delimiter=",", header=..., comments="", fmt="%.9g")'s bytes, formatted
    # with one % over every row instead of one per row
    row = ",".join(["%.9g"] * x.shape[1]) + "\n"
    path.write_text("t,ax,ay,az,gx,gy,gz,temp\n" + (row * x.shape[0]) % tuple(x.ravel().tolist()))
    path.with_suffix(".json").write_text(json.dumps(segs))
    return path
