"""Thermal calibration: each error parameter as a polynomial in temperature, with covariance,
and the closed loop over thermal candidates. Pure functions of arrays (no I/O).

Model of one sensor (accelerometer or gyro), sensor axis i, for a window n whose reference input
(specific force or rate, body axes) is u_n and whose IMU temperature runs through T(t)::

    y_i = sum_j <dT^j> b_ij + sum_k sum_j <dT^j> u_k M_ikj + k2_i <u_i^2> + sum_c gamma_ic <X_c>

dT = T - T_ref, <.> the mean over the window's samples (so a temperature changing inside the
window enters exactly, not through its mean), j = 0..degree of the group (bias, scale = the
diagonal k = i, misalignment = k != i), k2 the accelerometer's quadratic term (constant), X_c
the regressors of the thermal candidates the loop accepted:

* ``hysteresis``: H(t) in [-1, 1], a play operator of width ``hysteresis_width_K`` on the IMU
  temperature normalised to its half-width (+1 after heating, -1 after cooling) -- a bias that
  differs between the heating and cooling halves at the same temperature;
* ``temperature_rate``: dT/dt, K/s (a bias proportional to how fast the unit heats or cools);
* ``thermal_gradient``: chamber air minus IMU temperature, K (a gradient across the unit).

**Noise of the window means.** Over a one-hour ramp the bias instability (flicker) and the
rate random walk make the window means' errors correlated: the bias wanders while the
temperature moves. Each axis is fitted by generalised least squares with the covariance Sigma of
its window means under the IEEE 952 model (white + bias instability + rate random walk,
:mod:`rigctl.solvers.segment_cov`, the same kernels as the pose calibration), factored once
(Sigma = L L^T, :class:`~rigctl.solvers.segment_cov.Whitener`); parameter covariance
(A^T Sigma^-1 A)^-1, chi2 = r^T Sigma^-1 r, 95 % intervals from Student's t with the fit's degrees
of freedom. Sigma comes from given IEEE 952 coefficients (``rigctl allan`` of the same unit) or
is estimated from the session by REML (:func:`estimate_noise`,
:func:`rigctl.solvers.segment_noise.estimate_channel_noise`): the batch-mean contrasts within
each window that are free of a straight line in time (a window in a ramp drifts along its
thermal coefficients), plus the window means about a *protected* design -- the highest
polynomial degrees, every thermal candidate and an offset per window kind -- so that neither a
thermal effect nor the loop's candidates can be absorbed into the noise terms. Without window
times the means are independent with standard uncertainties ``sigma`` (weighted least squares).
The ramp method's balance: every window counts once whichever half of the cycle it was taken
in, and the fit reports how many windows each half gave and the temperature span each covered.

**One orientation.** When every window has the same reference input (a static record on a
bench: a warm-up, a record in a climatic chamber without a table), the scale and misalignment
columns are proportional to the bias columns and only the sum b(T) + M(T) u is identified.
:func:`fit_thermal` then refuses the full model (ValueError naming the restriction) and is called
with the scale and misalignment groups *held* (degree :data:`HELD`, e.g. :data:`BIAS_ONLY`): M
stays the identity, the model is y_i - u_i = sum_j <dT^j> b_ij [+ effects], and the "bias"
coefficients are the apparent ones -- the unit's bias plus, on an axis along gravity, the scale
factor's temperature dependence times g (:func:`one_orientation`).

**Several static poses without a table.** A bench record held still in a few orientations (an
animal tag in a fridge, a board turned by hand between soaks) has a different reference input
per pose but no table to say exactly what it is, and a gyro whose bias depends on the specific
force (g-sensitivity) and sees the earth's rate along a different axis in each. With
``ThermalWindows.pose`` (a label per window) every pose after the first gets its own constant
per axis (``<sensor>_pose<k>_<axis>_<unit>``, relative to pose 1): what a static pose adds as a
constant -- (M0 - I) u of the pose, the g-sensitive bias, the earth rate, a tilt the reference
misses -- goes there, so the constant terms of scale and misalignment (j = 0) and the
accelerometer's quadratic term (constant in a pose) are not fitted, the temperature
coefficients (j >= 1) are. With three poses that each put one axis along gravity (no pose
upside down), scale per K is identifiable (the pose with the axis vertical against the others),
misalignment per K is not (it needs more poses than bias and scale leave): hold it.

The loop (forward selection): each candidate not yet in the model is added to all three axes of
the sensor; F = (dChi2 / 3) / (Chi2_ext / dof_ext); p from F(3, dof_ext), Bonferroni-adjusted over
the candidates still open; the smallest p_adj below ``alpha`` is accepted and the search repeats.
The chi-square of the final fit is reported with its two-sided 99 % band; outside it is a finding
(the status says so), never hidden by inflating the covariance.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import distributions as stats
from . import segment_noise as sn
from .segment_cov import Whitener
from .sensor_model import invert_quadratic

AXES = "xyz"
CANDIDATES = ("hysteresis", "temperature_rate", "thermal_gradient")
CANDIDATE_TEXT = {"hysteresis": "thermal hysteresis (heating and cooling differ)",
                  "temperature_rate": "dependence on the temperature rate",
                  "thermal_gradient": "thermal gradient (chamber air minus IMU temperature)"}
UNIT = {"accel": "m_s2", "gyro": "rad_s"}
#: the degree of a group that is not fitted: scale held at 1, misalignment at 0 (M = identity)
HELD = -1
#: degrees for a record with one orientation: only the bias terms are identifiable
BIAS_ONLY = {"scale": HELD, "misalignment": HELD}


@dataclass
class ThermalWindows:
    """The windows of one sensor (n windows).

    y, sigma: (n, 3) mean outputs and the standard uncertainty of each mean (SI);
    ref: (n, 3) mean reference input (m/s^2 or rad/s, body axes);
    powers: (n, D + 1) <dT^j>, j = 0..D (dT in K from ``reference_c``);
    temperature: (n,) mean IMU temperature, degC; heating: (n,) bool (heating half of the cycle);
    quad: (n, 3) <u_i^2> (accelerometer quadratic term) or None;
    regressors: {candidate: (n,)} window means of the candidates' regressors.

    For correlated noise (module docstring): t_start, t_end (n,) the windows' times (s, the
    clock of the recording, power-on at ``t0``), kind (n,) "orientation" / "rate", revolutions
    (n,) 0 for static, R for R whole turns, else None, batch (n, B, 3) the batch means of each
    window's samples about the reference; ``cov`` (3, n, n) the covariance of the means per axis
    (set by :func:`estimate_noise`), ``noise`` the per-axis noise models behind it.
    """

    sensor: str
    y: np.ndarray
    sigma: np.ndarray
    ref: np.ndarray
    powers: np.ndarray
    temperature: np.ndarray
    heating: np.ndarray
    reference_c: float
    quad: np.ndarray | None = None
    regressors: dict[str, np.ndarray] = field(default_factory=dict)
    t_start: np.ndarray | None = None
    t_end: np.ndarray | None = None
    kind: np.ndarray | None = None
    revolutions: list[float | None] | None = None
    batch: np.ndarray | None = None
    t0: float = 0.0
    cov: np.ndarray | None = None
    noise: list[Any] | None = None
    #: (n,) a pose label per window (several static poses without a table, module docstring)
    pose: np.ndarray | None = None
    #: (n, 2) each window's first and end (exclusive) sample index in the record, where the
    #: windows were cut from one series of samples (a static record), else None
    rows: np.ndarray | None = None
    _white: dict[int, Whitener] = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return int(self.y.shape[0])

    def poses(self) -> list[str]:
        """The pose labels in order of first appearance when there are two or more (each after
        the first gets an offset per axis), else []."""
        if self.pose is None:
            return []
        labels = [str(p) for p in np.asarray(self.pose)]
        out = list(dict.fromkeys(labels))
        return out if len(out) > 1 else []

    def whitener(self, axis: int) -> Whitener:
        """The factored covariance of axis' window means (cached: the loop refits many times)."""
        if axis not in self._white:
            self._white[axis] = (Whitener(sigma=self.sigma[:, axis]) if self.cov is None
                                 else Whitener(cov=self.cov[axis]))
        return self._white[axis]

    def set_cov(self, cov: np.ndarray | None) -> None:
        """Use the covariance cov (3, n, n) of the window means (None: independent, ``sigma``)."""
        self.cov = None if cov is None else np.asarray(cov, float)
        if self.cov is not None:
            self.sigma = np.sqrt(np.stack([np.diag(c) for c in self.cov], axis=1))
        self._white = {}


