"""Tones (periodic components) found before the Allan fit and carried in the model as their
own Allan term (rigctl.solvers.allan_tones, rigctl.solvers.allan_fit ``tones``, the pipeline
in rigctl.analysis.allan). The expected Allan contribution of a tone is computed here in plain
numpy, as the overlapping Allan variance of the sampled sinusoid itself."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from rigctl.analysis import allan as AL
from rigctl.solvers import allan_tones as TN

from recording_helpers import write_recording

FS = 100.0
F_TONE = 47.3  # the emulator's vibration tone, just below the 50 Hz Nyquist of a 100 Hz output
N_TRUE = 8.73e-5  # rad/s/sqrt(Hz), consumer_mems gyro
AMP = 4.0e-4  # rad/s


def _oavar_numpy(y: np.ndarray, tau0: float, m: int) -> float:
    """Overlapping Allan variance at factor m from the phase (plain numpy, every term)."""
    x = np.concatenate(([0.0], np.cumsum(y) * tau0))
    d = x[2 * m:] - 2.0 * x[m:-m] + x[: -2 * m]
    return float(np.mean(d * d) / (2.0 * (m * tau0) ** 2))


@pytest.mark.parametrize("f_hz", [F_TONE, 152.7, 13.0])  # 152.7 Hz folds onto 47.3 Hz at 100 Hz
def test_tone_avar_is_the_sampled_sinusoid_avar(f_hz: float) -> None:
    n, tau0 = 400_000, 1.0 / FS
    y = 2.0 * np.sin(2 * np.pi * f_hz * np.arange(n) * tau0 + 0.7)
    ms = np.array([1, 2, 3, 4, 5, 7, 8, 15, 16, 33, 64, 101, 128, 255])
    got = TN.tone_avar(tau0, ms, f_hz, 2.0)
    want = np.array([_oavar_numpy(y, tau0, int(m)) for m in ms])
    scale = 4.0 / ms.astype(float) ** 2  # a^2 / m^2: the term's envelope
    assert np.max(np.abs(got - want) / scale) < 2e-3, (got, want)
    if f_hz == F_TONE:  # at short taus odd m carry it, even m hardly (the octave/all
        # disagreement; the pattern beats with a period of 1 / (2 (50 - 47.3) Hz) = 18.5 samples)
        short = ms <= 8
        odd = (want / scale)[short & (ms % 2 == 1)]
        even = (want / scale)[short & (ms % 2 == 0)]
        assert odd.min() > 0.4 and even.max() < 0.5 * odd.min()


def test_tone_detected_at_its_frequency_and_amplitude() -> None:
    n = 360_000
    rng = np.random.default_rng(3)
    w = rng.standard_normal(n) * N_TRUE * math.sqrt(FS)
    y = w + AMP * np.sin(2 * np.pi * F_TONE * np.arange(n) / FS + 0.4)
    r = TN.detect_tones(y, FS)
    assert len(r["tones"]) == 1, r["tones"]
    t = r["tones"][0]
    assert abs(t["freq_hz"] - F_TONE) < 0.5 * r["bin_hz"]
    assert abs(t["amp_si"] / AMP - 1.0) < 0.02
    # a tone of 1/4 of the white noise's sd per sample (7.5e-4 rad/s here) is also found
    weak = w + 0.25 * w.std() * np.sin(2 * np.pi * 13.1 * np.arange(n) / FS)
    assert [round(t["freq_hz"], 1) for t in TN.detect_tones(weak, FS)["tones"]] == [13.1]
    for seed in range(4):  # white noise alone: nothing (false-alarm probability 1e-3 each)
        assert TN.detect_tones(np.random.default_rng(10 + seed).standard_normal(n), FS)["tones"] == []


@pytest.mark.parametrize("n, nper, fs", [(360_000, 1 << 14, FS), (1 << 20, 1 << 16, FS),
                                         (100_037, 4096, 400.0), (20_000, 1001, 3.0)])
def test_welch_hann_is_scipys_welch_bit_for_bit(n: int, nper: int, fs: float) -> None:
    """TN.welch_hann against scipy.signal.welch with the options detect_tones used with it:
    every frequency and every PSD value equal, with an offset (the mean removed per segment),
    a tone, a tail shorter than a segment (left out) and an odd segment length (no fs/2 bin)."""
    from scipy.signal import welch

    rng = np.random.default_rng(n)
    y = 0.5 + rng.standard_normal(n) * 1e-3 + 1e-4 * np.sin(2 * np.pi * 13.1 * np.arange(n) / fs)
    f_want, p_want = welch(y, fs=fs, window="hann", nperseg=nper, noverlap=0,
                           detrend="constant", scaling="density")
    f_got, p_got = TN.welch_hann(y, fs, nper)
    np.testing.assert_array_equal(f_got, f_want)
    np.testing.assert_array_equal(p_got, p_want)


def _fit_n(path: Path, taus: str) -> tuple[dict, dict]:
    r = AL.compute(str(path), ["gx"], taus)["axes"]["gx"]
    return r["fit"], r["tones"]


def test_white_noise_N_recovered_with_and_without_tone(tmp_path: Path, monkeypatch) -> None:
    n = 360_000  # 1 h at 100 Hz
    rng = np.random.default_rng(5)
    w = rng.standard_normal((n, 3)) * N_TRUE * math.sqrt(FS)
    tone = AMP * np.sin(2 * np.pi * F_TONE * np.arange(n) / FS + 0.4)
    plain = write_recording(tmp_path / "plain.h5", FS, angular_rate=w, specific_force=w)
    toned = write_recording(tmp_path / "tone.h5", FS, angular_rate=w + tone[:, None],
                            specific_force=w)
    got = {}
    for taus in ("octave", "all"):
        fp, tp = _fit_n(plain, taus)
        ft, tt = _fit_n(toned, taus)
        assert tp["tones"] == []
        assert len(tt["tones"]) == 1 and abs(tt["tones"][0]["freq_hz"] - F_TONE) < 0.01
        assert abs(tt["tones"][0]["amp_si"] / AMP - 1.0) < 0.02
        assert ft["tones"]["max_share"] > 0.1  # the tone is a tenth of sigma^2 somewhere
        for fit in (fp, ft):
            n = fit["coefficients"].N  # rad/sqrt(s)
            assert n.resolved and n.ci95[0] <= N_TRUE <= n.ci95[1], (taus, n)
            assert not fit["coefficients"].Q.resolved, (taus, fit["coefficients"].Q)
        # the tone moves N by less than a third of its interval (undetected it moves the all-tau
        # N by 2.5 half-widths: the control below)
        np_, nt = fp["coefficients"].N, ft["coefficients"].N
        half = 0.5 * (np_.ci95[1] - np_.ci95[0])
        assert abs(nt.value - np_.value) < half / 3
        got[taus] = nt
    lo = max(got["octave"].ci95[0], got["all"].ci95[0])
    hi = min(got["octave"].ci95[1], got["all"].ci95[1])
    assert lo <= hi  # octave and all agree
    # control: without the detection the same tone is fitted as a quantization term (so the
    # assertions above are about something the tone does)
    monkeypatch.setattr(AL.TN, "detect_tones", lambda y, fs: {"tones": []})
    for taus in ("octave", "all"):
        fit, _ = _fit_n(toned, taus)
        assert fit["coefficients"].Q.resolved, (taus, fit["coefficients"].Q)
        assert "tones" not in fit
        if taus == "all":
            fp, _ = _fit_n(plain, taus)
            np_ = fp["coefficients"].N
            half = 0.5 * (np_.ci95[1] - np_.ci95[0])
            assert abs(fit["coefficients"].N.value - np_.value) > half


def test_fit_terms_carries_the_tone_term() -> None:
    """The pure fit: an exact curve N^2/tau + the tone's term at every m (computed here in
    numpy) gives N back with the tone, and without it a spurious slope -1 term or a biased N."""
    from rigctl.solvers import allan_fit as F

    tau0 = 1.0 / FS
    m = np.unique(np.round(np.logspace(0, 3, 120))).astype(float)
    tau = m * tau0
    tone = AMP ** 2 * np.sin(np.pi * F_TONE * m * tau0) ** 4 / (m * np.sin(np.pi * F_TONE * tau0)) ** 2
    adev = np.sqrt(N_TRUE ** 2 / tau + tone)
    edf = np.full(m.size, 1e4)
    with_t = F.fit_terms(tau, adev, edf, "gyro", tau0=tau0,
                         tones=[{"freq_hz": F_TONE, "amp_si": AMP}])
    assert abs(with_t["coefficients"].N.value / N_TRUE - 1.0) < 1e-3
    assert not with_t["coefficients"].Q.resolved
    assert with_t["tones"]["max_share"] > 0.1 and with_t["tones"]["tau0_s"] == tau0
    without = F.fit_terms(tau, adev, edf, "gyro", tau0=tau0)
    assert without["coefficients"].Q.resolved or \
        abs(without["coefficients"].N.value / N_TRUE - 1.0) > 1e-2


def test_plot_draws_the_tones(tmp_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rigctl.report.report_plots import draw_allan_axis

    n = 360_000
    rng = np.random.default_rng(8)
    y = rng.standard_normal((n, 3)) * N_TRUE * math.sqrt(FS)
    y += AMP * np.sin(2 * np.pi * F_TONE * np.arange(n) / FS)[:, None]
    rec = write_recording(tmp_path / "t.h5", FS, angular_rate=y, specific_force=y)
    r = AL.compute(str(rec), ["gx"], "all")["axes"]["gx"]
    fig, ax = plt.subplots()
    draw_allan_axis(ax, r["tau_s"], r[f"adev_{r['_unit']}"], r["fit"], "gyro", r["_unit"],
                    float(r[f"adev_{r['_unit']}"][0] / r[f"adev_{r['_si']}"][0]), "gx")
    labels = ax.get_legend_handles_labels()[1]
    plt.close(fig)
    assert "tones (47.3 Hz)" in labels and "fitted total with tones" in labels


def _band_noise(rng: np.random.Generator, n: int, f_lo: float, f_hi: float, rms: float) -> np.ndarray:
    """Gaussian noise whose power lies in [f_lo, f_hi] Hz only (flat there, zero elsewhere:
    built on the FFT grid), scaled to the given rms (its own sample rms, numpy)."""
    f = np.fft.rfftfreq(n, 1.0 / FS)
    spec = (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) * ((f >= f_lo) & (f <= f_hi))
    x = np.fft.irfft(spec, n)
    return x * rms / np.sqrt(np.mean(x * x))


def test_vibration_band_found_as_a_band_and_a_tone_as_a_tone() -> None:
    """A band of random power at 9.5-11 Hz (rms 0.3 of the white noise's per-sample sd: 4x
    the white level in the band) beside a 3 Hz tone and white noise: the tone is a tone, the
    band a band (not a tone: it raises the tones' local level), its span and rms those of the
    noise made here (its power over the white level: rms within 10 %, centre within 0.1 Hz),
    and white noise alone, or through a 2nd-order low-pass at 0.4 Nyquist, has no band (0 in
    6 + 6 series of 1e6 samples here; 0 in 50 when written: white, Butterworth at 40 and 20
    Hz of a 1 kHz stream kept every 10th sample, white + flicker + random walk, quantized)."""
    from scipy.signal import butter, lfilter

    n = 1_000_000
    rng = np.random.default_rng(7)
    band = _band_noise(rng, n, 9.5, 11.0, 0.3)
    tone = 0.05 * np.sin(2 * np.pi * 3.0 * np.arange(n) / FS + 0.3)
    out = TN.detect_tones(rng.standard_normal(n) + band + tone, FS)
    assert [round(t["freq_hz"], 2) for t in out["tones"]] == [3.0], out["tones"]
    assert len(out["bands"]) == 1, out["bands"]
    b = out["bands"][0]
    assert 9.2 <= b["f_lo_hz"] <= 9.6 and 10.9 <= b["f_hi_hz"] <= 11.3, b
    assert abs(b["freq_hz"] - 10.25) < 0.1 and abs(b["rms_si"] / 0.3 - 1.0) < 0.10, b
    assert all(abs(c["freq_hz"] - 3.0) > 0.1 for c in b["components"])
    found = 0
    for s in range(6):
        r = np.random.default_rng(100 + s)
        w = r.standard_normal(n)
        found += len(TN.detect_tones(w, FS)["bands"])
        bb, aa = butter(2, 0.4)
        found += len(TN.detect_tones(lfilter(bb, aa, w), FS)["bands"])
    assert found == 0
