"""The closed loop for static-pose sessions without a table (hand-held, imported, six-face).

A session is a sequence of P static poses with motion between them. What such data can reveal,
and how each sub-model is tested:

* **Accelerometer, magnitude model** (Tedaldi et al. 2014). Calibrated specific force of pose p

      a_p = T K (u_p - b - sum_e B_e(u_p, t_p, T_p) theta_e),     |a_p| = g at rest,

  u_p the pose mean (SI with nominal scale), T K misalignment and scale, b the bias; the
  candidates B_e theta_e (each 3 parameters, one per axis):
  ``accel_quadratic`` u_i^2 (s^2/m), ``accel_cross_quadratic`` u_j u_k (s^2/m),
  ``accel_scale_asymmetry`` |u_i| (ratio), ``accel_bias_time_drift`` (t - t_mid)
  (m/s^2 per h), ``accel_bias_temperature`` (T - T_mid) (m/s^2 per K). Residual of pose p:
  (|a_p| - g) / s_p, s_p^2 = sum_c (d|a_p|/du_c)^2 var(u_pc).
* **Gyro, static poses** (linear). w_p = b_g + Omega_E,p + sum_e X_e theta_e + v_p, with the
  Earth rate's vertical part Omega sin(lat) along the pose's up direction (latitude given:
  subtracted; unknown: one parameter with the prior 0 +- Omega/sqrt(3), since it is exactly
  collinear with the diagonal of G) and its horizontal part, whose direction depends on the
  unknown heading, as variance Omega^2 cos^2(lat) (1 - up_i^2) / 2 per axis (cos^2 = 2/3 when
  the latitude is unknown). Candidates: ``gyro_g_sensitivity`` G f (9, rad/s per m/s^2),
  ``gyro_anisoelastic`` f_j f_k (3), ``gyro_bias_time_drift`` (3), ``gyro_bias_temperature`` (3).
* **Gyro, rotations between poses**: the calibrated rate w = T_g K_g (u - b_g) integrated
  over each motion must turn the gravity direction of pose k into that of pose k+1. Candidates
  (applied to the calibrated rate): ``gyro_scale_asymmetry`` d_i |w_i| (ratio) and
  ``gyro_scale_nonlinearity`` n_i w_i |w_i| (s/rad).

Every sub-model runs the same loop (:func:`select_effects`) while its chi2/dof is above the
99 % band (a fit inside its band has nothing left to explain): forward selection, each round
adding the candidate with the smallest F-test p-value below alpha / m (Bonferroni over the m
candidates left), if leave-one-pose-out cross-validation (PRESS, whitened, linearised at the
solution) drops too. Then :func:`judge`: the final chi2/dof against its 99 % band (F band: the
variances behind the residuals are estimated with ``noise_dof`` degrees of freedom). Above the
band the residual is UNEXPLAINED: the whitened residuals are correlated with the variables a
lab would check (time, temperature, gravity direction, the previous pose's gravity direction,
pose order), each as a partial correlation off the fitted model, and an added effect that
removed less than half of the excess over the band is not claimed (it is the nearest
candidate to an effect outside the library, not that effect).

Pure functions of arrays; SI throughout.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
import scipy.optimize
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from . import distributions as _dist

OMEGA_EARTH = 7.292115e-5  # rad/s
AX = "xyz"
Arr = NDArray[np.float64]


# ------------------------------------------------------------------------------ pose statistics
@dataclass
class PoseData:
    """Per-pose statistics of a static-pose session (SI).

    Attributes:
        acc, gyr: (P, 3) pose means, m/s^2 (nominal scale) and rad/s.
        var_acc, var_gyr: (P, 3) variances of those means (white part from batch means, plus the
            slow part measured on the longest rest, see :func:`pose_statistics`).
        t_s: (P,) mid times, s.  temp_c: (P,) mean temperature, degC, or None.
        intervals: the poses' [start, end) sample ranges.  fs_hz: sample rate.
        noise_dof: degrees of freedom behind the variances.
        slow: per channel (6) the slow variance added to each pose mean (0 when not resolved).
    """

    acc: Arr
    gyr: Arr
    var_acc: Arr
    var_gyr: Arr
    t_s: Arr
    temp_c: Arr | None
    intervals: list[tuple[int, int]]
    fs_hz: float
    noise_dof: float
    slow: Arr = field(default_factory=lambda: np.zeros(6))
    notes: list[str] = field(default_factory=list)
    white: Arr = field(default_factory=lambda: np.zeros(6))
    rest_white: Arr = field(default_factory=lambda: np.zeros(6))
    wander: Arr = field(default_factory=lambda: np.zeros(0))

    @property
    def t_ref(self) -> float:
        """Reference time of the drift terms: the mean pose time, s."""
        return float(np.mean(self.t_s))

    @property
    def temp_ref(self) -> float:
        """Reference temperature of the thermal terms: the mean pose temperature, degC."""
        return float(np.mean(self.temp_c)) if self.temp_c is not None else float("nan")


def _batch_white(x: Arr, intervals: list[tuple[int, int]], nb: int) -> tuple[Arr, float]:
    """Per-sample white variance (per channel) pooled over poses from batch means of ``nb``
    samples: v = sum_p sum_b nb (m_pb - m_p)^2 / sum_p (B_p - 1). Returns (v, dof)."""
    num, dof = np.zeros(x.shape[1]), 0.0
    for s, e in intervals:
        B = (e - s) // nb
        if B < 2:
            continue
        m = x[s:s + B * nb].reshape(B, nb, -1).mean(axis=1)
        num += nb * ((m - m.mean(axis=0)) ** 2).sum(axis=0)
        dof += B - 1
    return num / max(dof, 1.0), dof


def pose_statistics(acc: Arr, gyr: Arr, intervals: list[tuple[int, int]], fs_hz: float,
                    temp_c: Arr | None = None, rest: tuple[int, int] | None = None,
                    batch_s: float = 0.25) -> PoseData:
    """Pose means and their variances.

    White part: per-sample variance from batch means of ``batch_s`` seconds pooled over the poses
    (short-term correlation up to the batch length included), var(mean_p) = v / n_p.
    Slow part (bias instability, random walk): on the longest rest (``rest``, default the
    longest interval) the differences of block means of the median pose length L separated by
    the median pose spacing D; the excess of their variance over the white prediction 2 v / n_L,
    when larger than twice its own standard error, is split evenly between two poses and added.
    """
    acc, gyr = np.asarray(acc, float), np.asarray(gyr, float)
    x = np.hstack([acc, gyr])
    nb = max(2, int(round(batch_s * fs_hz)))
    lens = np.array([e - s for s, e in intervals])
    nb = max(2, min(nb, int(lens.min() // 4)))
    v, dof = _batch_white(x, intervals, nb)
    means = np.array([x[s:e].mean(axis=0) for s, e in intervals])
    var = v[None, :] / lens[:, None]
    notes = [f"white noise from batch means of {nb / fs_hz:.3g} s pooled over {len(intervals)} poses "
             f"({dof:.0f} dof)"]
    rs, re_ = rest if rest is not None else max(intervals, key=lambda iv: iv[1] - iv[0])
    L = int(np.median(lens))
    starts = np.array([s for s, _ in intervals])
    D = int(np.median(np.diff(starts))) if len(starts) > 1 else L
    D = min(D, (re_ - rs) - L)
    slow = np.zeros(6)
    if D >= L // 2 and L >= nb:
        k0 = np.arange(rs, re_ - L - D + 1, max(1, L // 2))
        if len(k0) >= 4:
            cs = np.vstack([np.zeros((1, 6)), np.cumsum(x[rs:re_] - x[rs:re_].mean(axis=0), axis=0)])
            blk = lambda a: (cs[a - rs + L] - cs[a - rs]) / L  # noqa: E731
            d = blk(k0 + D) - blk(k0)
            n_ind = max(2.0, (re_ - rs - L - D) / max(L, D) + 1)
            vd = (d ** 2).mean(axis=0)
            excess = vd - 2 * v / L
            se = vd * np.sqrt(2.0 / n_ind)
            slow = np.where(excess > 2 * se, excess / 2, 0.0)
            notes.append(f"slow noise from the {(re_ - rs) / fs_hz:.3g} s rest: block means of "
                         f"{L / fs_hz:.3g} s, {D / fs_hz:.3g} s apart; resolved on "
                         f"{int(np.sum(slow > 0))} of 6 channels")
    else:
        notes.append("slow noise not measured: the longest rest is shorter than a pose plus the pose spacing")
    var = var + slow[None, :]
    # the sensor's own white noise: batch means on the longest rest alone (placed, not held)
    rest_white, _ = _batch_white(x, [(rs, re_)], nb)
    # within-pose wander of the gravity direction (a held pose turns a little): variance of the
    # batch-mean directions about the pose's mean direction, white part removed (rad^2, per axis)
    wander = np.zeros(len(intervals))
    for i, (s, e) in enumerate(intervals):
        B = (e - s) // nb
        if B < 2:
            continue
        m = acc[s:s + B * nb].reshape(B, nb, 3).mean(axis=1)
        u = m / np.linalg.norm(m, axis=1)[:, None]
        u0 = means[i, :3] / np.linalg.norm(means[i, :3])
        spread = np.mean(np.sum((u - u0) ** 2, axis=1)) / 2
        wander[i] = max(spread - np.mean(v[:3]) / nb / np.dot(means[i, :3], means[i, :3]), 0.0)
    t = np.array([(s + e) / 2 / fs_hz for s, e in intervals])
    tc = None if temp_c is None else np.array([np.nanmean(temp_c[s:e]) for s, e in intervals])
    return PoseData(acc=means[:, :3], gyr=means[:, 3:], var_acc=var[:, :3], var_gyr=var[:, 3:], t_s=t,
                    temp_c=tc, intervals=list(intervals), fs_hz=fs_hz, noise_dof=float(dof), slow=slow,
                    notes=notes, white=v, rest_white=rest_white, wander=wander)


# ------------------------------------------------------------------------------ fits and selection
@dataclass
class Fit:
    """One least-squares fit: whitened residuals r, whitened Jacobian J (for PRESS), groups."""

    names: list[str]
    values: Arr
    cov: Arr
    chi2: float
    dof: int
    r: Arr
    J: Arr
    groups: Arr
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def chi2_per_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")


def press(fit: Fit) -> float:
    """Leave-one-group-out prediction error sum_g |(I - H_gg)^-1 r_g|^2 (whitened, linearised)."""
    J, r = fit.J, fit.r
    q, _ = np.linalg.qr(J)
    H = q @ q.T
    tot = 0.0
    for g in np.unique(fit.groups):
        if g < 0:
            continue
        i = np.flatnonzero(fit.groups == g)
        A = np.eye(len(i)) - H[np.ix_(i, i)]
        try:
            e = np.linalg.solve(A, r[i])
        except np.linalg.LinAlgError:
            return float("inf")
        tot += float(e @ e)
    return tot


@dataclass
class Candidate:
    """A library effect for a sub-model: ``testable`` and ``why`` say whether and why (not)."""

    name: str
    k: int
    testable: bool = True
    why: str = ""


def chi2_band(dof: int, noise_dof: float, level: float = 0.99) -> tuple[float, float]:
    """(low, high) band of chi2/dof when the model and the noise model are right: the F(dof,
    noise_dof) quantiles (the variances are estimates), chi2 quantiles for noise_dof = inf."""
    a = (1 - level) / 2
    if dof <= 0:
        return float("nan"), float("nan")
    if not np.isfinite(noise_dof) or noise_dof > 1e6:
        return (float(_dist.chi2.ppf(a, dof) / dof), float(_dist.chi2.ppf(1 - a, dof) / dof))
    return float(_dist.f.ppf(a, dof, noise_dof)), float(_dist.f.ppf(1 - a, dof, noise_dof))


def select_effects(fit_fn: Callable[[list[str]], Fit], cands: Sequence[Candidate], alpha: float = 0.01,
                   needed: Callable[[Fit], bool] | None = None
                   ) -> tuple[list[str], list[Fit], list[dict[str, Any]]]:
    """Forward selection (module doc). Returns (accepted names, fits after each step with the
    declared fit first, explain rows). ``needed(fit)``: a round runs only while it is true (the
    loop runs while the chi2 is above its band)."""
    cur: list[str] = []
    fits = [fit_fn(cur)]
    rows: list[dict[str, Any]] = []
    ambiguous: list[str] = []
    for c in cands:
        if not c.testable:
            rows.append({"step": 0, "candidate": c.name, "statistic": "-", "decision": f"not testable: {c.why}"})
    pool = [c for c in cands if c.testable]
    step = 0
    while pool:
        base = fits[-1]
        if needed is not None and not needed(base):
            why = (f"the {'declared' if step == 0 else 'current'} model's chi2/dof {base.chi2_per_dof:.3g} is inside "
                   "its 99 % band: nothing left to explain")
            rows += [{"step": step + 1, "candidate": c.name, "statistic": "-", "decision": f"not run: {why}"}
                     for c in pool]
            break
        step += 1
        tried = []
        for c in pool:
            try:
                f = fit_fn(cur + [c.name])
            except (np.linalg.LinAlgError, ValueError) as exc:
                rows.append({"step": step, "candidate": c.name, "statistic": "-", "decision": f"fit failed: {exc}"})
                continue
            if f.dof < 1 or base.chi2 <= f.chi2:
                tried.append((1.0, c, f, 0.0))
                continue
            F = ((base.chi2 - f.chi2) / c.k) / (f.chi2 / f.dof)
            tried.append((float(_dist.f.sf(F, c.k, f.dof)), c, f, F))
        if not tried:
            break
        tried.sort(key=lambda x: x[0])
        thr = alpha / len(pool)
        done = False
        for p, c, f, F in tried:
            stat = f"F({c.k},{f.dof}) = {F:.3g}, p = {p:.2g} (threshold {thr:.2g})"
            if p >= thr:
                rows.append({"step": step, "candidate": c.name, "statistic": stat, "decision": "rejected: not significant"})
                continue
            cv0, cv1 = press(base), press(f)
            stat += f"; PRESS {cv0:.4g} -> {cv1:.4g}"
            if cv1 >= cv0:
                rows.append({"step": step, "candidate": c.name, "statistic": stat,
                             "decision": "rejected: cross-validation does not improve"})
                continue
            # a runner-up that fits as well (chi2 within the 95 % likelihood-ratio margin, scaled
            # by the residual variance) is indistinguishable on this recording: say so
            scale = f.chi2 / max(f.dof, 1)
            rivals = [q for q2, q, f2, _ in tried if q is not c and q2 < thr and f2.chi2 - f.chi2 < 3.84 * scale]
            if rivals:
                alt = " or ".join([c.name] + [q.name for q in rivals])
                rows.append({"step": step, "candidate": alt, "statistic": stat,
                             "decision": "ambiguous: these candidates fit equally well; none is claimed"})
                ambiguous.append(alt)
                done = False
                break
            rows.append({"step": step, "candidate": c.name, "statistic": stat, "decision": "added"})
            cur.append(c.name)
            fits.append(f)
            pool = [q for q in pool if q.name != c.name]
            done = True
            break
        if not done:
            break
    if ambiguous:
        rows.append({"step": step, "candidate": ambiguous[0], "statistic": "-", "decision": "ambiguous"})
    return cur, fits, rows


def partial_correlations(fit: Fit, variables: dict[str, Arr], per_group: bool = True) -> list[dict[str, Any]]:
    """Correlation of the whitened residuals with each variable projected off the model's span
    (the score test of adding it): r, t statistic, p (two-sided, df = n - rank - 1)."""
    q, _ = np.linalg.qr(fit.J)
    out = []
    n = len(fit.r)
    for name, v in variables.items():
        x = np.asarray(v, float)
        if x.shape != fit.r.shape or not np.all(np.isfinite(x)):
            continue
        x = x - q @ (q.T @ x)
        nx = np.linalg.norm(x)
        df = n - q.shape[1] - 1
        if nx < 1e-8 * max(1.0, np.linalg.norm(v)) or df < 3:
            continue
        rr = float(x @ fit.r / (nx * max(np.linalg.norm(fit.r), 1e-300)))
        t = rr * np.sqrt(df / max(1 - rr * rr, 1e-12))
        out.append({"variable": name, "r": rr, "t": float(t), "p": float(2 * _dist.t.sf(abs(t), df))})
    return sorted(out, key=lambda d: d["p"])


@dataclass
class SubLoop:
    """The loop's result for one sub-model (accel, gyro_static, gyro_rotation, faces)."""

    name: str
    declared: Fit
    final: Fit
    accepted: list[str]
    claimed: list[str]
    not_claimed: list[str]
    explain: list[dict[str, Any]]
    band: tuple[float, float]
    status: str
    correlations: list[dict[str, Any]]
    findings: list[str]

    def to_dict(self) -> dict[str, Any]:
        f = self.final
        return {"name": self.name, "status": self.status, "band_chi2_per_dof": list(self.band),
                "declared": {"chi2": self.declared.chi2, "dof": self.declared.dof,
                             "chi2_per_dof": self.declared.chi2_per_dof},
                "final": {"chi2": f.chi2, "dof": f.dof, "chi2_per_dof": f.chi2_per_dof,
                          "parameters": [{"name": n, "value": float(v), "sigma": float(np.sqrt(max(c, 0.0)))}
                                         for n, v, c in zip(f.names, f.values, np.diag(f.cov))]},
                "effects_claimed": self.claimed, "effects_not_claimed": self.not_claimed,
                "explain": self.explain, "correlations": self.correlations[:6], "findings": self.findings}