@dataclass
class AxisFit:
    names: list[str]
    values: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    residuals: np.ndarray  # (n,) y - model, SI


@dataclass
class ThermalFit:
    """One sensor's thermal model."""

    sensor: str
    degrees: dict[str, int]
    accepted: list[str]
    axes: list[AxisFit]
    explain: list[dict[str, Any]]
    reference_c: float
    alpha: float = 1e-3
    #: for each accepted candidate, the others that were significant when it was accepted and
    #: explain it away (it adds nothing significant to a model holding one of them instead):
    #: this run cannot tell them apart (:func:`fit_thermal`)
    confounded: dict[str, list[str]] = field(default_factory=dict)
    #: the pose labels when the windows have several (``<sensor>_pose<k>_...`` is the offset of
    #: poses[k - 1] against poses[0])
    poses: list[str] = field(default_factory=list)

    @property
    def chi2(self) -> float:
        return float(sum(a.chi2 for a in self.axes))

    @property
    def dof(self) -> int:
        return int(sum(a.dof for a in self.axes))

    def band(self, level: float = 0.99) -> tuple[float, float]:
        """Two-sided band of chi2/dof at ``level`` for this fit's dof."""
        lo, hi = stats.chi2.ppf([(1 - level) / 2, (1 + level) / 2], self.dof)
        return float(lo / self.dof), float(hi / self.dof)

    def parameters(self) -> list[dict[str, Any]]:
        """Every coefficient with its standard uncertainty and 95 % interval (SI)."""
        out = []
        for a in self.axes:
            t = float(stats.t.ppf(0.975, max(a.dof, 1)))
            for i, name in enumerate(a.names):
                v, u = float(a.values[i]), float(np.sqrt(max(a.cov[i, i], 0.0)))
                out.append({"name": name, "value": v, "sigma": u, "ci95": [v - t * u, v + t * u]})
        return out


