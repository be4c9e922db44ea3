"""Time sync on taps the solver was not built around: responses that differ from its template
(another natural frequency and damping, two modes, clipping, a tap on another axis).

The sessions come from a generator written here, independent of the emulator (sim/taps.py) and
of the solver's template (rigctl.solvers.tap_detect.SecondOrderResponse): each mode's impulse
response is taken from scipy's state-space realisation of wn^2 / (s^2 + 2 zeta wn s + wn^2)
(``scipy.signal.tf2ss``) in modal form, C V exp(L t) V^-1 B. The IMU clock has a known offset and
drift; the expected values (true reference time of every counter, the quantisation limit of the
timing) are computed here in plain numpy.

What the solver does (docs/sync.md, "Taps unlike the template"): it learns the frequency and
damping of a one-mode response, so a single mode of any frequency and damping, clipped taps and
the 15 % that reaches the analysed axis from a tap on another axis keep sub-sample timing; a
two-mode response does not fit its one-mode template, the fit guard rejects it and the pipeline
falls back to half-sample timing (errors of the sample quantisation, ~2.9 ms per tap at 100 Hz),
with intervals that still cover the truth.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from rigctl.analysis.sync import SyncOptions, synchronise

RATE = 100.0
OFFSET_S, DRIFT_PPM = 0.3, 40.0
JITTER_S = 1e-4  # hammer edge jitter
NOISE = 0.02  # m/s^2, white, per sample


def impulse(fn: float, zeta: float, t: np.ndarray) -> np.ndarray:
    """Impulse response of wn^2 / (s^2 + 2 zeta wn s + wn^2) at times t (0 before 0)."""
    wn = 2 * np.pi * fn
    A, B, C, _ = signal.tf2ss([wn * wn], [1.0, 2 * zeta * wn, wn * wn])
    lam, V = np.linalg.eig(A)
    w = (C @ V).ravel() * np.linalg.solve(V, B).ravel()
    t = np.asarray(t, dtype=float)
    h = np.real(np.exp(np.outer(np.maximum(t, 0.0), lam)) @ w)
    return np.where(t >= 0, h, 0.0)


def true_time(counter: np.ndarray) -> np.ndarray:
    return OFFSET_S + np.asarray(counter, float) / RATE * (1 + DRIFT_PPM * 1e-6)


def session(seed: int, modes: list[tuple[float, float, float]], clip: float | None = None,
            gain: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """25 min at 100 Hz, 4 groups of 10 taps; lognormal peaks (median 40 m/s^2) on the analysed
    axis times ``gain``; ``modes``: (natural frequency Hz, damping, weight); ``clip``: the
    sensor's range (m/s^2). Returns counter, analysed-axis specific force, pulse times."""
    rng = np.random.default_rng(seed)
    n = int(1500 * RATE)
    k = np.arange(n)
    t_ref = true_time(k)
    taps = np.concatenate([s + np.cumsum(rng.uniform(1.5, 3.0, 10)) for s in (60, 450, 900, 1400)])
    amp = 40 * np.exp(0.3 * rng.standard_normal(taps.size))
    grid = np.linspace(0, 1, 20001)
    peak = np.max(np.abs(sum(w * impulse(f, z, grid) for f, z, w in modes)))
    a = NOISE * rng.standard_normal(n)
    for ti, ai in zip(taps, amp):
        k0 = int(np.searchsorted(t_ref, ti)) - 2
        x = t_ref[k0:k0 + int(0.6 * RATE)] - ti
        a[k0:k0 + x.size] += gain * ai * sum(w * impulse(f, z, x) for f, z, w in modes) / peak
    if clip is not None:
        a = np.clip(a, -clip, clip)
    return k.astype(np.uint64), a, taps + JITTER_S * rng.standard_normal(taps.size)


def _run(**kw):
    counter, a, pulses = session(1, **kw)
    res = synchronise(counter, a, RATE, pulses, SyncOptions(response="auto"))
    s = res.summary
    every = np.arange(0, counter.size, 50, dtype=float)
    err = res.clock.time_of_counter(every) - true_time(every)
    m = res.match
    rows = counter[res.detections.index[m.tap_index[m.inlier]]].astype(float)
    centre = float(np.mean(res.clock.time_of_counter(rows) - true_time(rows)))
    return res, s, err, centre


def test_the_generator_is_the_transfer_function() -> None:
    """The modal form against scipy's own impulse response on an even grid."""
    t = np.arange(0, 0.5, 1e-4)
    wn = 2 * np.pi * 12.0
    _, ref = signal.impulse(([wn * wn], [1.0, 2 * 0.25 * wn, wn * wn]), T=t)
    assert np.max(np.abs(impulse(12.0, 0.25, t) - ref)) < 1e-6 * np.max(np.abs(ref))
    assert impulse(12.0, 0.25, np.array([-1e-3]))[0] == 0.0


@pytest.mark.parametrize("case, kw", [
    ("12 Hz, damping 0.25", dict(modes=[(12.0, 0.25, 1.0)])),
    ("clipped at 25 m/s^2", dict(modes=[(30.0, 0.7, 1.0)], clip=25.0)),
    ("tap on another axis, 15 % inverted on this one", dict(modes=[(30.0, 0.7, 1.0)], gain=-0.15)),
])
def test_one_mode_responses_keep_subsample_timing(case: str, kw: dict) -> None:
    res, s, err, centre = _run(**kw)
    assert s["timing"] == "subsample", case
    assert s["n_inliers"] == 40, s
    # the stated 95 % intervals hold the truth (offset at the taps' centroid, drift)
    assert abs(centre) <= s["offset_ci95_s"], (case, centre, s["offset_ci95_s"])
    assert abs(s["drift_ppm"] - DRIFT_PPM) <= s["drift_ci95_ppm"], (case, s["drift_ppm"])
    # sub-sample: every sample's reference time within 0.1 ms (quantisation alone: 2.9 ms std)
    assert np.max(np.abs(err)) < 1e-4, (case, np.max(np.abs(err)))
    if "12 Hz" in case:  # the response is learned, not assumed
        assert abs(s["response"]["natural_freq_hz"] - 12.0) < 0.12
        assert abs(s["response"]["damping"] - 0.25) < 0.0125
    if "clipped" in case:
        assert s["n_saturated_taps"] >= 20, s["n_saturated_taps"]


def test_two_modes_fall_back_to_half_sample_timing() -> None:
    """A 30 Hz + 9 Hz response does not fit the one-mode template: the guard rejects the fit
    and the taps are timed to the sample (half-sample corrected). The timing error is then the
    quantisation, T / sqrt(12) per tap, and the intervals widen to match."""
    res, s, err, centre = _run(modes=[(30.0, 0.6, 1.0), (9.0, 0.15, 0.6)])
    assert s["timing"] == "half_sample" and s["response"] is None
    limit_ms = 1e3 * np.sqrt((1 / RATE) ** 2 / 12 + JITTER_S ** 2)
    n = s["n_inliers"]
    assert n == 40
    # residual std of n - 2 dof against the quantisation model: 3 relative standard errors
    assert abs(s["residual_std_ms"] - limit_ms) < 3 * limit_ms / np.sqrt(2 * (n - 2)), s["residual_std_ms"]
    assert abs(centre) <= s["offset_ci95_s"], (centre, s["offset_ci95_s"])
    assert abs(s["drift_ppm"] - DRIFT_PPM) <= s["drift_ci95_ppm"], s["drift_ppm"]
    assert np.max(np.abs(err)) < 2.0e-3  # well below one sample period (10 ms)
