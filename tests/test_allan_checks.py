"""The spike screen's scale (rigctl.solvers.allan_checks.spike_scale) on outputs that dwell on
their levels, and on plain Gaussian noise. Every expected value is computed here in numpy: the
running median of 25 (edge-padded), the MAD of the residual, its 90 % point, the samples' own
spread and the injected spikes' indices."""
from __future__ import annotations

import math

import numpy as np

from rigctl.solvers import allan_checks as C

W = 25


def _residual(y: np.ndarray) -> np.ndarray:
    h = W // 2
    pad = np.concatenate((np.full(h, y[0]), y, np.full(h, y[-1])))
    return y - np.median(np.lib.stride_tricks.sliding_window_view(pad, W), axis=1)


def _mad(v: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(v - np.median(v))))


def _inject(y: np.ndarray, rng: np.random.Generator, size: float, k: int = 20) -> np.ndarray:
    idx = np.sort(rng.choice(np.arange(100, y.size - 100, 200), k, replace=False))
    y[idx] += size * np.where(np.arange(k) % 2, 1.0, -1.0)
    return idx


def test_gaussian_noise_keeps_the_residual_scale() -> None:
    """White Gaussian noise with 20 spikes of 30 sd: the scale is the residual's MAD (numpy),
    and exactly the injected samples are found."""
    rng = np.random.default_rng(5)
    y = rng.normal(0.0, 1.0, 100_000)
    idx = _inject(y, rng, 30.0)
    found, _, sd, basis = C.find_spikes_scaled(y)
    assert basis == "residual"
    assert sd == _mad(_residual(y))
    assert np.array_equal(found, idx)


def test_a_dwelling_output_is_judged_against_its_spread() -> None:
    """A quantized output (step q) whose level wanders slowly (AR(1), sd 3 q, correlation 500
    samples) and whose noise (0.1 q) is far below a step: it dwells on each level for many
    samples, so most running-median residuals are exactly 0 and their MAD collapses (numpy:
    0 here) while their 90 % point and the samples' spread do not. The scale is then the
    samples' spread (1.4826 MAD of the samples, numpy): no level change is a spike, and 20
    injected spikes of 40 q are found, exactly."""
    rng = np.random.default_rng(7)
    n, q, rho = 200_000, 1.0, math.exp(-1.0 / 500.0)
    e = rng.normal(0.0, 3.0 * q * math.sqrt(1.0 - rho * rho), n)
    x = np.empty(n)
    x[0] = 0.0
    for i in range(1, n):  # a plain AR(1) recursion
        x[i] = rho * x[i - 1] + e[i]
    y = q * np.round((x + rng.normal(0.0, 0.1 * q, n)) / q)
    r = _residual(y)
    assert _mad(r) < 0.1 * _mad(y)  # the collapse, read here
    found0, _, sd0, basis0 = C.find_spikes_scaled(y, step=C.quantization_step(y))
    assert basis0 == "samples" and sd0 == _mad(y) and found0.size == 0
    idx = _inject(y, rng, 40.0 * q)
    found, _, sd, basis = C.find_spikes_scaled(y, step=C.quantization_step(y))
    assert basis == "samples" and sd == _mad(y)
    assert np.array_equal(found, idx)
    assert np.array_equal(found, np.flatnonzero(np.abs(_residual(y)) > 10.0 * _mad(y)))


def test_a_quantizer_below_one_step_has_the_rounding_as_its_floor() -> None:
    """Noise of 0.2 steps around one level: nearly every sample is on that level, the rest one
    step away; every median (of the residual, of the samples) is 0. A one-step residual is the
    quantizer, not an outlier: the scale is at least the rounding's sd q / sqrt(12), so 10 sd
    is 2.9 steps; 20 injected spikes of 5 steps are found, exactly, and no single step."""
    rng = np.random.default_rng(11)
    q = 0.05
    y = q * np.round(rng.normal(0.0, 0.2 * q, 100_000) / q)
    idx = _inject(y, rng, 5 * q)
    step = C.quantization_step(y)
    assert step is not None and abs(step / q - 1.0) < 1e-9
    found, _, sd, basis = C.find_spikes_scaled(y, step=step)
    assert basis == "quantization step" and abs(sd / (q / math.sqrt(12.0)) - 1.0) < 1e-9
    assert np.array_equal(found, idx)
    # the one-step residuals are there (numpy), and none is reported
    r = _residual(y)
    one = np.flatnonzero(np.isclose(np.abs(r), q))
    assert _mad(r) == 0.0 and one.size > 100 and not np.intersect1d(one, found).size


def test_step_source_tells_file_digits_from_an_output_step() -> None:
    """A power of ten of a unit the file may be written in is its printed digits; an LSB such
    as the ADIS16405's 0.05 deg/s or 3.33 mg is an output step."""
    d2r = math.pi / 180.0
    assert C.step_source(1e-6, "gyro") == {"kind": "file_digits", "unit": "rad/s", "decimals": 6}
    assert C.step_source(0.001 * d2r, "gyro") == {"kind": "file_digits", "unit": "deg/s", "decimals": 3}
    assert C.step_source(1e-6 * 9.80665, "accel") == {"kind": "file_digits", "unit": "g", "decimals": 6}
    assert C.step_source(0.05 * d2r, "gyro") == {"kind": "output_step"}
    assert C.step_source(3.33e-3 * 9.80665, "accel") == {"kind": "output_step"}
    assert C.step_source(0.0, "gyro") == {"kind": "output_step"}