def _quad(w: ThermalWindows, degrees: dict[str, int]) -> bool:
    """The accelerometer's quadratic term is fitted with the scale factor (not when it is held,
    nor with pose offsets: it is a constant of each pose)."""
    return w.quad is not None and degrees["scale"] > HELD and not w.poses()


def _first_power(w: ThermalWindows) -> int:
    """The lowest power of dT of the scale and misalignment columns: 1 with pose offsets (the
    constant M0 u of a static pose is in its offset), else 0."""
    return 1 if w.poses() else 0


def one_orientation(ref: np.ndarray, rtol: float = 1e-6) -> bool:
    """True when every window has the same reference input (n, 3): scale and misalignment are
    then not separable from the bias (module docstring)."""
    ref = np.asarray(ref, float)
    return bool(np.max(np.ptp(ref, axis=0)) <= rtol * max(1.0, float(np.max(np.abs(ref)))))


def check_identifiable(w: ThermalWindows, degrees: dict[str, int]) -> None:
    """ValueError when the degrees ask for scale or misalignment terms that the windows' reference
    inputs cannot separate from the bias (one orientation): fit with :data:`BIAS_ONLY`."""
    if len(w) and one_orientation(w.ref) and (degrees["scale"] > HELD or degrees["misalignment"] > HELD):
        raise ValueError(f"{w.sensor}: every window has the same reference input (one orientation): only the "
                         "bias terms are identifiable (they absorb M(T) u) -- fit with the scale and "
                         "misalignment held, degrees {'scale': -1, 'misalignment': -1}")


