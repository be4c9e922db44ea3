"""Checks of a static capture's samples before the Allan fit (pure functions of arrays).

* :func:`quantization_step`: the output step of a quantized sensor, read from the samples
  (every value on one grid), e.g. 0.05 deg/s and 3.33 mg for an ADIS16405.
* :func:`step_source`: whether that step is the file's decimal digits (a power of ten of a unit
  the numbers may be written in) or an output step of the sensor.
* :func:`quantization_noise`: what that rounding adds to the curve. Rate-quantized output
  (each sample rounded to a multiple of q) carries white rounding noise of variance q^2/12 per
  sample while the sensor's own noise spans a few steps, i.e. a white-noise term
  N_q = q sqrt(tau0 / 12) that adds to N in quadrature (IEEE 952's Q is the quantization of the
  *integrated* output, slope -1; rate quantization is slope -1/2, part of N). When the noise per
  sample is below about half a step the rounding is not random any more and the short taus of
  the curve describe the quantizer, not the sensor.
* :func:`find_spikes`: samples far from their neighbours (a running median and the median
  absolute deviation of the residual, or the samples' own spread where that collapses on a
  dwelling output: :func:`spike_scale`), reported before the fit instead of being folded into
  the noise.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import maximum_filter1d, median_filter, minimum_filter1d

from . import allan_kernels as K

#: at most this many samples are examined for the grid (the first ones)
QUANT_SAMPLES = 200_000
#: a quantized output: the values' offsets from the grid are below this fraction of a step
QUANT_TOL = 1e-3
#: spikes: |sample - running median| above this many robust standard deviations
SPIKE_SIGMA = 10.0
#: running-median window (samples)
SPIKE_WINDOW = 25
#: the residual's MAD scale has collapsed (a dwelling output) when both its 90 % point and the
#: samples' own spread exceed it by more than this factor (see spike_scale)
SPIKE_COLLAPSE = 2.0
#: |N(0, 1)|'s 90 % point
SPIKE_Q90_Z = 1.6448536269514722


def quantization_step(y: np.ndarray, max_samples: int = QUANT_SAMPLES) -> float | None:
    """The step q (units of y) when every one of the first ``max_samples`` samples is
    y0 + k q with integer k (within QUANT_TOL of a step), and there are at least 3 distinct
    values; None otherwise (a float output, or noise below one step)."""
    v = np.unique(np.asarray(y[:max_samples], dtype=float))
    v = v[np.isfinite(v)]
    if v.size < 3:
        return None
    d = np.diff(v)
    scale = max(float(np.max(np.abs(v))), 1e-300)
    d = d[d > 1e-12 * scale]
    if d.size == 0:
        return None
    q = float(np.min(d))
    k = (v - v[0]) / q
    if np.max(np.abs(k - np.round(k))) > QUANT_TOL:
        return None
    # a grid of many more steps than values is a float output that happens to look regular
    if (v[-1] - v[0]) / q > 50.0 * v.size:
        return None
    return q


#: units a file's numbers may be written in (SI per unit), per sensor: a step that is a power of
#: ten of one of them is most likely the digits the file was printed with
FILE_UNITS = {"gyro": {"rad/s": 1.0, "deg/s": math.pi / 180.0, "deg/h": math.pi / 648000.0},
              "accel": {"m/s^2": 1.0, "g": 9.80665}}
#: |log10(step / unit) - nearest integer| below this: a power of ten of that unit
DECIMAL_TOL = 1e-6


def step_source(q: float, sensor: str) -> dict:
    """What a step read by :func:`quantization_step` most likely is. A power of ten of a unit
    the file may be written in (1e-6 rad/s, 1e-8 rad/s, 1e-6 g: the Astro Pi's and the Galaxy
    S5's CSVs, printed with 6 decimals and 7 significant digits) is the resolution of the
    file's decimal digits -- the sensor's own LSB is then not visible in the numbers (the S5
    gyro's 0.061 deg/s levels were smoothed by its publisher's filter): {"kind": "file_digits",
    "unit": that unit, "decimals": -log10(step / unit)}. Anything else (0.05 deg/s, 3.33 mg on
    the ADIS16405, an integer count scaled by its factor) is an output step: {"kind":
    "output_step"}. A sensor whose LSB is itself a power of ten of such a unit reads as file
    digits: the wording says "most likely"."""
    if not (q > 0 and math.isfinite(q)):
        return {"kind": "output_step"}
    for unit, f in FILE_UNITS.get(sensor, {"SI": 1.0}).items():
        x = math.log10(q / f)
        if abs(x - round(x)) < DECIMAL_TOL:
            return {"kind": "file_digits", "unit": unit, "decimals": int(-round(x))}
    return {"kind": "output_step"}


def quantization_noise(q: float, tau0: float, n_fit: float | None, sigma0: float) -> dict:
    """Rounding noise of a rate output quantized in steps q: its white-noise coefficient
    N_q = q sqrt(tau0/12) (units of N), its share of the fitted N^2, N with it taken out, and
    whether the rounding is random (per-sample noise ``sigma0`` >= q/2)."""
    nq = q * math.sqrt(tau0 / 12.0)
    out = {"step": q, "white_N": nq, "random_rounding": bool(sigma0 >= 0.5 * q),
           "noise_per_sample_steps": sigma0 / q}
    if n_fit is not None and n_fit > 0:
        out["share_of_N2"] = (nq / n_fit) ** 2
        out["N_without_rounding"] = math.sqrt(max(n_fit ** 2 - nq ** 2, 0.0))
    return out


def spike_scale(y: np.ndarray, r: np.ndarray, step: float | None = None) -> tuple[float, str]:
    """The robust standard deviation spikes are judged against, and what it was read from.

    Normally 1.4826 x the median absolute deviation of the running-median residual ``r``
    (``"residual"``). That scale collapses on an output that dwells on its levels -- a
    quantized sensor whose noise is below a step, or such an output after a smoothing filter
    (a phone gyro decimated by its publisher: most samples sit within a few deg/h of a level
    0.061 deg/s apart, between bursts that cross several levels): the residual is then ~0
    for most samples, its median absolute value says nothing about the bursts, and every
    burst sample comes out "10 sd" away (5.5 % of the samples of such a capture). The collapse
    is read off two independent signs, both needed:

    * the residual's body is not Gaussian: its 90 % point of |r| / 1.645 (which a
      collapsed centre leaves alone) exceeds the MAD scale by more than SPIKE_COLLAPSE
      (1.0 for Gaussian noise, 1.26 for Student-t with 3 dof, 1.36 for Laplace);
    * the data's own spread (1.4826 x the MAD of the samples about their median) exceeds the
      MAD scale by more than SPIKE_COLLAPSE (white noise: 1.03, the running median of 25
      taking a little of each sample).

    Then the data's spread is the scale (``"samples"``): a spike has to stand out of what the
    output does, not out of its dwell. A capture with real spikes in Gaussian-bodied noise
    keeps the residual's scale (the MTi-G capture in the tests: 2.9 on the first sign, 0.99 on
    the second), and so does a smooth (low-pass filtered) output without dwell (its residual is
    small but Gaussian). With the output's step ``step`` known (:func:`quantization_step`)
    the scale is at least the rounding's sd, step / sqrt(12) (``"quantization step"``): a
    residual of one step is the quantizer, not an outlier. With everything zero (a constant
    output with a few departures) the plain sd of the residual is taken (``"residual sd"``)."""
    sigma, basis = 0.0, "residual"
    if r.size:
        # one partition gives the median of |r - median r| (as np.median: the mean of the two
        # middle values for an even count) and its 90 % point (the order statistic at
        # floor(0.9 (n - 1))); the samples' spread only where the first sign is there
        a = np.abs(r - np.median(r))
        n = a.size
        k90 = int(0.9 * (n - 1))
        mid = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
        part = np.partition(a, sorted(set(mid + [k90])))
        mad_r = 1.4826 * float(np.mean(part[mid]))
        sigma = mad_r
        if float(part[k90]) / SPIKE_Q90_Z > SPIKE_COLLAPSE * mad_r:
            spread = 1.4826 * float(np.median(np.abs(y - np.median(y))))
            if spread > SPIKE_COLLAPSE * mad_r:
                sigma, basis = spread, "samples"
    if sigma <= 0 and r.size:
        sigma, basis = float(np.std(r)), "residual sd"
    if step is not None and step > 0 and sigma < step / math.sqrt(12.0):
        sigma, basis = step / math.sqrt(12.0), "quantization step"
    return sigma, basis


def find_spikes(y: np.ndarray, sigma: float | None = None, k: float = SPIKE_SIGMA,
                window: int = SPIKE_WINDOW, step: float | None = None
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Indices of samples more than ``k`` robust standard deviations from the running median
    of ``window`` samples, the running median itself (the replacement if they are excluded)
    and the robust standard deviation used (:func:`spike_scale`: 1.4826 x the median absolute
    residual unless that collapses on a dwelling output; ``step`` the output's quantization
    step if known; or ``sigma`` if given). A static capture's samples scatter around a slowly
    moving bias: a sample 10 sigma away from its neighbours has a probability below 1e-22
    under Gaussian noise, so on a day of 100 Hz data none is expected."""
    return find_spikes_scaled(y, sigma, k, window, step)[:3]