STATUS_OK = "OK"
STATUS_UNEXPLAINED = "UNEXPLAINED RESIDUAL"
STATUS_PESSIMISTIC = "NOISE MODEL TOO PESSIMISTIC"


def judge(name: str, fit_fn: Callable[[list[str]], Fit], cands: Sequence[Candidate], noise_dof: float,
          variables: dict[str, Arr], alpha: float = 0.01) -> SubLoop:
    """Run the selection, then the band and the claims (module doc)."""
    def needed(f: Fit) -> bool:
        return f.dof <= 0 or f.chi2_per_dof > chi2_band(f.dof, noise_dof)[1]

    accepted, fits, rows = select_effects(fit_fn, cands, alpha, needed)
    final, declared = fits[-1], fits[0]
    band = chi2_band(final.dof, noise_dof)
    claimed, not_claimed, findings = list(accepted), [], []
    amb = [r["candidate"] for r in rows if r["decision"] == "ambiguous"]
    if amb:
        findings.append(f"ambiguous: {amb[0]} -- each explains the residual as well as the other on these poses; "
                        "none is claimed (more poses, or poses at intermediate tilts, would separate them)")
    corr: list[dict[str, Any]] = []
    if final.dof > 0 and final.chi2_per_dof > band[1]:
        status = STATUS_UNEXPLAINED
        excess0 = declared.chi2 - band[1] * declared.dof
        for i, eff in enumerate(accepted):
            gain = fits[i].chi2 - fits[i + 1].chi2
            if excess0 <= 0 or gain < 0.5 * excess0:
                not_claimed.append(eff)
        if not_claimed:
            claimed = [e for e in accepted if e not in not_claimed]
            final = fit_fn(claimed)
            band = chi2_band(final.dof, noise_dof)
            findings.append("not claimed (each removed less than half of the excess, the residual stays "
                            f"above its band): {', '.join(not_claimed)}")
        corr = partial_correlations(final, variables)
        sig = [c for c in corr if c["p"] < alpha / max(len(corr), 1)]
        findings.append(f"chi2/dof {final.chi2_per_dof:.3g} above its 99 % band [{band[0]:.3g}, {band[1]:.3g}] "
                        "after the final model: an effect outside the library (or motion during the poses)")
        if sig:
            findings.append("the residual correlates with " + "; ".join(
                f"{c['variable']} (r = {c['r']:.2f}, p = {c['p']:.2g})" for c in sig[:4]))
        else:
            findings.append("no tested variable explains it (largest: " + (
                f"{corr[0]['variable']} r = {corr[0]['r']:.2f}, p = {corr[0]['p']:.2g})" if corr else "none)"))
    elif final.dof > 0 and final.chi2_per_dof < band[0]:
        status = STATUS_PESSIMISTIC
        findings.append(f"chi2/dof {final.chi2_per_dof:.3g} below its 99 % band [{band[0]:.3g}, {band[1]:.3g}]: "
                        "the noise model overstates the scatter of the pose means")
    elif final.dof <= 0:
        status = STATUS_UNEXPLAINED
        findings.append("no degrees of freedom left: the fit cannot be tested")
    else:
        status = STATUS_OK
    return SubLoop(name, declared, final, accepted, claimed, not_claimed, rows, band, status, corr, findings)


