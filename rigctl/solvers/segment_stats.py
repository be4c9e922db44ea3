"""Mean of a static or constant-rate segment and its standard uncertainty from the noise model.

Why not sigma/sqrt(n): that is the uncertainty of a mean only for white noise. Under coloured
noise (Gauss-Markov, bias instability, random walk) neighbouring samples are correlated and the
mean of a T-second window scatters more. The Allan variance at cluster time tau = T is by
definition half the mean squared difference of two adjacent T-second means, so

    Var(mean over T)  ~=  sigma_A^2(T)

(exact for white noise, where sigma_A^2(T) = sigma^2 t0 / T = sigma^2 / n; larger for coloured
noise; for random walk the "variance of a mean" is only defined relative to a neighbour, which
is exactly what a calibration comparing segments needs).

Noise models accepted:

* IEEE Std 952 coefficients: the three axes' :class:`~rigctl.solvers.noise_coefficients.
  NoiseCoefficients` (a :data:`~rigctl.solvers.noise_coefficients.Triad`; SI units and the
  Allan variance of each term documented there).
* :class:`AllanCurve`: a measured Allan deviation curve, interpolated linearly in log-log and
  extrapolated with the end slopes.
* none: estimated from the segment itself (:func:`self_noise_sigma`): non-overlapping batch
  means, extrapolated in batch length, never below the white-noise value. (An Allan variance
  at tau = T cannot be formed inside a single T-second window.)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import allan as _allan
from .noise_coefficients import NoiseCoefficients, triad_avar

#: batches of the within-window statistic :func:`batch_var`
N_BATCHES = 8


@dataclass(frozen=True)
class AllanCurve:
    """A tabulated Allan deviation: tau (M,) in s, adev (M, 3) in the signal's unit."""

    tau: NDArray[np.float64]
    adev: NDArray[np.float64]

    def avar(self, tau_s: ArrayLike) -> NDArray[np.float64]:
        """Allan variance at tau (log-log interpolation, end slopes extrapolated): (..., 3)."""
        t = np.asarray(self.tau, dtype=np.float64)
        a = np.asarray(self.adev, dtype=np.float64).reshape(t.size, -1)
        lt, la = np.log(t), np.log(a)
        x = np.log(np.asarray(tau_s, dtype=np.float64))
        out = np.empty(np.shape(x) + (a.shape[1],))
        for j in range(a.shape[1]):
            y = np.interp(x, lt, la[:, j])
            if t.size >= 2:
                lo_slope = (la[1, j] - la[0, j]) / (lt[1] - lt[0])
                hi_slope = (la[-1, j] - la[-2, j]) / (lt[-1] - lt[-2])
                y = np.where(x < lt[0], la[0, j] + lo_slope * (x - lt[0]), y)
                y = np.where(x > lt[-1], la[-1, j] + hi_slope * (x - lt[-1]), y)
            out[..., j] = np.exp(2.0 * y)
        return out


@dataclass(frozen=True)
class SegmentMean:
    """Mean of a segment and its standard uncertainty.

    mean, sigma: (3,) in the samples' unit; duration_s: T = n / fs;
    method: "noise_model", "allan_curve" or "self"; naive_sigma: the white-noise figure
    std/sqrt(n), kept for comparison only.
    """

    mean: NDArray[np.float64]
    sigma: NDArray[np.float64]
    duration_s: float
    n: int
    method: str
    naive_sigma: NDArray[np.float64]


#: a sensor's noise: its three axes' IEEE 952 coefficients, or a measured Allan curve
SensorNoise = Union[Sequence[NoiseCoefficients], "AllanCurve"]


def sensor_avar(model: SensorNoise, tau_s: ArrayLike) -> NDArray[np.float64]:
    """Allan variance (..., 3) at tau (...,) of either kind of sensor noise."""
    return model.avar(tau_s) if isinstance(model, AllanCurve) else triad_avar(model, tau_s)


def mean_sigma_from_model(duration_s: float, model: SensorNoise) -> NDArray[np.float64]:
    """Standard uncertainty of a T-second mean: sqrt(sigma_A^2(T)), (3,)."""
    return np.sqrt(sensor_avar(model, float(duration_s)))


