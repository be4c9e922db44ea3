"""Periodic components (tones) in a static capture, found before the Allan fit (pure functions).

A sinusoid a sin(2 pi f t + phi) in the rate samples y_k = y(k tau0) is not an IEEE 952 term.
Its overlapping Allan variance at factor m (tau = m tau0), averaged over the phase (the
overlapping estimator of a long record converges to this), is that of the difference of two
adjacent m-sample means::

    sigma^2_tone(m) = a^2 sin^4(pi f m tau0) / (m sin(pi f tau0))^2

(the sampled form of IEEE Std 952-1997 annex C's Omega0^2 (sin^2(pi f0 tau) / (pi f0 tau))^2,
which it becomes for f tau0 -> 0). f is the frequency as the samples see it: a tone above
the Nyquist frequency fs/2 of the output is already folded into [0, fs/2] in the samples, and
the formula holds for the folded frequency (sin^2(pi f tau0) and sin^4(pi f m tau0) are
unchanged by f -> fs - f and by f -> f + fs). Near fs/2 (a 47.3 Hz vibration at a 100 Hz
output) the term is ~a^2/m^2 at every odd m and ~0 at every even m, so an octave tau set
(m = 2^k, all even past m = 1) hardly sees it while a dense set fits it into Q or N.

:func:`detect_tones`: Welch periodogram of the rate samples (Hann window, K segments without
overlap, constant detrend). For a smooth spectrum S each bin's estimate is S(f) chi2_nu / nu
with nu = 2 K (independent segments; 50 % overlap would make the tail heavier than the
Satterthwaite chi-square, and gave 1 % false alarms where 0.1 % were stated). The local level
is the running median of the PSD over ``LEVEL_BINS`` bins divided by the median of
chi2_nu / nu (a narrow peak does not move a median; a broad bump raises it, so it is not
called a tone); the level is itself an estimate, with about nu_l = nu LEVEL_BINS / (2 pi / 2)
degrees of freedom (a median's efficiency 2/pi, adjacent Hann bins correlated: half as many
independent ones). A bin is significant when PSD / level exceeds the F(nu, nu_l) quantile
F.isf(ALPHA / M, nu, nu_l), M the number of bins tested (Bonferroni: under a smooth spectrum
the probability of any false detection on an axis is at most about ALPHA = 1e-3). Contiguous
significant bins (within the Hann main lobe, +-``LOBE_BINS``) form one tone; its power is the
PSD in excess of the level summed over +-LOBE_BINS bins around the highest bin (times the bin
width), a = sqrt(2 power); its frequency the excess-weighted centroid of those bins. Bins
within LEVEL_BINS / 2 of 0 Hz and of fs/2 are not tested (no two-sided level there; the red
noise of B/K lives at the bottom).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import fft
from scipy.ndimage import median_filter
from .distributions import chi2, f as fdist

#: family-wise false-detection probability per axis under a smooth spectrum
ALPHA = 1e-3
#: running-median window of the local level (bins)
LEVEL_BINS = 129
#: half-width of a tone's main lobe (Hann: +-2 bins hold 99.9 % of a centred tone's power;
#: +-4 also hold one that falls between bins, and a slight frequency wander)
LOBE_BINS = 4
#: longest Welch segment (samples)
MAX_SEG = 1 << 16
#: welch_hann transforms this many samples' segments at once
WELCH_BLOCK = 1 << 18
#: at most this many tones are reported (the strongest)
MAX_TONES = 8
#: vibration bands: a second periodogram whose segments are this many times shorter than the
#: tones' (bins this many times wider, this many times more segments): a band of ~0.1-5 Hz
#: raises the tones' local level (so it is no tone) but stands out of this one's
BAND_SEG_DIV = 16
#: at least this many contiguous significant bins of that periodogram make a band (wider than
#: any line's Hann main lobe; the tones' own lobes are not tested)
BAND_MIN_BINS = 3


def tone_avar(tau0: float, m: np.ndarray, freq_hz: float, amp: float) -> np.ndarray:
    """Overlapping Allan variance of a sampled sinusoid of amplitude ``amp`` (rate units) and
    frequency ``freq_hz`` at factors ``m`` (tau = m tau0), phase-averaged (see the module
    docstring). 0 where sin(pi f tau0) = 0 (a tone at 0 or fs: a constant)."""
    m = np.asarray(m, dtype=float)
    s1 = math.sin(math.pi * freq_hz * tau0)
    if abs(s1) < 1e-12:
        return np.zeros(m.shape)
    return amp * amp * np.sin(math.pi * freq_hz * m * tau0) ** 4 / (m * s1) ** 2


def tones_avar(tau0: float, m: np.ndarray, tones: list[dict]) -> np.ndarray:
    """The summed :func:`tone_avar` of ``tones`` (dicts with freq_hz and amp_si)."""
    out = np.zeros(np.shape(m), dtype=float)
    for t in tones:
        out += tone_avar(tau0, m, float(t["freq_hz"]), float(t["amp_si"]))
    return out


def welch_hann(y: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch power spectral density of the real samples ``y`` (sample rate ``fs``
    in Hz; PSD in units(y)^2/Hz at the frequencies f_j = j fs / nperseg, j = 0 .. nperseg/2)
    over the K = len(y) // nperseg adjacent segments without overlap, each with its mean removed
    and a periodic Hann window w_n = 1/2 - 1/2 cos(2 pi n / nperseg)::

        P_j = (c_j / K) sum_k |sum_n w_n (y_kn - mean_k) exp(-2 pi i j n / nperseg)|^2
              / (fs sum_n w_n^2),     c_j = 2 except at 0 Hz and (nperseg even) fs/2, c_j = 1

    This is ``scipy.signal.welch(y, fs, window="hann", nperseg=nperseg, noverlap=0,
    detrend="constant", scaling="density")`` with scipy's own arithmetic (scipy 1.17:
    ``get_window``, ``ShortTimeFFT.spectrogram`` with the window scaled to 'psd', ``csd``'s
    doubling and mean), bit for bit (tests/test_allan_tones.py compares them), without
    importing scipy.signal, which pulls in scipy.stats: ~0.45 s of CPU in every ``rigctl
    allan``, ``run`` and daemon solve step that looked for tones."""
    y = np.asarray(y, dtype=np.float64)
    k = y.size // nperseg
    # get_window("hann", nperseg): the symmetric window of nperseg + 1 points, last one dropped
    phase = np.linspace(-np.pi, np.pi, nperseg + 1, dtype=np.float64)
    w = np.zeros(nperseg + 1, dtype=np.float64)
    w += 0.5 * np.cos(0 * phase)
    w += 0.5 * np.cos(1 * phase)
    w = w[:-1]
    # ShortTimeFFT.scale_to("psd"): w / sqrt(sum(|w|^2) / T), T = 1 / fs, a Python sum as there
    w = w * (1 / np.sqrt(sum(w ** 2) / (1 / fs)))
    s = np.empty((nperseg // 2 + 1, k))
    # the segments as rows, WELCH_BLOCK samples of them per transform (each row's mean, window
    # and transform the same arithmetic as one segment's alone; memory bounded)
    rows = max(1, WELCH_BLOCK // nperseg)
    for i in range(0, k, rows):
        j = min(k, i + rows)
        seg = y[i * nperseg:j * nperseg].reshape(j - i, nperseg)
        seg = seg - np.mean(seg, -1, keepdims=True)
        x = fft.rfft(seg * w, n=nperseg, axis=-1)
        s[:, i:j] = (x.real ** 2 + x.imag ** 2).T
    s[1:-1 if nperseg % 2 == 0 else None] *= 2
    return fft.rfftfreq(nperseg, 1 / fs), s.mean(axis=-1)


def _local_level(y: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, ...]:
    """The periodogram both tests read (:func:`detect_tones`, :func:`detect_bands`): Welch
    (Hann, ``nperseg``-sample segments, no overlap; K = len(y) // nperseg segments) ``f`` (Hz)
    and ``p``; the local level, the running median over LEVEL_BINS bins over chi2_nu's median
    / nu (nu = 2K); the bins tested (not within LEVEL_BINS / 2 of 0 Hz or fs / 2); nu and the
    level's EDF nu LEVEL_BINS / pi."""
    f, p = welch_hann(y, fs, nperseg)
    nu = 2.0 * (y.size // nperseg)
    level = median_filter(p, size=LEVEL_BINS, mode="nearest") / (chi2.median(nu) / nu)
    half = LEVEL_BINS // 2
    test = np.zeros(p.size, dtype=bool)
    test[half: p.size - half] = True
    return f, p, level, test, nu, nu * LEVEL_BINS / math.pi


def detect_tones(y: np.ndarray, fs: float, alpha: float = ALPHA) -> dict:
    """Tones in the rate samples ``y`` (sample rate ``fs``): see the module docstring.
    Returns {"tones": [{freq_hz, amp_si, psd_ratio, bins}...] strongest first, "nperseg",
    "segments", "edf", "threshold_ratio", "bins_tested", "alpha"}; no tones for fewer than
    16 segments of 4 LEVEL_BINS samples."""
    y = np.asarray(y, dtype=np.float64)
    finite = np.isfinite(y)
    if not finite.all():  # (a copy only where one is left out)
        y = y[finite]
    del finite
    out = {"tones": [], "alpha": alpha, "method": "Welch (Hann, no overlap), local median "
           "level, Bonferroni F test"}
    nper = MAX_SEG
    while nper > 4 * LEVEL_BINS and y.size < 16 * nper:
        nper //= 2
    if y.size < 16 * nper or nper < 4 * LEVEL_BINS:
        out["skipped"] = "too few samples for a periodogram"
        return out
    f, p, level, test, nu, nu_level = _local_level(y, fs, nper)
    k = y.size // nper
    n_test = int(np.count_nonzero(test))
    thr = float(fdist.isf(alpha / max(n_test, 1), nu, nu_level))
    ratio = np.where(level > 0, p / np.where(level > 0, level, 1.0), 0.0)
    sig = np.flatnonzero(test & (ratio > thr))
    out.update({"nperseg": int(nper), "segments": int(k), "edf": nu, "threshold_ratio": thr,
                "bins_tested": n_test, "bin_hz": float(f[1] - f[0])})
    df = float(f[1] - f[0])
    tones = []
    used = np.zeros(p.size, dtype=bool)
    for i in sig[np.argsort(-ratio[sig])]:  # strongest first; one tone per main lobe
        if used[i]:
            continue
        a, b = max(0, i - LOBE_BINS), min(p.size, i + LOBE_BINS + 1)
        used[a:b] = True
        exc = np.maximum(p[a:b] - level[a:b], 0.0)
        power = float(exc.sum() * df)
        if power <= 0:
            continue
        tones.append({"freq_hz": float((f[a:b] * exc).sum() / exc.sum()),
                      "amp_si": math.sqrt(2.0 * power), "psd_ratio": float(ratio[i])})
    tones.sort(key=lambda t: -t["amp_si"])
    out["tones"] = tones[:MAX_TONES]
    out["bands"] = detect_bands(y, fs, out["tones"], nper // BAND_SEG_DIV, alpha)
    return out


def detect_bands(y: np.ndarray, fs: float, tones: list[dict], nperseg: int,
                 alpha: float = ALPHA) -> list[dict]:
    """Vibration bands in the rate samples ``y``: narrowband random power (a resonance, a
    motor whose speed wanders) spread over more than a line's main lobe, so that it raises
    :func:`detect_tones`' local level and is no tone, but is not white either (docs/allan.md,
    "Tones", the ADIS16405 accelerometers' 10 Hz band). The same test as the tones' on a
    Welch periodogram of ``nperseg``-sample segments (Hann, no overlap; K segments, each bin
    chi2_2K / 2K for a smooth spectrum), the local level the running median over LEVEL_BINS
    bins, a bin significant above the F(2K, 2K LEVEL_BINS / pi) quantile at alpha / (bins
    tested); bins within 2.5 bins of a tone (its main lobe) and within LEVEL_BINS / 2 of 0 Hz
    and fs/2 are not tested. BAND_MIN_BINS or more contiguous significant bins make a band's
    core; the band runs on to either side while the PSD stays above the level. Its power is
    the PSD above the level summed over its bins (times the bin width); each bin's excess
    P_j - L_j is a component of the band's Allan term, a sinusoid of power (P_j - L_j) df
    at f_j: sum_j 2 (P_j - L_j) df sin^4(pi f_j m tau0) / (m sin(pi f_j tau0))^2, the Allan
    variance of that excess spectrum (its integral against the estimator's transfer
    function) on the bins. Returns [{f_lo_hz, f_hi_hz, freq_hz (excess-weighted centroid),
    rms_si, peak_ratio, bins, components: [{freq_hz, amp_si}]}]; [] where the segments would
    be shorter than 4 LEVEL_BINS samples."""
    if nperseg < 4 * LEVEL_BINS or y.size < 16 * nperseg:
        return []
    f, p, level, test, nu, nu_level = _local_level(y, fs, nperseg)
    df = float(f[1] - f[0])
    for t in tones:
        test &= np.abs(f - float(t["freq_hz"])) > 2.5 * df
    n_test = int(np.count_nonzero(test))
    if n_test == 0:
        return []
    thr = float(fdist.isf(alpha / n_test, nu, nu_level))
    above = test & (level > 0) & (p > thr * level)
    spans: list[list[int]] = []
    i = 0
    while i < p.size:
        if not above[i]:
            i += 1
            continue
        j = i
        while j < p.size and above[j]:
            j += 1
        if j - i >= BAND_MIN_BINS:
            a, b = i, j
            while a > 0 and test[a - 1] and p[a - 1] > level[a - 1]:
                a -= 1
            while b < p.size and test[b] and p[b] > level[b]:
                b += 1
            if spans and a <= spans[-1][1]:
                spans[-1][1] = b
            else:
                spans.append([a, b])
        i = j
    bands = []
    for a, b in spans:
        exc = np.maximum(p[a:b] - level[a:b], 0.0)
        bands.append({"f_lo_hz": float(f[a]), "f_hi_hz": float(f[b - 1]),
                      "freq_hz": float((f[a:b] * exc).sum() / exc.sum()),
                      "rms_si": math.sqrt(float(exc.sum()) * df),
                      "peak_ratio": float(np.max(p[a:b] / level[a:b])), "bins": int(b - a),
                      "bin_hz": df, "threshold_ratio": thr,
                      "components": [{"freq_hz": float(f[a + q]),
                                      "amp_si": math.sqrt(2.0 * float(exc[q]) * df)}
                                     for q in range(b - a) if exc[q] > 0]})
    bands.sort(key=lambda bd: -bd["rms_si"])
    return bands