# ------------------------------------------------------------------------------ accelerometer
def _tk(m: Arr, s: Arr) -> Arr:
    T = np.array([[1.0, -m[0], m[1]], [0.0, 1.0, -m[2]], [0.0, 0.0, 1.0]])
    return T @ np.diag(s)


ACCEL_CANDIDATES = {
    "accel_quadratic": ("s2_per_m", lambda u, d: u ** 2),
    # at rest the magnitude sees only the sum of the three cross-coupling coefficients (each adds
    # 2 c u_x u_y u_z to |u|^2): one common coefficient is what the data can test
    "accel_cross_quadratic": ("s2_per_m", lambda u, d: np.stack([u[:, 1] * u[:, 2], u[:, 0] * u[:, 2],
                                                                 u[:, 0] * u[:, 1]], axis=1)[:, :, None]),
    "accel_scale_asymmetry": ("ratio", lambda u, d: np.abs(u)),
    "accel_bias_time_drift": ("m_s2_per_h", lambda u, d: np.repeat(((d.t_s - d.t_ref) / 3600)[:, None], 3, 1)),
    "accel_bias_temperature": ("m_s2_per_K", lambda u, d: np.repeat((d.temp_c - d.temp_ref)[:, None], 3, 1)),
}


def accel_k(name: str) -> int:
    """Number of parameters of an accelerometer candidate (3 per-axis, 1 for a common one)."""
    return 1 if name == "accel_cross_quadratic" else 3