def find_spikes_scaled(y: np.ndarray, sigma: float | None = None, k: float = SPIKE_SIGMA,
                       window: int = SPIKE_WINDOW, step: float | None = None,
                       before: np.ndarray | None = None, after: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray, float, str]:
    """:func:`find_spikes` and what its scale was read from (:func:`spike_scale`'s basis,
    ``"given"`` for a given ``sigma``). ``before`` / ``after``: the samples just before y[0]
    and just after y[-1] where y is a piece of a longer record (a streamed chunk): the windows
    of y's first and last samples reach into them (:func:`window_medians`), as in one pass
    over the record."""
    y = np.asarray(y, dtype=float)
    if y.size < window:
        return np.zeros(0, dtype=np.int64), y.copy(), 0.0, "too few samples"
    med = K.running_median(y, window)  # compiled, without the GIL
    if med is None:
        med = median_filter(y, size=window, mode="nearest")
    # both paths repeat the end values into the windows of the first window // 2 and the last
    # (window - 1) // 2 samples (an end sample would be up to 13 of 25 values of its own
    # window, its own median: never flagged); those windows are taken as they are instead
    lo, hi = window // 2, (window - 1) // 2
    ends = np.union1d(np.arange(min(lo, y.size)), np.arange(max(y.size - hi, 0), y.size))
    med[ends] = window_medians(y, ends, window, before, after)
    r = y - med
    basis = "given"
    if sigma is None:
        sigma, basis = spike_scale(y, r, step)
    if sigma <= 0:
        return np.zeros(0, dtype=np.int64), med, 0.0, basis
    return np.flatnonzero(np.abs(r) > k * sigma), med, sigma, basis


