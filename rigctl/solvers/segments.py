"""Per-segment table: the input of the calibration solvers and of the closed loop.

One row per static or constant-rate segment (K rows). The lead builds it from a recording:
the means and their uncertainties from :mod:`rigctl.solvers.segment_stats`, the references
from :func:`rigctl.frames.body_references` (gravity along up and Earth rate rotated into the
body frame, plus the table rate), the attitude from :func:`rigctl.frames.gimbal_dcm`.

Required fields (SI units):

=================  ========  =====================================================
field              shape     meaning
=================  ========  =====================================================
kind               (K,)      "orientation" (static), "rate" (constant rate), "ramp"
                             (window with angular acceleration), or any other label
f                  (K, 3)    measured mean specific force, m/s^2
w                  (K, 3)    measured mean angular rate, rad/s
f_sigma            (K, 3)    standard uncertainty of f, m/s^2 (Allan deviation at T)
w_sigma            (K, 3)    standard uncertainty of w, rad/s
f_ref              (K, 3)    true mean specific force in the body frame, m/s^2
w_ref              (K, 3)    true mean angular rate in the body frame (Earth + table), rad/s
=================  ========  =====================================================

Optional fields (None when unknown; candidates needing them are then "not available"):

=================  ==========  ===================================================
label              (K,)        human label of the segment
time               (K,)        segment mid time since run start, s
temperature        (K,)        mean IMU temperature, degC
table_rate         (K, 3)      gimbal rates [outer, middle, inner], rad/s
ang_accel          (K, 3)      mean body angular acceleration, rad/s^2 (0 for constant rate)
angles             (K, 3)      mean gimbal angles [outer, middle, inner], rad (for the gimbal
                               non-orthogonality candidate; with table_rate as gimbal rates)
attitude           (K, 3, 3)   segment mean of C_b^n (body-to-ENU of the nominally level
                               table); equals C_b^n for a static segment
earth_rate_n       (3,)        Earth rate in ENU, rad/s (for the levelling candidate)
gravity_m_s2       float       local gravity used in f_ref
f_ref_outer        (K, 3, 3)   mean of f f^T over the segment, m^2/s^4
w_ref_outer        (K, 3, 3)   mean of w w^T over the segment, rad^2/s^2
w_ref_cube         (K, 3)      mean of w_i^3, rad^3/s^3
w_ref_abs          (K, 3)      mean of |w_i|, rad/s
f_ref_abs          (K, 3)      mean of |f_i|, m/s^2
temperature_ref    float       temperature at which biases are reported when a warm-up
                               effect is added, degC (default: the settled temperature, i.e.
                               that of the last segment in time)
time_ref           float       time at which biases are reported when a linear drift is
                               added, s (default: mean of time)
t_start, t_end     (K,)        sampled window [t_start, t_end) of each segment, s (run time;
                               needed for the covariance of time-correlated noise)
batch_means        (K, 6, 8)   means of 8 equal consecutive batches of each window, per
                               channel, less what the reference explains inside the window
                               (the within-window data of rigctl.solvers.segment_noise)
rest               dict        a long static record taken for the noise model only (the
                               warm-up): "t_start", "t_end" (M,) batch windows, s; "mean" (M, 6)
                               batch means; "temperature" (M,) or None (rest_batches())
cov                (6, K, K)   covariance of the segment means per channel (time-correlated
                               noise, rigctl.solvers.segment_cov); None: independent means,
                               diag(sigma^2). When given, f_sigma/w_sigma = sqrt(diag(cov)).
=================  ==========  ===================================================

The moment fields matter only for segments whose reference changes within the window
(ramps, rotation about a horizontal axis): nonlinear terms act on the moments, not on the
mean. For constant segments they equal the functions of the mean, which are the defaults.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from ..sensor_axes import AXES
from .segment_stats import SensorNoise, batch_means, segment_mean

#: Sensor channels in the order used by every solver: 3 accelerometers, then 3 gyros, named
#: as every command names them (rigctl.sensor_axes: ax, ay, az, gx, gy, gz)
CHANNELS: tuple[str, ...] = AXES


@dataclass
class SegmentTable:
    """Per-segment means, uncertainties and references (see the module docstring)."""

    kind: NDArray[Any]
    f: NDArray[np.float64]
    w: NDArray[np.float64]
    f_sigma: NDArray[np.float64]
    w_sigma: NDArray[np.float64]
    f_ref: NDArray[np.float64]
    w_ref: NDArray[np.float64]
    label: NDArray[Any] | None = None
    time: NDArray[np.float64] | None = None
    temperature: NDArray[np.float64] | None = None
    table_rate: NDArray[np.float64] | None = None
    ang_accel: NDArray[np.float64] | None = None
    angles: NDArray[np.float64] | None = None
    attitude: NDArray[np.float64] | None = None
    earth_rate_n: NDArray[np.float64] | None = None
    gravity_m_s2: float | None = None
    f_ref_outer: NDArray[np.float64] | None = None
    w_ref_outer: NDArray[np.float64] | None = None
    w_ref_cube: NDArray[np.float64] | None = None
    w_ref_abs: NDArray[np.float64] | None = None
    f_ref_abs: NDArray[np.float64] | None = None
    temperature_ref: float | None = None
    time_ref: float | None = None
    t_start: NDArray[np.float64] | None = None
    t_end: NDArray[np.float64] | None = None
    batch_means: NDArray[np.float64] | None = None
    rest: dict[str, Any] | None = None
    cov: NDArray[np.float64] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.kind = np.asarray(self.kind).astype(str)
        k = self.kind.shape[0]
        for name in ("f", "w", "f_sigma", "w_sigma", "f_ref", "w_ref"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != (k, 3):
                raise ValueError(f"SegmentTable.{name} must have shape ({k}, 3), got {a.shape}")
            setattr(self, name, a)
        for name in ("f_sigma", "w_sigma"):
            a = getattr(self, name)
            if np.any(a[np.isfinite(a)] <= 0):
                raise ValueError(f"SegmentTable.{name} must be positive")
        for name, shape in (("time", (k,)), ("temperature", (k,)), ("table_rate", (k, 3)),
                            ("ang_accel", (k, 3)), ("angles", (k, 3)), ("attitude", (k, 3, 3)),
                            ("f_ref_outer", (k, 3, 3)), ("w_ref_outer", (k, 3, 3)),
                            ("w_ref_cube", (k, 3)), ("w_ref_abs", (k, 3)), ("f_ref_abs", (k, 3)),
                            ("t_start", (k,)), ("t_end", (k,)), ("cov", (6, k, k))):
            v = getattr(self, name)
            if v is not None:
                a = np.asarray(v, dtype=np.float64)
                if a.shape != shape:
                    raise ValueError(f"SegmentTable.{name} must have shape {shape}, got {a.shape}")
                setattr(self, name, a)
        if self.batch_means is not None:
            bm = np.asarray(self.batch_means, dtype=np.float64)
            if bm.ndim != 3 or bm.shape[:2] != (k, 6):
                raise ValueError(f"SegmentTable.batch_means must have shape ({k}, 6, B), got {bm.shape}")
            self.batch_means = bm
        if self.label is None:
            self.label = np.array([f"{kd}{i}" for i, kd in enumerate(self.kind)])
        else:
            self.label = np.asarray(self.label).astype(str)

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    # moments with defaults from the means --------------------------------------------------
    def f_outer(self) -> NDArray[np.float64]:
        """(K, 3, 3) mean of f_ref f_ref^T (default: outer product of the means)."""
        if self.f_ref_outer is not None:
            return self.f_ref_outer
        return np.einsum("ki,kj->kij", self.f_ref, self.f_ref)

    def w_outer(self) -> NDArray[np.float64]:
        """(K, 3, 3) mean of w_ref w_ref^T."""
        if self.w_ref_outer is not None:
            return self.w_ref_outer
        return np.einsum("ki,kj->kij", self.w_ref, self.w_ref)

    def w_cube(self) -> NDArray[np.float64]:
        """(K, 3) mean of w_i^3."""
        return self.w_ref_cube if self.w_ref_cube is not None else self.w_ref**3

    def w_abs(self) -> NDArray[np.float64]:
        """(K, 3) mean of |w_i|."""
        return self.w_ref_abs if self.w_ref_abs is not None else np.abs(self.w_ref)

    def f_abs(self) -> NDArray[np.float64]:
        """(K, 3) mean of |f_i|."""
        return self.f_ref_abs if self.f_ref_abs is not None else np.abs(self.f_ref)

    def y(self) -> NDArray[np.float64]:
        """(K, 6) observations [f, w] in channel order :data:`CHANNELS`."""
        return np.concatenate([self.f, self.w], axis=1)

    def sigma(self) -> NDArray[np.float64]:
        """(K, 6) standard uncertainties of :meth:`y`."""
        return np.concatenate([self.f_sigma, self.w_sigma], axis=1)

    def channel_cov(self, c: int) -> NDArray[np.float64]:
        """(K, K) covariance of channel c's means (diagonal when no cov is set)."""
        if self.cov is not None:
            return self.cov[c]
        return np.diag(self.sigma()[:, c] ** 2)

    def set_cov(self, cov: NDArray[np.float64]) -> None:
        """Set the (6, K, K) covariance of the means and the sigmas from its diagonal."""
        cov = np.asarray(cov, dtype=np.float64)
        if cov.shape != (6, len(self), len(self)):
            raise ValueError(f"cov must have shape (6, {len(self)}, {len(self)})")
        self.cov = cov
        d = np.sqrt(np.diagonal(cov, axis1=1, axis2=2)).T  # (K, 6)
        self.f_sigma, self.w_sigma = d[:, :3].copy(), d[:, 3:].copy()

    def subset(self, mask: NDArray[np.bool_]) -> "SegmentTable":
        """Rows selected by a boolean mask or an index array."""
        idx = np.arange(len(self))[mask]
        kw: dict[str, Any] = {}
        for name in ("kind", "f", "w", "f_sigma", "w_sigma", "f_ref", "w_ref", "label", "time",
                     "temperature", "table_rate", "ang_accel", "angles", "attitude", "f_ref_outer",
                     "w_ref_outer", "w_ref_cube", "w_ref_abs", "f_ref_abs", "t_start", "t_end",
                     "batch_means"):
            v = getattr(self, name)
            kw[name] = None if v is None else np.asarray(v)[idx]
        kw["cov"] = None if self.cov is None else self.cov[:, idx][:, :, idx]
        kw["extra"] = {k: v for k, v in self.extra.items() if k != "noise_components"}
        return replace(self, **kw)