def accel_correction(effects: dict[str, Arr], u: Arr, data: Any) -> Arr:
    """sum_e B_e(u) o theta_e: the candidates' correction to the raw means (P, 3)."""
    out = np.zeros_like(u)
    for e, th in effects.items():
        B = ACCEL_CANDIDATES[e][1](u, data)
        out += (B[:, :, 0] * th[0]) if B.ndim == 3 else B * th
    return out


def _accel_split(p: Arr, effects: list[str]) -> dict[str, Arr]:
    out, i = {}, 9
    for e in effects:
        out[e] = p[i:i + accel_k(e)]
        i += accel_k(e)
    return out


def accel_candidates(d: PoseData) -> list[Candidate]:
    """The accelerometer candidates and whether this session can test each."""
    P = len(d.acc)
    out = []
    for name in ACCEL_CANDIDATES:
        c = Candidate(name, accel_k(name))
        if name == "accel_bias_temperature":
            if d.temp_c is None or not np.all(np.isfinite(d.temp_c)):
                c.testable, c.why = False, "no temperature recorded"
            elif np.ptp(d.temp_c) < 1.0:
                c.testable, c.why = False, f"temperature spans {np.ptp(d.temp_c):.2g} K (< 1 K)"
        elif name == "accel_bias_time_drift" and np.ptp(d.t_s) < 60:
            c.testable, c.why = False, f"poses span {np.ptp(d.t_s):.3g} s"
        if c.testable and P - 9 - 3 < 3:
            c.testable, c.why = False, f"{P} poses leave {P - 12} dof with 12 parameters (need >= 3)"
        if c.testable:
            # linearised magnitude: d|u| = sum_i (u_i/|u|) du_i; the base model spans bias (u_i),
            # scale (u_i^2) and the three misalignments (u_x u_y, u_x u_z, u_y u_z), over |u|
            u = d.acc
            n = np.linalg.norm(u, axis=1)[:, None]
            base = np.hstack([u, u ** 2, u[:, [0]] * u[:, [1]], u[:, [0]] * u[:, [2]], u[:, [1]] * u[:, [2]]]) / n
            B = ACCEL_CANDIDATES[name][1](u, d)
            B = B[:, :, 0] if B.ndim == 3 else B
            cand = (u * B / n) if accel_k(name) == 3 else np.sum(u * B, axis=1, keepdims=True) / n
            X = np.hstack([base, cand])
            X = X / np.maximum(np.linalg.norm(X, axis=0), 1e-300)
            sv = np.linalg.svd(X, compute_uv=False)
            if sv[-1] < 1e-6 * sv[0]:
                c.testable, c.why = False, "the poses do not separate it from scale, bias and misalignment"
        out.append(c)
    return out


