"""The spike screen's scale (rigctl.solvers.allan_checks.spike_scale) on outputs that dwell on
their levels, and on plain Gaussian noise. Every expected value is computed here in numpy: the
running median of 25 (windows cut at the ends, not padded), the MAD of the residual, its 90 % point, the samples' own
spread and the injected spikes' indices."""
from __future__ import annotations

import math

import numpy as np

from rigctl.solvers import allan_checks as C

W = 25


def _window_median(y: np.ndarray, w: int = W) -> np.ndarray:
    """Median of y[i - w//2 .. i + w//2] (odd w) over the samples that exist: inside, numpy's
    median of the full window; within w//2 of an end, the middle of the cut window (upper
    middle for an even count), sorted here sample by sample."""
    h = w // 2
    med = np.empty(y.size)
    med[h: y.size - h] = np.median(np.lib.stride_tricks.sliding_window_view(y, w), axis=1)
    for i in [*range(min(h, y.size)), *range(max(y.size - h, 0), y.size)]:
        seg = np.sort(y[max(i - h, 0): i + h + 1])
        med[i] = seg[seg.size // 2]
    return med


def _residual(y: np.ndarray) -> np.ndarray:
    return y - _window_median(y)


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


def test_spikes_at_the_ends_are_judged_by_their_neighbours() -> None:
    """A spike on sample 0, 1, N-2 or N-1 is flagged (the old screen padded the window with
    the end value, so an end sample was its own median and never flagged), by the screen with
    its own scale and by the given-sigma fast path (compiled and scipy paths alike), on white
    noise; on a small array the flags equal an independent numpy screen's."""
    from rigctl.solvers import allan_kernels as K

    rng = np.random.default_rng(3)
    for n in (2000, 20_001):
        y = rng.normal(0.0, 1.0, n)
        ends = np.array([0, 1, n - 2, n - 1])
        y[ends] += np.array([25.0, -25.0, 25.0, -25.0])
        found, med, sd, basis = C.find_spikes_scaled(y)
        assert basis == "residual" and np.array_equal(found, ends), (n, found)
        assert np.array_equal(med[ends], _window_median(y)[ends])
        got, got_med = C.spikes_beyond(y, sd)
        assert np.array_equal(got, ends) and np.array_equal(got_med, med[ends])
    # compiled and scipy paths: the same flags and medians
    y = rng.normal(0.0, 1.0, 3000)
    y[[0, 2999]] += 20.0
    ref = C.find_spikes(y, 1.0)
    orig = K.running_median
    try:
        K.running_median = lambda *_: None  # the scipy fallback
        alt = C.find_spikes(y, 1.0)
    finally:
        K.running_median = orig
    assert np.array_equal(ref[0], [0, 2999]) and np.array_equal(ref[0], alt[0])
    assert np.array_equal(ref[1], alt[1])
    # small arrays, spikes anywhere (the ends included), k = 4 so that noise is flagged too:
    # the same flags as numpy's screen with the same sigma
    for seed in range(30):
        r = np.random.default_rng(100 + seed)
        y = r.normal(0.0, 1.0, int(r.integers(W, 200)))
        hit = r.integers(0, y.size, 4)
        y[hit] += r.choice([-1.0, 1.0], 4) * r.uniform(3.0, 15.0, 4)
        want = np.flatnonzero(np.abs(_residual(y)) > 4.0 * 1.1)
        assert np.array_equal(C.find_spikes(y, 1.1, k=4.0)[0], want), seed
        assert np.array_equal(C.spikes_beyond(y, 1.1, k=4.0)[0], want), seed


def test_false_alarms_on_white_noise() -> None:
    """Clean Gaussian noise: no sample beyond 10 sd; at 4.5 sd the count matches what the
    residual's spread predicts (two-sided Gaussian tail of |r| / sd_r, with the residual's own
    sd, 1.03 x the noise for a median of 25), ends included."""
    from scipy.stats import norm

    count, expect = 0, 0.0
    for seed in range(6):
        y = np.random.default_rng(seed).normal(0.0, 1.0, 50_000)
        found, _, sd, _ = C.find_spikes_scaled(y)
        assert C.find_spikes(y)[0].size == 0
        r = _residual(y)
        count += C.find_spikes(y, sd, k=4.5)[0].size
        expect += y.size * 2 * norm.sf(4.5 * sd / np.std(r))
    assert abs(count - expect) < 4 * math.sqrt(expect) + 2, (count, expect)


def test_cs5071a_first_phase_point_is_a_spike() -> None:
    """The Stable32 Cs5071A set (tests/data): its first phase point is ~20 ns off the next ones.
    In the frequency samples y = diff(x) / tau0 that is y[0], > 60 robust sd from the median
    of its neighbours y[0..12] (numpy), and the screen reports it (before: 0 spikes)."""
    import gzip
    import itertools
    from pathlib import Path

    path = Path(__file__).parent / "data" / "stable32-reference" / "Cs5071A" / "5071A_phase.txt.gz"
    with gzip.open(path, "rt") as f:
        x = np.loadtxt(itertools.islice(f, 100_000))
    y = np.diff(x)  # tau0 = 1 s
    sd_np = _mad(_residual(y))
    size_np = abs(y[0] - np.median(y[:13])) / sd_np
    assert size_np > 60
    found, med, sd, basis = C.find_spikes_scaled(y)
    assert basis == "residual" and math.isclose(sd, sd_np, rel_tol=1e-12)
    assert found.size and found[0] == 0
    assert math.isclose(abs(y[0] - med[0]) / sd, size_np, rel_tol=1e-12)


def test_a_piece_with_its_neighbours_is_screened_as_the_whole() -> None:
    """A piece y[a:b] of a record screened with the record's 12 samples before and after it
    (``before`` / ``after``: a streamed chunk) gives the whole record's medians and flags at
    every index of the piece, the first and last 12 included (k = 3 so that noise is flagged
    too: the windows' medians decide), by the screen with a given sigma, the fast path and
    the medians themselves (a piece shorter than the window too: a short last chunk); without
    them the piece's end windows are cut and differ."""
    r = np.random.default_rng(8)
    y = r.normal(0.0, 1.0, 3000)
    med_all = _window_median(y)
    want = np.flatnonzero(np.abs(y - med_all) > 3.0)
    for a, b in ((0, 700), (700, 1400), (1400, 1413), (1413, 2988), (2988, 3000), (5, 2995)):
        pre, post = y[max(a - 12, 0): a], y[b: b + 12]
        piece = y[a:b]
        idx = np.arange(piece.size)
        assert np.array_equal(C.window_medians(piece, idx, before=pre, after=post),
                              med_all[a:b]), (a, b)
        sel = want[(want >= a) & (want < b)]
        if piece.size >= W:
            got, med, _, _ = C.find_spikes_scaled(piece, 1.0, k=3.0, before=pre, after=post)
            assert np.array_equal(got + a, sel) and np.array_equal(med, med_all[a:b]), (a, b)
        # (a piece shorter than the window, too: every sample examined)
        fast, fmed = C.spikes_beyond(piece, 1.0, k=3.0, before=pre, after=post)
        assert np.array_equal(fast + a, sel) and np.array_equal(fmed, med_all[sel]), (a, b)
    cut = C.window_medians(y[700:1400], np.arange(700))
    assert not np.array_equal(cut, med_all[700:1400])