def param_names(sensor: str, axis: int, degrees: dict[str, int], quad: bool,
                accepted: list[str], n_poses: int = 0, first: int = 0) -> list[str]:
    """Names of one axis' coefficients, in the column order of :func:`design` (a group of degree
    :data:`HELD` has none; ``n_poses`` >= 2: an offset for each pose after the first, and the
    scale and misalignment powers from ``first``)."""
    a, u = AXES[axis], UNIT[sensor]
    names = []
    for j in range(degrees["bias"] + 1):
        names.append(f"{sensor}_bias_{a}_{u}" + ("" if j == 0 else "_per_K" if j == 1 else f"_per_K{j}"))
    for k in range(3):
        b = AXES[k]
        deg = degrees["scale"] if k == axis else degrees["misalignment"]
        for j in range(first, deg + 1):
            if j == 0:
                names.append(f"{sensor}_M_{a}{b}_ratio")
            elif k == axis:
                names.append(f"{sensor}_scale_{a}_per_K" + ("" if j == 1 else str(j)))
            else:
                names.append(f"{sensor}_misalignment_{a}{b}_rad_per_K" + ("" if j == 1 else str(j)))
    if quad:
        names.append(f"{sensor}_quad_{a}_s2_per_m")
    names += [f"{sensor}_pose{k}_{a}_{u}" for k in range(2, n_poses + 1)]
    for c in accepted:
        names.append({"hysteresis": f"{sensor}_hysteresis_{a}_{u}",
                      "temperature_rate": f"{sensor}_temp_rate_{a}_{u}_per_K_per_s",
                      "thermal_gradient": f"{sensor}_gradient_{a}_{u}_per_K"}[c])
    return names


def design(w: ThermalWindows, axis: int, degrees: dict[str, int], accepted: list[str]) -> np.ndarray:
    """Design matrix (n, p) of one axis (columns as :func:`param_names`)."""
    cols = [w.powers[:, j] for j in range(degrees["bias"] + 1)]
    first = _first_power(w)
    for k in range(3):
        deg = degrees["scale"] if k == axis else degrees["misalignment"]
        cols += [w.powers[:, j] * w.ref[:, k] for j in range(first, deg + 1)]
    if _quad(w, degrees):
        cols.append(w.quad[:, axis])
    labels = np.asarray(w.pose).astype(str) if w.pose is not None else None
    cols += [(labels == p).astype(float) for p in w.poses()[1:]]
    cols += [w.regressors[c] for c in accepted]
    return np.column_stack(cols)


def held_part(w: ThermalWindows, axis: int, degrees: dict[str, int]) -> np.ndarray:
    """(n,) the part of the output the held groups fix: u_i when the scale is held at 1 (the
    misalignment held at 0 adds nothing), or when its constant is in the pose offsets."""
    return w.ref[:, axis] if degrees["scale"] <= HELD or w.poses() else np.zeros(len(w))