def fit_accel(d: PoseData, g: float, effects: list[str]) -> Fit:
    """Magnitude-model fit with the named effects (module doc)."""
    u = d.acc
    P = len(u)
    k = sum(accel_k(e) for e in effects)

    def unpack(p: Arr) -> tuple[Arr, dict[str, Arr]]:
        return _tk(p[0:3], p[3:6]), _accel_split(p, effects)

    def resid(p: Arr) -> Arr:
        M, eff = unpack(p)
        v0 = u - p[6:9]  # the effects act on the input (specific force), not on the biased output
        v = v0 - accel_correction(eff, v0, d)
        a = v @ M.T
        na = np.linalg.norm(a, axis=1)
        dn = (a / na[:, None]) @ M
        return (na - g) / np.sqrt(np.sum(dn ** 2 * d.var_acc, axis=1))

    p0 = np.concatenate([[0, 0, 0, 1, 1, 1, 0, 0, 0], np.zeros(k)])
    sc = np.concatenate([[1e-3] * 3, [1e-3] * 3, [1e-2] * 3, np.full(k, 1e-3)])
    sol = scipy.optimize.least_squares(resid, p0, x_scale=sc, method="lm" if P > 9 + k else "trf",
                                       xtol=1e-12, ftol=1e-12)
    J = sol.jac
    cov = np.linalg.pinv(J.T @ J)
    names = ["accel_misalign_yz_rad", "accel_misalign_zy_rad", "accel_misalign_zx_rad"] + \
            [f"accel_scale_{a}_ratio" for a in AX] + [f"accel_bias_{a}_m_s2" for a in AX] + \
            [f"{e}_{a}_{ACCEL_CANDIDATES[e][0]}" if accel_k(e) == 3 else f"{e}_{ACCEL_CANDIDATES[e][0]}"
             for e in effects for a in (AX if accel_k(e) == 3 else "x")]
    r = sol.fun
    return Fit(names, sol.x, cov, float(r @ r), P - 9 - k, r, J, np.arange(P))


def accel_apply(fit: Fit, effects: list[str], u: Arr, data: Any) -> Arr:
    """Calibrated specific force for raw (nominal-scale) vectors u (n, 3)."""
    p = fit.values
    v0 = u - p[6:9]
    return (v0 - accel_correction(_accel_split(p, effects), v0, data)) @ _tk(p[0:3], p[3:6]).T


def direction_variance(fit: Fit, effects: list[str], u: Arr, data: Any) -> Arr:
    """(P,) variance of each pose's gravity direction (rad^2, two axes summed / 2) that the
    accelerometer model's parameter uncertainty causes: J Cov J^T of up = a / |a|, numerically."""
    p0 = fit.values.copy()

    def up_of(p: Arr) -> Arr:
        a = accel_apply(Fit(fit.names, p, fit.cov, 0, 0, fit.r, fit.J, fit.groups), effects, u, data)
        return a / np.linalg.norm(a, axis=1)[:, None]

    base = up_of(p0)
    sd = np.sqrt(np.clip(np.diag(fit.cov), 0, None))
    Jc = []
    for i in range(len(p0)):
        h = sd[i] * 1e-3 if sd[i] > 0 else 1e-9
        q = p0.copy()
        q[i] += h
        Jc.append((up_of(q) - base) / h)
    Jm = np.stack(Jc, axis=-1)  # (P, 3, n)
    C = np.einsum("pin,nm,pjm->pij", Jm, fit.cov, Jm)
    return np.trace(C, axis1=1, axis2=2) / 2


def pose_variables(d: PoseData, up: Arr) -> dict[str, Arr]:
    """Variables the residual is checked against, one value per pose (callers tile them per row)."""
    P = len(up)
    prev = np.vstack([up[:1], up[:-1]])
    v = {"time": d.t_s, "pose order parity": (np.arange(P) % 2).astype(float)}
    if d.temp_c is not None and np.all(np.isfinite(d.temp_c)):
        v["temperature"] = d.temp_c
    for i, a in enumerate(AX):
        v[f"gravity direction {a}"] = up[:, i]
        v[f"previous pose's gravity direction {a}"] = prev[:, i]
    return v


# ------------------------------------------------------------------------------ gyro, static
GYRO_STATIC_CANDIDATES = ("gyro_g_sensitivity", "gyro_anisoelastic", "gyro_bias_time_drift",
                          "gyro_bias_temperature")


def _gyro_columns(name: str, f: Arr, d: PoseData) -> tuple[Arr, list[str]]:
    """(3P, k) regressors (rows: axis-major, x of every pose, then y, then z) and names."""
    P = len(f)
    cols, names = [], []
    if name == "gyro_g_sensitivity":
        for i in range(3):
            for j in range(3):
                c = np.zeros(3 * P)
                c[i * P:(i + 1) * P] = f[:, j]
                cols.append(c)
                names.append(f"gyro_g_sens_{AX[i]}{AX[j]}_rad_s_per_m_s2")
    elif name == "gyro_anisoelastic":
        prod = np.stack([f[:, 1] * f[:, 2], f[:, 0] * f[:, 2], f[:, 0] * f[:, 1]], axis=1)
        for i in range(3):
            c = np.zeros(3 * P)
            c[i * P:(i + 1) * P] = prod[:, i]
            cols.append(c)
            names.append(f"gyro_anisoelastic_{AX[i]}_rad_s_per_m2_s4")
    else:
        x, unit = ((d.t_s - d.t_ref) / 3600, "rad_s_per_h") if name == "gyro_bias_time_drift" else \
            (d.temp_c - d.temp_ref, "rad_s_per_K")
        for i in range(3):
            c = np.zeros(3 * P)
            c[i * P:(i + 1) * P] = x
            cols.append(c)
            names.append(f"{name}_{AX[i]}_{unit}")
    return np.stack(cols, axis=1), names


def gyro_static_candidates(d: PoseData) -> list[Candidate]:
    """The static-gyro candidates and whether this session can test each."""
    P = len(d.gyr)
    out = []
    for name, k in zip(GYRO_STATIC_CANDIDATES, (9, 3, 3, 3)):
        c = Candidate(name, k)
        if name == "gyro_bias_temperature":
            if d.temp_c is None or not np.all(np.isfinite(d.temp_c)):
                c.testable, c.why = False, "no temperature recorded"
            elif np.ptp(d.temp_c) < 1.0:
                c.testable, c.why = False, f"temperature spans {np.ptp(d.temp_c):.2g} K (< 1 K)"
        elif name == "gyro_bias_time_drift" and np.ptp(d.t_s) < 60:
            c.testable, c.why = False, f"poses span {np.ptp(d.t_s):.3g} s"
        elif 3 * P - 4 - k < 3:
            c.testable, c.why = False, f"{P} poses give {3 * P} pose means for {4 + k} parameters"
        out.append(c)
    return out