def rest_batches(t: NDArray[np.float64], acc: NDArray[np.float64], gyro: NDArray[np.float64], fs_hz: float,
                 temperature: NDArray[np.float64] | None = None, batch_s: float = 30.0) -> dict[str, Any]:
    """Batch means of a long static record (the warm-up) for the noise model (SegmentTable.rest).

    t (n,) sample times, s; acc, gyro (n, 3); batches of about ``batch_s`` seconds (at least 8,
    at most 128), leftover samples dropped. Returns {"t_start", "t_end", "mean" (M, 6),
    "temperature" (M,) or None}.
    """
    n = len(t)
    M = int(np.clip(round(n / fs_hz / batch_s), 8, 128))
    L = n // M
    x = np.concatenate([np.asarray(acc, dtype=np.float64), np.asarray(gyro, dtype=np.float64)], axis=1)
    starts = float(t[0]) + np.arange(M) * L / fs_hz
    temp = None
    if temperature is not None and np.all(np.isfinite(temperature)):
        temp = np.asarray(temperature, dtype=np.float64)[: M * L].reshape(M, L).mean(axis=1)
    return {"t_start": starts, "t_end": starts + L / fs_hz, "mean": batch_means(x[: M * L], M),
            "temperature": temp}


def about_reference(x: NDArray[np.float64], ref: NDArray[np.float64]) -> NDArray[np.float64]:
    """Samples x (n, c) less what the reference explains: on a rate segment gravity turns through
    the axes and the samples swing by ~g, which is not noise. When the reference varies, x is
    regressed on [1, ref - mean(ref)] (least squares per column) and the residual returned;
    otherwise x itself.
    """
    x = np.asarray(x, dtype=np.float64)
    ref = np.atleast_2d(np.asarray(ref, dtype=np.float64))
    if ref.shape[0] == x.shape[0] and np.ptp(ref, axis=0).max() > 0:
        A = np.column_stack([np.ones(len(ref)), ref - ref.mean(axis=0)])
        coef, *_ = np.linalg.lstsq(A, x, rcond=1e-9)
        return x - A @ coef
    return x