def _gls(A: np.ndarray, y: np.ndarray, W: Whitener) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Generalised least squares via QR of the whitened system L^-1 A x = L^-1 y:
    (x, cov, chi2, residuals)."""
    Aw, yw = W.apply(A), W.apply(y)
    scale = np.sqrt(np.sum(Aw * Aw, axis=0))
    scale[scale == 0] = 1.0
    Q, R = np.linalg.qr(Aw / scale)
    if np.min(np.abs(np.diag(R))) < 1e-10 * np.max(np.abs(np.diag(R))):
        raise np.linalg.LinAlgError("thermal fit is rank-deficient: too few windows or temperatures "
                                    "for the polynomial degrees")
    x = np.linalg.solve(R, Q.T @ yw) / scale
    Rinv = np.linalg.inv(R)
    cov = (Rinv @ Rinv.T) / np.outer(scale, scale)
    rw = yw - Aw @ x
    return x, cov, float(rw @ rw), y - A @ x


def fit_axes(w: ThermalWindows, degrees: dict[str, int], accepted: list[str]) -> list[AxisFit]:
    out = []
    for i in range(3):
        A = design(w, i, degrees, accepted)
        x, cov, chi2, r = _gls(A, w.y[:, i] - held_part(w, i, degrees), w.whitener(i))
        out.append(AxisFit(param_names(w.sensor, i, degrees, _quad(w, degrees), accepted, len(w.poses()),
                                       _first_power(w)), x, cov, chi2, len(w) - A.shape[1], r))
    return out


def protected_design(w: ThermalWindows, axis: int) -> np.ndarray:
    """(n, p) design for the noise estimate of one axis: the highest degrees the windows' powers
    allow (misalignment at most 2), every candidate with a regressor, an offset per window kind
    beyond the first (dependent columns are dropped by the estimator)."""
    D = w.powers.shape[1] - 1
    deg = ({"bias": D, **BIAS_ONLY} if one_orientation(w.ref)
           else {"bias": D, "scale": D, "misalignment": min(2, D)})
    cands = [c for c in CANDIDATES if c in w.regressors and np.ptp(w.regressors[c]) > 0]
    X = design(w, axis, deg, cands)
    if w.kind is not None:
        kinds, counts = np.unique(np.asarray(w.kind), return_counts=True)
        extra = [(np.asarray(w.kind) == k).astype(float) for k in kinds[np.argsort(-counts, kind="stable")][1:]]
        if extra:
            X = np.column_stack([X, *extra])
    return X


def estimate_noise(w: ThermalWindows, model: Any = None, tau_min_s: float = 1.0,
                   tau_max_s: float = 1.0e4) -> list[Any]:
    """Set ``w.cov`` from the IEEE 952 noise of each axis and return the three
    :class:`~rigctl.solvers.noise_coefficients.NoiseCoefficients`.

    model: the three axes' :class:`~rigctl.solvers.noise_coefficients.NoiseCoefficients` (given, e.g. from
    ``rigctl allan`` of the same unit) or None: estimated from the session by REML
    (:func:`rigctl.solvers.segment_noise.estimate_channel_noise`) on the windows' batch means
    (contrasts free of a linear drift) and means (about :func:`protected_design`). Needs the
    window times (and ``batch`` for the estimate); without them nothing changes and [] is returned.
    """
    if w.t_start is None or w.t_end is None:
        return []
    a, b = np.asarray(w.t_start, float), np.asarray(w.t_end, float)
    kind = np.asarray(w.kind if w.kind is not None else ["orientation"] * len(w)).astype(str)
    if model is not None:
        models = list(model)
        covs = sn.channel_covs(models, a, b, kind, w.t0)
    else:
        if w.batch is None:
            return []
        revs = list(w.revolutions) if w.revolutions is not None else [0.0 if k == "orientation" else None
                                                                          for k in kind]
        terms = sn.WindowTerms.build(a, b, kind, revs, w.t0, tau_min_s, tau_max_s,
                                     n_batches=w.batch.shape[1], trend=True)
        held = {"scale": HELD} if one_orientation(w.ref) else {"scale": 0}
        models = [sn.estimate_channel_noise(w.y[:, i] - held_part(w, i, held), protected_design(w, i), terms,
                                            w.batch[:, :, i]) for i in range(3)]
        covs = sn.channel_covs(models, a, b, kind, w.t0, flicker=terms.comps[-2], rw=terms.comps[-1])
    w.set_cov(covs)
    w.noise = models
    return models


def fit_thermal(w: ThermalWindows, degrees: dict[str, int] | None = None, loop: bool = True,
                alpha: float = 1e-3) -> ThermalFit:
    """The sensor's thermal model; with ``loop`` the candidates of :data:`CANDIDATES` whose
    regressors are in ``w.regressors`` are tested by forward selection (module docstring).
    ValueError when the windows have one orientation and the degrees ask for scale or
    misalignment terms (:func:`check_identifiable`)."""
    degrees = dict(degrees or {"bias": 2, "scale": 2, "misalignment": 1})
    check_identifiable(w, degrees)
    accepted: list[str] = []
    explain: list[dict[str, Any]] = []
    confounded: dict[str, list[str]] = {}
    base = fit_axes(w, degrees, accepted)
    open_ = [c for c in CANDIDATES if c in w.regressors and np.ptp(w.regressors[c]) > 0] if loop else []
    step = 0
    while open_:
        step += 1
        chi_base = sum(a.chi2 for a in base)
        trials = []
        for c in open_:
            ext = fit_axes(w, degrees, accepted + [c])
            chi_ext, dof_ext = sum(a.chi2 for a in ext), sum(a.dof for a in ext)
            F = ((chi_base - chi_ext) / 3.0) / (chi_ext / dof_ext)
            p = float(stats.f.sf(F, 3, dof_ext))
            trials.append((min(1.0, p * len(open_)), c, F, ext))
        trials.sort(key=lambda x: x[0])
        for p_adj, c, F, _ in trials:
            explain.append({"step": step, "sensor": w.sensor, "candidate": c, "statistic": f"F(3) = {F:.3g}",
                            "p_adj": p_adj, "decision": "accepted" if (p_adj < alpha and c == trials[0][1])
                            else "rejected"})
        p_adj, c, _, ext = trials[0]
        if p_adj >= alpha:
            break
        # in a ramp at one rate the hysteresis state, the temperature rate and the air-minus-IMU
        # gradient all change sign between heating and cooling (only the holds separate them):
        # a runner-up that was significant too, and with which c adds nothing significant, is
        # an alternative this run cannot rule out
        confounded[c] = []
        for p_o, o, _, ext_o in trials[1:]:
            if p_o >= alpha:
                continue
            both = fit_axes(w, degrees, accepted + [o, c])
            chi_o, chi_b, dof_b = sum(a.chi2 for a in ext_o), sum(a.chi2 for a in both), sum(a.dof for a in both)
            if float(stats.f.sf(((chi_o - chi_b) / 3.0) / (chi_b / dof_b), 3, dof_b)) >= alpha:
                confounded[c].append(o)
        accepted.append(c)
        open_.remove(c)
        base = ext
    return ThermalFit(w.sensor, degrees, accepted, base, explain, w.reference_c, alpha, confounded, w.poses())


def select_degrees(w: ThermalWindows, max_degree: int = 3, alpha: float = 0.01) -> dict[str, int]:
    """Polynomial degrees chosen from the data: starting from (bias 1, scale 1, misalignment 1),
    raise the degree of a group while the F test of its new coefficients (3 axes) is significant
    at ``alpha`` (Bonferroni over the groups), up to ``max_degree``. With one orientation the
    scale and misalignment stay held (:data:`BIAS_ONLY`) and only the bias degree is chosen."""
    deg = {"bias": 1, **BIAS_ONLY} if one_orientation(w.ref) else {"bias": 1, "scale": 1, "misalignment": 1}
    n_pow = w.powers.shape[1] - 1
    while True:
        base = fit_axes(w, deg, [])
        chi_b = sum(a.chi2 for a in base)
        best = None
        for g in deg:
            if deg[g] <= HELD or deg[g] >= min(max_degree, n_pow):
                continue
            trial = dict(deg, **{g: deg[g] + 1})
            try:
                ext = fit_axes(w, trial, [])
            except np.linalg.LinAlgError:
                continue
            q = sum(len(e.names) for e in ext) - sum(len(b.names) for b in base)
            chi_e, dof_e = sum(a.chi2 for a in ext), sum(a.dof for a in ext)
            p = float(stats.f.sf(((chi_b - chi_e) / q) / (chi_e / dof_e), q, dof_e)) * len(deg)
            if p < alpha and (best is None or p < best[0]):
                best = (p, trial)
        if best is None:
            return deg
        deg = best[1]


def evaluate(params: dict[str, float], sensor: str, T: np.ndarray, reference_c: float) -> dict[str, np.ndarray]:
    """Bias (n, 3) and matrix M (n, 3, 3) of a fitted model at temperatures T (degC)."""
    dT = np.asarray(T, float) - reference_c
    n, u = dT.size, UNIT[sensor]
    bias = np.zeros((n, 3))
    M = np.zeros((n, 3, 3))
    for i, a in enumerate(AXES):
        for j in range(6):
            key = f"{sensor}_bias_{a}_{u}" + ("" if j == 0 else "_per_K" if j == 1 else f"_per_K{j}")
            if key in params:
                bias[:, i] += params[key] * dT**j
        for k, b in enumerate(AXES):
            M[:, i, k] += params.get(f"{sensor}_M_{a}{b}_ratio", float(i == k))
            for j in range(1, 6):
                key = (f"{sensor}_scale_{a}_per_K" if i == k else f"{sensor}_misalignment_{a}{b}_rad_per_K") \
                    + ("" if j == 1 else str(j))
                if key in params:
                    M[:, i, k] += params[key] * dT**j
    return {"bias": bias, "M": M}


def play_operator(T: np.ndarray, width_K: float, start: float | None = None) -> np.ndarray:
    """H in [-1, 1]: the play (backlash) operator of width ``width_K`` on the sequence T,
    normalised to its half-width (+1 while heating, -1 while cooling, memory in between)."""
    half = width_K / 2.0
    T = np.asarray(T, float)
    out = np.empty(T.size)
    p = float(T[0]) if start is None else start
    for i, x in enumerate(T):
        p = min(max(p, x - half), x + half)
        out[i] = (x - p) / half
    return out


def power_means(T: np.ndarray, bounds: np.ndarray, reference_c: float, degree: int) -> np.ndarray:
    """<dT^j> per window for j = 0..degree; windows are [a, z) row ranges of T."""
    dT = np.asarray(T, float) - reference_c
    out = np.empty((len(bounds), degree + 1))
    for n, (a, z) in enumerate(bounds):
        seg = dT[a:z]
        for j in range(degree + 1):
            out[n, j] = np.mean(seg**j)
    return out


def regressors_along(T: np.ndarray, t: np.ndarray, accepted: list[str], hysteresis_width_K: float,
                     air: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per-sample regressors of the accepted effects along a record (temperature T degC at times
    t s): the hysteresis state (play operator on T at about 1 Hz), the temperature rate (slope
    over a 10 s moving window, K/s) and the gradient (``air`` - T; zeros without ``air``)."""
    out: dict[str, np.ndarray] = {}
    if "hysteresis" in accepted:
        dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
        step = max(1, int(round(1.0 / dt)))
        Hs = play_operator(T[::step], hysteresis_width_K)
        out["hysteresis"] = np.interp(np.arange(T.size), np.arange(0, T.size, step)[: Hs.size], Hs)
    if "temperature_rate" in accepted:
        dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
        k = max(1, int(round(5.0 / dt)))
        lo, hi = np.clip(np.arange(T.size) - k, 0, T.size - 1), np.clip(np.arange(T.size) + k, 0, T.size - 1)
        span = t[hi] - t[lo]
        out["temperature_rate"] = np.where(span > 0, (T[hi] - T[lo]) / np.where(span > 0, span, 1.0), 0.0)
    if "thermal_gradient" in accepted:
        out["thermal_gradient"] = (air - T) if air is not None else np.zeros(T.size)
    return out