def fit_gyro_static(d: PoseData, f: Arr, effects: list[str], latitude_rad: float | None) -> Fit:
    """Linear WLS of the static gyro means (module doc); f: (P, 3) calibrated specific force."""
    P = len(f)
    up = f / np.linalg.norm(f, axis=1)[:, None]
    y = d.gyr.T.reshape(-1).copy()
    if latitude_rad is None:
        cos2 = 2.0 / 3.0
    else:
        y -= OMEGA_EARTH * np.sin(latitude_rad) * up.T.reshape(-1)
        cos2 = np.cos(latitude_rad) ** 2
    h2 = OMEGA_EARTH ** 2 * cos2 / 2  # horizontal Earth rate, random heading: (I - up up^T) h2 per pose
    cols = [np.kron(np.eye(3), np.ones((P, 1)))]
    names = [f"gyro_bias_{a}_rad_s" for a in AX]
    if latitude_rad is None:
        cols.append(up.T.reshape(-1, 1))
        names.append("earth_rate_vertical_rad_s")
    for e in effects:
        c, n = _gyro_columns(e, f, d)
        cols.append(c)
        names += n
    X = np.hstack(cols)
    Xw, yw = np.empty_like(X), np.empty_like(y)
    for p in range(P):  # whiten each pose's three rows by the Cholesky factor of their covariance
        rows = np.array([p, P + p, 2 * P + p])
        C = np.diag(d.var_gyr[p]) + h2 * (np.eye(3) - np.outer(up[p], up[p]))
        L = np.linalg.cholesky(C)
        Xw[rows] = np.linalg.solve(L, X[rows])
        yw[rows] = np.linalg.solve(L, y[rows])
    groups = np.tile(np.arange(P), 3)
    if latitude_rad is None:  # prior row: sin(lat) uniform on [-1, 1]
        pr = np.zeros((1, X.shape[1]))
        pr[0, 3] = 1.0 / (OMEGA_EARTH / np.sqrt(3))
        Xw, yw = np.vstack([Xw, pr]), np.append(yw, 0.0)
        groups = np.append(groups, -1)
    beta, *_ = np.linalg.lstsq(Xw, yw, rcond=None)
    r = yw - Xw @ beta
    cov = np.linalg.pinv(Xw.T @ Xw)
    dof = 3 * P - (X.shape[1] - (1 if latitude_rad is None else 0))
    return Fit(names, beta, cov, float(r @ r), int(dof), r, Xw, groups, extra={"resid": y - X @ beta, "y": y})


def gyro_static_model(fit: Fit, f: Arr, t_s: Arr, temp_c: Arr | None, d: PoseData) -> Arr:
    """(n, 3) what the static gyro model predicts at specific force f (n, 3) and times t_s
    (bias, g-sensitivity, anisoelastic, drift, temperature; no Earth rate): the part of the
    rate that the motions between poses must have removed."""
    v = dict(zip(fit.names, fit.values))
    out = np.tile([v.get(f"gyro_bias_{a}_rad_s", 0.0) for a in AX], (len(f), 1))
    G = np.array([[v.get(f"gyro_g_sens_{a}{b}_rad_s_per_m_s2", 0.0) for b in AX] for a in AX])
    out += f @ G.T
    prod = np.stack([f[:, 1] * f[:, 2], f[:, 0] * f[:, 2], f[:, 0] * f[:, 1]], axis=1)
    out += prod * np.array([v.get(f"gyro_anisoelastic_{a}_rad_s_per_m2_s4", 0.0) for a in AX])
    out += np.outer((t_s - d.t_ref) / 3600, [v.get(f"gyro_bias_time_drift_{a}_rad_s_per_h", 0.0) for a in AX])
    if temp_c is not None and d.temp_c is not None:
        out += np.outer(np.nan_to_num(temp_c - d.temp_ref),
                        [v.get(f"gyro_bias_temperature_{a}_rad_s_per_K", 0.0) for a in AX])
    return out


# ------------------------------------------------------------------------------ gyro, rotations
def _tg(p: Arr) -> Arr:
    T = np.array([[1.0, p[0], p[1]], [p[2], 1.0, p[3]], [p[4], p[5], 1.0]])
    return T @ np.diag(p[6:9])


ROTATION_CANDIDATES = {"gyro_scale_asymmetry": "ratio", "gyro_scale_nonlinearity": "s_per_rad"}


class _MotionProduct:
    """R = prod_k exp([w_k dt]x) in sample order for each motion [s, e) of ``bounds`` (K, 2), all
    motions at once: each motion's increments padded with identities to a common power-of-two
    length L and multiplied pairwise (log2 L vectorised levels).

    The layout is worked out once per set of motions: ``src``, the motions' sample indices in
    the order :meth:`product` takes the rates (``w[src]``). Each level is the
    Hamilton product of quaternions (x, y, z, w), a_w b_v + b_w a_v + a_v x b_v and
    a_w b_w - a_v . b_v, written per component on (rows, K) planes (np.cross's and np.sum's
    operations in their order: the same bits as on (K, L, 4) arrays, several times faster);
    rows past the longest motion, where both factors of every pair are the identity padding
    (whose product is exactly the identity), are not computed."""

    def __init__(self, bounds: Arr) -> None:
        bounds = np.asarray(bounds)
        lens = bounds[:, 1] - bounds[:, 0]
        self.levels = int(np.ceil(np.log2(max(int(lens.max()), 1))))
        self.K, self.n = len(bounds), max(int(lens.max()), 1)
        pos = np.arange(self.n)[:, None]
        self.real = pos < lens[None, :]  # (n, K): a sample, not padding
        self.src = (bounds[:, 0][None, :] + pos)[self.real]  # their sample indices, (n, K) order

    def product(self, ws: Arr, dt: float) -> Arr:
        """The K rotations from the rates already gathered (``w[src]``)."""
        qr = Rotation.from_rotvec(ws * dt).as_quat()
        x, y, z = (np.zeros((self.n, self.K)) for _ in range(3))
        q = np.ones((self.n, self.K))  # padding: the identity (0, 0, 0, 1)
        for c, plane in enumerate((x, y, z, q)):
            plane[self.real] = qr[:, c]
        for _ in range(self.levels):
            if len(x) % 2:  # the pair of the last row is padding
                x, y, z = (np.vstack([v, np.zeros((1, self.K))]) for v in (x, y, z))
                q = np.vstack([q, np.ones((1, self.K))])
            ax, ay, az, aw = x[0::2], y[0::2], z[0::2], q[0::2]
            bx, by, bz, bw = x[1::2], y[1::2], z[1::2], q[1::2]
            x = aw * bx + bw * ax + (ay * bz - az * by)
            y = aw * by + bw * ay + (az * bx - ax * bz)
            z = aw * bz + bw * az + (ax * by - ay * bx)
            q = aw * bw - (ax * bx + ay * by + az * bz)
        return Rotation.from_quat(np.stack([x[0], y[0], z[0], q[0]], axis=-1)).as_matrix()