def segment_table_from_samples(
    kind: Sequence[str],
    acc: Sequence[NDArray[np.float64]],
    gyro: Sequence[NDArray[np.float64]],
    fs_hz: float,
    f_ref: Sequence[NDArray[np.float64]],
    w_ref: Sequence[NDArray[np.float64]],
    acc_noise: SensorNoise | None = None,
    gyro_noise: SensorNoise | None = None,
    **optional: Any,
) -> SegmentTable:
    """Build a SegmentTable from the samples of each segment.

    Args:
        kind: (K,) segment kinds.
        acc, gyro: K arrays (n_k, 3) of IMU samples in m/s^2 and rad/s (transients excluded).
        fs_hz: IMU sample rate, Hz.
        f_ref, w_ref: K arrays of the true body specific force / rate, either (3,) for a constant
            segment or (n_k, 3) sampled at the IMU times (from rigctl.frames.body_references on
            table angles interpolated to the IMU times); moments and the mean angular
            acceleration (finite differences) are computed from the samples.
        acc_noise, gyro_noise: noise models (None: estimated from each segment's own data).
        **optional: any optional SegmentTable field (time, temperature, attitude, t_start,
            t_end, ...).

    ``batch_means`` (the within-window data of :mod:`rigctl.solvers.segment_noise`) are
    computed here, about what the reference explains (:func:`about_reference`).
    """
    cols: dict[str, list[Any]] = {k: [] for k in ("f", "w", "fs", "ws", "fr", "wr", "fo", "wo", "wc",
                                                   "wa", "fa", "wd")}
    bv = []
    for a, g, fr, wr in zip(acc, gyro, f_ref, w_ref):
        ma, mg = segment_mean(a, fs_hz, acc_noise), segment_mean(g, fs_hz, gyro_noise)
        fr = np.atleast_2d(np.asarray(fr, dtype=np.float64))
        wr = np.atleast_2d(np.asarray(wr, dtype=np.float64))
        # the window's samples less what the reference explains inside it (gravity turning
        # through the axes swings them by ~g; a fraction of a batch of misalignment between
        # batches and revolutions would leak it into every contrast), mean kept
        bv.append(np.concatenate([batch_means(about_reference(a, fr)) + ma.mean,
                                  batch_means(about_reference(g, wr)) + mg.mean], axis=1).T)
        wd = (np.gradient(wr, 1.0 / fs_hz, axis=0).mean(axis=0) if len(wr) > 2 else np.zeros(3))
        for key, val in (("f", ma.mean), ("w", mg.mean), ("fs", ma.sigma), ("ws", mg.sigma),
                         ("fr", fr.mean(axis=0)), ("wr", wr.mean(axis=0)),
                         ("fo", np.einsum("ni,nj->ij", fr, fr) / len(fr)),
                         ("wo", np.einsum("ni,nj->ij", wr, wr) / len(wr)),
                         ("wc", (wr**3).mean(axis=0)), ("wa", np.abs(wr).mean(axis=0)),
                         ("fa", np.abs(fr).mean(axis=0)), ("wd", wd)):
            cols[key].append(val)
    optional.setdefault("ang_accel", np.array(cols["wd"]))
    optional.setdefault("batch_means", np.array(bv))
    return SegmentTable(kind=np.asarray(kind), f=np.array(cols["f"]), w=np.array(cols["w"]),
                        f_sigma=np.array(cols["fs"]), w_sigma=np.array(cols["ws"]),
                        f_ref=np.array(cols["fr"]), w_ref=np.array(cols["wr"]),
                        f_ref_outer=np.array(cols["fo"]), w_ref_outer=np.array(cols["wo"]),
                        w_ref_cube=np.array(cols["wc"]), w_ref_abs=np.array(cols["wa"]),
                        f_ref_abs=np.array(cols["fa"]), **optional)