def overlapping_avar(x: NDArray[np.float64], m_list: NDArray[np.int64]) -> NDArray[np.float64]:
    """Overlapping Allan variance of samples x (n, c) at cluster sizes m (in samples).

        sigma^2(m t0) = 1/(2 (n - 2m + 1)) sum_k (xbar_{k+m} - xbar_k)^2

    with xbar_k the mean of x[k:k+m]. Computed per column by :func:`rigctl.solvers.allan.oadev`
    (exact, fully overlapping sums; the variance does not depend on t0, so t0 = 1). Cluster
    sizes with no term (m < 1 or 2m > n) give NaN. Returns (len(m), c).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    m_arr = np.asarray(m_list, dtype=np.int64).ravel()
    out = np.full((m_arr.size, x.shape[1]), np.nan)
    ok = (m_arr >= 1) & (2 * m_arr <= n)
    if not np.any(ok) or n < 2:
        return out
    ms = np.unique(m_arr[ok])
    for j in range(x.shape[1]):
        res = _allan.oadev(x[:, j], tau0=1.0, taus=ms, data_type="rate", mode="exact")
        dev = dict(zip(res.m.tolist(), res.dev.tolist()))
        out[:, j] = [dev.get(int(m), np.nan) ** 2 if okk else np.nan for m, okk in zip(m_arr, ok)]
    return out


def batch_means(x: ArrayLike, n_batches: int = N_BATCHES) -> NDArray[np.float64]:
    """(n_batches, c) means of n_batches equal consecutive batches of x (n, c) (leftover dropped;
    NaN when n < n_batches)."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    L = x.shape[0] // n_batches
    if L < 1:
        return np.full((n_batches, x.shape[1]), np.nan)
    return x[: L * n_batches].reshape(n_batches, L, -1).mean(axis=1)


def batch_var(x: ArrayLike, n_batches: int = N_BATCHES) -> NDArray[np.float64]:
    """Within-window statistic v = var(batch means, ddof=1)/B per column (leftover dropped)."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    L = x.shape[0] // n_batches
    if L < 1:
        return np.full(x.shape[1], np.nan)
    bm = x[: L * n_batches].reshape(n_batches, L, -1).mean(axis=1)
    return bm.var(axis=0, ddof=1) / n_batches


def self_noise_sigma(x: ArrayLike, fs_hz: float, n_batches: int = 8) -> NDArray[np.float64]:
    """Uncertainty of the mean of one segment estimated from the segment itself.

    Non-overlapping batch means: with B batches of length L = n/B, v(L) = var(batch means)/B
    estimates Var(mean); for noise correlated over a time Tc it is biased low by about Tc/(L t0),
    so the estimate with 2B batches (half the length) extrapolates it (first order in 1/L):

        Var(mean) ~= max(2 v(L) - v(L/2),  v(L),  s^2 / n)

    never below the white-noise value s^2/n (s the sample standard deviation). With B = 8 the
    estimate has about 7 degrees of freedom. ``fs_hz`` is accepted for symmetry with the
    model-based path (the result does not depend on it). Returns (c,) standard uncertainties.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    white = x.var(axis=0, ddof=1) / n
    if n < 4 * n_batches:
        return np.sqrt(white) * 2.0  # too short to say more: be generous
    v1 = batch_var(x, n_batches)
    v2 = batch_var(x, 2 * n_batches)
    return np.sqrt(np.maximum.reduce([2.0 * v1 - v2, v1, white]))


def segment_mean(
    samples: ArrayLike,
    fs_hz: float,
    noise: SensorNoise | None = None,
) -> SegmentMean:
    """Mean of a segment's samples (n, 3) and its standard uncertainty.

    Args:
        samples: (n, 3) (or (n,)) samples of a static or constant-rate window, SI units.
        fs_hz: sample rate, Hz (T = n / fs).
        noise: the sensor's noise model; None estimates it from the segment (see
            :func:`self_noise_sigma`).
    """
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    if n < 2:
        raise ValueError("a segment needs at least two samples")
    T = n / float(fs_hz)
    naive = x.std(axis=0, ddof=1) / np.sqrt(n)
    if noise is None:
        sig, method = self_noise_sigma(x, fs_hz), "self"
    else:
        sig = mean_sigma_from_model(T, noise)[: x.shape[1]]
        method = "allan_curve" if isinstance(noise, AllanCurve) else "noise_model"
    return SegmentMean(mean=x.mean(axis=0), sigma=np.asarray(sig, dtype=np.float64), duration_s=T,
                       n=n, method=method, naive_sigma=naive)


def allan_curve_from_samples(samples: ArrayLike, fs_hz: float, min_clusters: int = 8) -> AllanCurve:
    """Overlapping Allan deviation of a (long, static) record at octave cluster times.

    Useful to build a noise model from an initial static period when no characterisation of
    the sensor exists (e.g. hand-held multi-position data).
    """
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    m_max = max(1, n // min_clusters)
    m_list = np.unique(2 ** np.arange(0, int(np.log2(m_max)) + 1))
    av = overlapping_avar(x, m_list)
    return AllanCurve(tau=m_list / float(fs_hz), adev=np.sqrt(av))


def gauss_markov_avar(tau_s: ArrayLike, sigma: float, tc_s: float) -> NDArray[np.float64]:
    """Allan variance of a first-order Gauss-Markov process (variance sigma^2, time const Tc):

        sigma_A^2(tau) = (2 sigma^2 Tc / tau) [1 - Tc/(2 tau) (3 - 4 e^{-tau/Tc} + e^{-2 tau/Tc})]
    """
    tau = np.asarray(tau_s, dtype=np.float64)
    r = tau / tc_s
    return 2.0 * sigma**2 * tc_s / tau * (1.0 - (3.0 - 4.0 * np.exp(-r) + np.exp(-2.0 * r)) / (2.0 * r))