SPLIT = "accel_cross_quadratic_split"


def _rot_k(e: str) -> int:
    return 2 if e == SPLIT else 3


def _rotation_problem(gyr_raw: Arr, d: PoseData, up: Arr, bias: Arr, effects: list[str],
                      keep: Arr | None = None, dir_var: Arr | None = None,
                      up_fn: Callable[[Arr], Arr] | None = None) -> tuple[Callable[[Arr], Arr], Arr]:
    """(normalised residual function of the parameters, sigma per motion) for the motions.

    ``bias``: (3,) constant, or (n, 3) per sample (bias + g-sensitivity G f(t) during the motion).
    ``up_fn(delta)``: the poses' gravity directions when the accelerometer's cross-coupling is split
    unevenly between its axes (candidate ``accel_cross_quadratic_split``, 2 parameters: the
    magnitude model sees only the common coefficient, the directions see the split).

    Residual of motion k: up_{k+1} - R_k^T up_k (3 components, 2 independent), scaled by the
    direction uncertainty of both poses (accelerometer noise, the pose's own wander -- a held
    pose turns a little, so its ends differ from its mean -- and the accelerometer model's
    uncertainty) plus the gyro's angle random walk over the motion (white noise measured on the
    longest rest, not in held poses where real motion would count as noise)."""
    dt = 1.0 / d.fs_hz
    iv = d.intervals
    ks = np.arange(len(iv) - 1) if keep is None else np.flatnonzero(keep)
    bounds = np.array([(iv[k][1] - 1, iv[k + 1][0] + 1) for k in ks])
    lo, hi = bounds[:, 0].min(), bounds[:, 1].max()
    b = np.asarray(bias, float)
    w0 = np.asarray(gyr_raw, float)[lo:hi] - (b[lo:hi] if b.ndim == 2 else b)
    bnd = bounds - lo
    g = np.linalg.norm(d.acc, axis=1)
    wander = d.wander if len(d.wander) == len(iv) else np.zeros(len(iv))
    dsig = np.sqrt(d.var_acc.mean(axis=1) / g ** 2 + wander + (0 if dir_var is None else dir_var))
    arw2 = float(np.mean(d.rest_white[3:])) / d.fs_hz  # rad^2/s: the gyro's white noise at rest
    sig = np.sqrt(dsig[ks] ** 2 + dsig[ks + 1] ** 2 + arw2 * (bnd[:, 1] - bnd[:, 0]) * dt)
    u0, u1 = up[ks], up[ks + 1]
    rot = _MotionProduct(bnd)
    w0 = w0[rot.src]  # only the motions' samples (every step below is per sample)

    def resid(p: Arr) -> Arr:
        w = w0 @ _tg(p).T
        a, b0, b1 = 9, u0, u1
        for e in effects:
            th = p[a:a + _rot_k(e)]
            a += _rot_k(e)
            if e in (SPLIT, "accel_cross_quadratic"):
                upd = up_fn(th)  # type: ignore[misc]
                b0, b1 = upd[ks], upd[ks + 1]
            else:
                w = w - (th * np.abs(w) if e == "gyro_scale_asymmetry" else th * w * np.abs(w))
        R = rot.product(w, dt)
        pred = np.einsum("kji,kj->ki", R, b0)
        return ((b1 - pred) / sig[:, None]).reshape(-1)

    return resid, sig


def rotation_residuals_at(gyr_raw: Arr, d: PoseData, up: Arr, bias: Arr, p: Arr, keep: Arr | None = None,
                          dir_var: Arr | None = None) -> Arr:
    """Unnormalised motion residuals (K, 3) at fixed parameters (e.g. nominal: no calibration)."""
    f, sig = _rotation_problem(gyr_raw, d, up, bias, [], keep, dir_var)
    return f(np.asarray(p, float)).reshape(-1, 3) * sig[:, None]


def fit_rotations(gyr_raw: Arr, d: PoseData, up: Arr, bias: Arr, effects: list[str],
                  keep: Arr | None = None, dir_var: Arr | None = None,
                  up_fn: Callable[[Arr], Arr] | None = None) -> Fit:
    """Gyro scale/misalignment (+ candidates) from the motions between poses (module doc);
    ``keep``: (P-1,) bool, the motions to use (clipped ones excluded)."""
    resid, sig = _rotation_problem(gyr_raw, d, up, bias, effects, keep, dir_var, up_fn)
    K = len(sig)
    ne = sum(_rot_k(e) for e in effects)
    p0 = np.concatenate([np.zeros(6), np.ones(3), np.zeros(ne)])
    sol = scipy.optimize.least_squares(resid, p0, x_scale=np.concatenate([np.full(6, 1e-2), np.full(3, 1e-2),
                                                                          np.full(ne, 1e-3)]), method="trf")
    J = sol.jac
    cov = np.linalg.pinv(J.T @ J)
    names = ["gyro_misalign_yz_rad", "gyro_misalign_zy_rad", "gyro_misalign_xz_rad", "gyro_misalign_zx_rad",
             "gyro_misalign_xy_rad", "gyro_misalign_yx_rad"] + [f"gyro_scale_{a}_ratio" for a in AX] + \
        [f"{e}_{a}_{ROTATION_CANDIDATES.get(e, 's2_per_m')}" for e in effects for a in (AX if e != SPLIT else "xy")]
    r = sol.fun
    return Fit(names, sol.x, cov, float(r @ r), 2 * K - 9 - ne, r, J, np.repeat(np.arange(K), 3),
               extra={"sigma_rad": sig, "n_motions": K, "resid": r.reshape(-1, 3) * sig[:, None]})


