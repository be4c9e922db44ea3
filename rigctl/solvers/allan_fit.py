"""IEEE Std 952 noise terms from an Allan deviation curve: joint weighted least squares.

Model (IEEE Std 952-1997 annex C; rate units u, e.g. rad/s or m/s^2)::

    sigma^2(tau) = 3 Q^2 / tau^2 + N^2 / tau + (2 ln2 / pi) B^2 + K^2 tau / 3 + R^2 tau^2 / 2

Q quantization (u s), N angle/velocity random walk (u sqrt(s)), B bias instability (u),
K rate/acceleration random walk (u / sqrt(s)), R rate ramp (u / s).

The model is linear in p = (Q^2, N^2, B^2, K^2, R^2). All taus are fitted at once with
non-negative least squares (scipy.optimize.nnls), weighted by the inverse variance of each
AVAR estimate, var(sigma^2) ~= 2 sigma^4 / edf (chi-square with edf degrees of freedom), with
sigma^2 taken from the model (iteratively reweighted, so low estimates get no extra weight).
The covariance (A^T W A)^-1 is inflated by the reduced chi-square when > 1 and by the number
of taus per octave (overlapping AVAR estimates within an octave are strongly correlated, so
only about one per octave is independent). A term whose 95 % lower bound reaches zero is
reported as a one-sided 95 % upper bound instead of a value.

For comparison the classic piecewise read-offs (slope -1 below 0.5 s -> Q at tau = sqrt(3),
slope -1/2 between 0.5 s and 2 s -> N at tau = 1 s, flat minimum above 20 s -> B = min/0.664,
slope +1/2 above the minimum -> K at tau = 3 s) are reported beside it.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import nnls
from scipy.stats import norm

TERMS = ("Q", "N", "B", "K", "R")
_B_FACTOR = 2.0 * math.log(2.0) / math.pi
G0 = 9.80665  # m/s^2, standard gravity (for mg)
_DEG = 180.0 / math.pi

#: (field unit label, factor from SI) per sensor and term; SI: gyro rad/s, accel m/s^2
FIELD_UNITS = {
    "gyro": {"Q": ("deg", _DEG), "N": ("deg/sqrt(h)", _DEG * 60.0),
             "B": ("deg/h", _DEG * 3600.0), "K": ("deg/h/sqrt(h)", _DEG * 3600.0 * 60.0),
             "R": ("deg/h/h", _DEG * 3600.0 ** 2)},
    "accel": {"Q": ("m/s", 1.0), "N": ("m/s/sqrt(h)", 60.0),
              "B": ("mg", 1000.0 / G0), "K": ("m/s/h/sqrt(h)", 3600.0 * 60.0),
              "R": ("m/s/h/h", 3600.0 ** 2)},
}
SI_UNITS = {"gyro": {"Q": "rad", "N": "rad/sqrt(s)", "B": "rad/s", "K": "rad/s/sqrt(s)",
                     "R": "rad/s^2"},
            "accel": {"Q": "m/s", "N": "m/s/sqrt(s)", "B": "m/s^2", "K": "m/s^2/sqrt(s)",
                      "R": "m/s^3"}}
TERM_NAMES = {"gyro": {"Q": "angle_quantization", "N": "angle_random_walk",
                       "B": "bias_instability", "K": "rate_random_walk", "R": "rate_ramp"},
              "accel": {"Q": "velocity_quantization", "N": "velocity_random_walk",
                        "B": "bias_instability", "K": "acceleration_random_walk",
                        "R": "acceleration_ramp"}}


def design_matrix(tau: np.ndarray) -> np.ndarray:
    """Columns d sigma^2 / d p for p = (Q^2, N^2, B^2, K^2, R^2)."""
    tau = np.asarray(tau, dtype=float)
    return np.column_stack((3.0 / tau ** 2, 1.0 / tau, np.full(tau.shape, _B_FACTOR),
                            tau / 3.0, tau ** 2 / 2.0))


def model_avar(tau: np.ndarray, coeffs: dict[str, float]) -> np.ndarray:
    """sigma^2(tau) of the IEEE 952 model from SI coefficients {Q, N, B, K, R}."""
    p = np.array([coeffs.get(t, 0.0) ** 2 for t in TERMS])
    return design_matrix(tau) @ p


def _nnls_weighted(a: np.ndarray, s2: np.ndarray, w: np.ndarray) -> np.ndarray:
    sw = np.sqrt(w)
    scale = np.linalg.norm(a * sw[:, None], axis=0)
    scale[scale == 0] = 1.0
    p, _ = nnls(a * sw[:, None] / scale, s2 * sw)
    return p / scale


def fit_terms(tau: np.ndarray, adev: np.ndarray, edf: np.ndarray, sensor: str = "gyro",
              terms: tuple[str, ...] = TERMS, iterations: int = 6) -> dict:
    """Joint EDF-weighted NNLS fit of the IEEE 952 terms. See the module docstring.

    tau in s, adev in SI rate units, edf per tau. Returns per-term dicts with SI and field
    values (unit in the key), 68 % / 95 % intervals or a 95 % upper bound.
    """
    tau = np.asarray(tau, dtype=float)
    s2 = np.asarray(adev, dtype=float) ** 2
    e = np.asarray(edf, dtype=float)
    ok = np.isfinite(s2) & np.isfinite(e) & (e > 0) & (s2 > 0)
    tau, s2, e = tau[ok], s2[ok], e[ok]
    if tau.size < 2:
        raise ValueError("need at least two finite Allan variance points to fit")
    cols = [TERMS.index(t) for t in terms]
    a = design_matrix(tau)[:, cols]
    w = e / (2.0 * s2 ** 2)
    p = _nnls_weighted(a, s2, w)
    for _ in range(iterations):
        mod = np.maximum(a @ p, 1e-300)
        w = e / (2.0 * mod ** 2)
        p = _nnls_weighted(a, s2, w)
    mod = a @ p
    resid = (s2 - mod) * np.sqrt(w)
    dof = max(1, tau.size - int(np.count_nonzero(p)))
    chi2_red = float(resid @ resid) / dof
    octaves = max(1.0, math.log2(tau.max() / tau.min()))
    per_octave = max(1.0, tau.size / octaves)
    fisher = (a * w[:, None]).T @ a
    cov = np.linalg.pinv(fisher) * max(1.0, chi2_red) * per_octave
    z68, z95, z95_one = norm.ppf(0.8415), norm.ppf(0.975), norm.ppf(0.95)
    out_terms: dict[str, dict] = {}
    for j, t in enumerate(terms):
        sd = math.sqrt(max(cov[j, j], 0.0))
        unit_f, fac = FIELD_UNITS[sensor][t]
        unit_si = SI_UNITS[sensor][t]
        entry: dict = {"name": TERM_NAMES[sensor][t]}
        if p[j] - z95 * sd > 0:
            val = math.sqrt(p[j])
            lo68, hi68 = math.sqrt(max(p[j] - z68 * sd, 0.0)), math.sqrt(p[j] + z68 * sd)
            lo95, hi95 = math.sqrt(max(p[j] - z95 * sd, 0.0)), math.sqrt(p[j] + z95 * sd)
            entry.update({"supported": True,
                          f"value_{unit_si}": val, f"value_{unit_f}": val * fac,
                          f"ci68_{unit_si}": [lo68, hi68],
                          f"ci68_{unit_f}": [lo68 * fac, hi68 * fac],
                          f"ci95_{unit_si}": [lo95, hi95],
                          f"ci95_{unit_f}": [lo95 * fac, hi95 * fac]})
        else:
            ub = math.sqrt(max(p[j], 0.0) + z95_one * sd)
            entry.update({"supported": False, f"upper95_{unit_si}": ub,
                          f"upper95_{unit_f}": ub * fac,
                          f"estimate_{unit_si}": math.sqrt(max(p[j], 0.0))})
        out_terms[t] = entry
    return {"method": "joint EDF-weighted NNLS (IEEE 952 model)", "sensor": sensor,
            "terms": out_terms, "coeff_sq_si": dict(zip(terms, p.tolist())),
            "reduced_chi2": chi2_red, "taus_per_octave": per_octave, "n_taus": int(tau.size)}


def term_value_si(fit: dict, term: str) -> float:
    """Point value (SI) of a fitted term; the estimate for an upper-bounded term."""
    return math.sqrt(max(fit["coeff_sq_si"].get(term, 0.0), 0.0))


def piecewise_readoffs(tau: np.ndarray, adev: np.ndarray, sensor: str = "gyro") -> dict:
    """The paper's hand-ranged read-offs (SI and field units; None where no points)."""
    tau = np.asarray(tau, dtype=float)
    sig = np.asarray(adev, dtype=float)

    def gmean(v: np.ndarray) -> float | None:
        v = v[np.isfinite(v) & (v > 0)]
        return float(np.exp(np.mean(np.log(v)))) if v.size else None

    sel_q = tau < 0.5
    sel_n = (tau >= 0.5) & (tau <= 2.0)
    vals: dict[str, float | None] = {
        "Q": gmean(sig[sel_q] * tau[sel_q] / math.sqrt(3.0)),
        "N": gmean(sig[sel_n] * np.sqrt(tau[sel_n])),
        "B": None, "K": None, "R": None}
    flat = tau >= 20.0
    if np.any(flat):
        i = int(np.argmin(np.where(flat, sig, np.inf)))
        vals["B"] = float(sig[i] / 0.664)
        sel_k = tau >= 4.0 * tau[i]
        vals["K"] = gmean(sig[sel_k] * np.sqrt(3.0 / tau[sel_k]))
    out = {}
    for t, v in vals.items():
        unit_f, fac = FIELD_UNITS[sensor][t]
        out[t] = {f"value_{SI_UNITS[sensor][t]}": v,
                  f"value_{unit_f}": None if v is None else v * fac}
    return {"method": "piecewise read-offs (slope -1 < 0.5 s, -1/2 in 0.5-2 s, "
                      "min/0.664 above 20 s, +1/2 above 4x the minimum)",
            "terms": out, "si": vals}