def correct(sensor: str, y: np.ndarray, T: np.ndarray, params: dict[str, float], reference_c: float,
            regressors: dict[str, np.ndarray] | None = None, max_iter: int = 20) -> np.ndarray:
    """Invert a fitted thermal model sample by sample: the true input u (n, 3) from the measured
    y (n, 3) at temperatures T (n,): y = b(T) + M(T) u [+ k2 o u^2] + effects (Newton's method
    with the per-sample M when k2 is present: :func:`rigctl.solvers.sensor_model.invert_quadratic`)."""
    m = evaluate(params, sensor, T, reference_c)
    b, M = m["bias"], m["M"]
    u_name = UNIT[sensor]
    for c, x in (regressors or {}).items():
        key = {"hysteresis": "{s}_hysteresis_{a}_{u}", "temperature_rate": "{s}_temp_rate_{a}_{u}_per_K_per_s",
               "thermal_gradient": "{s}_gradient_{a}_{u}_per_K"}[c]
        coef = np.array([params.get(key.format(s=sensor, a=a, u=u_name), 0.0) for a in AXES])
        b = b + np.asarray(x, float)[:, None] * coef
    k2 = np.array([params.get(f"{sensor}_quad_{a}_s2_per_m", 0.0) for a in AXES])
    return invert_quadratic(y, b, M, k2, max_iter)