def rotation_candidates(n_motions: int, peak_rate: float) -> list[Candidate]:
    """Rotation candidates: testable with >= 3 spare dof and motions faster than 0.5 rad/s."""
    out = []
    for name in ROTATION_CANDIDATES:
        c = Candidate(name, 3)
        if 2 * n_motions - 12 < 3:
            c.testable, c.why = False, f"{n_motions} motions leave {2 * n_motions - 12} dof"
        elif peak_rate < 0.5:
            c.testable, c.why = False, f"peak rate {peak_rate:.2g} rad/s: too slow to show a rate-dependent scale"
        out.append(c)
    return out


# ------------------------------------------------------------------------------ six faces
FACE_CANDIDATES = {"accel_quadratic": "s2_per_m", "accel_bias_time_drift": "m_s2_per_h"}


def face_candidates(d: PoseData) -> list[Candidate]:
    """Six-face candidates (quadratic, time drift); temperature and asymmetry need more poses."""
    out = [Candidate("accel_quadratic", 3), Candidate("accel_bias_time_drift", 3)]
    if np.ptp(d.t_s) < 60:
        out[1].testable, out[1].why = False, f"poses span {np.ptp(d.t_s):.3g} s"
    if 3 * len(d.acc) - 12 - 3 < 3:
        for c in out:
            c.testable, c.why = False, f"{len(d.acc)} faces leave {3 * len(d.acc) - 15} dof"
    return out


def fit_faces(d: PoseData, ref: Arr, effects: list[str]) -> Fit:
    """Six-face linear fit f_p = b + M a_p (+ candidates), a_p = +-g along the labelled axis
    (Ferraris): rows axis-major, 12 parameters, 3P observations."""
    P = len(ref)
    cols, names = [], []
    for i in range(3):
        blk = np.zeros((P, 4))
        blk[:, 0] = 1.0
        blk[:, 1:] = ref
        c = np.zeros((3 * P, 4))
        c[i * P:(i + 1) * P] = blk
        cols.append(c)
        names += [f"accel_bias_{AX[i]}_m_s2"] + [f"accel_M_{AX[i]}{AX[j]}_ratio" for j in range(3)]
    for e in effects:
        x = ref ** 2 if e == "accel_quadratic" else np.repeat(((d.t_s - d.t_ref) / 3600)[:, None], 3, 1)
        for i in range(3):
            c = np.zeros(3 * P)
            c[i * P:(i + 1) * P] = x[:, i]
            cols.append(c[:, None])
            names.append(f"{e}_{AX[i]}_{FACE_CANDIDATES[e]}")
    X = np.hstack(cols)
    y = d.acc.T.reshape(-1)
    s = np.sqrt(d.var_acc.T.reshape(-1))
    Xw, yw = X / s[:, None], y / s
    beta, *_ = np.linalg.lstsq(Xw, yw, rcond=None)
    r = yw - Xw @ beta
    return Fit(names, beta, np.linalg.pinv(Xw.T @ Xw), float(r @ r), 3 * P - X.shape[1], r, Xw,
               np.tile(np.arange(P), 3), extra={"resid": y - X @ beta})


def clipped_motions(gyr: Arr, intervals: list[tuple[int, int]], rel: float = 0.005, min_hits: int = 2
                    ) -> tuple[Arr, int]:
    """Motions during which the gyro hit its range: samples equal to a channel's extreme value,
    that value hit at least ``min_hits`` times and within ``rel`` of the largest |rate| of any
    channel (the rail is the same on every axis). Returns ((P-1,) bool clipped, samples)."""
    g = np.asarray(gyr, float)
    top = np.max(np.abs(g))
    mask = np.zeros(len(g), bool)
    for c in range(g.shape[1]):
        for v in (g[:, c].max(), g[:, c].min()):
            hit = g[:, c] == v
            if hit.sum() >= min_hits and abs(v) >= (1 - rel) * top:
                mask |= hit
    out = np.array([mask[intervals[k][1]:intervals[k + 1][0]].any() for k in range(len(intervals) - 1)])
    return out, int(mask.sum())


def stationarity(x: Arr, intervals: list[tuple[int, int]], white_var: Arr) -> tuple[Arr, Arr]:
    """Half-split test of each pose: z = (mean of first half - mean of second half) / its white
    standard error; per channel chi2 = sum_p z^2 ~ chi2(P) for static poses. Returns (chi2/P, p)."""
    z = []
    for s, e in intervals:
        m = (s + e) // 2
        z.append((x[s:m].mean(axis=0) - x[m:e].mean(axis=0)) / np.sqrt(white_var * (1 / (m - s) + 1 / (e - m))))
    c = np.sum(np.array(z) ** 2, axis=0)
    P = len(intervals)
    return c / P, _dist.chi2.sf(c, P)


def cross_split_up(fit: Fit, effects: list[str], u: Arr, data: Any) -> Callable[[Arr], Arr]:
    """up(delta): pose gravity directions with the cross-coupling split (c + dx, c + dy,
    c - dx - dy) instead of the common c the magnitude model fitted, or with per-axis
    coefficients (3 values) when it fitted none (s^2/m)."""
    p = fit.values
    M = _tk(p[0:3], p[3:6])
    v0 = u - p[6:9]
    base = (v0 - accel_correction(_accel_split(p, effects), v0, data)) @ M.T
    B = np.stack([v0[:, 1] * v0[:, 2], v0[:, 0] * v0[:, 2], v0[:, 0] * v0[:, 1]], axis=1)

    def up(delta: Arr) -> Arr:
        # 2 values: the split of a claimed common coefficient; 3: per-axis coefficients seen only
        # through the directions (the magnitude model did not claim the effect)
        dd = np.array([delta[0], delta[1], -delta[0] - delta[1]]) if len(delta) == 2 else np.asarray(delta)
        a = base - (B * dd) @ M.T
        return a / np.linalg.norm(a, axis=1)[:, None]

    return up