def may_have_spikes(extremes: tuple[np.ndarray, np.ndarray], sigma: float,
                    k: float = SPIKE_SIGMA) -> bool:
    """Whether :func:`spikes_beyond` with these block extremes (compiled path) would look at
    any sample: False when every block's neighbourhood spans at most k sigma, so it finds no
    spike (nor with sigma not > 0) -- the samples themselves are not needed then."""
    if not sigma > 0:
        return False
    return K.any_block_examined(extremes[0], extremes[1], k * sigma)


def spikes_beyond(y: np.ndarray, sigma: float, k: float = SPIKE_SIGMA,
                  window: int = SPIKE_WINDOW,
                  extremes: tuple[np.ndarray, np.ndarray] | None = None,
                  before: np.ndarray | None = None, after: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The spikes :func:`find_spikes` finds with a given ``sigma`` (the same indices) and the
    running median at them, without the running median of every sample: the median of a
    window lies between its minimum and maximum (running min and max cost a few ns per
    sample, the median ~40), so a sample within k sigma of both cannot be a spike; the exact
    median is taken only at the others (the same order statistic of the same window).
    ``extremes``: the minimum and maximum of y's blocks of ``K.extremes_block(window)``
    samples, when the caller has them (the streamed pipeline takes them in its running-sum
    pass); the compiled path then starts from them. ``before`` / ``after``: the record's
    samples just before and after y (a streamed chunk), as in :func:`find_spikes_scaled`. The
    prefilter looks at y alone: a window cut at y's ends still holds at least
    window // 2 + 1 of the full window's samples (13 of 25), so a sample within k sigma of
    all of them has at most (window - 1) // 2 of the full window's beyond k sigma, too few
    to move the median there: it is no spike of the full window either."""
    y = np.asarray(y, dtype=float)
    none = np.zeros(0, dtype=np.int64)
    if not sigma > 0 or y.size == 0 or (y.size < window and before is None and after is None):
        return none, np.zeros(0)
    thr = k * sigma
    if y.size < window:  # a short last chunk: its cut windows may hold fewer than 13 samples
        cand = np.arange(y.size)
        med = window_medians(y, cand, window, before, after)
        keep = np.abs(y - med) > thr
        return cand[keep], med[keep]
    if K.HAVE_NUMBA:  # one compiled pass (scipy's min/max filters take ~18 ns per sample each)
        cand = K.far_from_window_range(y, window, thr, extremes)
    else:
        mn = minimum_filter1d(y, window, mode="nearest")
        cand = np.flatnonzero(y - mn > thr)
        mx = maximum_filter1d(y, window, mode="nearest")
        cand = np.union1d(cand, np.flatnonzero(mx - y > thr))
    if cand.size == 0:
        return none, np.zeros(0)
    med = window_medians(y, cand, window, before, after)
    keep = np.abs(y[cand] - med) > thr
    return cand[keep], med[keep]


def window_medians(y: np.ndarray, idx: np.ndarray, window: int = SPIKE_WINDOW,
                   before: np.ndarray | None = None, after: np.ndarray | None = None
                   ) -> np.ndarray:
    """The median of the window of each sample y[i], i in ``idx``: the samples
    y[i - window // 2 .. i + (window - 1) // 2] that exist (scipy.ndimage's alignment), the
    value of rank m // 2 of the m samples in it (the middle one for odd m, the upper of the
    two middle ones for even m). Inside the record m = window; near its ends the window is
    cut, not padded: sample 0 is judged against its own value and the next window // 2
    samples (13 of them for 25), as any other sample against its neighbours. (A window
    padded by repeating y[0] holds y[0] 13 times of 25, so y[0] is its own median and a
    spike there is never flagged.) The median lies between the window's minimum and maximum,
    so spikes_beyond's prefilter stands. Where y is a piece of a longer record (a streamed
    chunk), ``before`` and ``after`` are the record's samples just before y[0] and just
    after y[-1] (up to window // 2 and (window - 1) // 2 of them; fewer or none at the
    record's ends): the windows of y's first and last samples take them, the same window as
    in one pass over the record."""
    y = np.asarray(y, dtype=float)
    idx = np.asarray(idx, dtype=np.int64)
    n = y.size
    lo, hi = window // 2, (window - 1) // 2
    med = np.empty(idx.size)
    inner = (idx >= lo) & (idx < n - hi)
    if inner.any():
        rows = idx[inner][:, None] + np.arange(-lo, hi + 1)[None, :]
        med[inner] = np.partition(y[rows], lo, axis=1)[:, lo]
    pre = np.asarray(before if before is not None else (), dtype=float)
    pre = pre[pre.size - min(lo, pre.size):]
    post = np.asarray(after if after is not None else (), dtype=float)[:hi]
    for j in np.flatnonzero(~inner):  # at most window - 1 of them
        a, b = int(idx[j]) - lo, int(idx[j]) + hi + 1
        seg = y[max(a, 0): b]
        if (a < 0 and pre.size) or (b > n and post.size):
            seg = np.concatenate((pre[max(pre.size + a, 0):] if a < 0 else pre[:0], seg,
                                  post[: max(b - n, 0)]))
        med[j] = np.partition(seg, seg.size // 2)[seg.size // 2]
    return med