def truth_from_emulator(params: dict[str, Any]) -> dict[str, float]:
    """The emulator's /truth params_json (rigctl.sim.error_model.ImuErrorModel.truth) under the
    solvers' parameter names, for before/after errors against truth.

    Biases are the run's actual ones (bias + turn-on bias). Keys missing in ``params`` are skipped.
    """
    out: dict[str, float] = {}
    ax = "xyz"

    def vec(key: str) -> NDArray[np.float64] | None:
        return None if params.get(key) is None else np.asarray(params[key], dtype=np.float64).reshape(3)

    for sensor, unit_in, unit_out in (("accel", "m_per_s2", "m_s2"), ("gyro", "rad_per_s", "rad_s")):
        b = vec(f"{sensor}_bias_{unit_in}")
        t = vec(f"{sensor}_turn_on_bias_{unit_in}")
        if b is not None:
            b = b + (t if t is not None else 0.0)
            out.update({f"{sensor}_bias_{ax[i]}_{unit_out}": float(b[i]) for i in range(3)})
        M = params.get(f"{sensor}_scale_misalignment_matrix")
        if M is not None:
            M = np.asarray(M, dtype=np.float64).reshape(3, 3)
            out.update({f"{sensor}_M_{ax[i]}{ax[j]}_ratio": float(M[i, j]) for i in range(3) for j in range(3)})
    q = vec("accel_quadratic_per_m_per_s2")
    if q is not None:
        out.update({f"accel_quad_{ax[i]}_s2_per_m": float(q[i]) for i in range(3)})
    return out
